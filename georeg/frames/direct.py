"""Direct 2-D/3-D matching of a frame against the geo-referenced map, and the pose verification.

Direct path: around a start pose (the coarse location), the map window under the frame's
footprint is re-extracted densely (``DenseWindow``: SIFT on the orthophoto at about the frame's
ground sampling, z of every keypoint from the DSM, or a flat ground), the frame's SIFT features
(at a scale whose GSD is about the map's) are 2-NN ratio matched against it, and a PnP in RANSAC
(USAC MAGSAC++) + Levenberg-Marquardt gives the pose. Both sides rotation-invariant: the map
may be in any orientation to the frame.

Verification: one score for every pose hypothesis of a frame, whichever path produced it.
Guided matching (``guided_matches``): the map features of the window are projected with the
pose, each frame keypoint takes the nearest descriptor among those within ``tol_px``, kept when
distinct (ratio test among them and against its second-nearest in the whole window). A
hypothesis is first polished (``polish``: LM on its guided matches, re-predicted per round), then
its score is the number of distinct frame keypoints whose guided match reprojects within
``tol_px``. Every hypothesis of a place is scored on the same frame and map features, so scores
compare; ``chance`` is the count expected from the window's ratio matches scattered uniformly
over the frame (the a-contrario reference).
"""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass, field
from typing import Any

import cv2
import numpy as np

from georeg.frames.coarse import DenseWindow, plausible
from georeg.frames.outputs import footprint_xy
from georeg.frames.pnp import FrameFeatures, PnPResult, frame_features, solve_pnp
from georeg.frames.render import PinholeCamera

log = logging.getLogger(__name__)

DEFAULTS: dict[str, Any] = {
    "ratio": 0.8,  # 2-NN ratio frame -> map window
    "reproj_px": 4.0,  # RANSAC threshold (full-resolution frame pixels), at least
    "max_iters": 10000,
    "margin_frac": 0.25,  # map window: the footprint grown by this x its extent ...
    "margin_m": 120.0,  # ... and at least this
    "max_window_px": 16_000_000,  # map window read decimated above this
    "gsd_factor": 1.0,  # frame matched at about this x the map GSD (never upsampled)
    "whole_map_px": 16_000_000,  # no verified pose from the coarse starts: the whole map when smaller
    "whole_map_first_px": 4_000_000,  # known camera, map smaller: the whole map before the coarse step
    "verify_px": 3.0,  # verification tolerance (full-resolution frame pixels), at least
    "polish_rounds": 3,  # LM rounds on the guided matches of a hypothesis before its score
    "polish_distinct": True,  # polish on guided matches that are also window-wide nearest
    "seed": 0,
}


@dataclass
class DirectResult:
    pnp: PnPResult
    info: dict[str, Any] = field(default_factory=dict)


def ground_distance(cam: PinholeCamera, z_ground: float) -> float:
    """Distance along the optical axis from the camera to the plane z = z_ground."""
    down = max(-float(np.asarray(cam.R)[2, 2]), 0.2)  # cos(off-nadir), floored at ~78 deg
    return max(float(cam.C[2]) - z_ground, 1.0) / down


class Matches:
    """The frame's features and the dense map features of one window: ``uv`` <-> ``xyz`` are the
    2-NN ratio matches (frame keypoints ``qi``); ``d2`` the second-nearest descriptor distance of
    every frame keypoint in the whole window (the distinctiveness reference of guided matching)."""

    def __init__(self, win: DenseWindow, ff: FrameFeatures, d2: np.ndarray, uv: np.ndarray,
                 xyz: np.ndarray, qi: np.ndarray) -> None:  # fmt: skip
        self.win, self.ff, self.d2, self.uv, self.xyz, self.qi = win, ff, d2, uv, xyz, qi
        self.map_xyz = np.c_[win.xy, win.z] if len(win) else np.zeros((0, 3))

    @property
    def n_frame(self) -> int:
        return len(self.ff.xy)

    def contains(self, xy: np.ndarray) -> bool:
        b = self.win.bounds
        return bool(b[0] <= xy[0] <= b[2] and b[1] <= xy[1] <= b[3])


