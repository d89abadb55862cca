"""Modality-independent structure as a hypothesis source: CFOG peaks confirmed by tie points.

The oriented-gradient channels (georeg.register.refine.cfog: |gradient| per orientation,
contrast-sign free, so optical, infrared and depth images of one place look alike) of the query,
brought to the map's GSD, are correlated with the map's by FFT at every ``step_deg`` rotation
(georeg.register.dense.dense_search). Each of the ``peaks`` best peaks (a similarity) is then
confirmed by tie points: the map is rendered into the query's frame by the peak's similarity,
and every ``step`` px a ``window`` px CFOG patch is matched within +-``search_px``
(georeg.register.refine.measure_shifts). The tie points (query px, map px) are the candidate's
evidence; a chance tie point falls anywhere in its search box, the a-contrario area
(``Candidate.area_px``); ``tests`` = every rotation and offset the correlation searched.

The peak and its tie points must not see the same pixels: a peak chosen as the best overlap of
the whole query makes every patch of it agree with the peak's shift more often than chance, and
such tie points would confirm an unrelated place (measured on a synthetic unrelated texture: 20
of 31 tie points within 2.5 px, log10 NFA -8). The query is cut into a ``cells`` x ``cells``
checkerboard: the correlation sees the black cells only, the tie points lie in the white cells,
at least half a window from any black cell. The split is not enough (neighbouring cells share
structure; 3 of 8 synthetic unrelated textures still confirmed, log10 NFA down to -4.0), so the
a-contrario count is that of the whole search, every rotation and offset of the correlation
(the peaks are chosen among them: log10 NFA + 5 to 6), and tie points need an NCC >= 0.3
(with 0.2: 1 of 40 synthetic unrelated textures accepted, log10 NFA -1.1; with 0.3: 0 of 40,
the lowest at +3.9, the true crop at -44; 0.4 leaves 1 tie point on a real SRIF
optical-infrared pair where 0.3 leaves 59, 37 of them right).
"""

from __future__ import annotations

from typing import Any

import cv2
import numpy as np

from georeg.register.candidate import Candidate, resample, scale_matrix, similarity_ransac
from georeg.register.dense import dense_search
from georeg.register.refine import cfog, measure_shifts

DEFAULTS: dict[str, Any] = {
    "step_deg": 10.0,  # rotations of the correlation
    "max_side": 96,  # the correlation's query side (px), as register.dense
    "peaks": 3,  # peaks confirmed by tie points
    "work_side": 256,  # query side (px) of the tie-point measurement
    "window": 24,  # tie-point patch (work px)
    "step": 6,  # tie-point grid (work px)
    "search_px": 10,  # +- search of a tie point (work px)
    "min_ncc": 0.3,  # tie points of lower NCC are dropped (0.2: 1 of 40 unrelated accepted)
    "cells": 3,  # checkerboard: the peak from one colour, the tie points from the other
    "reproj_px": 3.0,  # RANSAC threshold, map px
}


def checker(shape: tuple[int, int], cells: int, margin: float = 0.0) -> np.ndarray:
    """White cells of a ``cells`` x ``cells`` checkerboard over ``shape`` (bool), shrunk by
    ``margin`` px from every black cell."""
    h, w = shape
    rr, cc = np.arange(h) * cells / h, np.arange(w) * cells / w
    ri, ci = np.floor(rr).astype(int), np.floor(cc).astype(int)
    dr = np.minimum(rr - ri, ri + 1 - rr) * h / cells  # px to the nearest cell edge
    dc = np.minimum(cc - ci, ci + 1 - cc) * w / cells
    white = ((ri[:, None] + ci[None, :]) % 2) == 1
    # the image border is no black cell
    inner_r = (dr >= margin - 1) | ((ri == 0) & (rr < 0.5)) | ((ri == cells - 1) & (rr - ri >= 0.5))
    inner_c = (dc >= margin - 1) | ((ci == 0) & (cc < 0.5)) | ((ci == cells - 1) & (cc - ci >= 0.5))
    return white & inner_r[:, None] & inner_c[None, :]


