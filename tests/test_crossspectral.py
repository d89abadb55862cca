"""Cross-spectral matching front-end (issue 11): polarity flip, the `vote` matcher, calibration.

The real-data tests use ../shared/data/swir_dates (skipped when absent): a Landsat SWIR band of
2000 rotated and cropped, against the RGB of 2002 as the map.
"""

from __future__ import annotations

import math
from pathlib import Path

import cv2
import numpy as np
import pytest

from georeg.index.features import detect_and_describe
from georeg.register import matching, search

DATA = Path(__file__).resolve().parents[2] / "shared" / "data" / "swir_dates"
CONF = {
    "ratio": 0.7,
    "max_matches": 100,
    "ransac": {"method": "magsac", "reproj_px": 3.0},
    "acceptance": {"mode": "nfa", "log_nfa_max": 0.0},
}


def test_flip_polarity_is_the_inverted_image_descriptor():
    rng = np.random.default_rng(0)
    img = cv2.GaussianBlur(rng.uniform(0, 255, (200, 200)).astype(np.float32), (0, 0), 3)
    img = cv2.normalize(img, None, 0, 255, cv2.NORM_MINMAX).astype(np.uint8)
    sift = cv2.SIFT_create(300)
    kp, d = sift.detectAndCompute(img, None)
    assert len(kp) > 20
    kp2 = [cv2.KeyPoint(k.pt[0], k.pt[1], k.size, (k.angle + 180) % 360, 0, k.octave) for k in kp]
    kp2, d2 = sift.compute(255 - img, kp2)
    rel = np.linalg.norm(d2 - matching.flip_polarity(d), axis=1) / np.linalg.norm(d2, axis=1)
    assert np.median(rel) < 0.1  # exact up to OpenCV's sampling of the rotated grid
    # without the flip the inverted descriptors are far apart
    assert np.median(np.linalg.norm(d2 - d, axis=1) / np.linalg.norm(d2, axis=1)) > 0.5
    assert np.array_equal(matching.flip_polarity(matching.flip_polarity(d)), d)


def _stretch(a: np.ndarray) -> np.ndarray:
    v = np.isfinite(a)
    lo, hi = np.percentile(a[v], [1, 99])
    out = np.clip((a - lo) / (hi - lo), 0, 1) * 254 + 1
    return np.where(v, out, 0).round().astype(np.uint8)


def _landsat(city: str, k: int):
    from georeg.io.query import open_query

    d = DATA / f"landsat_{city}"
    cubes = sorted(p for p in d.iterdir() if p.suffix.lower() != ".hdr")
    return open_query(str(cubes[k]))


def _map_source(city: str) -> search.MapSource:
    """RGB luminance of the second date; map x = col * 30, y = -row * 30 (north-up, metres)."""
    m = _landsat(city, 1)
    rgb = [m.read_band(i).astype(np.float32) for i in (2, 1, 0)]
    gray = _stretch(0.299 * rgb[0] + 0.587 * rgb[1] + 0.114 * rgb[2])
    f = detect_and_describe(gray, None, {"rootsift": True})
    xy = np.c_[f.xy[:, 0] * 30.0, -f.xy[:, 1] * 30.0].astype(np.float64)
    return search.MapSource(xy, f.desc, 30.0, angle=f.angle, scale=f.scale * 30.0)


def _query(theta_deg: float, centre: tuple[float, float], n: int = 300):
    """Nanjing 2000, 2.22 um, rotated by theta and cropped to n x n; (band, A, t): src = A q + t."""
    band = _landsat("nanjing", 0).read_band(5).astype(np.float32)
    c, s = math.cos(math.radians(theta_deg)), math.sin(math.radians(theta_deg))
    A = np.array([[c, -s], [s, c]])
    t = np.asarray(centre, float) - A @ np.array([(n - 1) / 2, (n - 1) / 2])
    flags = cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP
    w = cv2.warpAffine(band, np.c_[A, t], (n, n), flags=flags, borderValue=np.nan)
    u8 = _stretch(w)
    return search.query_features(u8, (0, n), [1.0], {"rootsift": True}), A, t


def _error_px(H: np.ndarray, A: np.ndarray, t: np.ndarray, n: int = 300) -> float:
    qp = np.array([[0, 0], [n - 1, 0], [0, n - 1], [n - 1, n - 1], [n / 2, n / 2]], float)
    est = matching.apply_h(H, qp) / np.array([30.0, -30.0])
    return float(np.median(np.linalg.norm(est - (qp @ A.T + t), axis=1)))


needs_data = pytest.mark.skipif(not DATA.is_dir(), reason="../shared/data/swir_dates absent")


@needs_data
def test_vote_registers_cross_date_landsat_that_paper_misses():
    src = _map_source("nanjing")
    qf, A, t = _query(20.0, (250.0, 250.0))
    paper, _m, _f = search.verify(
        qf, src, src.bounds, {**CONF, "matcher": {"method": "paper"}}, 30.0
    )
    assert paper["matcher"] == "paper"
    assert not paper["accepted"]
    vote, _m, fit = search.verify(
        qf, src, src.bounds, {**CONF, "matcher": {"method": "vote"}}, 30.0
    )
    assert vote["matcher"] == "vote"
    assert vote["accepted"], vote.get("reason")
    assert vote["log10_nfa"] < -5
    assert _error_px(fit.H, A, t) < 2.0


@needs_data
def test_vote_rejects_an_unrelated_map_and_guided_rematch_refines():
    qf, A, t = _query(75.0, (550.0, 300.0))
    other = _map_source("taizhou")
    rec, _m, _f = search.verify(qf, other, other.bounds, CONF, 30.0)  # default matcher: vote
    assert rec["matcher"] == "vote"
    assert not rec["accepted"]
    assert rec.get("log10_nfa") is None or rec["log10_nfa"] > 0
    # the fuse stage's guided re-match around a (perturbed) accepted homography
    src = _map_source("nanjing")
    rec, _m, fit = search.verify(qf, src, src.bounds, CONF, 30.0)
    assert rec["accepted"]
    H0 = np.array([[1, 0, 90.0], [0, 1, -90.0], [0, 0, 1]]) @ fit.H  # 3 px off in x and y
    g, _m, gfit = search.verify(qf, src, src.bounds, CONF, 30.0, guide=(H0, 150.0))
    assert g["matcher"] == "guided" and g["accepted"]
    assert gfit.n_inliers >= fit.n_inliers
    assert _error_px(H0, A, t) > 3.0
    assert _error_px(gfit.H, A, t) < 1.5


def test_vote_matcher_config_and_fallback():
    assert matching.matcher_conf({})["method"] == "vote"
    assert matching.matcher_conf({})["polarity"] == "both"
    assert matching.matcher_conf({"matcher": {"method": "paper"}})["polarity"] == "one"
    with pytest.raises(ValueError, match="matcher"):
        qf = search.QueryFeatures(
            np.zeros((4, 2)), np.zeros((4, 128), np.float32), np.zeros(4), 10, 10, (0, 0), [1.0]
        )
        src = search.MapSource(np.random.default_rng(0).uniform(0, 100, (20, 2)),
                               np.ones((20, 128), np.float32), 1.0)  # fmt: skip
        search.verify(qf, src, (0, 0, 100, 100), {"matcher": {"method": "nope"}}, 1.0)
