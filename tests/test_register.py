"""Query registration: matching, acceptance, search strategies, fusion, geolocation, workflow."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest
import rasterio
from rasterio.transform import Affine

from georeg.index.features import detect_and_describe, pixel_to_map
from georeg.io.query import open_query
from georeg.register import acceptance, matching, search
from georeg.register import fuse as fuse_mod
from georeg.register.band import select_band, stretch_uint8
from georeg.register.fuse import fuse
from georeg.register.geolocation import evaluate, map_xy, write_geolocation
from georeg.register.search import MapSource, paper_centres, part_rows, query_features, search_part

REPO = Path(__file__).resolve().parents[1]
FEAT = {"rootsift": True, "max_features_per_mpx": None}


def reg_conf(**kw) -> dict:
    conf = {
        "strategy": "index",
        "parts": 2,
        "ratio": 0.7,
        "max_matches": 100,
        "ransac": {"method": "magsac", "reproj_px": 3.0, "max_seconds": 2.0, "max_iters": 10000},
        "acceptance": {"mode": "nfa"},
        "paper": {"neighbourhood_factor": 2.0, "max_candidates": 50, "max_seconds": 60},
        "index": {"top_candidates": 5},
        "fuse": {},
    }
    for k, v in kw.items():
        if isinstance(v, dict):
            conf[k] = {**conf.get(k, {}), **v}
        else:
            conf[k] = v
    return conf


def map_source(img: np.ndarray, mask: np.ndarray, transform: Affine) -> MapSource:
    f = detect_and_describe(img, mask, FEAT)
    x, y = pixel_to_map(transform, f.xy[:, 0], f.xy[:, 1])
    return MapSource(np.c_[x, y], f.desc, abs(transform.a))


def warp_query(img: np.ndarray, scale: float, angle_deg: float, shift=(7.3, 4.1)):
    """Rotate/scale an image; returns (query uint8, matrix query px -> source px)."""
    a = np.deg2rad(angle_deg)
    h, w = img.shape
    A = np.array(
        [[scale * np.cos(a), -scale * np.sin(a), 0], [scale * np.sin(a), scale * np.cos(a), 0]]
    )
    corn = np.array([[0, 0, 1], [w, 0, 1], [0, h, 1], [w, h, 1]], float) @ A.T
    A[:, 2] -= corn.min(axis=0) - np.array(shift)
    W, H = (corn.max(axis=0) - corn.min(axis=0) + 2 * np.array(shift)).astype(int)
    q = cv2.warpAffine(img, A, (int(W), int(H)), flags=cv2.INTER_LINEAR)
    qm = cv2.warpAffine((img > 0).astype(np.uint8), A, (int(W), int(H)), flags=cv2.INTER_NEAREST)
    q[qm == 0] = 0
    return q, np.linalg.inv(np.vstack([A, [0, 0, 1]]))


def true_map_xy(Minv: np.ndarray, transform: Affine, pts: np.ndarray) -> np.ndarray:
    src = np.c_[pts, np.ones(len(pts))] @ Minv.T
    return np.c_[pixel_to_map(transform, src[:, 0], src[:, 1])]


def error_px(H, Minv, transform, q) -> np.ndarray:
    rr, cc = np.nonzero(q[::3, ::3])
    pts = np.c_[cc * 3, rr * 3].astype(float)
    return np.linalg.norm(
        matching.apply_h(H, pts) - true_map_xy(Minv, transform, pts), axis=1
    ) / abs(transform.a)


def texture(shape, seed, sigma=3.0) -> np.ndarray:
    """A random multi-scale texture (uint8 1..255): plenty of distinctive SIFT features."""
    rng = np.random.default_rng(seed)
    acc = np.zeros(shape, np.float32)
    for s in (sigma, 2 * sigma, 6 * sigma):
        acc += cv2.GaussianBlur(rng.standard_normal(shape).astype(np.float32), (0, 0), s) * s
    u8, _ = stretch_uint8(acc, np.ones(shape, bool))
    return u8


# ----------------------------------------------------------------------------- units


def test_ratio_matches_stop_at_nt_and_keep_closest_per_map_point():
    rng = np.random.default_rng(0)
    mdesc = rng.random((50, 128)).astype(np.float32)
    mxy = rng.random((50, 2)) * 100
    # query i is a noisy copy of map feature i % 50: 80 features, 30 duplicated map points
    qdesc = mdesc[np.arange(80) % 50] + rng.normal(0, 0.01, (80, 128)).astype(np.float32)
    qxy = rng.random((80, 2))
    knn = matching.knn2(mdesc)
    m = matching.ratio_matches(qxy, qdesc, None, mxy, knn, 0.7, None)
    assert len(m) == 50 and len(np.unique(m.m_idx)) == 50
    # the kept duplicate is the closer descriptor
    d = np.linalg.norm(qdesc[:, None] - mdesc[None], axis=2)
    for qi, mi in zip(m.q_idx, m.m_idx, strict=True):
        others = np.flatnonzero(np.arange(80) % 50 == mi)
        assert d[qi, mi] == pytest.approx(d[others, mi].min())
    m10 = matching.ratio_matches(qxy, qdesc, np.arange(80.0), mxy, knn, 0.7, 10)
    assert len(m10) == 10 and np.all(np.diff(m10.q_idx) < 0)  # strongest query features first
    assert set(zip(m10.q_idx, m10.m_idx, strict=True)) <= set(zip(m.q_idx, m.m_idx, strict=True))


def test_fit_homography_recovers_known_mapping_with_outliers():
    rng = np.random.default_rng(1)
    H = np.array([[0.6, 0.5, 500000.0], [0.45, -0.62, 4100000.0], [1e-6, 2e-6, 1.0]])
    q = rng.random((100, 2)) * 800
    m = matching.apply_h(H, q)
    m[60:] = m[60:] + rng.uniform(-300, 300, (40, 2))
    fit = matching.fit_homography(
        q, m + rng.normal(0, 0.2, m.shape), 1.0, {"reproj_px": 3.0}, seed=3
    )
    assert fit.n_inliers >= 58 and not fit.inliers[60:].any()
    err = np.linalg.norm(matching.apply_h(fit.H, q) - matching.apply_h(H, q), axis=1)
    assert err.max() < 0.5
    for method in ("ransac", "usac_accurate"):
        f2 = matching.fit_homography(q, m, 1.0, {"reproj_px": 3.0, "method": method}, seed=3)
        assert f2.n_inliers >= 58


def test_inliers_in_a_strip_refused_unless_the_evidence_is_strong():
    """Inliers in a thin strip (a road) leave a homography free across it: refused, whatever
    the NFA, unless the caller's model is fixed by a strip and the log10 NFA is below its
    ``strip_log_nfa`` (rift's rigid poses)."""
    H = np.array([[0.8, 0, 1000.0], [0, -0.8, 5000.0], [0, 0, 1]])
    rng = np.random.default_rng(0)
    strip = np.c_[rng.uniform(0, 800, 30), rng.uniform(290, 310, 30)]  # 20 px of a 600 px side
    res = np.r_[np.full(30, 0.8), np.full(70, 5000.0)]
    conf = {"mode": "nfa", "log_nfa_max": 0.0}
    d = acceptance.decide(H, res, 30, 2000 * 2000, 800, 600, 0.8, conf, inlier_q_xy=strip)
    assert not d["accepted"] and "collinear" in d["reason"] and d["log10_nfa"] < -30
    d = acceptance.decide(H, res, 30, 2000 * 2000, 800, 600, 0.8, conf, inlier_q_xy=strip,
                          strip_log_nfa=-6.0)  # fmt: skip
    assert d["accepted"] and d["strip_accepted"]
    weak = np.r_[np.full(6, 2.5), np.full(94, 5000.0)]
    d = acceptance.decide(H, weak, 6, 2000 * 2000, 800, 600, 0.8, {**conf, "log_nfa_max": 5.0},
                          inlier_q_xy=strip[:6], strip_log_nfa=-6.0)  # fmt: skip
    assert d["log10_nfa"] < 5.0 and d["log10_nfa"] > -6.0
    assert not d["accepted"] and "collinear" in d["reason"]
    spread = np.c_[rng.uniform(0, 800, 30), rng.uniform(0, 600, 30)]
    assert acceptance.decide(H, res, 30, 2000 * 2000, 800, 600, 0.8, conf, inlier_q_xy=spread)["accepted"]


def test_plausibility_handedness_scale_and_nfa():
    conf = {"scale_tolerance": 0.3}
    # north-up nadir image at 0.8 m: col -> +x, row -> -y; det < 0
    good = np.array([[0.8, 0, 1000.0], [0, -0.8, 5000.0], [0, 0, 1]])
    assert acceptance.plausibility(good, 800, 600, 0.8, conf)["ok"]
    mirrored = np.array([[0.8, 0, 1000.0], [0, 0.8, 5000.0], [0, 0, 1]])
    p = acceptance.plausibility(mirrored, 800, 600, 0.8, conf)
    assert not p["ok"] and "mirrored" in p["reasons"][0]
    assert not acceptance.plausibility(good * [[3], [3], [1]], 800, 600, 0.8, conf)[
        "ok"
    ]  # scale 2.4
    sheared = np.array([[0.8, 0.6, 1000.0], [0, -0.8, 5000.0], [0, 0, 1]])
    assert not acceptance.plausibility(sheared, 800, 600, 0.8, conf)["ok"]
    # NFA: many tight inliers -> very negative; 6 loose inliers of 100 in a big area -> positive
    res = np.r_[np.full(40, 0.8), np.full(60, 500.0)]
    assert acceptance.log10_nfa(res, 2000 * 2000)[0] < -50
    # chance matches: uniform in the region, so P(residual < r) = pi r^2 / area
    rand = np.sqrt(2000 * 2000 / np.pi * np.random.default_rng(0).random(94))
    assert acceptance.log10_nfa(rand, 2000 * 2000)[0] > 0
    res6 = np.r_[np.full(6, 2.5), rand]
    assert acceptance.log10_nfa(res6, 2000 * 2000, n_tests_extra=10)[0] > 0


def test_split_plan_keeps_paper_halves_for_large_queries_and_searches_small_ones_whole():
    conf = reg_conf()
    # the default demo query (829 x 1163 px at 0.8 m on a 1 m map; about 7300 features per
    # feature Mpx, as measured on the tiny demo) keeps the paper's two halves
    plan = search.split_plan(4500, 829, 1163, 0.8, 2, conf)
    assert plan["parts"] == 2 and plan["searches"] == ["part 0", "part 1", "whole"]
    # a 166 x 156 px Sentinel-2 query at 20 m on a 10 m map: too few features per half
    plan = search.split_plan(900, 166, 156, 2.0, 2, conf)
    assert plan["parts"] == 1 and "features per part" in plan["reason"]
    assert plan["searches"] == ["whole", "part 0", "part 1"]
    # enough features, but a part's footprint is too narrow on the map
    plan = search.split_plan(5000, 1000, 200, 1.0, 2, conf)
    assert plan["parts"] == 1 and "part side 100 map px" in plan["reason"]
    assert search.split_plan(5000, 900, 900, 1.0, 1, conf)["searches"] == ["whole"]
    off = reg_conf(split={"parts_if_whole_fails": False, "count_searches": False})
    plan = search.split_plan(900, 166, 156, 2.0, 2, off)
    assert plan["searches"] == ["whole"] and search.search_count(plan) == 1


def test_small_query_searched_whole_then_fused_and_idle_part_recorded(synthetic_map):
    img, tr, src = synthetic_map
    q, Minv = warp_query(img[100:260, 120:300], 1.0, 30.0)
    Minv = np.array([[1, 0, 120], [0, 1, 100], [0, 0, 1]]) @ Minv
    conf = reg_conf()
    factors = [1.0]
    parts = [search.search_one_part(q, k, src, conf, None, factors, 5) for k in range(2)]
    assert parts[0]["split"]["parts"] == 1 and parts[0]["accepted"]
    assert parts[0]["rows"] == [0, q.shape[0]] and parts[1]["skipped"]
    full = query_features(q, (0, q.shape[0]), factors, None)
    parts, split = fuse_mod.whole_query_fallback(full, src, parts, conf, None, 5)
    assert split["idle_part_jobs"] == [1] and split["whole_query_searched"] == "first, in part 0"
    fused = fuse(full, src, parts, conf, None)
    assert fused["status"] == "registered"
    assert np.median(error_px(np.array(fused["homography"]), Minv, tr, q)) < 1.0


def _whole_query_parts(synthetic_map):
    """A 30-deg query of the synthetic map searched whole (one accepted part): (q, Minv, tr,
    src, conf, full query features, parts)."""
    img, tr, src = synthetic_map
    q, Minv = warp_query(img[100:260, 120:300], 1.0, 30.0)
    Minv = np.array([[1, 0, 120], [0, 1, 100], [0, 0, 1]]) @ Minv
    conf = reg_conf()
    parts = [search.search_one_part(q, k, src, conf, None, [1.0], 5) for k in range(2)]
    full = query_features(q, (0, q.shape[0]), [1.0], None)
    parts, _ = fuse_mod.whole_query_fallback(full, src, parts, conf, None, 5)
    return q, Minv, tr, src, conf, full, parts


def test_fused_rematch_moves_the_best_part_only_when_as_strong(synthetic_map):
    """One model choice: the full-query re-match around the best part is one more candidate; with
    fewer inliers or a higher NFA than the part it may refine the part's pose (a move within the
    inlier threshold) but not move it (rift poses moved 16 px: SRIF wide oi 57 and 77)."""
    q, Minv, tr, src, conf, full, parts = _whole_query_parts(synthetic_map)
    best = next(p for p in parts if p.get("accepted"))
    H0, n = np.array(best["homography"]), best["inliers"]
    cases = [  # (part's pose moved by map px, its log10 NFA, its inliers, expected)
        (8.0, -1e4, n, "best_part"), (8.0, -1.0, 10 * n, "best_part"), (8.0, -1.0, n, "fused"),
        (2.0, -1e4, 10 * n, "fused"),  # a weaker re-match 2 px away refines the part's pose
    ]  # fmt: skip
    for shift, nfa, inliers, expect in cases:
        H_part = np.array([[1, 0, shift * tr.a], [0, 1, 0], [0, 0, 1.0]]) @ H0
        best.update(homography=H_part.tolist(), log10_nfa=nfa, inliers=inliers, method="rift")
        fused = fuse(full, src, parts, conf, None)
        assert fused["status"] == "registered" and fused["method"] == expect, (shift, nfa, inliers)
        err = np.median(error_px(np.array(fused["homography"]), Minv, tr, q))
        assert (abs(err - shift) < 0.5) if expect == "best_part" else err < 1.0
        assert fused["fused_candidate"].get("kept", True) is (expect == "fused")
        assert fused["pose_source"] == ("rift" if expect == "best_part" else "features")


def test_best_part_pose_must_hold_over_the_whole_query(synthetic_map):
    """When the re-match does not replace the best part's pose, that pose is the whole query's
    only if it is a plausible mapping of the whole query: a perspective that changes the scale
    several times across it is not registered (SRIF oo 77 in a 120-reference mosaic)."""
    q, Minv, tr, src, conf, full, parts = _whole_query_parts(synthetic_map)
    best = next(p for p in parts if p.get("accepted"))
    H0, n = np.array(best["homography"]), best["inliers"]
    shift = np.array([[1, 0, 8.0 * tr.a], [0, 1, 0], [0, 0, 1.0]])
    for tilt, expect in ((0.0, "registered"), (0.004, "not_found")):
        persp = np.array([[1, 0, 0], [0, 1, 0], [tilt, 0, 1.0]])  # in query px
        best.update(homography=(shift @ H0 @ persp).tolist(), log10_nfa=-1e4, inliers=n)
        fused = fuse(full, src, parts, conf, None)
        assert fused["status"] == expect, tilt
        if expect == "not_found":
            assert fused["homography"] is None and "whole query" in fused["reason"]
            assert "scale changes" in fused["reason"]


def test_disagreeing_parts_are_each_rematched_and_the_whole_query_decides(synthetic_map):
    """Two accepted parts at different places: the full query is re-matched around each, and the
    re-match with the lowest NFA wins even when its part was the less significant one (SRIF oo
    pair 129: the re-match around the more significant part was 34 px off)."""
    q, Minv, tr, src, conf, full, parts = _whole_query_parts(synthetic_map)
    right = dict(next(p for p in parts if p.get("accepted")))
    H_wrong = np.array([[1, 0, 60 * tr.a], [0, 1, -45 * tr.a], [0, 0, 1.0]]) @ np.array(right["homography"])
    wrong = {**right, "part": 0, "rows": [0, q.shape[0] // 2], "homography": H_wrong.tolist(),
             "log10_nfa": -1e4}  # fmt: skip
    right.update(part=1, rows=[q.shape[0] // 2, q.shape[0]], log10_nfa=-5.0)
    fused = fuse(full, src, [wrong, right], conf, None)
    assert fused["status"] == "registered" and fused["best_part"] == 1
    assert [r["part"] for r in fused["rematches"]] == [0, 1]
    assert np.median(error_px(np.array(fused["homography"]), Minv, tr, q)) < 1.0
    # parts that agree: one re-match, around the best
    near = {**wrong, "homography": right["homography"]}
    fused = fuse(full, src, [near, right], conf, None)
    assert fused["best_part"] == 0 and "rematches" not in fused


def test_query_features_pool_a_band_stack():
    a, b = texture((120, 140), seed=1), texture((120, 140), seed=2)
    fa = query_features(a, (10, 90), [1.0], FEAT)
    fb = query_features(b, (10, 90), [1.0], FEAT)
    fab = query_features(np.stack([a, b]), (10, 90), [1.0], FEAT)
    assert len(fab) == len(fa) + len(fb) and (fab.width, fab.height) == (140, 80)
    assert np.allclose(fab.xy[: len(fa)], fa.xy) and fab.xy[:, 1].min() >= 10


def test_pooled_bands_register_a_query_whose_primary_band_has_no_structure(synthetic_map):
    """The workflow's stages on a band stack: the primary band is flat (valid, no feature),
    the second band holds the scene; pooled, the query is registered to the truth."""
    from georeg.register.fuse import register_query

    img, tr, src = synthetic_map
    q, Minv = warp_query(img[300:560, 500:760], 1.25, 50.0)  # 0.8 m, rotated
    Minv = np.array([[1, 0, 500], [0, 1, 300], [0, 0, 1]]) @ Minv
    flat = np.where(q > 0, 128, 0).astype(np.uint8)
    conf = reg_conf()
    alone = register_query(flat, src, conf, 0.8, [0.8], seed=4)
    assert alone["status"] == "not_found"
    assert "one value" in alone["reason"]  # said as such, and no source after the features ran
    assert {s["name"] for s in alone["sources"]} <= {"features", "whole_query"}
    res = register_query(np.stack([flat, q]), src, conf, 0.8, [0.8], seed=4)
    assert res["status"] == "registered", res.get("reason")
    err = error_px(np.array(res["homography"]), Minv, tr, q)
    assert np.median(err) < 0.5 and np.percentile(err, 90) < 1.0


def test_paper_centres_cover_the_map_without_replacement():
    c = paper_centres((0, 0, 1000, 800), 400, seed=5)
    assert len(np.unique(c, axis=0)) == len(c) >= 5 * 4
    np.testing.assert_array_equal(c, paper_centres((0, 0, 1000, 800), 400, seed=5))
    assert not np.array_equal(c, paper_centres((0, 0, 1000, 800), 400, seed=6))
    assert part_rows(1163, 2, 0) == (0, 582) and part_rows(1163, 2, 1) == (582, 1163)


def test_geolocation_and_evaluation(tmp_path):
    H = np.array([[0.6, 0.5, 500000.0], [0.45, -0.62, 4100000.0], [0.0, 0.0, 1.0]])
    x, y = map_xy(H, 30, 20)
    assert x.shape == (20, 30) and x[3, 7] == pytest.approx(0.6 * 7 + 0.5 * 3 + 500000)
    # a DSM around the footprint: z = x - 500000
    tr = Affine(1, 0, 499990, 0, -1, 4100020)
    cols = np.arange(80) + 0.5
    dsm = np.tile((499990 + cols - 500000).astype(np.float32), (80, 1))
    with rasterio.open(
        tmp_path / "dsm.tif",
        "w",
        driver="GTiff",
        width=80,
        height=80,
        count=1,
        dtype="float32",
        transform=tr,
        crs="EPSG:32611",
    ) as d:
        d.write(dsm, 1)
    write_geolocation(tmp_path / "g.tif", H, 30, 20, tmp_path / "dsm.tif", "WKT")
    with rasterio.open(tmp_path / "g.tif") as g:
        assert g.count == 3 and g.dtypes[0] == "float64" and (g.width, g.height) == (30, 20)
        xyz = g.read()
    np.testing.assert_allclose(xyz[2], xyz[0] - 500000, atol=1e-3)
    truth = tmp_path / "truth.tif"
    with rasterio.open(
        truth, "w", driver="GTiff", width=30, height=20, count=2, dtype="float64"
    ) as t:
        t.write(np.stack([x + 0.3, y]))
    ev = evaluate(H, truth, 0.5)
    assert ev["m"]["median"] == pytest.approx(0.3) and ev["px"]["max"] == pytest.approx(0.6)
    write_geolocation(tmp_path / "nan.tif", None, 30, 20, None, None)
    with rasterio.open(tmp_path / "nan.tif") as g:
        assert np.isnan(g.read()).all()


# ----------------------------------------------------------------------------- search


@pytest.fixture(scope="module")
def synthetic_map():
    """A 1200 x 1200 m textured map at 1 m with a CRS-like transform."""
    img = texture((1200, 1200), seed=11)
    tr = Affine(1.0, 0, 430000.0, 0, -1.0, 3770000.0)
    return img, tr, map_source(img, np.ones(img.shape, bool), tr)


@pytest.mark.parametrize("strategy", ["paper", "index"])
def test_search_strategies_find_a_warped_crop(synthetic_map, strategy):
    img, tr, src = synthetic_map
    crop = img[700:1000, 150:450]
    q, Minv = warp_query(crop, 1.25, -35.0)  # query at 0.8 m, rotated
    Minv = np.array([[1, 0, 150], [0, 1, 700], [0, 0, 1]]) @ Minv
    conf = reg_conf(strategy=strategy, paper={"neighbourhood_factor": 1.5})
    qf = query_features(q, (0, q.shape[0]), [0.8], FEAT)
    res = search_part(qf, src, conf, 0.8, seed=2)
    assert res["accepted"], res["candidates"]
    assert all(not c["accepted"] for c in res["candidates"][:-1])
    err = error_px(np.array(res["homography"]), Minv, tr, q)
    assert np.median(err) < 0.5 and err.max() < 1.5
    assert res["candidates_tried"] <= (5 if strategy == "index" else 50)


def test_decide_rejects_six_chance_inliers_that_the_paper_rule_accepts():
    rng = np.random.default_rng(4)
    H = np.array([[0.8, 0, 1000.0], [0, -0.8, 5000.0], [0, 0, 1]])  # plausible geometry
    area = 1500.0 * 1500.0
    chance = np.sqrt(area / np.pi * rng.random(94))
    res = np.r_[rng.uniform(0.5, 2.5, 6), chance]
    conf = {"scale_tolerance": 0.3}
    paper = acceptance.decide(H, res, 6, area, 800, 600, 0.8, {**conf, "mode": "paper"})
    nfa = acceptance.decide(
        H, res, 6, area, 800, 600, 0.8, {**conf, "mode": "nfa"}, n_candidates=20
    )
    assert paper["accepted"] and not nfa["accepted"] and nfa["log10_nfa"] > 0
    # 20 tight inliers of 100 are far beyond chance
    res20 = np.r_[rng.uniform(0.3, 1.5, 20), chance[:80]]
    assert acceptance.decide(H, res20, 20, area, 800, 600, 0.8, {**conf, "mode": "nfa"})["accepted"]
    # ... unless the geometry is implausible (mirror image)
    Hm = H * [[1], [-1], [1]]
    bad = acceptance.decide(Hm, res20, 20, area, 800, 600, 0.8, {**conf, "mode": "nfa"})
    assert not bad["accepted"] and "mirrored" in bad["reason"]


# ----------------------------------------------------------------------------- real data


@pytest.fixture(scope="module")
def enmap(shared_data_dir=REPO.parent / "shared" / "data"):
    p = shared_data_dir / "enmap_potsdam" / "enmap_potsdam_mosaic_subset.tif"
    if not p.exists():
        pytest.skip("../shared/data is absent")
    cube = open_query(p)
    with rasterio.open(p) as s:
        tr = s.transform
    return cube, tr


@pytest.mark.shared
@pytest.mark.parametrize("swir", ["2200nm", "1650nm"])
def test_enmap_swir_registers_onto_visible(enmap, swir):
    cube, tr = enmap
    vis, vm, _ = select_band(cube, "650nm")
    v8, _ = stretch_uint8(vis, vm)
    src = map_source(v8, vm, tr)
    sw, sm, _ = select_band(cube, swir)
    s8, _ = stretch_uint8(sw, sm)
    q, Minv = warp_query(s8, 2.0, 25.0)  # query GSD 15 m, rotated by 25 degrees, shifted
    qf = query_features(q, (0, q.shape[0]), [0.5], FEAT)
    res = search_part(qf, src, reg_conf(), 15.0, seed=1)
    assert res["accepted"], res["candidates"]
    err = error_px(np.array(res["homography"]), Minv, tr, q)
    assert np.median(err) < 1.0 and np.percentile(err, 90) < 1.5
    # the same query split in two parts, searched separately, then fused
    parts = []
    for i in range(2):
        rows = part_rows(q.shape[0], 2, i)
        r = search_part(query_features(q, rows, [0.5], FEAT), src, reg_conf(), 15.0, seed=i)
        parts.append({"part": i, **r})
    assert any(p["accepted"] for p in parts)
    fused = fuse(qf, src, parts, reg_conf(), 15.0)
    assert fused["status"] == "registered"
    err = error_px(np.array(fused["homography"]), Minv, tr, q)
    assert np.median(err) < 1.0 and np.percentile(err, 90) < 1.5


def default_register_conf() -> dict:
    """The workflow's default ``register`` section (config/config.yaml)."""
    import yaml

    return yaml.safe_load((REPO / "config" / "config.yaml").read_text())["register"]


def _small_enmap_query(enmap, angle: float, centre: tuple[int, int]):
    """The cube's 650 nm band as the map (float band, its mask, u8, MapSource) and a 150 x 150 px
    crop of its 2200 nm band at 15 m, rotated by ``angle``, centred at ``centre``; Minv: query
    px -> map px."""
    cube, tr = enmap
    vis, vm, _ = select_band(cube, "650nm")
    v8, _ = stretch_uint8(vis, vm)
    src = map_source(v8, vm, tr)
    sw, sm, _ = select_band(cube, "2200nm")
    s8, _ = stretch_uint8(sw, sm)
    q, Minv = warp_query(s8, 2.0, angle)
    c0, r0 = centre[0] - 75, centre[1] - 75
    q = np.ascontiguousarray(q[r0 : r0 + 150, c0 : c0 + 150])
    return vis, vm, v8, src, q, Minv @ np.array([[1.0, 0, c0], [0, 1.0, r0], [0, 0, 1]])


@pytest.mark.shared
@pytest.mark.parametrize(("angle", "centre"), [(25.0, (257, 321)), (140.0, (176, 251))])
def test_small_enmap_swir_query_registers_in_default_config(enmap, angle, centre):
    """A 150 x 150 px EnMAP SWIR query (15 m, rotated) against the cube's own visible band."""
    from georeg.register.fuse import register_query

    tr = enmap[1]
    *_, src, q, Minv = _small_enmap_query(enmap, angle, centre)
    assert q.shape == (150, 150) and (q > 0).mean() > 0.5
    conf = default_register_conf()
    res = register_query(q, src, conf, 15.0, [15.0 / 30.0], seed=3)
    assert res["status"] == "registered", res.get("reason")
    assert res["split"]["parts"] == 1 and "whole query" in res["split"]["reason"]
    err = error_px(np.array(res["homography"]), Minv, tr, q)
    assert np.median(err) < 1.0 and np.percentile(err, 90) < 2.0


@pytest.mark.shared
def test_small_enmap_swir_cube_registers_through_the_query_stage(enmap, tmp_path):
    """The workflow's query stage in its default (`band: auto`, `bands: auto`) on a real
    150 x 150 px EnMAP SWIR cube (bands >= 900 nm, 15 m, rotated 25 deg): band.tif pools 1200
    and 2200 nm, then the default registration stages find it against the 650 nm band."""
    import warnings

    from georeg.register.band import read_query_bands, write_query_band
    from georeg.register.fuse import register_query

    cube, tr = enmap
    vis, vm, _ = select_band(cube, "650nm")
    v8, _ = stretch_uint8(vis, vm)
    src = map_source(v8, vm, tr)
    wl = cube.wavelengths_nm
    swir = np.flatnonzero(wl >= 900.0)
    c0, r0 = 257 - 75, 321 - 75
    planes = []
    for i in swir:
        b, m, _ = select_band(cube, int(i))
        q, Minv = warp_query(np.where(m, b, 0.0).astype(np.float32), 2.0, 25.0)
        planes.append(q[r0 : r0 + 150, c0 : c0 + 150])
    Minv = Minv @ np.array([[1.0, 0, c0], [0, 1.0, r0], [0, 0, 1]])
    path = tmp_path / "swir.tif"
    prof = {"driver": "GTiff", "width": 150, "height": 150, "count": len(swir),
            "dtype": "float32", "nodata": 0.0}  # fmt: skip
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", rasterio.errors.NotGeoreferencedWarning)
        with rasterio.open(path, "w", **prof) as dst:
            dst.write(np.stack(planes))
            for k, i in enumerate(swir):
                dst.set_band_description(k + 1, f"{wl[i]:.2f} nm")
    meta = write_query_band(str(path), "auto", 15.0, tmp_path / "band.tif", tmp_path / "b.json")
    nm = [b["wavelength_nm"] for b in meta["pooled_bands"]]
    assert abs(nm[0] - 1200) < 10 and abs(nm[1] - 2200) < 10 and len(nm) == 2
    u8 = read_query_bands(str(tmp_path / "band.tif"))
    res = register_query(u8, src, default_register_conf(), 15.0, [15.0 / 30.0], seed=3)
    assert res["status"] == "registered", res.get("reason")
    err = error_px(np.array(res["homography"]), Minv, tr, u8[0])
    assert np.median(err) < 1.0 and np.percentile(err, 90) < 2.0


@pytest.mark.shared
def test_dense_search_finds_real_swir(enmap):
    """CFOG correlation over rotations: the EnMAP 2200 nm query's rotation and place found in the
    650 nm band with no feature search at all."""
    from georeg.register.dense import dense_search

    vis, vm, v8, src, q, Minv = _small_enmap_query(enmap, 140.0, (176, 251))
    r = dense_search(q, 0.5, v8, 10.0)
    assert r is not None and abs(((r.angle_deg - 140.0) + 180) % 360 - 180) <= 10.0
    assert r.log10_nfa < -3


def test_kdtree_matches_do_not_depend_on_what_the_process_drew_before():
    """Above ``FLAT_MAX`` map descriptors the 2-NN search is a randomised kd-tree: its matches
    must be the same whatever OpenCV's process-wide generator was left at (a library user
    registering several queries in one process)."""
    import cv2

    rng = np.random.default_rng(0)
    md = rng.random((matching.FLAT_MAX + 2000, 32), dtype=np.float32)
    q = rng.random((300, 32), dtype=np.float32)
    got = []
    for s in (1, 2):
        cv2.setRNGSeed(s)
        cv2.randu(np.zeros((10, 10), np.float32), 0, 1)
        d, ii = matching.knn2(md)(q)
        got.append(ii)
    assert np.array_equal(got[0], got[1])


def test_structureless_names_a_query_without_anything_to_match():
    from georeg.register.fuse import structureless

    rng = np.random.default_rng(0)
    tex = rng.integers(1, 255, (40, 50)).astype(np.uint8)
    assert "no valid pixel" in structureless(np.zeros((40, 50), np.uint8))
    assert "one value" in structureless(np.where(tex > 30, 77, 0).astype(np.uint8))  # holes allowed
    assert "one value" in structureless(np.stack([np.full((40, 50), 9, np.uint8), np.full((40, 50), 200, np.uint8)]))
    assert structureless(tex) is None
    assert structureless(np.stack([np.full((40, 50), 9, np.uint8), tex])) is None  # one band suffices