def tie_points(q: np.ndarray, m_img: np.ndarray, S: np.ndarray,
               c: dict[str, Any]) -> tuple[np.ndarray, np.ndarray, float]:  # fmt: skip
    """Tie points of the query ``q`` (uint8, 0 = nodata) in the map around the similarity ``S``
    (query px -> map px): (query px (n, 2), map px (n, 2), search box area in map px)."""
    w = min(1.0, float(c["work_side"]) / max(q.shape))
    qw = resample(q, w)
    Sw = S @ np.linalg.inv(scale_matrix(w))  # work px -> map px
    h, wd = qw.shape
    mf = np.where(m_img > 0, m_img, 0).astype(np.float32)
    mr = cv2.warpPerspective(mf, Sw, (wd, h), flags=cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP)
    mv = cv2.warpPerspective((m_img > 0).astype(np.uint8), Sw, (wd, h),
                             flags=cv2.INTER_NEAREST | cv2.WARP_INVERSE_MAP) > 0  # fmt: skip
    qv = qw > 0
    if qv.sum() < 64 or mv.sum() < 64:
        return np.zeros((0, 2)), np.zeros((0, 2)), 1.0
    qf, rf = cfog(qw.astype(np.float32), qv), cfog(mr, mv)
    win, st, r = int(c["window"]), int(c["step"]), int(c["search_px"])
    half = win // 2
    cc, rr = np.meshgrid(np.arange(half, wd - half + 1, st), np.arange(half, h - half + 1, st))
    pts = np.c_[cc.ravel(), rr.ravel()].astype(np.float64)
    white = checker(qw.shape, int(c["cells"]), margin=win / 2)  # the peak never saw these
    pts = pts[white[pts[:, 1].astype(int), pts[:, 0].astype(int)]]
    if len(pts) == 0:
        return np.zeros((0, 2)), np.zeros((0, 2)), 1.0
    ms = measure_shifts(qf, rf, qv, mv, pts, win, r)
    ok = ms["valid"] & ~ms["border"] & (np.nan_to_num(ms["score"], nan=-1) >= float(c["min_ncc"]))
    pw, sh = pts[ok], ms["shift"][ok]
    m_xy = np.c_[pw + sh, np.ones(len(pw))] @ Sw.T
    m_xy = m_xy[:, :2] / m_xy[:, 2:3]
    q_xy = (pw + 0.5) / w - 0.5
    scale = float(np.sqrt(abs(np.linalg.det(Sw[:2, :2]))))  # map px per work px
    return q_xy, m_xy, float(((2 * r + 1) * scale) ** 2)


def candidates(query_img: np.ndarray, map_img: np.ndarray, conf: dict[str, Any]) -> list[Candidate]:
    """One candidate per confirmed CFOG peak (query px -> map px similarity, tie points)."""
    c = {**DEFAULTS, **conf}
    f = float(conf["query_gsd_m"]) / float(conf["map_gsd_m"])  # query px -> map px
    black = ~checker(query_img.shape, int(c["cells"]))
    res = dense_search(np.where(black, query_img, 0).astype(np.uint8), f, map_img, float(c["step_deg"]), int(c["max_side"]),
                       n_peaks=int(c["peaks"]), apart_px=16.0)  # fmt: skip
    if res is None:
        return []
    peaks = [res.S] + [o[0] for o in (res.others or [])]
    out = []
    for k, S in enumerate(peaks):
        q_xy, m_xy, area = tie_points(query_img, map_img, S, c)
        H, inl = similarity_ransac(q_xy, m_xy, float(c["reproj_px"]), int(c.get("seed", 0)) + k)
        if H is None:
            continue
        out.append(Candidate(H, q_xy, m_xy, float(inl.sum()), int(res.tests), area, "structure"))
    return out
