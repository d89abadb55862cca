"""The focal (and k1) of an unknown camera from 2-D/3-D matches (georeg.frames.focal)."""

from __future__ import annotations

import cv2
import numpy as np


def _view(f: float, k1: float, n: int = 300, seed: int = 0):
    """Ground points with 40 m of relief seen 35 deg off nadir from 150 m, projected with focal
    ``f`` and radial distortion ``k1``; 30 % of the matches replaced by random pixels."""
    rng = np.random.default_rng(seed)
    w, h = 1200, 800
    xyz = np.c_[rng.uniform(-150, 150, n), rng.uniform(0, 300, n), rng.uniform(0, 40, n)]
    t = np.deg2rad(35.0)
    R = np.array([[1, 0, 0], [0, -1, 0], [0, 0, -1]], float) @ cv2.Rodrigues(np.array([-t, 0, 0]))[0]
    C = np.array([0.0, -20.0, 190.0])
    Xc = (xyz - C) @ R.T
    x, y = Xc[:, 0] / Xc[:, 2], Xc[:, 1] / Xc[:, 2]
    d = 1 + k1 * (x * x + y * y)
    uv = np.c_[f * x * d + (w - 1) / 2, f * y * d + (h - 1) / 2]
    keep = (Xc[:, 2] > 0) & (uv[:, 0] >= 0) & (uv[:, 0] < w) & (uv[:, 1] >= 0) & (uv[:, 1] < h)
    xyz, uv = xyz[keep], uv[keep] + rng.normal(0, 0.5, (keep.sum(), 2))
    bad = rng.random(len(uv)) < 0.3
    uv[bad] = rng.uniform([0, 0], [w, h], (bad.sum(), 2))
    return xyz, uv, w, h


def test_focal_and_k1_recovered_from_matches():
    from georeg.frames.focal import focal_from_matches

    xyz, uv, w, h = _view(900.0, -0.2)
    est = focal_from_matches(xyz, uv, w, h, [0.6, 0.8, 1.0, 1.3, 1.7], 4.0)
    assert est is not None and est["fitted"], est
    assert abs(est["fx"] / 900.0 - 1) < 0.03 and abs(est["k1"] + 0.2) < 0.04, est
    # without the distortion term in the data, k1 comes out near 0
    est0 = focal_from_matches(*_view(700.0, 0.0, seed=1), [0.6, 0.8, 1.0, 1.3, 1.7], 4.0)
    assert est0["fitted"] and abs(est0["fx"] / 700.0 - 1) < 0.02 and abs(est0["k1"]) < 0.02, est0


def test_no_focal_from_random_matches():
    from georeg.frames.focal import focal_from_matches

    rng = np.random.default_rng(3)
    xyz = np.c_[rng.uniform(0, 300, (200, 2)), rng.uniform(0, 40, 200)]
    uv = rng.uniform([0, 0], [1200, 800], (200, 2))
    est = focal_from_matches(xyz, uv, 1200, 800, [0.6, 1.0, 1.7], 4.0)
    assert est is None or est["inliers"] < 30
