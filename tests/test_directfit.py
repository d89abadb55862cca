"""Whole-footprint direct alignment (georeg.register.directfit): recovers a known similarity on
a small query whose contrast differs from the map's, keeps a fit that is already right, and
refuses what it should not do."""

from __future__ import annotations

import math

import cv2
import numpy as np
import pytest
from rasterio.transform import Affine

from georeg.register.directfit import direct_fit, warp_matrix
from georeg.register.geolocation import apply_h
from georeg.register.refine import MapImage, refine


def _similarity(theta_deg: float, scale: float, tx: float, ty: float) -> np.ndarray:
    c = math.cos(math.radians(theta_deg)) * scale
    s = math.sin(math.radians(theta_deg)) * scale
    return np.array([[c, -s, tx], [s, c, ty], [0, 0, 1.0]])


@pytest.fixture(scope="module")
def scene() -> tuple[MapImage, np.ndarray, np.ndarray]:
    """A textured map (1 unit = 1 map px), a 60 px query at 2 map px per query px, rotated by
    20 deg, with inverted contrast (a SWIR band against a visible one), and the truth."""
    rng = np.random.default_rng(3)
    m = cv2.GaussianBlur(rng.random((400, 400)).astype(np.float32), (0, 0), 3)
    m = (m - m.min()) / (m.max() - m.min()) * 200 + 20
    mi = MapImage(m, Affine(1, 0, 0, 0, 1, 0))
    T = _similarity(20, 2.0, 150.5, 120.5)
    x, y = apply_h(T, np.arange(60.0)[None, :], np.arange(60.0)[:, None])
    q = np.clip(275 - mi.render(x, y), 1, 255).astype(np.uint8)
    return mi, q, T


def _err(H: np.ndarray, T: np.ndarray, w: int, h: int) -> np.ndarray:
    cols, rows = np.meshgrid(np.arange(w, dtype=float), np.arange(h, dtype=float))
    xa, ya = apply_h(H, cols, rows)
    xb, yb = apply_h(T, cols, rows)
    return np.hypot(xa - xb, ya - yb)


@pytest.mark.parametrize("model", ["rigid", "similarity", "affine"])
def test_recovers_a_perturbed_fit(scene, model) -> None:
    mi, q, T = scene
    H0 = T @ _similarity(1.0, 1.0 if model == "rigid" else 1.01, 0.8, -0.6)
    assert _err(H0, T, 60, 60).max() > 2.0  # map px
    H, info = direct_fit(q, H0, mi, {"model": model})
    assert info["accepted"], info
    assert _err(H, T, 60, 60).max() < 0.1
    assert info["ncc"][1] > info["ncc"][0]
    assert info["disagree_px"] < 0.1  # the two boards' fits agree on a clean scene


def test_keeps_a_right_fit_where_it_is(scene) -> None:
    mi, q, T = scene
    H, info = direct_fit(q, T, mi, {})
    assert _err(H, T, 60, 60).max() < 0.05
    assert info["moved_px"] < 0.05


def test_a_large_move_is_refused(scene) -> None:
    mi, q, T = scene
    H0 = T @ _similarity(0.0, 1.0, 1.5, 0.0)  # 1.5 query px off
    H, info = direct_fit(q, H0, mi, {"max_move_px": 0.5})
    assert not info["accepted"] and "moved" in info["reason"]
    assert np.array_equal(H, H0)


def test_a_large_footprint_is_left_to_the_tie_points(scene) -> None:
    mi, q, T = scene
    H, info = direct_fit(q, T, mi, {"max_pixels": 100})
    assert not info["accepted"] and "max_pixels" in info["reason"]
    assert np.array_equal(H, T)


def test_unknown_model_is_a_clear_error(scene) -> None:
    mi, q, T = scene
    with pytest.raises(ValueError, match="unknown direct_fit model"):
        direct_fit(q, T, mi, {"model": "spline"})


def test_warp_matrix_is_the_displacement_it_describes() -> None:
    M = warp_matrix(np.array([0.5, -0.25, 0.1, 0.2]), "similarity", 10.0, (4.0, 6.0))
    p = np.array([7.0, 1.0, 1.0])
    u, v = (p[0] - 4.0) / 10.0, (p[1] - 6.0) / 10.0
    expect = p[:2] + [0.5 + 0.1 * u - 0.2 * v, -0.25 + 0.1 * v + 0.2 * u]
    assert np.allclose((M @ p)[:2], expect)


def test_refine_runs_it_and_reports_it(scene) -> None:
    mi, q, T = scene
    H0 = T @ _similarity(0.8, 1.0, 0.7, 0.4)
    x, y, info = refine(q, H0, mi, {"direct_fit": {"enabled": True}})
    assert info["direct_fit"]["accepted"]
    xt, yt = apply_h(T, np.arange(60.0)[None, :], np.arange(60.0)[:, None])
    assert np.percentile(np.hypot(x - xt, y - yt), 90) < 0.2
    _, _, off = refine(q, H0, mi, {})  # the default: off
    assert off["direct_fit"] == {"enabled": False}
