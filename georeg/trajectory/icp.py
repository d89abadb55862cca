"""Rigid point-to-plane ICP of geo-registered SfM points onto the map (paper, after the Sim(3)).

The map target is a voxel-downsampled cloud (map ``PointCloud`` or a DSM window) with normals
from a hybrid KD-tree search. ICP runs in stages of decreasing correspondence distance with a
robust kernel, in a local frame centred on the source (UTM-sized coordinates would couple
rotation and translation). A correction that moves the points more than the configured bounds,
ends with too low a fitness, or hardly lowers the point-to-plane cost (flat roofs and ground
barely constrain horizontal motion: noise then drives the fit) is refused: identity plus reason.
"""

from __future__ import annotations

import logging
from typing import Any

import numpy as np

from georeg.frames.render import PointCloud, heightfield_cloud

log = logging.getLogger(__name__)

DEFAULTS: dict[str, Any] = {
    "voxel_m": 0.5,  # target downsampling
    "normal_radius_m": 2.0,  # hybrid KD-tree normal estimation: radius ...
    "normal_max_nn": 30,  # ... and at most this many neighbours
    "stages_m": [3.0, 1.0, 0.5],  # max correspondence distance per stage
    "max_iterations": 30,  # per stage
    "kernel": "tukey",  # tukey | huber | none
    "kernel_scale": 0.5,  # kernel parameter = this x the stage distance
    "max_shift_m": 5.0,  # refuse a correction moving any source (or guard) point further
    "max_rotation_deg": 2.0,  # refuse a correction rotating more
    "min_fitness": 0.2,  # refuse when fewer source points than this have a target (last stage)
    "min_gain": 0.1,  # refuse unless the truncated point-to-plane cost drops by this fraction
    "gain_cap_m": 1.0,  # truncation of that cost (residuals beyond count as this)
}


def dsm_points(dsm: np.ndarray, transform, walls: bool = True) -> np.ndarray:
    """(N, 3) points of a DSM window (pixel centres; ``transform`` affine, north-up), with wall
    points where the height jumps (as ``heightfield_cloud``) unless ``walls`` is False."""
    dsm = np.asarray(dsm, float)
    rgb = np.zeros((*dsm.shape, 3), np.uint8)
    cloud = heightfield_cloud(rgb, dsm, transform, wall_min_m=1.5 if walls else np.inf)
    return cloud.xyz


def _o3d_cloud(xyz: np.ndarray):
    import open3d as o3d

    pc = o3d.geometry.PointCloud()
    pc.points = o3d.utility.Vector3dVector(np.ascontiguousarray(xyz, dtype=np.float64))
    return pc


def icp_target(
    cloud: PointCloud | np.ndarray, origin: np.ndarray | None = None, conf: dict | None = None,
):  # fmt: skip
    """Open3D cloud of map points (``PointCloud`` or (N, 3)) minus ``origin``, voxel-downsampled,
    with normals (hybrid KD-tree search, oriented up)."""
    import open3d as o3d

    conf = {**DEFAULTS, **(conf or {})}
    xyz = cloud.xyz if isinstance(cloud, PointCloud) else np.asarray(cloud, float)
    if len(xyz) < 10:
        raise ValueError(f"icp_target: {len(xyz)} map points; need at least 10")
    o = np.zeros(3) if origin is None else np.asarray(origin, float)
    pc = _o3d_cloud(xyz - o).voxel_down_sample(float(conf["voxel_m"]))
    pc.estimate_normals(o3d.geometry.KDTreeSearchParamHybrid(
        radius=float(conf["normal_radius_m"]), max_nn=int(conf["normal_max_nn"])))  # fmt: skip
    pc.orient_normals_to_align_with_direction(np.array([0.0, 0.0, 1.0]))
    return pc


def _kernel(name: str, k: float):
    from open3d.pipelines import registration as reg

    if name == "tukey":
        return reg.TukeyLoss(k)
    if name == "huber":
        return reg.HuberLoss(k)
    if name == "none":
        return reg.L2Loss()
    raise ValueError(f"icp: unknown kernel {name!r} (tukey | huber | none)")


def _motion(T: np.ndarray, X: np.ndarray) -> tuple[float, float]:
    """(largest point displacement, rotation angle in degrees) of a local 4x4 rigid ``T``."""
    moved = X @ T[:3, :3].T + T[:3, 3]
    shift = float(np.max(np.linalg.norm(moved - X, axis=1))) if len(X) else 0.0
    ang = np.degrees(np.arccos(np.clip((np.trace(T[:3, :3]) - 1) / 2, -1.0, 1.0)))
    return shift, float(ang)


def plane_cost(X: np.ndarray, tgt, cap: float) -> float:
    """Mean of min(d, cap)^2, d = distance of each point to the plane of its nearest target point
    (``cap`` when that point is further than ``cap``)."""
    from scipy.spatial import cKDTree

    P = np.asarray(tgt.points)
    N = np.asarray(tgt.normals)
    dist, j = cKDTree(P).query(X, distance_upper_bound=cap)
    ok = np.isfinite(dist)
    d = np.full(len(X), cap)
    d[ok] = np.minimum(np.abs(np.einsum("ij,ij->i", X[ok] - P[j[ok]], N[j[ok]])), cap)
    return float(np.mean(d**2))


