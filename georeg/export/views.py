"""Registered frames as photogrammetry tools see them: the full-size image, its intrinsics with
distortion (OpenCV conventions: pixel (0, 0) = centre of the top-left pixel), its pose in the
map CRS, and the projection of map points into it."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from georeg.frames.render import PinholeCamera
from georeg.io.errors import InputError

IMAGE_SUFFIXES = (".jpg", ".jpeg", ".png", ".tif", ".tiff", ".bmp")


@dataclass(frozen=True)
class View(PinholeCamera):
    """One registered image as a tool sees it: the frames' pinhole camera (full-size intrinsics,
    world -> camera pose) with its file ``name`` and lens distortion ``dist``."""

    name: str
    dist: np.ndarray  # OpenCV (k1, k2, p1, p2[, k3[, k4, k5, k6]])

    def project(self, X: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(N, 3) world -> (N, 2) distorted pixel (col, row) of the full-size image and (N,) depth."""
        X = np.asarray(X, float).reshape(-1, 3)
        depth = (X - self.C) @ self.R[2]
        if not len(X):
            return np.zeros((0, 2)), depth
        uv, _ = cv2.projectPoints(X, self.rvec, self.tvec, self.K, self.dist)
        return uv.reshape(-1, 2), depth

    def sees(self, X: np.ndarray, margin_px: float = 2.0) -> tuple[np.ndarray, np.ndarray]:
        """(visible mask, uv): in front of the camera, inside the image by ``margin_px``, and
        within the field of view before distortion (a strong radial term folds far points back
        into the frame)."""
        X = np.asarray(X, float).reshape(-1, 3)
        uv, depth = self.project(X)
        un, _ = PinholeCamera.project(self, X)
        inside = lambda p: ((p[:, 0] >= margin_px) & (p[:, 0] <= self.width - 1 - margin_px)  # noqa: E731
                            & (p[:, 1] >= margin_px) & (p[:, 1] <= self.height - 1 - margin_px))  # fmt: skip
        # the undistorted point may lie a little outside (barrel distortion pulls it in)
        pad = 0.15 * max(self.width, self.height)
        loose = ((un[:, 0] > -pad) & (un[:, 0] < self.width + pad) & (un[:, 1] > -pad)
                 & (un[:, 1] < self.height + pad))  # fmt: skip
        return (depth > 0) & inside(uv) & loose & np.all(np.isfinite(uv), axis=1), uv


def export_name(image: str) -> str:
    """The file name a photogrammetry tool sees: the image's own name; a video frame
    ``clip.mp4#000012`` becomes ``clip_000012.png`` (the frame to extract under that name)."""
    base = Path(str(image)).name
    if "#" in base:
        stem, idx = base.rsplit("#", 1)
        return f"{Path(stem).stem}_{idx}.png"
    name = base.replace(" ", "_")
    return name if Path(name).suffix.lower() in IMAGE_SUFFIXES else f"{name}.png"


def full_size_intrinsics(intr: dict, pyramid: dict | None) -> dict[str, Any]:
    """Intrinsics of the full-size image from those of the level the frame was localised on
    (``pyramid.scale``; pixel centres kept: c = (c' + 0.5) / s - 0.5)."""
    s = float((pyramid or {}).get("scale") or 1.0)
    w, h = (pyramid or {}).get("full_size") or (intr["width"], intr["height"])
    return {"fx": intr["fx"] / s, "fy": intr["fy"] / s, "cx": (intr["cx"] + 0.5) / s - 0.5,
            "cy": (intr["cy"] + 0.5) / s - 0.5, "dist": list(intr.get("dist") or []),
            "width": int(w), "height": int(h)}  # fmt: skip


def views_from_poses(poses: list[dict], source: str | Path = "poses.json") -> list[View]:
    """Every registered record of a poses.json with its intrinsics; a registered record without
    intrinsics is an InputError naming ``source``."""
    out = []
    for p in poses:
        if p.get("status") != "registered" or p.get("R_world_to_cam") is None:
            continue
        if not p.get("intrinsics"):
            raise InputError(source, f"registered frame {p.get('image')!r} has no intrinsics",
                             "re-run the frame set with this version")  # fmt: skip
        k = full_size_intrinsics(p["intrinsics"], p.get("pyramid"))
        d = np.asarray(k["dist"] or [0.0] * 5, float)
        out.append(View(k["fx"], k["fy"], k["cx"], k["cy"], int(k["width"]), int(k["height"]),
                        np.asarray(p["R_world_to_cam"], float),
                        np.asarray(p["camera_center_xyz"], float), export_name(p["image"]), d))  # fmt: skip
    names = [v.name for v in out]
    if len(set(names)) != len(names):
        raise InputError(source, "two registered frames have the same file name",
                         "give every frame a distinct name")  # fmt: skip
    return out
