"""2-D/3-D registration of one frame: render around the estimate, match, PnP, iterate.

As in the seed paper (Bodensteiner et al., section 2 (B)): several views of the textured map are
rendered around the current pose (a star pattern: the pose itself, and moves sideways and along
the viewing axis), the frame's features are matched against every render (2-NN ratio test per
render), each matched render keypoint gets its 3-D point from the render's depth buffer, and all
2-D/3-D correspondences are pooled into one PnP in RANSAC (OpenCV USAC MAGSAC++), polished by
Levenberg-Marquardt on the reprojection error of the inliers. Render -> match -> PnP repeats
while the inlier count grows or the pose still moves.

The frame is matched at a reduced resolution whose ground sampling is about
``match_gsd_factor`` x the map's (a 1 m orthophoto holds no detail of a 0.15 m drone frame).
"""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass, field
from typing import Any

import cv2
import numpy as np

from georeg.frames.render import PinholeCamera, PointCloud, render
from georeg.index.features import detect_and_describe
from georeg.register.matching import usac_params

log = logging.getLogger(__name__)

DEFAULTS: dict[str, Any] = {
    "star_step": 0.15,  # star move as a fraction of the distance to the scene centre
    "star_views": 5,  # 1 = the pose only; 5 = pose + left/right/forward/back
    "ratio": 0.8,  # 2-NN ratio per render
    "reproj_px": 4.0,  # RANSAC inlier threshold (full-resolution frame pixels)
    "max_iters": 5000,
    "iterations": 5,  # render -> match -> PnP rounds at most
    "match_gsd_factor": 0.5,  # frame matched at this x the map GSD (0.5: twice finer than the map)
    "min_inliers": 15,
    "upright": True,  # upright SIFT: frame and renders share the orientation (paper: best)
    "max_features_per_mpx": None,  # no cap on the frame / render features
    "converged_frac": 0.01,  # stop when the pose moved less than this x the scene distance
    "seed": 0,
}


@dataclass
class PnPResult:
    ok: bool
    R: np.ndarray | None = None
    C: np.ndarray | None = None
    inliers: int = 0
    matches: int = 0
    reprojection_px: float = float("nan")
    history: list[dict] = field(default_factory=list)
    inlier_uv: np.ndarray | None = None
    inlier_xyz: np.ndarray | None = None


def solve_pnp(xyz: np.ndarray, uv: np.ndarray, K: np.ndarray, reproj_px: float, max_iters: int = 5000,
              seed: int = 0, origin: np.ndarray | None = None) -> PnPResult:  # fmt: skip
    """PnP in USAC MAGSAC++ then LM on the inliers. World points are shifted by ``origin`` (the
    mean by default) for conditioning; the returned C is in world coordinates."""
    n = len(xyz)
    if n < 6:
        return PnPResult(False, matches=n)
    o = np.mean(xyz, axis=0) if origin is None else np.asarray(origin, float)
    obj = np.ascontiguousarray(xyz - o, np.float64)
    img = np.ascontiguousarray(uv, np.float64)
    params = usac_params("magsac", reproj_px, 0.9999, max_iters, seed)
    try:
        ok, _, rvec, tvec, inl = cv2.solvePnPRansac(obj, img, K, None, params=params)
    except cv2.error as exc:
        log.debug("PnP RANSAC failed: %s", exc)
        return PnPResult(False, matches=n)
    if not ok or inl is None or len(inl) < 6:
        return PnPResult(False, matches=n)
    inl = inl.ravel()
    rvec, tvec = cv2.solvePnPRefineLM(obj[inl], img[inl], K, None, rvec, tvec)
    proj = cv2.projectPoints(obj, rvec, tvec, K, None)[0].reshape(-1, 2)
    err = np.linalg.norm(proj - img, axis=1)
    keep = np.flatnonzero(err < reproj_px)
    if len(keep) >= 6:
        rvec, tvec = cv2.solvePnPRefineLM(obj[keep], img[keep], K, None, rvec, tvec)
        proj = cv2.projectPoints(obj, rvec, tvec, K, None)[0].reshape(-1, 2)
        err = np.linalg.norm(proj - img, axis=1)
        keep = np.flatnonzero(err < reproj_px)
    R = cv2.Rodrigues(rvec)[0]
    C = -R.T @ tvec.ravel() + o
    # points must lie in front of the camera
    front = ((xyz[keep] - C) @ R.T)[:, 2] > 0
    keep = keep[front]
    rms = float(np.sqrt(np.mean(err[keep] ** 2))) if len(keep) else float("nan")
    return PnPResult(
        len(keep) >= 6, R, C, len(keep), n, rms, inlier_uv=uv[keep], inlier_xyz=xyz[keep]
    )


@dataclass
class FrameFeatures:
    """Frame features at the matching scale, positions in full-resolution (undistorted) pixels."""

    xy: np.ndarray
    desc: np.ndarray
    scale: float


def frame_features(gray: np.ndarray, scale: float, conf: dict | None) -> FrameFeatures:
    s = float(np.clip(scale, 0.05, 1.0))
    img = cv2.resize(gray, None, fx=s, fy=s, interpolation=cv2.INTER_AREA) if s < 1 else gray
    f = detect_and_describe(img, None, conf or {})
    xy = (f.xy.astype(np.float64) + 0.5) / s - 0.5
    return FrameFeatures(xy, f.desc.astype(np.float32), s)


