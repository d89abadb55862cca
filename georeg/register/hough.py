"""Wide-area retrieval by a Hough vote of nearest map features (``register.index.rank: hough``).

The TF-IDF ranking of tiles by shared visual words (``MapIndex.rank_tiles``) loses the query in
a large map when query and map come from different spectra: a SWIR descriptor and its visible
counterpart fall in the same word only about half the time, and the words' scores are flat over
hundreds of tiles (on a 268 Mpx synthetic map the true tile ranked 148th-214th of 289). Here every
query feature (both contrast polarities) takes its ``knn`` nearest map features over the whole
map (``MapIndex.knn_words``: an inverted-file search through the ``nprobe`` nearest words), and
each pair votes for the place of the query's centre: the map feature's position plus the
query-centre offset, rotated by the keypoints' orientation difference and scaled by the known
GSD (Lowe's generalized Hough transform over x, y and rotation). Pairs whose keypoint sizes
disagree by more than ``max_octaves`` do not vote; a query position votes once per bin. Right
pairs pile up in one (x, y, rotation) bin, wrong ones spread over the map, so the best bins are
the candidate regions, each a square of the footprint's diagonal (+ one cell) around the voted
centre. Unknown GSD: each resize factor's features vote at their own scale.
"""

from __future__ import annotations

import logging
import math
from typing import Any

import numpy as np

log = logging.getLogger(__name__)

Bounds = tuple[float, float, float, float]

DEFAULTS: dict[str, Any] = {
    "knn": 10,  # nearest map features per query descriptor
    "nprobe": 8,  # words whose features are searched per query descriptor
    "cell_frac": 0.25,  # vote cell side = this x the footprint diagonal
    "bin_deg": 30.0,  # rotation bin
    "max_octaves": 1.0,  # keypoint sizes must agree within this (log2)
    "max_cells": 1024,  # at most this many cells along the map's longer side
}


def _smooth(acc: np.ndarray) -> np.ndarray:
    """3 x 3 box sum in x, y, plus half of the neighbouring rotation bins (cyclic)."""
    nb, ny, nx = acc.shape
    p = np.pad(acc, ((0, 0), (1, 1), (1, 1)))
    sm = sum(
        p[:, 1 + dy : 1 + dy + ny, 1 + dx : 1 + dx + nx] for dy in (-1, 0, 1) for dx in (-1, 0, 1)
    )
    return sm + 0.5 * (np.roll(sm, 1, axis=0) + np.roll(sm, -1, axis=0))


