"""Orthophoto rendering: visible albedo x (sun shading + blue skylight), camera blur and noise."""

from __future__ import annotations

import cv2
import numpy as np

from georeg.demo import spectra as S
from georeg.demo.illumination import direct_and_sky
from georeg.demo.raster import Surface

SKY_RGB = np.array([0.16, 0.21, 0.32], np.float32)  # skylight / direct sun ratio per channel
EXPOSURE = 1.7


def render_orthophoto(surf: Surface, sun: S.Sun, rng: np.random.Generator) -> np.ndarray:
    """RGB uint8 (3, H, W) true orthophoto of ``surf`` lit by ``sun``."""
    direct, sky = direct_and_sky(surf.dsm, surf.label, surf.grid.res, sun)
    mean = S.RGB_MEAN.astype(np.float32)[surf.mat]  # (H, W, 3)
    var = S.RGB_VAR.astype(np.float32)[surf.mat]
    albedo = mean * (1.0 + surf.c1[..., None]) + surf.c2[..., None] * var
    albedo = np.clip(albedo, 0.005, 1.0)
    light = (direct[..., None] + sky[..., None] * SKY_RGB) / (1.0 + SKY_RGB)
    lin = albedo * light * EXPOSURE
    lin = cv2.GaussianBlur(lin, (0, 0), sigmaX=0.55)
    img = 255.0 * np.clip(lin, 0, 1) ** (1 / 2.2)
    img += rng.normal(0.0, 1.5, img.shape).astype(np.float32)
    return np.clip(np.rint(img), 0, 255).astype(np.uint8).transpose(2, 0, 1)
