"""CFOG tie points between a query and a map rendered into its geometry.

The primitives the refinement (``georeg.register.refine``), the global refit
(``georeg.register.densefit``), the dense correlation (``georeg.register.dense``) and the
verifier's orthophoto and LiDAR terms (``ortho_check``, ``lidar_check``) share: oriented-gradient
channels (``cfog``), a map window (``MapImage``, ``read_map_gray``), a window grid
(``grid_points``) and the shifts measured at its points (``measure_shifts``).
"""

from __future__ import annotations

import itertools
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import cv2
import numpy as np

#: the tie-point settings (``refine`` keys) with their defaults
DEFAULTS: dict[str, Any] = {
    "grid_step_px": 12,
    "window_px": 32,
    "search_px": 4,
    "orientations": 9,
    "cfog_sigma_px": 1.0,
    "min_score": 0.25,
    "min_valid_fraction": 0.8,
    "consistency_px": 0.6,
}


def merged(conf: dict[str, Any] | None) -> dict[str, Any]:
    """The tie-point settings of a ``refine``-like section, with defaults."""
    return {k: (conf or {}).get(k, v) if (conf or {}).get(k) is not None else v
            for k, v in DEFAULTS.items()}  # fmt: skip


# ----------------------------------------------------------------------------- images


def cfog(
    img: np.ndarray, valid: np.ndarray, orientations: int = 9, sigma: float = 1.0
) -> np.ndarray:
    """CFOG-like structure channels (C, H, W) float32: |oriented gradient|, smoothed, L2-normalised.

    Invalid pixels (and their gradient neighbours) are 0.
    """
    f = np.where(valid, img, 0).astype(np.float32)
    if (~valid).any():  # fill nodata with the valid mean to avoid false edges at the border
        f[~valid] = float(f[valid].mean()) if valid.any() else 0.0
    f = cv2.GaussianBlur(f, (0, 0), 0.7)
    gx = cv2.Sobel(f, cv2.CV_32F, 1, 0, ksize=3)
    gy = cv2.Sobel(f, cv2.CV_32F, 0, 1, ksize=3)
    th = np.pi * np.arange(orientations) / orientations
    ch = np.empty((orientations, *f.shape), np.float32)
    for k, t in enumerate(th):
        ch[k] = cv2.GaussianBlur(np.abs(np.cos(t) * gx + np.sin(t) * gy), (0, 0), sigma)
    # smoothing across orientation ([1 2 1], circular: 0 and 180 deg are the same direction)
    ch = 0.25 * np.roll(ch, 1, 0) + 0.5 * ch + 0.25 * np.roll(ch, -1, 0)
    ch /= np.sqrt((ch**2).sum(0)) + 1e-6 * (float(np.abs(ch).max()) + 1e-12)
    good = cv2.erode(valid.astype(np.uint8), np.ones((5, 5), np.uint8)).astype(bool)
    ch[:, ~good] = 0
    return ch


def query_valid(band: np.ndarray) -> np.ndarray:
    """Valid pixels of a query band (H, W) or band stack (B, H, W): uint8 > 0 or finite float,
    in every band."""
    stack = band if band.ndim == 3 else band[None]
    return np.all((stack > 0) if stack.dtype == np.uint8 else np.isfinite(stack), axis=0)


def query_cfog(band: np.ndarray, orientations: int = 9,
               sigma: float = 1.0) -> tuple[np.ndarray, np.ndarray]:  # fmt: skip
    """CFOG channels and valid mask of a query band (H, W) or of a stack of co-registered bands
    (B, H, W; uint8 with 0 = nodata, or float with NaN): a stack's channels are averaged over
    its bands and L2-normalised again (one band's noise is not the others'); valid = every
    band valid."""
    stack = band if band.ndim == 3 else band[None]
    valid = query_valid(band)
    ch = sum(cfog(b.astype(np.float32), valid, orientations, sigma) for b in stack)
    if len(stack) > 1:
        ch = ch / (np.sqrt((ch**2).sum(0)) + 1e-6 * (float(np.abs(ch).max()) + 1e-12))
    return ch.astype(np.float32), valid