def match_window(gray: np.ndarray, cam: PinholeCamera, ortho: str, dsm: str | None, feat_conf: dict,
                 map_gsd: float, z_ground: float, conf: dict, flat_z: float = 0.0,
                 bounds: tuple | None = None, scale: float | None = None,
                 cache: dict | None = None) -> Matches:  # fmt: skip
    """Ratio matches of the frame (at about the map's GSD) against the dense map features of the
    window under the footprint of ``cam`` (grown by ``margin_frac`` / ``margin_m``). ``bounds``
    and ``scale`` given (no pose known): that map window at its own GSD, the frame at that scale.
    ``cache``: dense windows kept by (bounds, GSD, features) for the next frame of a set."""
    c = {**DEFAULTS, **(conf or {})}
    fconf = {**(feat_conf or {}), "upright": False, "max_features_per_mpx": None}
    if bounds is None:
        gsd_frame = ground_distance(cam, z_ground) / cam.fx
        s = float(np.clip(gsd_frame / (float(c["gsd_factor"]) * map_gsd), 0.05, 1.0))
        fp = footprint_xy(cam, z_ground)
        lo, hi = fp.min(axis=0), fp.max(axis=0)
        m = max(float(c["margin_m"]), float(c["margin_frac"]) * float(np.max(hi - lo)))
        bounds = (lo[0] - m, lo[1] - m, hi[0] + m, hi[1] + m)
        wgsd = max(map_gsd, 0.5 * gsd_frame)
    else:
        s, wgsd = float(scale or 1.0), None
    ff = frame_features(gray, s, fconf)
    key = (ortho, dsm, tuple(bounds), wgsd, int(c["max_window_px"]), flat_z, repr(sorted(fconf.items())))  # fmt: skip
    win = cache.get(key) if cache is not None else None
    if win is None:
        win = DenseWindow(ortho, dsm, bounds, fconf, gsd=wgsd, max_px=int(c["max_window_px"]),
                          flat_z=flat_z)  # fmt: skip
        if cache is not None:
            cache[key] = win
    if len(win) < 2 or len(ff.xy) == 0:
        e = np.zeros(0, np.int64)
        return Matches(win, ff, np.full(len(ff.xy), np.inf), np.zeros((0, 2)), np.zeros((0, 3)), e)
    d, fid = win.knn(ff.desc, np.arange(len(win)), k=2)
    ok = (fid[:, 1] >= 0) & (d[:, 0] < float(c["ratio"]) * d[:, 1])
    qi, mi, dd = np.flatnonzero(ok), fid[ok, 0], d[ok, 0]
    order = np.lexsort((dd, mi))  # one frame keypoint per map keypoint (the closest)
    first = np.ones(len(order), bool)
    first[1:] = mi[order][1:] != mi[order][:-1]
    qi, mi = qi[order[first]], mi[order[first]]
    xyz = np.c_[win.xy[mi], win.z[mi]]
    good = np.isfinite(xyz).all(axis=1)
    log.info("direct: frame scale %.2f, %d frame / %d map features (window %.0f x %.0f m at %.2f m), "
             "%d matches", s, len(ff.xy), len(win), bounds[2] - bounds[0], bounds[3] - bounds[1],
             win.gsd, int(good.sum()))  # fmt: skip
    return Matches(win, ff, np.where(fid[:, 1] >= 0, d[:, 1], np.inf), ff.xy[qi[good]], xyz[good],
                   qi[good])  # fmt: skip


def guided_matches(mt: Matches, cam: PinholeCamera, radius: float, ratio: float = 0.9,
                   distinct: bool = True) -> tuple[np.ndarray, np.ndarray]:  # fmt: skip
    """Matches predicted by the pose ``cam``: each frame keypoint takes the nearest descriptor
    among the map features projecting within ``radius`` px, kept when it passes a ratio test
    against the second of those and (``distinct``) is the keypoint's nearest in the whole window
    (closer than its second-nearest); one frame keypoint per map feature. Returns (frame keypoint
    ids, map feature ids)."""
    from scipy.spatial import cKDTree

    e = np.zeros(0, np.int64)
    if len(mt.map_xyz) == 0 or mt.n_frame == 0:
        return e, e
    uv, z = cam.project(mt.map_xyz)
    ok = (z > 0) & np.isfinite(uv).all(axis=1)
    ok &= (uv[:, 0] > -radius) & (uv[:, 0] < cam.width + radius)
    ok &= (uv[:, 1] > -radius) & (uv[:, 1] < cam.height + radius)
    mi = np.flatnonzero(ok)
    if not len(mi):
        return e, e
    near = cKDTree(mt.ff.xy).query_ball_point(uv[mi], radius)
    cnt = np.fromiter((len(n) for n in near), np.int64, len(near))
    if not cnt.sum():
        return e, e
    qa = np.concatenate([np.asarray(n, np.int64) for n in near])
    ma = np.repeat(mi, cnt)
    d = np.linalg.norm(mt.ff.desc[qa] - mt.win.desc[ma], axis=1)
    o = np.lexsort((d, qa))
    qa, ma, d = qa[o], ma[o], d[o]
    idx = np.flatnonzero(np.r_[True, qa[1:] != qa[:-1]])  # best candidate per frame keypoint
    nxt = idx + 1
    has2 = nxt < len(qa)
    has2[has2] &= qa[nxt[has2]] == qa[idx[has2]]
    d2 = np.full(len(idx), np.inf)
    d2[has2] = d[nxt[has2]]
    keep = (d[idx] < ratio * d2) & ((d[idx] < mt.d2[qa[idx]]) | (not distinct))
    q, m, dd = qa[idx[keep]], ma[idx[keep]], d[idx[keep]]
    if not len(q):
        return e, e
    o = np.lexsort((dd, m))
    f = np.r_[True, m[o][1:] != m[o][:-1]]
    return q[o[f]], m[o[f]]