def star_poses(R: np.ndarray, C: np.ndarray, dist: float, step: float, n: int) -> list[np.ndarray]:
    """Camera centres of the star pattern: C, then +-x (sideways) and +-z (along the axis)."""
    moves = [np.zeros(3)]
    if n > 1:
        d = step * dist
        ax = [R[0], -R[0], R[2], -R[2], R[1], -R[1]]
        moves += [d * a for a in ax[: n - 1]]
    return [C + m for m in moves]


def _ratio_knn(qd: np.ndarray, md: np.ndarray, ratio: float) -> tuple[np.ndarray, np.ndarray]:
    import faiss

    if len(md) < 2 or len(qd) == 0:
        return np.zeros(0, np.int64), np.zeros(0, np.int64)
    ix = faiss.IndexFlatL2(md.shape[1])
    ix.add(np.ascontiguousarray(md, np.float32))
    d, i = ix.search(np.ascontiguousarray(qd, np.float32), 2)
    ok = np.sqrt(np.maximum(d[:, 0], 0)) < ratio * np.sqrt(np.maximum(d[:, 1], 0))
    q = np.flatnonzero(ok)
    return q, i[ok, 0].astype(np.int64)


def scene_distance(cam: PinholeCamera, cloud: PointCloud) -> float:
    """Depth of the scene at the image centre (median depth of the points near the axis)."""
    r = render(cloud, cam.scaled(min(1.0, 160 / cam.width)))
    d = r.depth[np.isfinite(r.depth)]
    return float(np.median(d)) if d.size else float(cam.C[2] - np.median(cloud.xyz[:, 2]))


def register_by_rendering(
    gray: np.ndarray, cam0: PinholeCamera, cloud: PointCloud, map_gsd: float, feat_conf: dict | None,
    conf: dict | None = None,
) -> PnPResult:  # fmt: skip
    """Iterate render -> match -> PnP from the initial camera ``cam0`` (full-resolution K)."""
    c = {**DEFAULTS, **(conf or {})}
    feat_conf = {**(feat_conf or {}), "upright": bool(c["upright"]),
                 "max_features_per_mpx": c["max_features_per_mpx"]}  # fmt: skip
    K = cam0.K
    cam = cam0
    best = PnPResult(False)
    history = []
    ff_cache: dict[float, FrameFeatures] = {}
    for it in range(int(c["iterations"])):
        t0 = time.perf_counter()
        dist = scene_distance(cam, cloud)
        gsd_frame = dist / cam.fx
        s = float(np.clip(gsd_frame / (c["match_gsd_factor"] * map_gsd), 0.1, 1.0))
        s = min(1.0, float(2.0 ** (np.round(np.log2(s) * 2) / 2)))  # few distinct scales
        if s not in ff_cache:
            ff_cache[s] = frame_features(gray, s, feat_conf)
        ff = ff_cache[s]
        rcam = cam.scaled(s)
        uv_all, xyz_all = [], []
        for Cs in star_poses(cam.R, cam.C, dist, float(c["star_step"]), int(c["star_views"])):
            rc = rcam.with_pose(cam.R, Cs)
            r = render(cloud, rc)
            f = detect_and_describe(r.gray(), r.mask, feat_conf or {})
            if len(f) < 2:
                continue
            qi, mi = _ratio_knn(ff.desc, f.desc.astype(np.float32), float(c["ratio"]))
            xyz, ok = r.points_at(f.xy[mi].astype(np.float64))
            uv_all.append(ff.xy[qi[ok]])
            xyz_all.append(xyz[ok])
        if not uv_all:
            break
        uv = np.concatenate(uv_all)
        xyz = np.concatenate(xyz_all)
        res = solve_pnp(xyz, uv, K, float(c["reproj_px"]), int(c["max_iters"]), int(c["seed"]) + it)
        if res.inlier_uv is not None and len(res.inlier_uv):
            # a frame keypoint matched in several renders counts once (distinct support)
            res.inliers = int(len(np.unique(np.round(res.inlier_uv, 3), axis=0)))
        step = {"iteration": it, "scale": s, "matches": len(uv), "inliers": res.inliers,
                "reprojection_px": res.reprojection_px, "seconds": time.perf_counter() - t0}  # fmt: skip
        if res.ok:
            step["moved_m"] = float(np.linalg.norm(res.C - cam.C))
        history.append(step)
        log.info("render-match-PnP %d: scale %.2f, %d matches, %d inliers, rms %.2f px (%.1f s)", it, s,
                 len(uv), res.inliers, res.reprojection_px, step["seconds"])  # fmt: skip
        # renders centred on a better pose see the frame better, but inlier counts of renders at
        # different poses are not comparable: adopt the new pose unless the support collapsed
        if not res.ok or res.inliers < 0.6 * best.inliers:
            break
        if it == 0 and res.inliers < 0.5 * int(c["min_inliers"]):
            best = res  # a wrong start: do not iterate
            break
        moved = float(np.linalg.norm(res.C - cam.C))
        best = res
        cam = cam.with_pose(res.R, res.C)
        if moved < float(c["converged_frac"]) * dist:
            break
    best.history = history
    best.ok = best.ok and best.inliers >= int(c["min_inliers"])
    return best
