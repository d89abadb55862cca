"""Maps that grow (issue 33): a registered frame set writes a new feature map, the feature maps
it used plus its own geo-registered points (``feature_map.laz`` + descriptors; inputs are never
overwritten).

Own points: a trajectory set's SfM points (``sfm_points.laz``, triangulated over its keyframes);
for single frames, each registered frame's COLMAP SIFT keypoints (the descriptors feature maps
store) cast along their rays onto the DSM through the frame's final pose, kept where the ray
meets the surface (the intersection converged) and the frame verified strongly enough to be
trusted (``min_score``)."""

from __future__ import annotations

import json
import logging
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from georeg.frames.feature_map import colmap_sift, load_feature_maps, write_feature_map
from georeg.frames.localize import camera_matrix, check_frame
from georeg.io.errors import InputError

log = logging.getLogger(__name__)

DEFAULTS: dict[str, Any] = {
    "max_features": 4000,  # keypoints per frame
    "min_score": 30,  # a frame adds points only when its pose verified at least this high
    "converge_m": 0.25,  # the ray-surface intersection moved less than this in its last step
}


def _dsm_window(dsm: str, bounds, ground_z: float):
    """(z array, inverse transform) of the DSM over bounds; a flat plane without a DSM."""
    import rasterio
    from rasterio.windows import from_bounds

    if not dsm:
        return None
    with rasterio.open(dsm) as ds:
        win = from_bounds(*bounds, ds.transform).round_offsets().round_lengths()
        z = ds.read(1, window=win, boundless=True, masked=True).astype(float).filled(np.nan)
        return z, ~ds.window_transform(win)


def surface_points(C: np.ndarray, d: np.ndarray, dsm_win, ground_z: float, iters: int = 12,
                   converge_m: float = 0.25) -> tuple[np.ndarray, np.ndarray]:  # fmt: skip
    """(xyz, ok) where rays C + s d (d: (N, 3), pointing down) meet the DSM (fixed-point
    iteration on the height); a flat plane at ground_z without a DSM."""
    down = d[:, 2] < -1e-6
    if dsm_win is None:
        s = (ground_z - C[2]) / np.where(down, d[:, 2], -1.0)
        return C + s[:, None] * d, down
    z_arr, inv = dsm_win
    h, w = z_arr.shape

    def z_at(xy):
        col, row = inv @ (xy[:, 0], xy[:, 1])
        r, c = np.floor(np.asarray(row)).astype(int), np.floor(np.asarray(col)).astype(int)
        ok = (r >= 0) & (r < h) & (c >= 0) & (c < w)
        out = np.full(len(xy), np.nan)
        out[ok] = z_arr[r[ok], c[ok]]
        return out

    z = np.full(len(d), float(np.nanmedian(z_arr)) if np.isfinite(z_arr).any() else ground_z)
    moved = np.full(len(d), np.inf)
    for _ in range(iters):
        s = (z - C[2]) / np.where(down, d[:, 2], -1.0)
        X = C + s[:, None] * d
        zn = z_at(X)
        moved = np.abs(zn - z)
        z = np.where(np.isfinite(zn), zn, z)
    s = (z - C[2]) / np.where(down, d[:, 2], -1.0)
    X = C + s[:, None] * d
    return X, down & (moved < converge_m) & (s > 0)


def frame_points(poses: list[dict], dsm: str | None, ground_z: float,
                 conf: dict | None = None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:  # fmt: skip
    """(xyz, rgb, descriptors) of the registered frames' keypoints on the surface."""
    c = {**DEFAULTS, **(conf or {})}
    extract = colmap_sift(int(c["max_features"]))
    xyz, rgb, desc = [], [], []
    for p in poses:
        score = (p.get("verification") or {}).get("score") or 0
        if p.get("status") != "registered" or score < int(c["min_score"]) or not p.get("intrinsics"):
            continue
        img = check_frame(p["image"])
        k = p["intrinsics"]
        if (img.shape[1], img.shape[0]) != (k["width"], k["height"]):  # the pyramid level
            img = cv2.resize(img, (k["width"], k["height"]), interpolation=cv2.INTER_AREA)
        K, dist = camera_matrix(k, k["width"], k["height"])
        und = cv2.undistort(img, K, dist) if np.any(dist) else img
        xy, d = extract(cv2.cvtColor(und, cv2.COLOR_RGB2GRAY))
        if not len(xy):
            continue
        R, C = np.asarray(p["R_world_to_cam"], float), np.asarray(p["camera_center_xyz"], float)
        rays = (np.c_[xy, np.ones(len(xy))] @ np.linalg.inv(K).T) @ R  # camera -> world directions
        fp = np.asarray(p.get("footprint_xy") or [C[:2]], float)
        b = (*(fp.min(0) - 50), *(fp.max(0) + 50))
        X, ok = surface_points(C, rays, _dsm_window(dsm, b, ground_z), ground_z, converge_m=float(c["converge_m"]))
        ij = np.round(xy[ok]).astype(int)
        xyz.append(X[ok])
        rgb.append(und[ij[:, 1].clip(0, und.shape[0] - 1), ij[:, 0].clip(0, und.shape[1] - 1)])
        desc.append(d[ok])
        log.info("%s: %d of %d keypoints on the surface", Path(p["image"]).name, int(ok.sum()), len(xy))
    if not xyz:
        return np.zeros((0, 3)), np.zeros((0, 3), np.uint8), np.zeros((0, 128), np.float32)
    return np.concatenate(xyz), np.concatenate(rgb), np.concatenate(desc)


def grow_feature_map(out_laz: str | Path, crs_wkt: str, used: list, own: list | None = None,
                     poses_json: str | Path | None = None, dsm: str | None = None,
                     ground_z: float = 0.0, conf: dict | None = None) -> dict:  # fmt: skip
    """Write ``out_laz``: the feature maps ``used`` + this set's points (``own`` feature-map files,
    e.g. its sfm_points.laz, and/or its registered frames in ``poses_json``)."""
    out_laz = Path(out_laz)
    if any(Path(p).resolve() == out_laz.resolve() for p in [*used, *(own or [])]):
        raise InputError(out_laz, "a grown feature map would overwrite one of its inputs",
                         "write_feature_map writes feature_map.laz beside the set's poses")  # fmt: skip
    parts, info = [], {}
    for key, paths in (("used", list(used)), ("own_sfm", list(own or []))):
        fm = load_feature_maps(paths, crs_wkt) if paths else None
        if fm is not None:
            parts.append((fm.xyz, fm.rgb, fm.desc))
        info[f"{key}_points"] = len(fm) if fm is not None else 0
    if poses_json is not None:
        try:
            poses = json.loads(Path(poses_json).read_text())
        except (OSError, ValueError) as exc:
            raise InputError(poses_json, f"cannot read the poses: {exc}") from exc
        xyz, rgb, desc = frame_points(poses, dsm, ground_z, conf)
        parts.append((xyz, rgb, desc))
        info["own_frame_points"] = len(xyz)
    xyz = np.concatenate([p[0] for p in parts]) if parts else np.zeros((0, 3))
    rgb = np.concatenate([p[1] for p in parts]) if parts else np.zeros((0, 3))
    desc = np.concatenate([p[2] for p in parts]) if parts else np.zeros((0, 128))
    write_feature_map(out_laz, xyz, rgb, desc, crs_wkt)
    info["points"] = len(xyz)
    log.info("feature map %s: %s", out_laz, info)
    return info
