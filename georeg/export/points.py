"""3-D points for the exports and where each registered view sees them.

Two sources: a set's geo-registered SfM points (``sfm_points.laz``: triangulated features of the
set's own images), or, for single frames, distinct map points (corners of the orthophoto under
the frames' footprints, z from the DSM, hidden points removed by a walk along the ray over the
DSM). Observations are the points' projections through the registered poses (with distortion):
they carry the registration to the tools, they are not new measurements."""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np

from georeg.export.views import View
from georeg.io.errors import InputError


@dataclass
class Points:
    """(N, 3) map points, (N, 3) uint8 colours, and per point the (view index, u, v) observations."""

    xyz: np.ndarray
    rgb: np.ndarray
    obs: list[list[tuple[int, float, float]]] = field(default_factory=list)

    def subset(self, keep: np.ndarray) -> Points:
        idx = np.flatnonzero(keep) if np.asarray(keep).dtype == bool else np.asarray(keep, int)
        return Points(self.xyz[idx], self.rgb[idx], [self.obs[i] for i in idx])

    def n_views(self) -> np.ndarray:
        return np.array([len(o) for o in self.obs], int)


def observe(views: list[View], xyz: np.ndarray, rgb: np.ndarray,
            visible=None) -> Points:  # fmt: skip
    """Where every view sees every point (inside the image, in front; ``visible(view, xyz, mask)``
    may remove hidden ones)."""
    xyz = np.asarray(xyz, float).reshape(-1, 3)
    obs: list[list[tuple[int, float, float]]] = [[] for _ in range(len(xyz))]
    for j, v in enumerate(views):
        ok, uv = v.sees(xyz)
        if visible is not None and ok.any():
            ok &= visible(v, xyz, ok)
        for i in np.flatnonzero(ok):
            obs[i].append((j, float(uv[i, 0]), float(uv[i, 1])))
    return Points(xyz, np.asarray(rgb, np.uint8).reshape(-1, 3), obs)


def spread(xyz: np.ndarray, score: np.ndarray, n: int) -> np.ndarray:
    """Indices of at most ``n`` points spread over the area: the best-scored point of each cell of
    a grid with about ``n`` occupied cells, cells taken in order of their best score."""
    m = len(xyz)
    if m <= n:
        return np.arange(m)
    lo, hi = xyz[:, :2].min(0), xyz[:, :2].max(0)
    for g in range(max(1, int(np.sqrt(n))), 4 * n + 2):
        cell = np.floor((xyz[:, :2] - lo) / np.maximum(hi - lo, 1e-9) * g).clip(0, g - 1).astype(int)
        key = cell[:, 0] * g + cell[:, 1]
        order = np.lexsort((-score, key))
        first = order[np.r_[True, key[order][1:] != key[order][:-1]]]
        if len(first) >= n:
            return np.sort(first[np.argsort(-score[first], kind="stable")[:n]])
    return np.argsort(-score, kind="stable")[:n]


