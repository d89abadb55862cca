"""Focal length estimation inside the render-match-PnP stage, for ``camera: null``.

The coarse step only picks the best of a few focal candidates (``focal_factors``), off by up to
~15 %: the PnP then absorbs the error into the camera height. Here the inlier 2-D/3-D
correspondences of the render stage (3-D from the depth buffer, valid whatever the focal) give
the focal length: a robust least squares of the reprojection error over the pose and
log(f) (fx = fy, principal point at the centre), then the render stage runs again with that
focal, until it moves less than ``tol`` (relative; then the joint fit's focal and pose are
kept). The focal and the camera distance are separable only through the depth spread of the
inliers (relief, an oblique view): over flat ground seen at nadir they are not, and the fit's
standard deviation of the focal (``fx_rel_sigma``, from the Jacobian) says so.
"""

from __future__ import annotations

import dataclasses
import logging
from typing import Any

import cv2
import numpy as np
from scipy.optimize import least_squares

from georeg.frames.pnp import PnPResult, register_by_rendering
from georeg.frames.render import PinholeCamera, PointCloud

log = logging.getLogger(__name__)


def _fit_pose_focal(xyz: np.ndarray, uv: np.ndarray, cam: PinholeCamera, loss_px: float,
                    with_k1: bool, max_nfev: int) -> tuple[np.ndarray, np.ndarray, float, float]:  # fmt: skip
    """Robust least squares of the reprojection error over the pose, log f (fx = fy) and, with
    ``with_k1``, OpenCV's first radial term; principal point kept. Returns (parameters:
    rotation vector, centre - origin, log f[, k1]; origin; RMS px; relative sigma of f)."""
    o = xyz.mean(axis=0)
    X = np.asarray(xyz, float) - o
    r0 = cv2.Rodrigues(np.asarray(cam.R, float))[0].ravel()
    x0 = np.r_[r0, np.asarray(cam.C, float) - o, np.log(cam.fx), [0.0] if with_k1 else []]

    def resid(p: np.ndarray) -> np.ndarray:
        R = cv2.Rodrigues(p[:3])[0]
        Xc = (X - p[3:6]) @ R.T
        z = np.where(np.abs(Xc[:, 2]) < 1e-6, 1e-6, Xc[:, 2])
        x, y = Xc[:, 0] / z, Xc[:, 1] / z
        d = 1.0 + p[7] * (x * x + y * y) if with_k1 else 1.0
        f = np.exp(p[6])
        return np.r_[f * x * d + cam.cx - uv[:, 0], f * y * d + cam.cy - uv[:, 1]]

    sol = least_squares(resid, x0, loss="huber", f_scale=loss_px, x_scale="jac", max_nfev=max_nfev)
    r = resid(sol.x).reshape(2, -1)
    rms = float(np.sqrt(np.mean(np.sum(r**2, axis=0))))
    dof = max(1, r.size - len(sol.x))
    cov = np.linalg.pinv(sol.jac.T @ sol.jac) * float(np.sum(r**2)) / dof
    return sol.x, o, rms, float(np.sqrt(max(cov[6, 6], 0.0)))  # sigma of log f = relative


def refine_focal(
    xyz: np.ndarray, uv: np.ndarray, cam: PinholeCamera, loss_px: float = 2.0
) -> tuple[float, np.ndarray, np.ndarray, float, float]:
    """(f, R, C, RMS px, relative standard deviation of f) minimising the robust reprojection
    error of ``xyz`` -> ``uv`` over the pose and f (fx = fy), from ``cam``; principal point
    kept."""
    p, o, rms, sigma = _fit_pose_focal(xyz, uv, cam, loss_px, False, 200)
    return float(np.exp(p[6])), cv2.Rodrigues(p[:3])[0], p[3:6] + o, rms, sigma