def vote_centres(
    q_xy: np.ndarray,
    q_angle: np.ndarray,
    q_scale: np.ndarray,
    q_centre: tuple[float, float],
    m_xy: np.ndarray,
    m_angle: np.ndarray,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Query centre in map x, y and the rotation (degrees) voted by each (query, map) pair.

    ``q_xy`` query pixels (col, row), ``q_scale`` map units per query pixel (per pair), angles in
    OpenCV's keypoint convention (both images row-down); ``m_xy`` map x, y (y up, the map's
    rows run down). Returns (x, y, rotation) per pair.
    """
    rot = (m_angle - q_angle) % 360.0
    # OpenCV's keypoint angle grows clockwise on screen (row-down): rotating the query by +a
    # on screen adds a to every angle, and maps an offset (dc, dr) to R(-a) (dc, dr)
    t = np.deg2rad(rot)
    c, s = np.cos(t), np.sin(t)
    v = (np.asarray(q_centre, np.float64)[None, :] - q_xy) * q_scale[:, None]
    dc = c * v[:, 0] + s * v[:, 1]
    dr = -s * v[:, 0] + c * v[:, 1]
    return m_xy[:, 0] + dc, m_xy[:, 1] - dr, rot


def hough_regions(
    qf: Any,
    index: Any,
    map_bounds: Bounds,
    map_gsd: float,
    diag: float,
    top: int,
    conf: dict[str, Any] | None = None,
) -> list[tuple[Bounds, float]]:
    """Candidate regions of the query part ``qf`` (georeg.register.search.QueryFeatures) in the
    indexed map, best first: ``[(bounds, votes), ...]``; empty when nothing votes.

    ``map_gsd``: map units per feature pixel; ``diag``: the part's ground diagonal (map units).
    """
    from georeg.register.matching import flip_polarity

    c = {**DEFAULTS, **(conf or {})}
    n = len(qf)
    if n == 0 or qf.angle is None or qf.size is None or not hasattr(index, "angle"):
        return []
    factor = np.asarray(qf.factor if qf.factor is not None else np.full(n, qf.factors[0]))
    desc = np.concatenate([qf.desc, flip_polarity(qf.desc)]).astype(np.float32)
    cq, cf, _d = index.knn_words(desc, int(c["knn"]), int(c["nprobe"]))
    if len(cq) == 0:
        return []
    qi = cq % n  # the polarity copy sits at the same place, with the angle turned by 180 deg
    q_ang = np.asarray(qf.angle, np.float64)[qi] + np.where(cq >= n, 180.0, 0.0)
    q_size = np.asarray(qf.size, np.float64)[qi]
    m_ang = np.asarray(index.angle[cf], np.float64)
    m_size = np.asarray(index.scale[cf], np.float64) / map_gsd
    ok = np.abs(np.log2(np.maximum(m_size, 1e-6) / np.maximum(q_size, 1e-6))) <= float(
        c["max_octaves"]
    )
    qi, cf, q_ang, m_ang = qi[ok], cf[ok], q_ang[ok], m_ang[ok]
    centre = (qf.origin[0] + qf.width / 2.0 - 0.5, qf.origin[1] + qf.height / 2.0 - 0.5)
    x, y, rot = vote_centres(
        np.asarray(qf.xy, np.float64)[qi],
        q_ang,
        factor[qi] * map_gsd,
        centre,
        np.asarray(index.xy[cf], np.float64),
        m_ang,
    )
    x0, y0, x1, y1 = map_bounds
    cell = max(float(c["cell_frac"]) * diag, max(x1 - x0, y1 - y0) / float(c["max_cells"]))
    nb = max(1, int(round(360.0 / float(c["bin_deg"]))))
    nx, ny = int(math.ceil((x1 - x0) / cell)) + 1, int(math.ceil((y1 - y0) / cell)) + 1
    gx = np.floor((x - x0) / cell).astype(np.int64)
    gy = np.floor((y - y0) / cell).astype(np.int64)
    gt = (rot / (360.0 / nb)).astype(np.int64) % nb
    inside = (gx >= 0) & (gx < nx) & (gy >= 0) & (gy < ny)
    key = ((gt * ny + gy) * nx + gx)[inside]
    # one vote per query position and bin (its k neighbours and polarity copies are not
    # independent evidence)
    key = np.unique(key * n + qi[inside]) // n
    acc = np.bincount(key, minlength=nb * ny * nx).reshape(nb, ny, nx).astype(np.float64)
    sm = _smooth(acc)
    best = sm.max(axis=0)  # the best rotation per cell
    out: list[tuple[Bounds, float]] = []
    half = 0.5 * diag + cell
    flat = best.ravel().copy()
    for o in np.argsort(-flat, kind="stable"):
        if len(out) >= top or flat[o] <= 0:
            break
        r, k = divmod(int(o), nx)
        if best[r, k] < 0:  # suppressed
            continue
        # the centre: vote-weighted mean of the 3 x 3 cells around the peak, at its rotation
        t = int(np.argmax(sm[:, r, k]))
        rs, ks = slice(max(0, r - 1), min(ny, r + 2)), slice(max(0, k - 1), min(nx, k + 2))
        win = acc[t, rs, ks]
        rr, kk = np.mgrid[rs, ks]
        wsum = float(win.sum())
        cx = x0 + (float((win * kk).sum()) / wsum + 0.5) * cell if wsum else x0 + (k + 0.5) * cell
        cy = y0 + (float((win * rr).sum()) / wsum + 0.5) * cell if wsum else y0 + (r + 0.5) * cell
        out.append(((cx - half, cy - half, cx + half, cy + half), float(flat[o])))
        best[max(0, r - 2) : r + 3, max(0, k - 2) : k + 3] = -1.0  # non-maximum suppression
    if out:
        bg = float(np.median(flat[flat > 0])) if (flat > 0).any() else 0.0
        log.info(
            "hough: %d pairs voted, best %.1f votes (median of voted cells %.1f), cell %.0f, "
            "%d rotation bins",
            int(ok.sum()),
            out[0][1],
            bg,
            cell,
            nb,
        )
    return out