def read_sfm_points(laz_path: str | Path) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(xyz, rgb uint8, track length) of a set's ``sfm_points.laz``."""
    import laspy

    try:
        las = laspy.read(str(laz_path))
    except Exception as exc:  # laspy raises several types for a bad file
        raise InputError(laz_path, f"cannot read the SfM point map: {exc}") from exc
    xyz = np.c_[las.x, las.y, las.z].astype(float)
    rgb = (np.c_[las.red, las.green, las.blue] // 257).astype(np.uint8)
    names = set(las.point_format.extra_dimension_names)
    tl = np.asarray(las.track_len, int) if "track_len" in names else np.full(len(xyz), 2)
    return xyz, rgb, tl


@dataclass
class MapWindow:
    """An orthophoto RGB and a DSM (or flat ground) window on one grid (rasterio transform)."""

    rgb: np.ndarray  # (H, W, 3) uint8
    z: np.ndarray  # (H, W) float, NaN = no data
    transform: object

    def rowcol(self, x: np.ndarray, y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        inv = ~self.transform
        col, row = inv @ (np.asarray(x, float), np.asarray(y, float))
        return np.asarray(row) - 0.5, np.asarray(col) - 0.5

    def z_at(self, x: np.ndarray, y: np.ndarray) -> np.ndarray:
        r, c = self.rowcol(x, y)
        ri, ci = np.round(r).astype(int), np.round(c).astype(int)
        h, w = self.z.shape
        ok = (ri >= 0) & (ri < h) & (ci >= 0) & (ci < w)
        out = np.full(len(ri), np.nan)
        out[ok] = self.z[ri[ok], ci[ok]]
        return out


def read_map_window(ortho: str | Path, dsm: str | Path | None, bounds, ground_z: float,
                    max_px: int = 2000) -> MapWindow:  # fmt: skip
    """The orthophoto and DSM over ``bounds`` (x0, y0, x1, y1), read at most ``max_px`` a side."""
    import rasterio
    from rasterio.enums import Resampling
    from rasterio.windows import from_bounds

    try:
        with rasterio.open(ortho) as ds:
            win = from_bounds(*bounds, ds.transform).round_offsets().round_lengths()
            s = max(1.0, max(win.width, win.height) / max_px)
            shape = (max(1, int(win.height / s)), max(1, int(win.width / s)))
            img = ds.read(indexes=list(range(1, min(3, ds.count) + 1)), window=win, boundless=True,
                          out_shape=(min(3, ds.count), *shape), resampling=Resampling.average)  # fmt: skip
            tr = ds.window_transform(win) @ rasterio.Affine.scale(win.width / shape[1],
                                                                   win.height / shape[0])  # fmt: skip
        z = np.full(shape, float(ground_z))
        if dsm:
            with rasterio.open(dsm) as dd:
                dwin = from_bounds(*bounds, dd.transform).round_offsets().round_lengths()
                z = dd.read(1, window=dwin, boundless=True, out_shape=shape, masked=True,
                            resampling=Resampling.bilinear).astype(float).filled(np.nan)  # fmt: skip
    except rasterio.errors.RasterioIOError as exc:
        raise InputError(ortho, f"cannot read the map for the exports: {exc}") from exc
    img = np.moveaxis(img, 0, -1)
    if img.shape[2] == 1:
        img = np.repeat(img, 3, axis=2)
    if img.dtype != np.uint8:
        f = img.astype(float)
        img = (255 * f / max(float(np.nanpercentile(f, 99.5)), 1e-9)).clip(0, 255).astype(np.uint8)
    return MapWindow(img, z, tr)


def map_corners(win: MapWindow, n: int) -> tuple[np.ndarray, np.ndarray]:
    """(xyz, rgb) of up to ``n`` distinct orthophoto corners (Shi-Tomasi) with a height."""
    gray = cv2.cvtColor(win.rgb, cv2.COLOR_RGB2GRAY)
    mask = np.isfinite(win.z).astype(np.uint8) * 255
    pts = cv2.goodFeaturesToTrack(gray, maxCorners=int(n), qualityLevel=0.01,
                                  minDistance=max(3, int(min(gray.shape) / 100)), mask=mask)  # fmt: skip
    if pts is None:
        return np.zeros((0, 3)), np.zeros((0, 3), np.uint8)
    cr = pts.reshape(-1, 2)
    x, y = win.transform @ (cr[:, 0] + 0.5, cr[:, 1] + 0.5)
    x, y = np.asarray(x), np.asarray(y)
    z = win.z_at(x, y)
    ok = np.isfinite(z)
    rgb = win.rgb[np.round(cr[ok, 1]).astype(int), np.round(cr[ok, 0]).astype(int)]
    return np.c_[x[ok], y[ok], z[ok]], rgb


def unoccluded(win: MapWindow, clearance: float, steps: int = 48):
    """A ``visible(view, xyz, mask)`` test: the segment point -> camera stays above the DSM
    (by ``clearance`` map units) over the map window."""

    def visible(view: View, xyz: np.ndarray, mask: np.ndarray) -> np.ndarray:
        out = np.ones(len(xyz), bool)
        idx = np.flatnonzero(mask)
        P = xyz[idx]
        t = np.linspace(0.02, 1.0, steps)[None, :, None]
        seg = P[:, None, :] + t * (view.C - P)[:, None, :]
        zg = win.z_at(seg[..., 0].ravel(), seg[..., 1].ravel()).reshape(len(P), steps)
        hidden = np.any(np.nan_to_num(zg, nan=-np.inf) > seg[..., 2] + clearance, axis=1)
        out[idx[hidden]] = False
        return out

    return visible
