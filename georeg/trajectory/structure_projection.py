"""Structure projection (paper, stage C): 3-D/3-D correspondences SfM points -> map, then Sim(3).

A keyframe registered to the map (an *anchor*: its map pose) is rendered from the map; each SfM
point observed in that keyframe gets the map point where its observation ray meets the rendered
surface (depth buffer). Pixels on depth discontinuities (building edges) are rejected. RANSAC
Sim(3) on the correspondences of all anchors, then robust least squares on the inliers.
"""

from __future__ import annotations

import logging
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import cv2
import numpy as np

from georeg.frames.render import PinholeCamera, PointCloud, Render, render
from georeg.trajectory.sfm import SfMModel
from georeg.trajectory.sim3 import Sim3, ransac_sim3, refine_sim3, transform_pose

log = logging.getLogger(__name__)

DEFAULTS: dict[str, Any] = {
    "max_depth_jump": 0.03,  # reject pixels whose 3x3 depth range exceeds this x depth
    "ransac_threshold_m": 2.5,  # Sim(3) inlier distance in the map
    "ransac_max_iters": 5000,
    "ransac_method": "pycolmap",  # pycolmap (LO-RANSAC) | numpy
    "min_inliers": 12,
    "huber_m": 1.0,  # refinement loss soft threshold
}

Target = PointCloud | Callable[[PinholeCamera], Render]


@dataclass
class Correspondences:
    """One anchor's SfM observations and the map points under them."""

    point_idx: np.ndarray  # (k,) SfM point indices observed in the keyframe
    src: np.ndarray  # (k, 3) SfM xyz
    dst: np.ndarray  # (k, 3) map xyz (NaN where invalid)
    valid: np.ndarray  # (k,) bool: surface hit, away from depth discontinuities
    n_empty: int  # rays that hit no map surface
    n_edge: int  # rays on depth discontinuities


def _render(target: Target, cam: PinholeCamera) -> Render:
    return render(target, cam) if isinstance(target, PointCloud) else target(cam)