def icp_refine(
    src_xyz: np.ndarray, target: PointCloud | np.ndarray, conf: dict | None = None,
    guard_xyz: np.ndarray | None = None,
) -> tuple[np.ndarray, dict[str, Any]]:  # fmt: skip
    """Rigid 4x4 correction ``T`` (map frame: X' = T X) aligning ``src_xyz`` onto ``target``.

    ``guard_xyz``: points that must not move more than ``max_shift_m`` either (e.g. the camera
    centres: a small tilt of ground points swings cameras 100 m above by metres).
    Returns (T, info): fitness, inlier RMSE and truncated point-to-plane cost before/after, the
    motion, and ``accepted``/``reason``; a refused correction is the identity.
    """
    from open3d.pipelines import registration as reg

    conf = {**DEFAULTS, **(conf or {})}
    src = np.asarray(src_xyz, float)
    if src.ndim != 2 or src.shape[1] != 3 or len(src) < 10:
        raise ValueError(f"icp_refine: need (N >= 10, 3) source points, got {src.shape}")
    origin = src.mean(0)
    X = src - origin
    txyz = target.xyz if isinstance(target, PointCloud) else np.asarray(target, float)
    pad = 2 * max(conf["stages_m"]) + float(conf["normal_radius_m"])
    near = np.all((txyz >= src.min(0) - pad) & (txyz <= src.max(0) + pad), axis=1)
    tgt = icp_target(txyz[near], origin, conf)
    source = _o3d_cloud(X)
    stages = [float(d) for d in conf["stages_m"]]
    before = reg.evaluate_registration(source, tgt, stages[-1], np.eye(4))
    T = np.eye(4)
    crit = reg.ICPConvergenceCriteria(relative_fitness=1e-7, relative_rmse=1e-7,
                                      max_iteration=int(conf["max_iterations"]))  # fmt: skip
    for d in stages:
        est = reg.TransformationEstimationPointToPlane(
            _kernel(conf["kernel"], float(conf["kernel_scale"]) * d)
        )
        T = np.asarray(reg.registration_icp(source, tgt, d, T, est, crit).transformation)
    after = reg.evaluate_registration(source, tgt, stages[-1], T)
    shift, ang = _motion(T, X)
    guard = np.zeros((0, 3)) if guard_xyz is None else np.asarray(guard_xyz, float).reshape(-1, 3)
    gshift = _motion(T, guard - origin)[0]
    cap = float(conf["gain_cap_m"])
    c0, c1 = plane_cost(X, tgt, cap), plane_cost(X @ T[:3, :3].T + T[:3, 3], tgt, cap)
    gain = 1.0 - c1 / c0 if c0 > 0 else 0.0
    info: dict[str, Any] = {
        "n_source": len(src), "n_target": len(tgt.points), "fitness_before": before.fitness,
        "rmse_before_m": before.inlier_rmse, "fitness": after.fitness,
        "rmse_after_m": after.inlier_rmse, "max_shift_m": shift, "max_guard_shift_m": gshift,
        "rotation_deg": ang, "translation_m": float(np.linalg.norm(T[:3, 3])), "cost_before": c0,
        "cost_after": c1, "gain": gain, "accepted": True, "reason": "",
    }  # fmt: skip
    if max(shift, gshift) > float(conf["max_shift_m"]):
        what = "guard points" if gshift > shift else "points"
        info["reason"] = (f"moves {what} by {max(shift, gshift):.2f} m > max_shift_m "
                          f"{conf['max_shift_m']}")  # fmt: skip
    elif ang > float(conf["max_rotation_deg"]):
        info["reason"] = f"rotates by {ang:.2f} deg > max_rotation_deg {conf['max_rotation_deg']}"
    elif after.fitness < float(conf["min_fitness"]):
        info["reason"] = f"fitness {after.fitness:.2f} < min_fitness {conf['min_fitness']}"
    elif gain < float(conf["min_gain"]):
        info["reason"] = f"point-to-plane cost gain {gain:.1%} < min_gain {conf['min_gain']:.0%}"
    if info["reason"]:
        info["accepted"] = False
        log.info("ICP refused: %s", info["reason"])
        return np.eye(4), info
    # back to the map frame: X' = R (X - o) + t + o
    M = np.eye(4)
    M[:3, :3] = T[:3, :3]
    M[:3, 3] = T[:3, 3] + origin - T[:3, :3] @ origin
    log.info("ICP: fitness %.2f -> %.2f, RMSE %.3f -> %.3f m, shift <= %.2f m, %.2f deg",
             before.fitness, after.fitness, before.inlier_rmse, after.inlier_rmse, shift, ang)  # fmt: skip
    return M, info
