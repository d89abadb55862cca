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

Maps too large for one FFT are scanned tile by tile with the same statistic (``tiled_scan``,
below).

An accepted peak is then a similarity at the known GSD: refined by a finer rotation search and a
sub-pixel peak around it (``fine_pose``).
"""

from __future__ import annotations

import logging
import math
from typing import Any

import numpy as np

from georeg.register.dense import correlation_surface, shrunk_query, window_u8

log = logging.getLogger(__name__)

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
    "peaks": 5,  # nothing accepted: the scan's best places checked densely (small.peaks_source)
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


def peaks(
    q_u8: np.ndarray,
    factor: float,
    m_u8: np.ndarray,
    n: int,
    step_deg: float = 10.0,
    max_side: int = 96,
    block_px: int = 8,
) -> list[tuple[np.ndarray, float, float]]:
    """The ``n`` best places of the query (uint8, 0 = nodata; ``factor`` = query GSD / map GSD)
    in the map ``m_u8`` by its CFOG correlation: the maxima of ``block_px`` blocks of the surface
    (best rotation per offset), best first, none within 1.5 blocks of a better one. Returns
    (S: 3 x 3 similarity query px -> map px of ``m_u8``, angle_deg, score) each."""
    sf = correlation_surface(q_u8, factor, m_u8, step_deg, max_side)
    if sf is None:
        return []
    surf = sf.scores.max(axis=0)
    vals, br, bc = block_maxima(np.where(np.isfinite(surf), surf, -np.inf), block_px)
    out: list[tuple[np.ndarray, float, float]] = []
    kept: list[tuple[float, float]] = []
    for i in np.argsort(vals)[::-1]:
        if len(out) >= n or not np.isfinite(vals[i]):
            break
        if any((br[i] - r) ** 2 + (bc[i] - c) ** 2 < (1.5 * block_px) ** 2 for r, c in kept):
            continue
        kept.append((br[i], bc[i]))
        # the block's own maximum, not its centre
        r0, c0 = int(br[i] - (block_px - 1) / 2), int(bc[i] - (block_px - 1) / 2)
        blk = surf[r0 : r0 + block_px, c0 : c0 + block_px]
        dy, dx = np.unravel_index(int(np.argmax(np.where(np.isfinite(blk), blk, -np.inf))), blk.shape)
        pr, pc = r0 + int(dy), c0 + int(dx)
        k = int(np.argmax(sf.scores[:, pr, pc]))
        out.append((sf.to_window(k, pr, pc), float(sf.angles[k]), float(vals[i])))
    return out


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


# ----------------------------------------------------------------------------- tiled scan
# The tiled scan: a map too large for one FFT.
#
# ``scan`` correlates the query with the whole map at once; here the map is read and
# correlated tile by tile with bounded memory, and the statistic is built to be the whole map's:
#
# 1. **Levels and grid** (a first pass of reads, each of about ``tile_px`` correlation px a side,
#    without overlap): every pixel is counted once in a (strided, at most ``sample_px`` values)
#    sample whose 1 and 99 percentiles stretch every tile alike (``dense.window_u8``'s levels of
#    the whole map), and the union of the reads gives the whole map's pixel grid, hence its
#    correlation grid (offsets of the shrunk query over the shrunk, padded map).
# 2. **Tiles** (second pass): the offsets are cut into cores (a partition); a tile reads the map
#    under its core's offsets grown by the query's rotated footprint and a margin (``margin_px``
#    correlation px, beyond the reach of the CFOG filters and nodata erosion), so every offset of
#    its core is evaluated as in the whole map; only the core's offsets are kept. Memory: one
#    tile's surfaces (rotations x ``tile_px``^2 float32) and its window at full resolution.
# 3. **Pooling**: the core's surface (best rotation per offset) goes into the block maxima of the
#    whole map's block grid (``block_px``, aligned to the global offsets) and the global peak is
#    kept (value, rotation, tile); then the same top-spacing test (``top_spacing``).
#
# A tile's pixel range is moved out a little (``_in_phase``) so that its shrink samples the whole
# map's shrunk grid in phase (origin and ``cv2.resize`` ratio within 0.02 shrunk px): the same
# surface up to float rounding when the query is <= ``max_side`` px at the map's GSD, a close
# resampling otherwise (measured in docs/BENCHMARKS.md, "Large maps: the tiled scan").


def query_geometry(q_u8: np.ndarray, factor: float, max_side: int) -> tuple[float, int, int]:
    """As ``dense.correlation_surface`` shrinks the query: (s = correlation px per map px, D =
    canvas side, pd = map padding), both in correlation px."""
    _, _, s, D = shrunk_query(q_u8, factor, max_side)
    return s, D, D // 2


def _edges(lo: float, hi: float, n: int) -> np.ndarray:
    """``n`` + 1 edges cutting [lo, hi] evenly, the outer ones open (-inf, +inf)."""
    e = np.linspace(lo, hi, n + 1)
    e[0], e[-1] = -np.inf, np.inf
    return e


class _Grid:
    """The orthophoto's pixel grid (from one window's affine ``A0``, north-up): window pixel
    offsets and map bounds of global pixel ranges."""

    def __init__(self, A0: np.ndarray) -> None:
        if abs(A0[0, 1]) > 1e-9 * abs(A0[0, 0]) or abs(A0[1, 0]) > 1e-9 * abs(A0[1, 1]):
            raise ValueError("tiled CFOG scan: the orthophoto grid is not north-up")
        self.A0 = np.asarray(A0, float)
        self.inv = np.linalg.inv(self.A0)

    def offset(self, A: np.ndarray) -> tuple[int, int]:
        """(col, row) of window pixel (0, 0) in the global grid."""
        if not np.allclose(A[:2, :2], self.A0[:2, :2], rtol=1e-6, atol=0.0):
            raise ValueError("tiled CFOG scan: the windows are not on one pixel grid")
        o = self.inv @ A @ np.array([0.0, 0.0, 1.0])
        c, r = round(float(o[0])), round(float(o[1]))
        if abs(o[0] - c) > 1e-3 or abs(o[1] - r) > 1e-3:
            raise ValueError("tiled CFOG scan: the windows are not on one pixel grid")
        return c, r

    def bounds(self, c0: int, r0: int, c1: int, r1: int) -> tuple[float, float, float, float]:
        """Map bounds (x0, y0, x1, y1) of global pixels [c0, c1) x [r0, r1) (centres +- half
        a pixel inside, so that a reader covering the bounds returns them)."""
        xy = self.A0 @ np.array([[c0, c1 - 1], [r0, r1 - 1], [1.0, 1.0]])
        hx, hy = 0.25 * abs(self.A0[0, 0]), 0.25 * abs(self.A0[1, 1])
        return (float(xy[0].min() - hx), float(xy[1].min() - hy),
                float(xy[0].max() + hx), float(xy[1].max() + hy))  # fmt: skip


def _probe(read_window: Any, bounds: tuple[float, ...], side: float) -> tuple[np.ndarray, Any]:
    """The affine (and dtype) of a small window of the orthophoto (``side`` map units each way
    from a place), tried at 5 x 5 places in ``bounds``; (None, None) when none is read."""
    for fy in (0.5, 0.3, 0.7, 0.1, 0.9):
        for fx in (0.5, 0.3, 0.7, 0.1, 0.9):
            x = bounds[0] + fx * (bounds[2] - bounds[0])
            y = bounds[1] + fy * (bounds[3] - bounds[1])
            got = read_window((x - side, y - side, x + side, y + side))
            if got is not None:
                return got[1], got[0].dtype
    return None, None


def tiled_scan(
    q_u8: np.ndarray,
    q_gsd: float,
    bounds: tuple[float, float, float, float],
    read_window: Any,
    probe_side: float,
    step_deg: float = 10.0,
    max_side: int = 96,
    block_px: int = 16,
    exclude_px: float = 12.0,
    tail_k: int = 30,
    tile_px: int = 1024,
    max_map_px: float = 64e6,
    margin_px: int = 12,
    sample_px: int = 16_000_000,
) -> dict[str, Any]:
    """``null_scan.scan`` of the query (uint8, 0 = nodata; GSD ``q_gsd`` map units) over the
    map in ``bounds`` (map x0, y0, x1, y1), read tile by tile through ``read_window(bounds)`` ->
    (gray, NaN = nodata; 3 x 3 window pixel centre -> map x, y) or None; ``probe_side``: map
    units of the first read (the orthophoto's pixel size).

    ``tile_px``: side of a tile in correlation px (the query shrunk to ``max_side``), overlap
    included; ``max_map_px``: not run above this many correlation px. Returns the scan's keys
    (``S`` = query px -> px of the winning tile, ``A`` = its window -> map affine, ``m_u8`` =
    the tile stretched, ``factor`` = query GSD / orthophoto px) plus ``tiles``, ``map_px``
    (correlation px of the map), ``levels``; or ``reason`` (and no ``S``) when not run."""
    A0, _ = _probe(read_window, bounds, probe_side * 64)
    if A0 is None:
        return {"reason": "no orthophoto"}
    grid = _Grid(A0)
    m_px = float(np.sqrt(abs(np.linalg.det(A0[:2, :2]))))
    factor = float(q_gsd) / m_px
    s, D, pd = query_geometry(q_u8, factor, max_side)
    area_px = (bounds[2] - bounds[0]) * (bounds[3] - bounds[1]) / m_px**2
    est = area_px * s * s
    if est > float(max_map_px):
        return {"reason": f"map too large for the tiled scan ({est:.0f} > {max_map_px:.0f} "
                          "correlation px, max_tiled_map_px)"}  # fmt: skip
    core = int(tile_px) - D - 2 * int(margin_px)
    if core < 4 * int(block_px):
        return {"reason": f"tile_px {tile_px} too small for the query ({D} + 2 x {margin_px} "
                          "correlation px of overlap)"}  # fmt: skip

    # pass 1: levels (strided sample, each pixel once) and the union of the reads
    k = max(1, math.ceil(math.sqrt(area_px / max(1, int(sample_px)))))
    side = int(tile_px) / s * m_px  # map units of about tile_px correlation px
    nx = max(1, math.ceil((bounds[2] - bounds[0]) / side))
    ny = max(1, math.ceil((bounds[3] - bounds[1]) / side))
    ex, ey = _edges(bounds[0], bounds[2], nx), _edges(bounds[1], bounds[3], ny)
    sample, ext = [], [math.inf, math.inf, -math.inf, -math.inf]
    for j in range(ny):
        for i in range(nx):
            rb = (max(ex[i], bounds[0]), max(ey[j], bounds[1]),
                  min(ex[i + 1], bounds[2]), min(ey[j + 1], bounds[3]))  # fmt: skip
            got = read_window(rb)
            if got is None:
                continue
            gray, A = got
            c0, r0 = grid.offset(A)
            h, w = gray.shape
            ext = [min(ext[0], c0), min(ext[1], r0), max(ext[2], c0 + w), max(ext[3], r0 + h)]
            cx = A[0, 0] * np.arange(w) + A[0, 2]
            ry = A[1, 1] * np.arange(h) + A[1, 2]
            cols = (cx >= ex[i]) & (cx < ex[i + 1]) & ((np.arange(w) + c0) % k == 0)
            rows = (ry >= ey[j]) & (ry < ey[j + 1]) & ((np.arange(h) + r0) % k == 0)
            v = gray[np.ix_(rows, cols)]
            sample.append(v[np.isfinite(v)].astype(np.float32))
    vals = np.concatenate(sample) if sample else np.zeros(0, np.float32)
    if vals.size < 16:
        return {"reason": "no orthophoto"}
    lo, hi = (float(x) for x in np.percentile(vals, [1.0, 99.0]))
    del sample, vals
    C0, R0, C1, R1 = (int(x) for x in ext)
    Hs, Ws = max(1, round((R1 - R0) * s)), max(1, round((C1 - C0) * s))
    sy, sx = Hs / (R1 - R0), Ws / (C1 - C0)  # the whole map's shrink as cv2.resize does it
    oy, ox = Hs + 2 * pd - D + 1, Ws + 2 * pd - D + 1
    if oy < 1 or ox < 1:
        return {"reason": "no overlap or too few null blocks"}
    b = max(1, int(block_px))
    nby, nbx = max(1, oy // b), max(1, ox // b)
    blocks = np.full((nby, nbx), -np.inf, np.float32)
    best: dict[str, Any] = {"score": -np.inf}

    # pass 2: the offsets' cores, each read with the query's footprint and a margin around it
    ty, tx = math.ceil(oy / core), math.ceil(ox / core)
    n_tiles, done, m = ty * tx, 0, int(margin_px)
    log.info("tiled CFOG null scan: %d x %d correlation px in %d tiles", oy, ox, n_tiles)
    for ti in range(ty):
        G0, G1 = ti * core, min(oy, (ti + 1) * core)
        for tj in range(tx):
            H0, H1 = tj * core, min(ox, (tj + 1) * core)
            done += 1
            # offset d's canvas covers shrunk map rows [d - pd, d - pd + D); the range is moved
            # out a little so that the tile's shrink keeps the whole map's phase
            pr0, pr1 = _in_phase(math.floor((G0 - pd - m) / s) - 2,
                                 math.ceil((G1 - 1 - pd + D + m) / s) + 2, R1 - R0, s, sy)
            pc0, pc1 = _in_phase(math.floor((H0 - pd - m) / s) - 2,
                                 math.ceil((H1 - 1 - pd + D + m) / s) + 2, C1 - C0, s, sx)  # fmt: skip
            if pr1 <= pr0 or pc1 <= pc0:
                continue
            got = read_window(grid.bounds(C0 + pc0, R0 + pr0, C0 + pc1, R0 + pr1))
            if got is None:
                continue
            gray, A = got
            c0, r0 = grid.offset(A)
            # exactly the range asked for when the reader returned more (its own margins)
            y0, x0 = max(0, pr0 - (r0 - R0)), max(0, pc0 - (c0 - C0))
            gray = gray[y0 : pr1 - (r0 - R0), x0 : pc1 - (c0 - C0)]
            A = A @ np.array([[1.0, 0, x0], [0, 1.0, y0], [0, 0, 1]])
            r0, c0 = r0 + y0, c0 + x0
            if min(gray.shape) < 8:
                continue
            u8 = window_u8(gray, (lo, hi))
            del gray
            sf = correlation_surface(q_u8, factor, u8, step_deg, max_side)
            if sf is None:
                continue
            sr, sc = round((r0 - R0) * sy), round((c0 - C0) * sx)  # tile offset + (sr, sc) = global
            surf = sf.scores.max(axis=0)
            a0, a1 = max(0, G0 - sr), min(surf.shape[0], G1 - sr)
            b0, b1 = max(0, H0 - sc), min(surf.shape[1], H1 - sc)
            if a1 <= a0 or b1 <= b0:
                continue
            V = surf[a0:a1, b0:b1]
            if np.isfinite(V).any():
                pr, pc = np.unravel_index(int(np.argmax(V)), V.shape)
                if V[pr, pc] > best["score"]:
                    kr = int(np.argmax(sf.scores[:, a0 + pr, b0 + pc]))
                    best = {"score": float(V[pr, pc]), "gy": a0 + pr + sr, "gx": b0 + pc + sc,
                            "S": sf.to_window(kr, a0 + pr, b0 + pc),
                            "angle_deg": float(sf.angles[kr]), "A": A, "m_u8": u8}  # fmt: skip
            _pool(blocks, V, a0 + sr, b0 + sc, b)
            del sf, surf, V, u8
            if done % max(1, n_tiles // 10) == 0 or done == n_tiles:
                log.info("tiled CFOG null scan: %d / %d tiles", done, n_tiles)
    info = {"tiles": n_tiles, "map_px": int(oy * ox), "levels": [lo, hi], "factor": factor}
    if not np.isfinite(best["score"]):
        return {**info, "reason": "no overlap or too few null blocks"}
    r_, c_ = np.mgrid[:nby, :nbx]
    ok = np.isfinite(blocks)
    vals_b = blocks[ok].astype(np.float64)
    br, bc = (r_[ok] + 0.5) * b - 0.5, (c_[ok] + 0.5) * b - 0.5
    r = top_spacing(best["score"], best["gy"], best["gx"], vals_b, br, bc, s, b, exclude_px,
                    tail_k)  # fmt: skip
    if r is None:
        return {**info, "reason": "no overlap or too few null blocks"}
    return {**info, **r, "S": best["S"], "A": best["A"], "m_u8": best["m_u8"],
            "angle_deg": best["angle_deg"], "peak_offset": [int(best["gy"]), int(best["gx"])]}  # fmt: skip


def _in_phase(lo: int, hi: int, n: int, s: float, sw: float, tol: float = 0.02) -> tuple[int, int]:
    """A pixel range [a, e) of [0, ``n``) containing [``lo``, ``hi``) whose shrink by ``s``
    (``cv2.resize`` to round(length x ``s``) px) samples the whole map's grid (shrunk by ``sw`` =
    its rows after / before) in phase: a x sw and the length x sw within ``tol`` of integers
    (else the nearest found), a moved down and e up by at most 64 shrunk px."""
    span = math.ceil(64 / sw)
    lo, hi = max(0, lo), min(n, hi)
    if hi <= lo:
        return lo, hi

    def off(v: float) -> float:
        return abs(v - round(v))

    def first(cands: list[int], cost: Any) -> int:
        good = [c for c in cands if cost(c) <= tol]
        return good[0] if good else min(cands, key=cost)

    a = first(list(range(lo, max(0, lo - span) - 1, -1)), lambda c: 0.0 if c == 0 else off(c * sw))
    ends = [e for e in range(hi, min(n, hi + span) + 1) if round((e - a) * s) == round((e - a) * sw)]
    e = first(ends, lambda c: off((c - a) * sw)) if ends else hi
    return a, e


def _pool(blocks: np.ndarray, V: np.ndarray, g0: int, h0: int, b: int) -> None:
    """Fold the surface ``V`` (global offsets from (``g0``, ``h0``)) into the block maxima
    ``blocks`` (block side ``b``; offsets beyond the last whole block are dropped, as in
    ``null_scan.block_maxima``)."""
    nby, nbx = blocks.shape
    g1, h1 = min(g0 + V.shape[0], nby * b), min(h0 + V.shape[1], nbx * b)
    if g1 <= g0 or h1 <= h0:
        return
    V = V[: g1 - g0, : h1 - h0]
    y0, x0 = (g0 // b) * b, (h0 // b) * b
    y1, x1 = -(-g1 // b) * b, -(-h1 // b) * b
    buf = np.full((y1 - y0, x1 - x0), -np.inf, np.float32)
    buf[g0 - y0 : g1 - y0, h0 - x0 : h1 - x0] = V
    bm = buf.reshape((y1 - y0) // b, b, (x1 - x0) // b, b).max(axis=(1, 3))
    sl = blocks[y0 // b : y1 // b, x0 // b : x1 // b]
    np.maximum(sl, bm, out=sl)