def sampling_step(col: np.ndarray, row: np.ndarray) -> float:
    """Map px between neighbouring samples of a 2-D sampling grid (geometric mean of the two
    directions, along the grid's middle row and column); 1 for anything else."""
    if col.ndim != 2 or min(col.shape) < 2:
        return 1.0
    h, w = col.shape
    du = np.hypot(np.diff(col[h // 2]), np.diff(row[h // 2]))
    dv = np.hypot(np.diff(col[:, w // 2]), np.diff(row[:, w // 2]))
    du, dv = du[np.isfinite(du)], dv[np.isfinite(dv)]
    if not len(du) or not len(dv):
        return 1.0
    return float(np.sqrt(np.median(du) * np.median(dv)))


@dataclass
class MapImage:
    """A gray map raster (float32, NaN = nodata) and its affine geotransform (rasterio order)."""

    gray: np.ndarray
    transform: Any
    #: low-passed copies of ``gray`` by blur sigma (map px): (values with nodata 0, nodata mask)
    _lowpass: dict[float, tuple[np.ndarray, np.ndarray]] = field(
        default_factory=dict, repr=False, compare=False
    )

    def lowpassed(self, sigma: float) -> tuple[np.ndarray, np.ndarray]:
        """The map Gaussian-blurred by ``sigma`` map px over its valid pixels only (normalised
        convolution: nodata neither darkens nor spreads), and its nodata mask; cached."""
        key = round(float(sigma), 1) if sigma >= 0.3 else 0.0
        if key not in self._lowpass:
            bad = ~np.isfinite(self.gray)
            src = np.where(bad, 0, self.gray).astype(np.float32)
            if key:
                ok = (~bad).astype(np.float32)
                num = cv2.GaussianBlur(src * ok, (0, 0), key)
                den = cv2.GaussianBlur(ok, (0, 0), key)
                src = np.where(den > 1e-6, num / np.maximum(den, 1e-6), 0).astype(np.float32)
            self._lowpass[key] = (src, bad)
        return self._lowpass[key]

    def render(self, x: np.ndarray, y: np.ndarray) -> np.ndarray:
        """The map sampled at map x, y: an image in query geometry, NaN outside.

        Bilinear, on the map low-passed first where the samples are more than a map px apart
        (Gaussian sigma = sqrt(step^2 - 1) / 2 map px): a query coarser than the map sees the
        map's area mean, not an aliased pick of its pixels (session 58)."""
        a, b, c, d, e, f = (float(v) for v in tuple(self.transform)[:6])
        det = a * e - b * d
        dx, dy = x - c, y - f
        col = (e * dx - b * dy) / det - 0.5
        row = (-d * dx + a * dy) / det - 0.5
        ok = np.isfinite(col) & np.isfinite(row)
        mx = np.where(ok, col, -1e6).astype(np.float32)
        my = np.where(ok, row, -1e6).astype(np.float32)
        step = sampling_step(col, row)
        src, bad = self.lowpassed(0.5 * np.sqrt(max(step * step - 1.0, 0.0)))
        out = cv2.remap(
            src, mx, my, cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT, borderValue=0
        )
        inv = cv2.remap(
            bad.astype(np.float32), mx, my, cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT,
            borderValue=1,
        )  # fmt: skip
        return np.where((inv < 1e-3) & ok, out, np.nan)


def read_map_gray(path: str | Path, x: np.ndarray, y: np.ndarray, pad: float = 20.0) -> MapImage:
    """The orthophoto (mosaic VRT) window covering map x, y (+ pad map units), as BT.601 gray."""
    import rasterio
    from rasterio.windows import Window, from_bounds

    from georeg.index.features import rgb_to_gray
    from georeg.io.errors import InputError

    ok = np.isfinite(x) & np.isfinite(y)
    try:
        with rasterio.open(path) as ds:
            p = pad * abs(ds.transform.a)
            win = from_bounds(x[ok].min() - p, y[ok].min() - p, x[ok].max() + p, y[ok].max() + p,
                              ds.transform)  # fmt: skip
            c0, r0 = max(0, int(np.floor(win.col_off))), max(0, int(np.floor(win.row_off)))
            c1 = min(ds.width, int(np.ceil(win.col_off + win.width)))
            r1 = min(ds.height, int(np.ceil(win.row_off + win.height)))
            if c1 <= c0 or r1 <= r0:
                raise InputError(path, "the registered footprint does not overlap the orthophoto")
            w = Window(c0, r0, c1 - c0, r1 - r0)
            data = ds.read(window=w)
            mask = ds.read_masks(1, window=w) > 0
            tr = ds.window_transform(w)
    except rasterio.errors.RasterioIOError as exc:
        raise InputError(path, f"cannot read the orthophoto: {exc}") from exc
    gray = rgb_to_gray(data[:3] if data.shape[0] >= 3 else data[0]).astype(np.float32)
    return MapImage(np.where(mask, gray, np.nan), tr)


# ----------------------------------------------------------------------------- tie points


def grid_points(width: int, height: int, step: int, window: int) -> np.ndarray:
    """Window centres (N, 2) (col, row) on a regular grid from step/2 to the far edge.

    Windows near the edge are clipped by the image (see ``window_centroid``).
    """
    h = max(1, min(window // 2, step // 2))
    cols = np.arange(h, width - h + 1e-9, step, dtype=np.float64)
    rows = np.arange(h, height - h + 1e-9, step, dtype=np.float64)
    if cols.size == 0 or rows.size == 0:
        return np.zeros((0, 2))
    cc, rr = np.meshgrid(cols, rows)
    return np.column_stack([cc.ravel(), rr.ravel()])


def window_centroid(pts: np.ndarray, width: int, height: int, window: int) -> np.ndarray:
    """Centre of each window clipped to the image: where a clipped window's shift applies."""
    h = window // 2
    out = np.empty_like(pts)
    for k, n in ((0, width), (1, height)):
        lo = np.maximum(np.round(pts[:, k]) - h, 0)
        hi = np.minimum(np.round(pts[:, k]) - h + window - 1, n - 1)
        out[:, k] = 0.5 * (lo + hi)
    return out


#: the 3 x 3 quadratic's least-squares solution: coefficients (1, x, y, x^2, xy, y^2) of a patch
_YY, _XX = np.mgrid[-1:2, -1:2]
_QUAD_PINV = np.linalg.pinv(np.column_stack([np.ones(9), _XX.ravel(), _YY.ravel(), _XX.ravel() ** 2,
                                             (_XX * _YY).ravel(), _YY.ravel() ** 2]))  # fmt: skip


def quad_peaks(s: np.ndarray) -> np.ndarray:
    """Sub-pixel offsets (m, 2) (dx, dy) of the maxima of ``m`` 3 x 3 patches (m, 3, 3): the
    least-squares quadratic's maximum when it has one within a pixel, else separable parabolas
    (each clipped to half a pixel; 0 where the parabola has no maximum)."""
    s = np.asarray(s, np.float64).reshape(-1, 3, 3)
    a = s.reshape(-1, 9) @ _QUAD_PINV.T
    m00, m01, m11 = 2 * a[:, 3], a[:, 4], 2 * a[:, 5]
    det = m00 * m11 - m01**2
    with np.errstate(invalid="ignore", divide="ignore"):
        d = np.column_stack([-(m11 * a[:, 1] - m01 * a[:, 2]) / det, -(m00 * a[:, 2] - m01 * a[:, 1]) / det])
    quad = (det > 0) & (m00 < 0) & np.all(np.abs(d) <= 1.0, axis=1)
    out = np.zeros((len(s), 2))
    for k, (lo, hi) in enumerate(((s[:, 1, 0], s[:, 1, 2]), (s[:, 0, 1], s[:, 2, 1]))):
        den = lo - 2 * s[:, 1, 1] + hi
        with np.errstate(invalid="ignore", divide="ignore"):
            out[:, k] = np.where(den < 0, np.clip(0.5 * (lo - hi) / den, -0.5, 0.5), 0.0)
    out[quad] = d[quad]
    return out


def inside_fraction(ci: np.ndarray, ri: np.ndarray, window: int, width: int,
                    height: int) -> np.ndarray:  # fmt: skip
    """The share of each window (centred on integer ``ci``, ``ri``) inside the image: a window
    clipped by the image edge counts its inside part only."""
    inside = np.ones(len(ci))
    for cc, size in ((ci, width), (ri, height)):
        lo = np.maximum(cc - window // 2, 0)
        inside *= (np.minimum(cc - window // 2 + window, size) - lo) / window
    return inside


def query_measurable(qvalid: np.ndarray, pts: np.ndarray, window: int,
                     min_valid: float) -> np.ndarray:  # fmt: skip
    """Which windows centred on ``pts`` hold enough valid query pixels: the query side of
    :func:`measure_shifts`'s validity."""
    h, w = qvalid.shape
    ci = np.round(pts[:, 0]).astype(int)
    ri = np.round(pts[:, 1]).astype(int)
    cnt = cv2.boxFilter(qvalid.astype(np.float32), cv2.CV_32F, (window, window), normalize=False,
                        borderType=cv2.BORDER_CONSTANT)[ri, ci]  # fmt: skip
    return cnt >= min_valid * inside_fraction(ci, ri, window, w, h) * window * window


def measure_shifts(
    qf: np.ndarray,
    rf: np.ndarray,
    qvalid: np.ndarray,
    rvalid: np.ndarray,
    pts: np.ndarray,
    window: int,
    search: int,
    min_valid: float = 0.8,
) -> dict[str, np.ndarray]:
    """Shift (dcol, drow) of the map features ``rf`` that best matches ``qf`` around each point.

    The query window centred on point p matches the rendered map window centred on p + shift.
    Returns shift (N, 2), score (N: peak NCC, NaN when not measurable), border (N: peak on the
    search border) and valid (N: enough valid pixels in both windows).
    """
    C, H, W = qf.shape
    n = len(pts)
    ci = np.round(pts[:, 0]).astype(int)
    ri = np.round(pts[:, 1]).astype(int)
    k = (window, window)

    def box(a: np.ndarray) -> np.ndarray:
        return cv2.boxFilter(a, cv2.CV_32F, k, normalize=False, borderType=cv2.BORDER_CONSTANT)

    r = search
    qv = qvalid.astype(np.float32)
    qsum = box(qf.sum(0))[ri, ci].astype(np.float64)
    qsq = box((qf**2).sum(0))[ri, ci].astype(np.float64)
    qcount = box(qv)[ri, ci].astype(np.float64)
    pad = ((0, 0), (r, r), (r, r))
    rpad = np.pad(rf, pad)
    rvpad = np.pad(rvalid.astype(np.float32), ((r, r), (r, r)))
    rsum_full = np.pad(box(rf.sum(0)), ((r, r), (r, r)))
    rsq_full = np.pad(box((rf**2).sum(0)), ((r, r), (r, r)))
    rcnt_full = np.pad(box(rvalid.astype(np.float32)), ((r, r), (r, r)))
    del rvpad
    side = 2 * r + 1
    ncc = np.full((n, side, side), -1.0)
    mincount = np.zeros(n)
    nn = np.maximum(C * qcount, 1.0)  # pooled over the valid query pixels of each window
    mincount[:] = qcount
    for iy, dy in enumerate(range(-r, r + 1)):
        for ix, dx in enumerate(range(-r, r + 1)):
            rs = rpad[:, r + dy : r + dy + H, r + dx : r + dx + W]
            sqr = box(np.einsum("chw,chw->hw", qf, rs))[ri, ci].astype(np.float64)
            rr, cc = ri + r + dy, ci + r + dx
            s_r, s_rr = rsum_full[rr, cc].astype(np.float64), rsq_full[rr, cc].astype(np.float64)
            cov = sqr - qsum * s_r / nn
            var = (qsq - qsum**2 / nn) * (s_rr - s_r**2 / nn)
            with np.errstate(invalid="ignore", divide="ignore"):
                ncc[:, iy, ix] = np.where(var > 1e-12, cov / np.sqrt(np.maximum(var, 1e-30)), -1.0)
            mincount = np.minimum(mincount, rcnt_full[rr, cc])
    valid = mincount >= min_valid * inside_fraction(ci, ri, window, W, H) * window * window
    flat = ncc.reshape(n, -1)
    best = flat.argmax(1)
    by, bx = np.unravel_index(best, (side, side))
    score = flat[np.arange(n), best]
    border = (by == 0) | (bx == 0) | (by == side - 1) | (bx == side - 1)
    shift = np.column_stack([bx - r, by - r]).astype(np.float64)
    i = np.flatnonzero(~border & valid)
    if i.size:
        o = np.arange(-1, 2)
        shift[i] += quad_peaks(ncc[i[:, None, None], (by[i, None] + o)[:, :, None], (bx[i, None] + o)[:, None, :]])
    score = np.where(valid, score, np.nan)
    return {"shift": shift, "score": score, "border": border, "valid": valid}


def _row_median(v: np.ndarray, count: np.ndarray) -> np.ndarray:
    """Median of each row's first ``count`` values (NaN after them; rows with ``count`` >= 1)."""
    v = np.sort(v, axis=1)  # NaN last
    r = np.arange(len(v))
    return 0.5 * (v[r, (count - 1) // 2] + v[r, count // 2])


def consistent(pts: np.ndarray, vec: np.ndarray, radius: float, tol: float) -> np.ndarray:
    """True where a vector agrees with the median of its neighbours within ``radius``.

    The bound is max(tol, 3 x the neighbourhood's robust spread). Points without neighbours pass.
    """
    from scipy.spatial import cKDTree

    n = len(pts)
    ok = np.ones(n, bool)
    if n < 3:
        return ok
    nbs = cKDTree(pts).query_ball_point(pts, radius)
    size = np.fromiter(map(len, nbs), np.intp, n)
    nb = np.fromiter(itertools.chain.from_iterable(nbs), np.intp, int(size.sum()))
    row = np.repeat(np.arange(n), size)
    other = nb != row
    nb, row = nb[other], row[other]
    count = np.bincount(row, minlength=n)
    has = count >= 2
    if not has.any():
        return ok
    pos = np.arange(len(nb)) - np.repeat(np.cumsum(count) - count, count)
    v = np.full((n, int(count.max()), 2), np.nan)
    v[row, pos] = vec[nb]
    v, count, own = v[has], count[has], vec[has]
    med = np.column_stack([_row_median(v[:, :, 0], count), _row_median(v[:, :, 1], count)])
    spread = 1.4826 * _row_median(np.hypot(*(v - med[:, None]).transpose(2, 0, 1)), count)
    ok[has] = np.hypot(*(own - med).T) <= np.maximum(tol, 3 * spread)
    return ok