def estimate_focal(
    gray: np.ndarray, res: PnPResult, cam: PinholeCamera, cloud: PointCloud, map_gsd: float,
    feat_conf: dict | None, pnp_conf: dict | None, rounds: int = 4, tol: float = 0.005,
    bounds: tuple[float, float] = (0.3, 3.0),
) -> tuple[PnPResult, PinholeCamera, dict[str, Any]]:  # fmt: skip
    """Alternate focal refinement on the inliers and the render stage at that focal.

    ``res`` is the render stage's result at ``cam`` (its focal). A round's result is kept when it
    is ``ok`` and keeps at least 0.6 x the previous inliers; the focal stays within ``bounds`` x
    the image width. Returns (result, camera with the final focal and pose, info)."""
    w = cam.width
    info: dict[str, Any] = {"start_fx": float(cam.fx), "rounds": []}
    for _ in range(int(rounds)):
        if res.inlier_xyz is None or len(res.inlier_xyz) < 8:
            break
        f, R, C, rms, sig = refine_focal(res.inlier_xyz, res.inlier_uv, cam.with_pose(res.R, res.C))
        f = float(np.clip(f, bounds[0] * w, bounds[1] * w))
        step: dict[str, Any] = {"fx": f, "lsq_rms_px": rms, "fx_rel_sigma": sig}
        info["fx_rel_sigma"] = sig
        info["rounds"].append(step)
        if abs(f / cam.fx - 1) < tol:  # adopt the joint fit (same inliers)
            step["converged"] = True
            cam = dataclasses.replace(cam, fx=f, fy=f)
            res = dataclasses.replace(res, R=R, C=np.asarray(C, float), reprojection_px=rms)
            break
        cam_f = dataclasses.replace(cam, fx=f, fy=f, R=R, C=np.asarray(C, float))
        new = register_by_rendering(gray, cam_f, cloud, map_gsd, feat_conf, pnp_conf)
        step.update(inliers=int(new.inliers), reprojection_px=float(new.reprojection_px))
        log.info("focal %.1f -> %.1f px: %d inliers (was %d)", cam.fx, f, new.inliers, res.inliers)
        if not new.ok or new.inliers < 0.6 * res.inliers:
            step["kept"] = False
            break
        step["kept"] = True
        res, cam = new, cam_f.with_pose(new.R, new.C)
    info["fx"] = float(cam.fx)
    if info.get("fx_rel_sigma", 0.0) > 0.05:
        log.warning("focal %.0f px poorly determined (+-%.0f %%): flat or distant inliers",
                    cam.fx, 100 * info["fx_rel_sigma"])  # fmt: skip
    return res, cam.with_pose(res.R, res.C), info


def focal_from_matches(xyz: np.ndarray, uv: np.ndarray, width: int, height: int,
                       factors: list[float], reproj_px: float, seed: int = 0,
                       max_iters: int = 5000, max_sigma: float = 0.05) -> dict[str, Any] | None:  # fmt: skip
    """Unknown camera: the focal from 2-D/3-D matches that do not depend on it (the frame's
    features matched to the map's geo-referenced ones). PnP at fx = each factor x ``width``
    (principal point at the centre), the most inliers wins; then pose and focal are fitted on
    its inliers (``refine_focal``) and the fit is kept when its relative sigma is below
    ``max_sigma`` (relief or an oblique view determine it; a flat nadir view does not). Returns
    ``{"fx", "searched_fx", "inliers", "fx_rel_sigma", "fitted"}`` or None (no PnP)."""
    from georeg.frames.pnp import solve_pnp

    best = None
    for fac in factors:
        f = float(fac) * width
        K = np.array([[f, 0, (width - 1) / 2], [0, f, (height - 1) / 2], [0, 0, 1]], float)
        res = solve_pnp(xyz, uv, K, reproj_px, max_iters, seed)
        if res.ok and (best is None or res.inliers > best[1].inliers):
            best = (f, res)
    if best is None or best[1].inlier_xyz is None or len(best[1].inlier_xyz) < 12:
        return None
    f0, res = best
    cam = PinholeCamera(f0, f0, (width - 1) / 2, (height - 1) / 2, width, height, res.R, res.C)
    f, k1, rms, sig = refine_focal_k1(res.inlier_xyz, res.inlier_uv, cam)
    fitted = bool(np.isfinite(f) and sig < max_sigma and 0.3 * width <= f <= 3.0 * width
                  and abs(k1) < 0.5)  # fmt: skip
    return {"fx": f if fitted else f0, "k1": k1 if fitted else 0.0, "searched_fx": f0,
            "inliers": int(res.inliers), "fx_rel_sigma": float(sig), "lsq_rms_px": float(rms),
            "fitted": fitted}  # fmt: skip


def refine_focal_k1(xyz: np.ndarray, uv: np.ndarray, cam: PinholeCamera, loss_px: float = 2.0
                    ) -> tuple[float, float, float, float]:  # fmt: skip
    """(f, k1, RMS px, relative sigma of f): ``refine_focal`` with the first radial distortion
    term k1 fitted too (normalised coordinates). An uncalibrated lens bends the image enough
    (k1 ~ -0.26 on a DJI FC6310 frame) to move a focal fitted without it by a third."""
    p, _, rms, sigma = _fit_pose_focal(xyz, uv, cam, loss_px, True, 400)
    return float(np.exp(p[6])), float(p[7]), rms, sigma
