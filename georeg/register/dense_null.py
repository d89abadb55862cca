"""A calibrated a-contrario test for the CFOG correlation peak of a small query (issue 20).

The dense search's own figure (robust z of the peak among every rotation and offset, Gaussian
tail) is not valid: the correlation surface is spatially correlated, so a wrong window can reach
a tiny "NFA". Here the null is empirical and carries both the query's and the map's own
structure: the query is correlated with the whole map (``dense.correlation_surface``, every
rotation step), the surface (best rotation per offset) is cut into blocks of ``block_px``
correlation px, and the blocks' maxima away from the tested peak (``exclude_px``) are the null
sample of "the best score of this query in a place where it is not".

The test is the **top spacing**: if the query is nowhere in the map, the map's best peak is just
the largest of the block maxima, and for maxima in the Gumbel domain of attraction the gap
between the largest and the next one is exponential with the tail's scale, whatever the number
of blocks (the count is in the law: one test per map). The scale is estimated from the null
sample's own top ``tail_k`` values (mean excess over the (k+1)-th); p = exp(-gap / scale).
A Gumbel law fitted to all block maxima by moments and tested at the peak (x the number of
blocks) was measured too: valid but with far less power (its fit is driven by the bulk, whose
spread overstates the tail's). Developed on the tuning cities only
(``benchmarks/diag_small_null.py``, docs/BENCHMARKS.md "A calibrated null for the CFOG peak").

Maps too large for one FFT are scanned tile by tile with the same statistic
(``georeg.register.dense_tiled``, ``top_spacing`` shared).

An accepted peak is then a similarity at the known GSD: refined by a finer rotation search and a
sub-pixel peak around it (``fine_pose``).
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np

from georeg.register.dense import correlation_surface

NULL_DEFAULTS: dict[str, Any] = {
    "enabled": True,
    "block_px": 16,  # block side (correlation px, i.e. after the max_side shrink)
    "exclude_px": 12.0,  # map px around the tested peak left out of the null sample
    "tail_k": 30,  # top null block maxima that give the tail's scale
    "max_map_px": 1_000_000,  # the map (shrunk) may have at most this many px for one FFT
    "tile_px": 1024,  # larger maps: tiles of this side (correlation px, overlap included) ...
    "max_tiled_map_px": 64_000_000,  # ... up to this many correlation px, else not run
    "log_nfa_max": -3.0,
    "fine_step_deg": 1.0,
    "fine_range_deg": 5.0,
    "check": True,  # a small query's feature fit checked by the scan (small.null_check)
    "conflict_px": 3.0,  # ... replaced when the significant peak is this far (correlation px)
}


def null_conf(small: dict[str, Any] | None) -> dict[str, Any]:
    """``register.small.null_test`` with defaults."""
    return {**NULL_DEFAULTS, **((small or {}).get("null_test") or {})}


def block_maxima(surf: np.ndarray, b: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Maxima of ``surf`` (-inf = not searched) over ``b`` x ``b`` blocks that hold a finite
    value: values and block centres (row, col) in surface px."""
    b = max(1, int(b))
    oy, ox = surf.shape
    ny, nx = max(1, oy // b), max(1, ox // b)
    pad = np.full((ny * b, nx * b), -np.inf, np.float32)
    pad[: min(oy, ny * b), : min(ox, nx * b)] = surf[: ny * b, : nx * b]
    a = pad.reshape(ny, b, nx, b).max(axis=(1, 3))
    r, c = np.mgrid[:ny, :nx]
    ok = np.isfinite(a)
    return a[ok].astype(np.float64), (r[ok] + 0.5) * b - 0.5, (c[ok] + 0.5) * b - 0.5


def scan(
    q_u8: np.ndarray,
    factor: float,
    m_u8: np.ndarray,
    step_deg: float = 10.0,
    max_side: int = 96,
    block_px: int = 16,
    exclude_px: float = 12.0,
    tail_k: int = 30,
) -> dict[str, Any] | None:
    """Correlate the query (uint8, 0 = nodata; ``factor`` = query GSD / map GSD) with the whole
    map ``m_u8`` (uint8, 0 = nodata) and test its best peak against the block maxima elsewhere.

    Returns ``S`` (3 x 3 similarity query px -> map px of ``m_u8``), ``angle_deg``, ``score``
    (the statistic: the peak's mean channel correlation), ``null_max``, ``gap``, ``tail_scale``,
    ``log10_p`` = ``log10_nfa`` (top spacing), ``blocks``, ``null_blocks``, ``shrink``; None
    when nothing overlaps or the null sample is too small (< 30 blocks)."""
    sf = correlation_surface(q_u8, factor, m_u8, step_deg, max_side)
    if sf is None:
        return None
    surf = sf.scores.max(axis=0)
    if not np.isfinite(surf).any():
        return None
    pr, pc = np.unravel_index(int(np.argmax(surf)), surf.shape)
    kr = int(np.argmax(sf.scores[:, pr, pc]))
    vals, br, bc = block_maxima(surf, block_px)
    r = top_spacing(float(surf[pr, pc]), pr, pc, vals, br, bc, sf.s, block_px, exclude_px, tail_k)
    if r is None:
        return None
    return {"S": sf.to_window(kr, int(pr), int(pc)), "angle_deg": float(sf.angles[kr]), **r}


def top_spacing(
    peak: float,
    pr: float,
    pc: float,
    vals: np.ndarray,
    br: np.ndarray,
    bc: np.ndarray,
    s: float,
    block_px: int,
    exclude_px: float,
    tail_k: int,
) -> dict[str, Any] | None:
    """The top-spacing test of the peak ``peak`` at surface px (``pr``, ``pc``) against the block
    maxima ``vals`` (block centres ``br``, ``bc``) farther than ``exclude_px`` map px (``s``:
    correlation px per map px) plus a block from it; None when fewer than 30 remain."""
    far = (br - pr) ** 2 + (bc - pc) ** 2 > (exclude_px * s + block_px) ** 2
    null = vals[far]
    if len(null) < 30:
        return None
    top = np.sort(null)[::-1]
    k = min(int(tail_k), len(top) - 1)
    scale = max(float(np.mean(top[:k] - top[k])), 1e-12)
    gap = peak - float(top[0])
    lp = -gap / scale / math.log(10.0)
    return {
        "score": peak,
        "null_max": float(top[0]),
        "gap": gap,
        "tail_scale": scale,
        "tail_k": k,
        "log10_p": lp,
        "log10_nfa": lp,  # one test per map: the count is in the law of the top spacing
        "blocks": int(len(vals)),
        "null_blocks": int(len(null)),
        "shrink": float(s),
    }


def _subpixel(v: np.ndarray, i: int) -> float:
    """Parabolic sub-sample offset of the maximum at ``i`` of the 1-D ``v``."""
    if i <= 0 or i >= len(v) - 1 or not np.isfinite(v[i - 1 : i + 2]).all():
        return 0.0
    a, b, c = (float(x) for x in v[i - 1 : i + 2])
    d = a - 2 * b + c
    return float(np.clip(0.5 * (a - c) / d, -0.5, 0.5)) if d < 0 else 0.0


def fine_pose(
    q_u8: np.ndarray,
    factor: float,
    m_u8: np.ndarray,
    S: np.ndarray,
    angle_deg: float,
    step_deg: float = 1.0,
    range_deg: float = 5.0,
    box_px: float = 3.0,
) -> tuple[np.ndarray, float, float]:
    """Refine a similarity ``S`` (query px -> map px of ``m_u8``, rotation ``angle_deg``): the
    correlation at full resolution, rotations ``angle_deg`` +- ``range_deg`` by ``step_deg``,
    the query centre within ``box_px`` map px of ``S``'s, in a crop of the map around it; the
    best offset to sub-pixel. Returns (S, angle, score)."""
    h, w = q_u8.shape
    c = S @ np.array([(w - 1) / 2, (h - 1) / 2, 1.0])
    half = int(math.ceil(0.5 * math.hypot(h, w) * factor + box_px + 8))
    c0, r0 = int(round(c[0])) - half, int(round(c[1])) - half
    crop = np.zeros((2 * half + 1, 2 * half + 1), np.uint8)
    ys, xs = max(0, r0), max(0, c0)
    ye, xe = min(m_u8.shape[0], r0 + 2 * half + 1), min(m_u8.shape[1], c0 + 2 * half + 1)
    if ye <= ys or xe <= xs:
        return S, angle_deg, float("nan")
    crop[ys - r0 : ye - r0, xs - c0 : xe - c0] = m_u8[ys:ye, xs:xe]
    cc, cr = c[0] - c0, c[1] - r0
    angles = angle_deg + np.arange(-range_deg, range_deg + 1e-9, step_deg)
    sf = correlation_surface(q_u8, factor, crop, max_side=1 << 14,
                             centre_box=(cc - box_px, cr - box_px, cc + box_px, cr + box_px),
                             angles=angles)  # fmt: skip
    if sf is None or not np.isfinite(sf.scores).any():
        return S, angle_deg, float("nan")
    k, dy, dx = np.unravel_index(int(np.argmax(sf.scores)), sf.scores.shape)
    fy = _subpixel(sf.scores[k, :, dx], int(dy))
    fx = _subpixel(sf.scores[k, dy, :], int(dx))
    Sc = sf.to_window(int(k), dy + fy, dx + fx)  # query px -> crop px
    T = np.array([[1.0, 0, c0], [0, 1.0, r0], [0, 0, 1]])
    return T @ Sc, float(sf.angles[k]), float(sf.scores[k, dy, dx])
