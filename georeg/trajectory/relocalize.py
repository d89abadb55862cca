"""Every video frame located against the geo-registered 3-D feature map.

Two ways, as in the seed paper (Bodensteiner et al., section 3):

* ``Tracker``: the SfM points observed in the last keyframe (already in the map CRS) are tracked
  frame to frame with pyramidal Lucas-Kanade (forward-backward checked); every frame gets a PnP
  (USAC MAGSAC++ then Levenberg-Marquardt) on the tracked 2-D / 3-D pairs. The 3-D points are
  fixed in the map, so the poses do not drift; only the 2-D tracks age, and they are renewed at
  each keyframe.
* ``PointMapLocalizer``: relocalisation by 2-D / 3-D matching of the frame's SIFT (COLMAP's own
  extractor, so the descriptors are those of the map) against the map points' descriptors, guided
  by a prior pose (only points projecting into the prior view are candidates), then PnP. Used
  when tracking is lost, and to place a frame with no keyframe before it.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from typing import Any

import cv2
import numpy as np

from georeg.frames.feature_map import colmap_sift
from georeg.frames.pnp import solve_pnp
from georeg.frames.render import PinholeCamera

log = logging.getLogger(__name__)

DEFAULTS: dict[str, Any] = {
    "lk_win": 21,  # LK window (px)
    "lk_levels": 3,
    "fb_max_px": 1.0,  # forward-backward error bound of a kept track
    "reproj_px": 3.0,  # PnP inlier threshold
    "min_inliers": 12,  # a frame pose needs this many PnP inliers
    "ratio": 0.8,  # relocalisation 2-NN ratio
    "max_features": 4000,  # relocalisation SIFT features per frame
    "prior_margin": 0.3,  # relocalisation: map points projecting this far outside the prior view
    "seed": 0,
}


@dataclass
class FramePose:
    ok: bool
    R: np.ndarray | None = None
    C: np.ndarray | None = None
    inliers: int = 0
    reprojection_px: float = float("nan")
    source: str = ""


def _pnp(xyz: np.ndarray, uv: np.ndarray, K: np.ndarray, c: dict, source: str) -> FramePose:
    if len(xyz) < int(c["min_inliers"]):
        return FramePose(False, inliers=0, source=source)
    r = solve_pnp(xyz, uv, K, float(c["reproj_px"]), seed=int(c["seed"]))
    ok = bool(r.ok and r.inliers >= int(c["min_inliers"]))
    return FramePose(ok, r.R, r.C, int(r.inliers), float(r.reprojection_px), source)


class Tracker:
    """LK tracking of geo-registered points from the last keyframe, PnP per frame."""

    def __init__(self, K: np.ndarray, conf: dict | None = None) -> None:
        self.K = np.asarray(K, float)
        self.c = {**DEFAULTS, **(conf or {})}
        self.prev: np.ndarray | None = None
        self.uv = np.zeros((0, 2), np.float32)
        self.xyz = np.zeros((0, 3))

    @property
    def n_tracks(self) -> int:
        return len(self.uv)

    def reset(self, gray: np.ndarray, uv: np.ndarray, xyz: np.ndarray) -> None:
        """Start tracks at a keyframe: its observations ``uv`` of the map points ``xyz``."""
        ok = np.all(np.isfinite(xyz), axis=1)
        self.prev = gray
        self.uv = np.asarray(uv, np.float32)[ok]
        self.xyz = np.asarray(xyz, float)[ok]

    def step(self, gray: np.ndarray) -> FramePose:
        """Track into ``gray`` and solve its pose."""
        if self.prev is None or len(self.uv) < int(self.c["min_inliers"]):
            self.prev = gray
            return FramePose(False, source="tracking")
        w, lv = int(self.c["lk_win"]), int(self.c["lk_levels"])
        crit = (cv2.TERM_CRITERIA_EPS | cv2.TERM_CRITERIA_COUNT, 30, 0.01)
        p0 = self.uv.reshape(-1, 1, 2)
        p1, st, _ = cv2.calcOpticalFlowPyrLK(self.prev, gray, p0, None, winSize=(w, w),
                                             maxLevel=lv, criteria=crit)  # fmt: skip
        p0b, stb, _ = cv2.calcOpticalFlowPyrLK(gray, self.prev, p1, None, winSize=(w, w),
                                               maxLevel=lv, criteria=crit)  # fmt: skip
        fb = np.linalg.norm((p0b - p0).reshape(-1, 2), axis=1)
        h, wd = gray.shape[:2]
        q = p1.reshape(-1, 2)
        keep = (st.ravel() == 1) & (stb.ravel() == 1) & (fb < float(self.c["fb_max_px"]))
        keep &= (q[:, 0] >= 0) & (q[:, 0] < wd) & (q[:, 1] >= 0) & (q[:, 1] < h)
        self.uv, self.xyz, self.prev = q[keep], self.xyz[keep], gray
        pose = _pnp(self.xyz, self.uv.astype(np.float64), self.K, self.c, "tracking")
        if pose.ok:  # drop tracks that no longer agree with the pose (drifted or occluded)
            proj, z = _project(self.xyz, pose.R, pose.C, self.K, gray.shape[::-1])
            good = (np.linalg.norm(proj - self.uv, axis=1) < 2 * float(self.c["reproj_px"]))
            good &= z > 0
            self.uv, self.xyz = self.uv[good], self.xyz[good]
        return pose


def _project(xyz: np.ndarray, R: np.ndarray, C: np.ndarray, K: np.ndarray, size: tuple[int, int]):
    """(uv, depth) of world points in the camera (K, R, C) of image ``size`` (w, h)."""
    return PinholeCamera(K[0, 0], K[1, 1], K[0, 2], K[1, 2], *size, R, C).project(xyz)


class PointMapLocalizer:
    """2-D / 3-D matching of a frame against the map points' descriptors, then PnP."""

    def __init__(self, xyz: np.ndarray, desc: np.ndarray, K: np.ndarray, image_size: tuple[int, int],
                 conf: dict | None = None) -> None:  # fmt: skip
        self.xyz = np.asarray(xyz, float)
        self.desc = np.ascontiguousarray(desc, np.float32)
        self.K = np.asarray(K, float)
        self.w, self.h = image_size
        self.c = {**DEFAULTS, **(conf or {})}
        self._extract = colmap_sift(int(self.c["max_features"]))

    def candidates(self, prior: tuple[np.ndarray, np.ndarray] | None) -> np.ndarray:
        """Indices of the map points in front of the prior camera and inside its (grown) view."""
        if prior is None:
            return np.arange(len(self.xyz))
        uv, z = _project(self.xyz, prior[0], prior[1], self.K, (self.w, self.h))
        m = float(self.c["prior_margin"])
        ok = (z > 0) & (uv[:, 0] > -m * self.w) & (uv[:, 0] < (1 + m) * self.w)
        ok &= (uv[:, 1] > -m * self.h) & (uv[:, 1] < (1 + m) * self.h)
        return np.flatnonzero(ok)

    def locate(self, gray: np.ndarray, prior: tuple[np.ndarray, np.ndarray] | None = None
               ) -> tuple[FramePose, np.ndarray, np.ndarray]:  # fmt: skip
        """(pose, inlier uv, inlier xyz) of ``gray``; the inliers can restart a ``Tracker``."""
        import faiss

        cand = self.candidates(prior)
        empty = (np.zeros((0, 2)), np.zeros((0, 3)))
        if len(cand) < int(self.c["min_inliers"]):
            return FramePose(False, source="relocalisation"), *empty
        xy, d = self._extract(gray)
        if len(xy) < 2:
            return FramePose(False, source="relocalisation"), *empty
        ix = faiss.IndexFlatL2(self.desc.shape[1])
        ix.add(self.desc[cand])
        dist, nn = ix.search(d, 2)
        ok = np.sqrt(np.maximum(dist[:, 0], 0)) < float(self.c["ratio"]) * np.sqrt(
            np.maximum(dist[:, 1], 0)
        )
        q = np.flatnonzero(ok)
        xyz, uv = self.xyz[cand[nn[q, 0]]], xy[q]
        pose = _pnp(xyz, uv, self.K, self.c, "relocalisation")
        if not pose.ok:
            return pose, *empty
        proj, z = _project(xyz, pose.R, pose.C, self.K, (self.w, self.h))
        good = (np.linalg.norm(proj - uv, axis=1) < float(self.c["reproj_px"])) & (z > 0)
        return pose, uv[good], xyz[good]
