"""Point-based rendering without a GPU: z-buffer splatting of coloured 3-D points into a pinhole.

The map is a cloud of coloured points (the ortho-coloured LiDAR ``points.laz`` of the map stage,
or a height field: one point per orthophoto pixel at its DSM height, plus wall points where the
height jumps). ``render`` projects them into a ``PinholeCamera``; each point covers a square splat
sized from its ground spacing and depth, the nearest splat wins per pixel (depth sort + first
occurrence, no atomics). Outputs: colour, depth along the optical axis (inf = empty), edges.

Conventions (the frames contract): world = map CRS (x east, y north, z up, metres); OpenCV camera
axes (x right, y down, z forward); ``X_cam = R (X - C)``; pixel centres at integer coordinates.
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from pathlib import Path

import cv2
import numpy as np


@dataclass(frozen=True)
class PinholeCamera:
    fx: float
    fy: float
    cx: float
    cy: float
    width: int
    height: int
    R: np.ndarray  # (3, 3) world -> camera
    C: np.ndarray  # (3,) camera centre, world

    @property
    def K(self) -> np.ndarray:
        return np.array([[self.fx, 0, self.cx], [0, self.fy, self.cy], [0, 0, 1]], float)

    @property
    def rvec(self) -> np.ndarray:
        return cv2.Rodrigues(np.asarray(self.R, float))[0].ravel()

    @property
    def tvec(self) -> np.ndarray:
        return -np.asarray(self.R, float) @ np.asarray(self.C, float)

    def with_pose(self, R: np.ndarray, C: np.ndarray) -> PinholeCamera:
        return replace(self, R=np.asarray(R, float), C=np.asarray(C, float))

    def scaled(self, s: float) -> PinholeCamera:
        """Same pose, image scaled by ``s`` (pixel centres kept: c' = (c + 0.5) s - 0.5)."""
        w, h = max(8, int(round(self.width * s))), max(8, int(round(self.height * s)))
        sx, sy = w / self.width, h / self.height
        return replace(self, fx=self.fx * sx, fy=self.fy * sy, cx=(self.cx + 0.5) * sx - 0.5,
                       cy=(self.cy + 0.5) * sy - 0.5, width=w, height=h)  # fmt: skip

    def project(self, X: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(N, 3) world -> (N, 2) pixel (col, row) and (N,) depth (z in the camera)."""
        Xc = (np.asarray(X, float) - self.C) @ np.asarray(self.R, float).T
        z = Xc[:, 2]
        with np.errstate(divide="ignore", invalid="ignore"):
            u = self.fx * Xc[:, 0] / z + self.cx
            v = self.fy * Xc[:, 1] / z + self.cy
        return np.c_[u, v], z

    def backproject(self, uv: np.ndarray, depth: np.ndarray) -> np.ndarray:
        """Pixels (col, row) with depths (camera z) -> (N, 3) world points."""
        uv = np.asarray(uv, float)
        d = np.asarray(depth, float)
        xc = np.c_[(uv[:, 0] - self.cx) / self.fx * d, (uv[:, 1] - self.cy) / self.fy * d, d]
        return xc @ np.asarray(self.R, float) + self.C

    def rays(self, uv: np.ndarray) -> np.ndarray:
        """Unit world directions of the rays through pixels (col, row)."""
        uv = np.asarray(uv, float)
        d = np.c_[(uv[:, 0] - self.cx) / self.fx, (uv[:, 1] - self.cy) / self.fy, np.ones(len(uv))]
        d = d @ np.asarray(self.R, float)
        return d / np.linalg.norm(d, axis=1, keepdims=True)


def look_at(C, target, up=(0.0, 0.0, 1.0)) -> np.ndarray:
    """World -> camera rotation of a camera at ``C`` looking at ``target``; image up ~ ``up``.

    For a nadir view give the heading as ``up`` (e.g. (0, 1, 0): north at the top of the image).
    """
    f = np.asarray(target, float) - np.asarray(C, float)
    f /= np.linalg.norm(f)
    u = np.asarray(up, float)
    right = np.cross(f, u)
    if np.linalg.norm(right) < 1e-6:
        raise ValueError("look_at: viewing direction parallel to 'up'; give the heading as up")
    right /= np.linalg.norm(right)
    down = np.cross(f, right)
    return np.vstack([right, down, f])


def pose_from_angles(C, heading_deg: float, off_nadir_deg: float) -> np.ndarray:
    """Rotation of a camera at ``C`` tilted ``off_nadir_deg`` from nadir towards ``heading_deg``
    (clockwise from north); the image top points along the heading."""
    h, t = np.radians(heading_deg), np.radians(off_nadir_deg)
    fwd = np.array([np.sin(h) * np.sin(t), np.cos(h) * np.sin(t), -np.cos(t)])
    up = np.array([np.sin(h) * np.cos(t), np.cos(h) * np.cos(t), np.sin(t)])
    return look_at(C, np.asarray(C, float) + fwd, up)


@dataclass
class PointCloud:
    xyz: np.ndarray  # (N, 3) float64 world
    rgb: np.ndarray  # (N, 3) uint8
    spacing: np.ndarray | float  # ground spacing (m) of each point: its splat footprint

    def __len__(self) -> int:
        return int(self.xyz.shape[0])


@dataclass
class Render:
    image: np.ndarray  # (H, W, 3) uint8, 0 where empty
    depth: np.ndarray  # (H, W) float32 camera z, inf where empty
    camera: PinholeCamera

    @property
    def mask(self) -> np.ndarray:
        return np.isfinite(self.depth)

    def gray(self) -> np.ndarray:
        return cv2.cvtColor(self.image, cv2.COLOR_RGB2GRAY)

    def edges(self, lo: int = 40, hi: int = 120) -> np.ndarray:
        """Canny edges of the intensity plus depth discontinuities (> 5 % of the depth)."""
        e = cv2.Canny(cv2.GaussianBlur(self.gray(), (0, 0), 1.0), lo, hi) > 0
        d = np.where(self.mask, self.depth, 0).astype(np.float32)
        dmax = cv2.dilate(d, np.ones((3, 3), np.uint8))
        dmin = cv2.erode(np.where(self.mask, d, np.float32(1e9)), np.ones((3, 3), np.uint8))
        return e | ((dmax - dmin) > 0.05 * np.maximum(dmin, 1.0)) & self.mask

    def points_at(self, uv: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """World 3-D points under pixels (col, row) from the depth buffer (nearest pixel);
        returns (xyz, valid)."""
        uv = np.asarray(uv, float)
        c = np.clip(np.rint(uv[:, 0]).astype(int), 0, self.camera.width - 1)
        r = np.clip(np.rint(uv[:, 1]).astype(int), 0, self.camera.height - 1)
        d = self.depth[r, c].astype(float)
        ok = np.isfinite(d)
        xyz = np.full((len(uv), 3), np.nan)
        if ok.any():
            xyz[ok] = self.camera.backproject(uv[ok], d[ok])
        return xyz, ok


def _depth_order(zz: np.ndarray, near: float) -> np.ndarray:
    """``np.argsort(zz, kind="stable")`` of float32 depths, faster: depths above ``near`` >= 0 are
    positive, so their bit patterns sort as their values and (bits << 32 | index) is a unique
    int64 key whose plain sort is the stable order."""
    n = len(zz)
    if near < 0 or n >= 2**31:
        return np.argsort(zz, kind="stable")
    key = zz.view(np.int32).astype(np.int64)
    key <<= 32
    key |= np.arange(n, dtype=np.int64)
    key.sort()
    key &= 0xFFFFFFFF
    return key


def render(
    cloud: PointCloud, cam: PinholeCamera, max_splat_px: int = 6, near: float = 0.5,
    background: int = 0,
) -> Render:  # fmt: skip
    """Z-buffer splatting of ``cloud`` into ``cam``.

    A point of ground spacing s at depth z covers a square of side ~ fx s / z pixels (at least 1,
    at most 2 ``max_splat_px`` + 1); the nearest splat wins every pixel.
    """
    W, H = cam.width, cam.height
    uv, z = cam.project(cloud.xyz)
    half = np.maximum(z, near)  # in place, the same arithmetic as ceil(0.5 fx s / z 1.1 - 0.5)
    np.divide(0.5 * cam.fx * np.broadcast_to(cloud.spacing, z.shape), half, out=half)
    half *= 1.1
    half -= 0.5
    np.ceil(half, out=half)
    half = np.clip(np.nan_to_num(half, nan=0, copy=False), 0, max_splat_px).astype(np.int32)
    m = (z > near) & (uv[:, 0] > -half - 1) & (uv[:, 0] < W + half) & (uv[:, 1] > -half - 1)
    m &= uv[:, 1] < H + half
    idx_pt = np.flatnonzero(m)
    col = np.rint(uv[idx_pt, 0]).astype(np.int64)
    row = np.rint(uv[idx_pt, 1]).astype(np.int64)
    zz = z[idx_pt].astype(np.float32)
    hh = half[idx_pt]
    # z-buffer: every pixel keeps the smallest depth rank among the splats that cover it. Per
    # splat size h, whichever is cheaper: np.minimum.at at each of the (2h + 1)^2 offsets, or at
    # the points' centres followed by a (2h + 1)^2 minimum filter (cv2.erode: exactly the square
    # splats' minimum), on a canvas padded by h so that points centred just outside still count.
    n = len(idx_pt)
    by_z = _depth_order(zz, near)
    rank = np.empty(n, np.float64)  # exact integers; cv2.erode takes float64
    rank[by_z] = np.arange(n)
    best = np.full((H, W), float(n))
    for h in np.unique(hh):
        sel = np.flatnonzero(hh == h)
        Hp, Wp = H + 2 * h, W + 2 * h
        rr, cc, rk = row[sel] + h, col[sel] + h, rank[sel]
        buf = np.full(Hp * Wp, float(n))
        if (2 * h + 1) ** 2 * len(sel) <= 4 * Hp * Wp:  # few points: one offset at a time
            for dr in range(-h, h + 1):
                okr = (rr + dr >= 0) & (rr + dr < Hp)
                for dc in range(-h, h + 1):
                    ok = okr & (cc + dc >= 0) & (cc + dc < Wp)
                    np.minimum.at(buf, (rr[ok] + dr) * Wp + cc[ok] + dc, rk[ok])
            buf = buf.reshape(Hp, Wp)
        else:  # many points: their centres, then the minimum filter
            ok = (rr >= 0) & (rr < Hp) & (cc >= 0) & (cc < Wp)
            np.minimum.at(buf, rr[ok] * Wp + cc[ok], rk[ok])
            buf = buf.reshape(Hp, Wp)
            if h:
                buf = cv2.erode(buf, np.ones((2 * h + 1, 2 * h + 1), np.uint8), borderType=cv2.BORDER_CONSTANT,
                                borderValue=float(n))  # fmt: skip
        np.minimum(best, buf[h : h + H, h : h + W], out=best)
    best = best.reshape(-1).astype(np.int64)
    image = np.full((H, W, 3), background, np.uint8)
    depth = np.full((H, W), np.inf, np.float32)
    hit = np.flatnonzero(best < n)
    if hit.size:
        win = by_z[best[hit]]
        depth.reshape(-1)[hit] = zz[win]
        image.reshape(-1, 3)[hit] = cloud.rgb[idx_pt[win]]
    return Render(image, depth, cam)


# --------------------------------------------------------------------------------------------
# Map clouds


def heightfield_cloud(
    rgb: np.ndarray, dsm: np.ndarray, transform, wall_step_m: float = 1.0, wall_min_m: float = 1.5,
    wall_shade: float = 0.6,
) -> PointCloud:  # fmt: skip
    """One point per valid pixel (centre, DSM height, orthophoto colour) plus wall points.

    rgb: (H, W, 3) uint8; dsm: (H, W) float (NaN = nodata); transform: affine (north-up).
    Where a pixel is more than ``wall_min_m`` above a 4-neighbour, points are added every
    ``wall_step_m`` down to the neighbour's height (the pixel's colour x ``wall_shade``): facades
    then occlude what is behind a building in oblique views.
    """
    H, W = dsm.shape
    res = abs(transform.a)
    rows, cols = np.mgrid[0:H, 0:W]
    x = transform.c + (cols + 0.5) * transform.a
    y = transform.f + (rows + 0.5) * transform.e
    valid = np.isfinite(dsm)
    xyz = [np.c_[x[valid], y[valid], dsm[valid]]]
    col = [rgb[valid]]
    z = np.where(valid, dsm, -np.inf)
    nb_min = z.copy()
    for dr, dc in ((1, 0), (-1, 0), (0, 1), (0, -1)):
        sh = np.full_like(z, np.inf)
        sh[max(dr, 0) : H + min(dr, 0), max(dc, 0) : W + min(dc, 0)] = z[
            max(-dr, 0) : H + min(-dr, 0), max(-dc, 0) : W + min(-dc, 0)
        ]
        sh = np.where(np.isfinite(sh), sh, np.inf)
        nb_min = np.minimum(nb_min, sh)
    with np.errstate(invalid="ignore"):  # -inf - inf off the valid pixels, dropped below
        drop = np.where(valid & np.isfinite(nb_min), z - nb_min, 0.0)
    wr, wc = np.nonzero(drop > wall_min_m)
    if wr.size:
        n = np.ceil(drop[wr, wc] / wall_step_m).astype(int)
        rep = np.repeat(np.arange(wr.size), n)
        k = np.arange(rep.size) - np.repeat(np.cumsum(n) - n, n) + 1
        zw = z[wr, wc][rep] - np.minimum(k * wall_step_m, drop[wr, wc][rep])
        xyz.append(np.c_[x[wr, wc][rep], y[wr, wc][rep], zw])
        col.append((rgb[wr, wc][rep] * wall_shade).astype(np.uint8))
    pts = np.concatenate(xyz)
    return PointCloud(pts, np.concatenate(col).astype(np.uint8), res)


def read_heightfield(ortho_path, dsm_path, bounds, max_px: int = 4_000_000,
                     flat_z: float = 0.0) -> PointCloud:  # fmt: skip
    """Height-field cloud of a map window (x0, y0, x1, y1) from the ortho and DSM mosaics.

    Decimated (out_shape) when the window would exceed ``max_px`` pixels. Any ortho: 1 band
    (panchromatic) is rendered gray, more than 8 bits is stretched (``to_uint8``). ``dsm_path``
    None: flat ground at ``flat_z``.
    """
    import rasterio
    from affine import Affine
    from rasterio.enums import Resampling
    from rasterio.windows import from_bounds

    from georeg.index.features import to_uint8

    with rasterio.open(ortho_path) as so:
        x0, y0, x1, y1 = bounds
        mb = so.bounds
        x0, y0 = max(x0, mb.left), max(y0, mb.bottom)
        x1, y1 = min(x1, mb.right), min(y1, mb.top)
        if x1 <= x0 or y1 <= y0:
            return PointCloud(np.zeros((0, 3)), np.zeros((0, 3), np.uint8), 1.0)
        win = from_bounds(x0, y0, x1, y1, so.transform).round_offsets().round_lengths()
        h, w = int(win.height), int(win.width)
        s = max(1.0, np.sqrt(h * w / max_px))
        shape = (max(1, int(h / s)), max(1, int(w / s)))
        bands = [1, 2, 3] if so.count >= 3 else [1]
        img = so.read(bands, window=win, out_shape=(len(bands), *shape), boundless=True, fill_value=0,
                      resampling=Resampling.average if s > 1 else Resampling.nearest)  # fmt: skip
        msk = so.read_masks(1, window=win, out_shape=shape, boundless=True) > 0
        wbounds = so.window_bounds(win)
        t0 = so.window_transform(win)
    if img.dtype != np.uint8:
        img = np.stack([to_uint8(b, msk) for b in img])
    if len(bands) == 1:
        img = np.repeat(img, 3, axis=0)
    if dsm_path is None:
        dsm = np.where(msk, np.float32(flat_z), np.nan).astype(np.float32)
    else:
        with rasterio.open(dsm_path) as sd:
            wd = from_bounds(*wbounds, sd.transform)
            dsm = sd.read(1, window=wd, out_shape=shape, boundless=True, fill_value=np.nan,
                          resampling=Resampling.average if s > 1 else Resampling.bilinear,
                          masked=True).astype(np.float32)  # fmt: skip
        dsm = np.where(np.ma.getmaskarray(dsm) | ~msk, np.nan, np.ma.getdata(dsm))
    tr = Affine(t0.a * w / shape[1], 0, t0.c, 0, t0.e * h / shape[0], t0.f)
    return heightfield_cloud(np.ascontiguousarray(img.transpose(1, 2, 0)), dsm, tr)


def read_laz_cloud(paths, bounds, spacing: float | None = None) -> PointCloud:
    """Points of the map's ``points.laz`` tiles inside ``bounds`` (RGB / 257 -> uint8)."""
    import laspy

    xyz, rgb = [], []
    for p in paths:
        with laspy.open(Path(p)) as f:
            hd = f.header
            if hd.maxs[0] < bounds[0] or hd.mins[0] > bounds[2] or hd.maxs[1] < bounds[1] or hd.mins[1] > bounds[3]:  # fmt: skip
                continue
            las = f.read()
        x, y, z = np.asarray(las.x), np.asarray(las.y), np.asarray(las.z)
        m = (x >= bounds[0]) & (x <= bounds[2]) & (y >= bounds[1]) & (y <= bounds[3])
        xyz.append(np.c_[x[m], y[m], z[m]])
        rgb.append(np.c_[las.red[m], las.green[m], las.blue[m]] // 257)
    if not xyz:
        return PointCloud(np.zeros((0, 3)), np.zeros((0, 3), np.uint8), 1.0)
    pts = np.concatenate(xyz)
    if spacing is None:
        area = max((bounds[2] - bounds[0]) * (bounds[3] - bounds[1]), 1.0)
        spacing = float(np.sqrt(area / max(len(pts), 1)))
    return PointCloud(pts, np.concatenate(rgb).astype(np.uint8), spacing)
