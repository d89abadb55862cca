"""The model of an accepted fit chosen by leave-one-out CV (georeg.register.matching.choose_model)."""

import numpy as np
import pytest

from georeg.register import matching
from georeg.register.matching import choose_model
from georeg.register.search import final_model

G = 10.0  # map units per map px
CORNERS = np.array([[0, 0], [80, 0], [0, 80], [80, 80]], float)


def _nadir(theta: float, scale: float = 20.0) -> np.ndarray:
    """Query (col, row) -> map (x, y), y up: rotation, ``scale`` m per query px, the row flip."""
    c, s = np.cos(theta), np.sin(theta)
    return np.array([[scale * c, scale * s, 5e5], [scale * s, -scale * c, 4e6], [0, 0, 1.0]])


def _corner_err(H: np.ndarray, T: np.ndarray) -> float:
    return float(np.abs(matching.apply_h(H, CORNERS) - matching.apply_h(T, CORNERS)).max() / G)


def test_few_noisy_inliers_of_a_nadir_view_give_a_similarity_that_extrapolates_better():
    """6-10 noisy inliers clustered in half of an 80 px footprint (a small query) of a nadir
    view: the rule picks the similarity on most draws, and the chosen fit's error at the
    footprint corners is lower than the affine and homography fits of the same inliers."""
    picks, err = [], []
    for seed in range(20):
        rng = np.random.default_rng(seed)
        T = _nadir(rng.uniform(0, 2 * np.pi))
        n = int(rng.integers(6, 11))
        q = rng.uniform(5, 45, (n, 2))
        m = matching.apply_h(T, q) + rng.normal(0, 0.8 * G, (n, 2))
        H, info = choose_model(q, m, G)
        picks.append(info["model"])
        aff = matching.affine_lsq(q, m)
        hom = matching.fit_homography(q, m, G, {"reproj_px": 50.0, "affine_below": 0}, seed=1).H
        err.append([_corner_err(H, T), _corner_err(aff, T), _corner_err(hom, T)])
    e = np.array(err)
    assert picks.count("similarity") >= 15
    assert np.median(e[:, 0]) < 0.75 * np.median(e[:, 1])
    assert np.median(e[:, 0]) < 0.5 * np.median(e[:, 2])


def test_many_inliers_of_a_perspective_view_keep_the_homography():
    """A strongly oblique view (perspective terms that move the footprint's far corner by tens
    of px) with 80 inliers at 0.3 px noise: the held-out residuals need the homography, and the
    chosen fit is within a pixel of the truth at the corners."""
    rng = np.random.default_rng(4)
    T = _nadir(0.6) @ np.array([[1.0, 0.1, 0], [0.05, 1.0, 0], [2e-3, 1.5e-3, 1.0]])
    q = rng.uniform(0, 80, (80, 2))
    m = matching.apply_h(T, q) + rng.normal(0, 0.3 * G, (80, 2))
    H, info = choose_model(q, m, G)
    assert info["model"] == "homography"
    assert info["loo_rms_px"]["homography"] < 0.5 * info["loo_rms_px"]["similarity"]
    assert _corner_err(H, T) < 1.0


def test_a_sheared_view_is_not_forced_into_a_similarity():
    """An affine truth (anisotropy 1.3, shear) with 40 inliers: the similarity's held-out
    residuals are far higher, so the affine map (or the homography) is chosen, close to truth."""
    rng = np.random.default_rng(5)
    T = _nadir(1.1) @ np.array([[1.3, 0.25, 0], [0.0, 1.0, 0], [0, 0, 1.0]])
    q = rng.uniform(0, 80, (40, 2))
    m = matching.apply_h(T, q) + rng.normal(0, 0.5 * G, (40, 2))
    H, info = choose_model(q, m, G)
    assert info["model"] in ("affine", "homography")
    assert _corner_err(H, T) < 1.5


def test_too_few_inliers_to_cross_validate_keep_the_fit():
    q = np.array([[0, 0], [10, 0], [0, 10]], float)
    H, info = choose_model(q, matching.apply_h(_nadir(0.3), q), G)
    assert H is None and info["model"] is None
    fit = matching.HomographyFit(_nadir(0.3), np.ones(3, bool), np.zeros(3), 3.0)
    m = matching.Matches(np.arange(3), np.arange(3), q, matching.apply_h(_nadir(0.3), q),
                         np.zeros(3, np.float32), 3)  # fmt: skip
    rec: dict = {}
    assert final_model(fit, m, G, {}, rec) is fit
    assert rec["final_model"]["model"] is None


def test_final_model_replaces_the_homography_keeps_the_inliers_and_checks_its_option():
    rng = np.random.default_rng(6)
    T = _nadir(2.0)
    q = rng.uniform(0, 60, (8, 2))
    mxy = matching.apply_h(T, q) + rng.normal(0, 0.5 * G, (8, 2))
    # a stand-in for the RANSAC fit: the affine map of the inliers
    fit = matching.HomographyFit(matching.affine_lsq(q, mxy), np.ones(8, bool), np.zeros(8), 3.0)
    m = matching.Matches(np.arange(8), np.arange(8), q, mxy, np.zeros(8, np.float32), 8)
    rec: dict = {}
    out = final_model(fit, m, G, {"final_model": "loo"}, rec)
    assert out.n_inliers == 8 and rec["final_model"]["model"] in ("similarity", "affine")
    assert np.allclose(out.residual_px,
                       np.linalg.norm(matching.apply_h(out.H, q) - mxy, axis=1) / G)  # fmt: skip
    assert final_model(fit, m, G, {"final_model": "ransac"}, {}) is fit
    with pytest.raises(ValueError, match="final_model"):
        final_model(fit, m, G, {"final_model": "best"}, {})