def _depth_at(depth: np.ndarray, uv: np.ndarray, max_jump: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:  # fmt: skip
    """Bilinear depth at (col, row), valid where the 3x3 depth range is < ``max_jump`` x depth.

    Returns (depth, valid, empty) with ``empty`` = the nearest pixel has no surface.
    """
    H, W = depth.shape
    d = np.where(np.isfinite(depth), depth, np.float32(0)).astype(np.float32)
    k = np.ones((3, 3), np.uint8)
    dmax = cv2.dilate(d, k, borderType=cv2.BORDER_REPLICATE)
    dmin = cv2.erode(np.where(d > 0, d, np.float32(np.inf)), k, borderType=cv2.BORDER_REPLICATE)
    c = np.clip(np.rint(uv[:, 0]).astype(int), 0, W - 1)
    r = np.clip(np.rint(uv[:, 1]).astype(int), 0, H - 1)
    inside = (uv[:, 0] > -0.5) & (uv[:, 0] < W - 0.5) & (uv[:, 1] > -0.5) & (uv[:, 1] < H - 0.5)
    empty = ~inside | (d[r, c] <= 0)
    smooth = np.isfinite(dmin[r, c]) & (dmax[r, c] - dmin[r, c] <= max_jump * dmin[r, c])
    ok = ~empty & smooth
    c0 = np.clip(np.floor(uv[:, 0]).astype(int), 0, W - 2)
    r0 = np.clip(np.floor(uv[:, 1]).astype(int), 0, H - 2)
    fc = np.clip(uv[:, 0] - c0, 0, 1)
    fr = np.clip(uv[:, 1] - r0, 0, 1)
    q = np.stack([d[r0, c0], d[r0, c0 + 1], d[r0 + 1, c0], d[r0 + 1, c0 + 1]], 1)
    wts = np.stack([(1 - fc) * (1 - fr), fc * (1 - fr), (1 - fc) * fr, fc * fr], 1)
    full = (q > 0).all(1)
    z = np.where(full, (q * wts).sum(1), d[r, c])
    return z, ok, empty


def project_structure(
    model: SfMModel, name: str, R_map: np.ndarray, C_map: np.ndarray, target: Target,
    K: np.ndarray | None = None, max_depth_jump: float = DEFAULTS["max_depth_jump"],
) -> Correspondences:  # fmt: skip
    """Correspondences of keyframe ``name`` at map pose (``R_map`` world -> camera, ``C_map``).

    ``K``: the anchor's intrinsics (keyframe pixels used as they are); None = the SfM camera of
    that image (``SfMModel.camera``), observations undistorted with its distortion. ``target``: the map cloud, or a callable
    rendering a ``PinholeCamera``.
    """
    idx, uv = model.observations(name)
    uv = np.asarray(uv, float)
    K_sfm, dist, width, height = model.camera(name)
    if K is None:
        K = K_sfm
        if np.any(dist != 0) and len(uv):
            uv = cv2.undistortPoints(uv.reshape(-1, 1, 2), K, dist, P=K).reshape(-1, 2)
    K = np.asarray(K, float)
    cam = PinholeCamera(K[0, 0], K[1, 1], K[0, 2], K[1, 2], width, height,
                        np.asarray(R_map, float), np.asarray(C_map, float))  # fmt: skip
    rnd = _render(target, cam)
    z, ok, empty = _depth_at(rnd.depth, uv, max_depth_jump)
    dst = np.full((len(uv), 3), np.nan)
    if ok.any():
        dst[ok] = cam.backproject(uv[ok], z[ok])
    return Correspondences(idx, model.xyz[idx], dst, ok, int(empty.sum()), int((~ok & ~empty).sum()))  # fmt: skip


def estimate_sfm_to_map(
    model: SfMModel, anchors: list[tuple], target: Target, conf: dict | None = None,
    seed: int = 0,
) -> tuple[Sim3, dict[str, Any]]:  # fmt: skip
    """Sim(3) from the SfM frame to the map from anchors ``(name, R_map, C_map[, K])``.

    Correspondences of all anchors -> RANSAC Sim(3) (threshold in metres) -> Huber refinement on
    the inliers. ValueError when too few correspondences agree.
    """
    conf = {**DEFAULTS, **(conf or {})}
    if not anchors:
        raise ValueError("estimate_sfm_to_map: no anchor keyframe")
    src, dst, per = [], [], []
    for a in anchors:
        name, R_map, C_map = a[:3]
        K = a[3] if len(a) > 3 else None
        cor = project_structure(model, name, R_map, C_map, target, K, conf["max_depth_jump"])
        src.append(cor.src[cor.valid])
        dst.append(cor.dst[cor.valid])
        per.append({"name": name, "n_obs": len(cor.valid), "n_valid": int(cor.valid.sum()),
                    "n_empty": cor.n_empty, "n_edge": cor.n_edge})  # fmt: skip
        log.info("structure projection %s: %d observations, %d on the map (%d empty, %d edges)",
                 name, len(cor.valid), cor.valid.sum(), cor.n_empty, cor.n_edge)  # fmt: skip
    S, D = np.concatenate(src), np.concatenate(dst)
    th = float(conf["ransac_threshold_m"])
    sim0, inl = ransac_sim3(S, D, th, int(conf["ransac_max_iters"]), seed,
                            int(conf["min_inliers"]), method=conf["ransac_method"])  # fmt: skip
    sim = refine_sim3(S[inl], D[inl], sim0, loss="huber", scale=float(conf["huber_m"]))
    res = np.linalg.norm(sim.apply(S) - D, axis=1)
    inl = res < th
    if inl.sum() < int(conf["min_inliers"]):
        raise ValueError(f"estimate_sfm_to_map: {int(inl.sum())} inliers after refinement "
                         f"(need {conf['min_inliers']})")  # fmt: skip
    for a, p in zip(anchors, per, strict=True):
        i = model.index(a[0])
        R2, C2 = transform_pose(sim, model.R[i], model.C[i])
        p["centre_err_m"] = float(np.linalg.norm(C2 - np.asarray(a[2], float)))
        cosang = (np.trace(R2 @ np.asarray(a[1], float).T) - 1) / 2
        p["rot_err_deg"] = float(np.degrees(np.arccos(np.clip(cosang, -1, 1))))
    info = {
        "n_correspondences": len(S), "n_inliers": int(inl.sum()),
        "inlier_rms_m": float(np.sqrt(np.mean(res[inl] ** 2))),
        "inlier_median_m": float(np.median(res[inl])), "scale": sim.s,
        "rotation_deg": sim.rotation_deg(), "ransac_scale": sim0.s, "anchors": per,
    }  # fmt: skip
    log.info("SfM -> map Sim(3): %d/%d inliers, RMS %.2f m, scale %.4f", info["n_inliers"],
             len(S), info["inlier_rms_m"], sim.s)  # fmt: skip
    return sim, info