def polish(mt: Matches, cam: PinholeCamera, tol_px: float, rounds: int = 3,
           distinct: bool = True) -> PinholeCamera:  # fmt: skip
    """Levenberg-Marquardt on the guided matches of the pose, radius 2 ``tol_px`` then
    ``tol_px``, matches re-predicted every round; the pose unchanged when too few."""
    for k in range(rounds):
        r = tol_px * (2.0 if k == 0 else 1.0)
        q, m = guided_matches(mt, cam, r, distinct=distinct)
        if len(q) < 6:
            break
        uv, xyz = mt.ff.xy[q], mt.map_xyz[m]
        err = np.linalg.norm(cam.project(xyz)[0] - uv, axis=1)
        sel = err < r
        if sel.sum() < 6:
            break
        o = xyz[sel].mean(axis=0)
        R = np.asarray(cam.R, float)
        rvec, tvec = cv2.Rodrigues(R)[0], (-R @ (np.asarray(cam.C) - o)).reshape(3, 1)
        rvec, tvec = cv2.solvePnPRefineLM(np.ascontiguousarray(xyz[sel] - o), np.ascontiguousarray(uv[sel]),
                                          cam.K, None, rvec, tvec)  # fmt: skip
        R2 = cv2.Rodrigues(rvec)[0]
        cam = cam.with_pose(R2, -R2.T @ tvec.ravel() + o)
    return cam


def direct_pose(gray: np.ndarray, cam0: PinholeCamera, ortho: str, dsm: str | None, feat_conf: dict,
                map_gsd: float, z_ground: float, conf: dict | None = None, flat_z: float = 0.0,
                bounds: tuple | None = None, scale: float | None = None, cache: dict | None = None,
                ) -> tuple[DirectResult, Matches]:  # fmt: skip
    """PnP (MAGSAC++ + LM) on the direct matches in the map window around ``cam0`` (or in
    ``bounds``, the frame at ``scale``: only ``cam0``'s intrinsics are used then)."""
    c = {**DEFAULTS, **(conf or {})}
    t0 = time.perf_counter()
    mt = match_window(gray, cam0, ortho, dsm, feat_conf, map_gsd, z_ground, c, flat_z, bounds, scale,
                      cache)  # fmt: skip
    thr = float(c["reproj_px"])
    if bounds is None:
        gsd_frame = ground_distance(cam0, z_ground) / cam0.fx
        thr = max(thr, 2.0 * map_gsd / max(gsd_frame, 1e-9))
    res = solve_pnp(mt.xyz, mt.uv, cam0.K, thr, int(c["max_iters"]), int(c["seed"]))
    why = plausible(res.R, res.C, mt.xyz) if res.ok else "PnP failed"
    if why:
        res.ok = False
    info = {"matches": len(mt.uv), "inliers": int(res.inliers), "threshold_px": thr,
            "map_features": len(mt.win), "window_gsd_m": mt.win.gsd, "reason": why,
            "seconds": time.perf_counter() - t0}  # fmt: skip
    return DirectResult(res, info), mt


def verification_tolerance(cam: PinholeCamera, map_gsd: float, z_ground: float,
                           verify_px: float) -> float:  # fmt: skip
    """Full-resolution frame pixels: ``verify_px``, or 1.5 map pixels seen from the frame."""
    gsd_frame = ground_distance(cam, z_ground) / cam.fx
    return max(float(verify_px), 1.5 * map_gsd / max(gsd_frame, 1e-9))


def verify(mt: Matches, cam: PinholeCamera, tol_px: float) -> dict[str, Any]:
    """Score of the pose ``cam``: distinct frame keypoints whose guided match (``guided_matches``
    within ``tol_px``) reprojects within ``tol_px``; with the RMS of those residuals and the
    count expected by chance (the window's ratio matches scattered uniformly over the frame)."""
    q, m = guided_matches(mt, cam, tol_px)
    chance = len(mt.uv) * np.pi * tol_px**2 / float(cam.width * cam.height)
    out = {"score": 0, "rms_px": None, "tolerance_px": float(tol_px), "chance": float(chance),
           "matches": int(len(mt.uv)), "frame_features": mt.n_frame}  # fmt: skip
    if len(q):
        err = np.linalg.norm(cam.project(mt.map_xyz[m])[0] - mt.ff.xy[q], axis=1)
        ok = err < tol_px
        out["score"] = int(len(np.unique(q[ok])))
        out["rms_px"] = float(np.sqrt(np.mean(err[ok] ** 2))) if ok.any() else None
    return out
