"""Direct-sun illumination of a height field: cosine shading and cast shadows."""

from __future__ import annotations

import cv2
import numpy as np

from georeg.demo import classes as C
from georeg.demo.spectra import Sun


def cast_shadow(dsm: np.ndarray, res: float, sun: Sun) -> np.ndarray:
    """Fraction (0..1) of each pixel in cast shadow, by a horizon scan along the sun azimuth.

    The height field is rotated so that light travels down the rows; a running envelope
    ``env[v] = max(h[v], env[v-1] - res * tan(elevation))`` is the shadow-casting surface.
    """
    H, W = dsm.shape
    az = np.radians(sun.azimuth_deg)
    d = np.array([-np.sin(az), np.cos(az)])  # shadow direction in (col, row)
    p = np.array([np.cos(az), np.sin(az)])  # perpendicular
    n = int(np.ceil(np.hypot(H, W))) + 2
    c_in = np.array([(W - 1) / 2, (H - 1) / 2])
    c_out = (n - 1) / 2
    t = c_in - c_out * (p + d)
    M = np.array([[p[0], d[0], t[0]], [p[1], d[1], t[1]]], dtype=np.float64)  # (u, v) -> (col, row)
    low = float(dsm.min()) - 1.0
    rot = cv2.warpAffine(dsm.astype(np.float32), M, (n, n), flags=cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP,
                         borderMode=cv2.BORDER_CONSTANT, borderValue=low)  # fmt: skip
    drop = np.float32(res * np.tan(np.radians(sun.elevation_deg)))
    shadow = np.zeros_like(rot)
    env = rot[0].copy()
    for v in range(1, n):
        env -= drop
        row = rot[v]
        shadow[v] = env > row + 0.05
        np.maximum(env, row, out=env)
    back = cv2.warpAffine(shadow, M, (W, H), flags=cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT,
                          borderValue=0.0)  # fmt: skip
    return np.clip(back, 0.0, 1.0)


def cosine_factor(dsm: np.ndarray, label: np.ndarray, res: float, sun: Sun) -> np.ndarray:
    """cos(incidence) / sin(elevation): 1 on flat ground, from the DSM slope (walls treated flat)."""
    gy, gx = np.gradient(dsm.astype(np.float32), res)
    dzdx, dzdy = gx, -gy  # rows run south
    g = np.hypot(dzdx, dzdy)
    steep = ((g > 1.2) & (label != C.TREE)) | (g > 4.0)
    dzdx = np.where(steep, 0.0, dzdx)
    dzdy = np.where(steep, 0.0, dzdy)
    s = sun.vector()
    cos_i = (-dzdx * s[0] - dzdy * s[1] + s[2]) / np.sqrt(dzdx**2 + dzdy**2 + 1.0)
    return (np.clip(cos_i, 0.0, None) / s[2]).astype(np.float32)


def sky_view(dsm: np.ndarray, res: float) -> np.ndarray:
    """Crude sky-view factor: darker at the foot of tall neighbours (0.55..1)."""
    blur = cv2.GaussianBlur(dsm.astype(np.float32), (0, 0), sigmaX=6.0 / res)
    occl = np.clip((blur - dsm) / 25.0, 0.0, 0.45)
    return (1.0 - occl).astype(np.float32)


def direct_and_sky(
    dsm: np.ndarray, label: np.ndarray, res: float, sun: Sun
) -> tuple[np.ndarray, np.ndarray]:
    """Direct illumination factor (shading x (1 - shadow)) and sky-view factor on a grid."""
    direct = cosine_factor(dsm, label, res, sun) * (1.0 - cast_shadow(dsm, res, sun))
    return direct.astype(np.float32), sky_view(dsm, res)
