"""Very small queries (georeg.register.small, ``register.small``): the similarity fit, the
binomial-tail NFA, and on real data (../shared/data, skipped when absent) a 45-100 px SWIR query
of a tuning city registered at its true place while the same query against another city's map
is rejected."""

from __future__ import annotations

import math
from pathlib import Path

import benchmark_module
import numpy as np
import pytest

from georeg.register import acceptance, matching
from georeg.register.small import fit_similarity, small_conf

ROOT = Path(__file__).resolve().parents[1]
DATA = ROOT.parent / "shared" / "data" / "swir_dates"


def _similarity(theta_deg: float, scale: float, t: tuple[float, float]) -> np.ndarray:
    """query (col, row) -> map (x, y), y up: rotation, scale, shift and the row flip."""
    c, s = math.cos(math.radians(theta_deg)), math.sin(math.radians(theta_deg))
    return np.array([[scale * c, -scale * s, t[0]], [-scale * s, -scale * c, t[1]], [0, 0, 1.0]])


def test_fit_similarity_recovers_a_flipped_similarity_among_outliers():
    rng = np.random.default_rng(3)
    H = _similarity(37.0, 19.5, (5000.0, -3000.0))  # 19.5 m per query px, map y up
    q = rng.uniform(0, 80, (60, 2))
    m = matching.apply_h(H, q) + rng.normal(0, 3.0, (60, 2))  # 0.3 feature px noise at 10 m
    bad = rng.random(60) < 0.4
    m[bad] += rng.uniform(-80, 80, (int(bad.sum()), 2))  # 40 % outliers within 8 px
    fit = fit_similarity(q, m, 10.0, 3.0, seed=1)
    assert fit is not None
    grid = rng.uniform(0, 80, (50, 2))
    err = np.linalg.norm(matching.apply_h(fit.H, grid) - matching.apply_h(H, grid), axis=1)
    assert np.median(err) < 5.0  # < 0.5 feature px
    assert fit.inliers[~bad].mean() > 0.9
    assert np.linalg.det(fit.H[:2, :2]) < 0  # the row flip is kept (plausibility needs it)


def test_binomial_nfa_rejects_uniform_residuals_and_accepts_a_cluster():
    rng = np.random.default_rng(5)
    disc = math.pi * 8.0**2
    worst = math.inf
    for _ in range(200):  # chance: residuals uniform in the disc of radius 8 px
        r = 8.0 * np.sqrt(rng.random(40))
        worst = min(worst, acceptance.log10_nfa_binomial(r, disc, 100, 2)[0])
    assert worst > 0.0
    r = np.r_[rng.uniform(0, 1.5, 20), 8.0 * np.sqrt(rng.random(20))]
    assert acceptance.log10_nfa_binomial(r, disc, 100, 2)[0] < -3.0
    # never looser than the ORSA bound of the same residuals (its sample is 4, here 2: compare
    # with the bound at sample 2 written out)
    lnfa, k, e = acceptance.log10_nfa_binomial(r, disc, 1, 2)
    p = math.pi * e**2 / disc
    orsa = (math.log10(len(r) - 2) + float(acceptance.log10_binom(len(r), k))
            + float(acceptance.log10_binom(k, 2)) + (k - 2) * math.log10(p))  # fmt: skip
    assert lnfa <= orsa + 1e-9


def test_small_conf_defaults_and_override():
    assert small_conf({})["max_side_px"] == 160
    assert small_conf({"small": {"enabled": True}})["enabled"] is True


# ----------------------------------------------------------------------------- real data


def _bench():
    return benchmark_module.load("bench_crossspectral")


needs_data = pytest.mark.skipif(not DATA.is_dir(), reason="../shared/data/swir_dates absent")


@needs_data
def test_small_sentinel2_query_registers_at_its_true_place_and_not_on_another_city():
    """A small-set query of a tuning city (the benchmark's ``--set small``) that the feature
    search misses: with ``register.small`` the fallback finds it within 5 map px; without it
    rift does (its search at the 10 m map's GSD, ``rift.max_upsample`` 2.5 since session 53; at
    the query's 20 m nothing found it); against another city's map it stays not found."""
    import cv2

    bc = _bench()
    from georeg.index.features import merged_conf
    from georeg.register.fuse import register_query
    from georeg.register.search import MapSource

    cv2.setNumThreads(1)
    scenes, qs = bc.build_small_set(6, 11)
    by = {s.name: s for s in scenes}
    name = "small_s2_saclay_w_rev_102_1.6um"
    q = next(x for x in qs if x.name == name)
    neg = next(x for x in qs if x.name.startswith(name + "_vs_"))
    assert max(q.bands[next(iter(q.bands))].shape) <= 100
    on = bc._deep(bc.workflow_register_conf(), {"small": {"enabled": True}})
    off = bc._deep(bc.workflow_register_conf(), {"small": {"enabled": False}})
    out = {}
    for key, qq, conf in (("off", q, off), ("on", q, on), ("neg", neg, on)):
        sc = by[qq.map_scene]
        g = sc.map_gsd
        mxy, mdesc, mang, msize = bc.map_features(sc, g, merged_conf(bc.FEATURES))
        src = MapSource(mxy, mdesc, g, angle=mang, scale=msize * g)
        u8 = bc.query_stack(qq, "auto")
        res = register_query(u8, src, conf, qq.gsd, [qq.gsd / g], 11,
                             bc.plain_window_reader(sc))  # fmt: skip
        out[key] = (res, bc.judge(qq, sc, {"accepted": res["status"] == "registered",
                                            "H": None if res.get("homography") is None
                                            else np.array(res["homography"])}))  # fmt: skip
    off = out["off"][0]  # the feature search misses it; rift, after the small path, finds it
    assert [x["name"] for x in off["sources"] if x.get("accepted")] == ["rift"], off["sources"]
    assert out["off"][1]["outcome"] == "success" and out["off"][1]["error_px"] < 5.0
    assert out["on"][1]["outcome"] == "success", out["on"][0]["split"].get("small")
    assert out["on"][1]["error_px"] < 5.0
    assert out["on"][0]["split"]["small"]["ran"]
    assert out["neg"][0]["status"] == "not_found"
    assert out["neg"][0]["split"]["small"]["ran"]


def test_dense_search_centre_box_restricts_the_query_centre():
    """``dense_search(centre_box=...)``: the peak's query centre stays inside the box; a box
    around the true place finds it to a pixel."""
    import cv2

    from georeg.register.dense import dense_search

    rng = np.random.default_rng(0)
    m = cv2.GaussianBlur(rng.random((200, 200)).astype(np.float32), (0, 0), 2.0)
    m = (1 + 254 * (m - m.min()) / (m.max() - m.min())).astype(np.uint8)
    q = m[60:120, 110:170].copy()  # true centre (139.5, 89.5) in window px
    centre = np.array([[(q.shape[1] - 1) / 2, (q.shape[0] - 1) / 2]])
    r = dense_search(q, 1.0, m, 10.0, 96, centre_box=(120.0, 70.0, 160.0, 110.0))
    c = matching.apply_h(r.S, centre)[0]
    assert np.hypot(c[0] - 139.5, c[1] - 89.5) < 1.5 and r.angle_deg == 0.0
    r2 = dense_search(q, 1.0, m, 10.0, 96, centre_box=(30.0, 30.0, 80.0, 80.0))
    c2 = matching.apply_h(r2.S, centre)[0]
    assert 29.0 <= c2[0] <= 81.0 and 29.0 <= c2[1] <= 81.0


def test_dense_search_further_peaks_find_a_second_copy_and_stay_apart():
    """``dense_search(n_peaks=3)``: with the query pasted at two places of the map, the best
    peak and the next one are the two places (both at 0 deg, within a pixel), in decreasing
    score; every further peak is > 20 deg or > ``apart_px`` from the ones before it."""
    import cv2

    from georeg.register.dense import dense_search

    rng = np.random.default_rng(1)
    m = cv2.GaussianBlur(rng.random((220, 220)).astype(np.float32), (0, 0), 2.0)
    m = (1 + 254 * (m - m.min()) / (m.max() - m.min())).astype(np.uint8)
    q = m[30:90, 40:100].copy()  # true centre (69.5, 59.5)
    m[130:190, 140:200] = q  # a second copy, centre (169.5, 159.5)
    centre = np.array([[(q.shape[1] - 1) / 2, (q.shape[0] - 1) / 2]])
    r = dense_search(q, 1.0, m, 10.0, 96, n_peaks=3, apart_px=8.0)
    assert r is not None and len(r.others) == 2
    peaks = [(r.S, r.angle_deg, r.score)] + r.others
    places = [matching.apply_h(S, centre)[0] for S, _, _ in peaks]
    truth = [np.array([69.5, 59.5]), np.array([169.5, 159.5])]
    got = sorted(min(range(2), key=lambda i: np.hypot(*(p - truth[i]))) for p in places[:2])
    assert got == [0, 1]
    for p, (_, a, _) in zip(places[:2], peaks[:2], strict=True):
        assert min(np.hypot(*(p - t)) for t in truth) < 1.5 and a == 0.0
    scores = [s for _, _, s in peaks]
    assert scores == sorted(scores, reverse=True)
    for i in range(1, 3):
        for j in range(i):
            dang = abs((peaks[i][1] - peaks[j][1] + 180.0) % 360.0 - 180.0)
            assert dang > 20.0 or np.hypot(*(places[i] - places[j])) > 8.0 - 1.5


def _field(seed: int, shape: tuple[int, int], sigma: float = 2.0) -> np.ndarray:
    """A smooth random uint8 image 1..255."""
    import cv2

    rng = np.random.default_rng(seed)
    m = cv2.GaussianBlur(rng.random(shape).astype(np.float32), (0, 0), sigma)
    return (1 + 254 * (m - m.min()) / (m.max() - m.min())).astype(np.uint8)


def test_cfog_null_accepts_the_true_place_and_rejects_an_unrelated_map():
    """``null_scan.scan``: a rotated, noisy, contrast-inverted crop of the map is found with a
    block-maxima NFA far below the default bound and ``fine_pose`` puts it within a pixel and a
    degree; the same kind of query cut from an unrelated field is not accepted (5 draws)."""
    import cv2

    from georeg.register.null_scan import NULL_DEFAULTS, fine_pose, scan

    m = _field(2, (320, 320))
    theta = 23.0
    A = cv2.getRotationMatrix2D((200.0, 120.0), theta, 1.0)  # query centre = map (200, 120)
    A[:, 2] += (30.0 - 200.0, 30.0 - 120.0)
    rng = np.random.default_rng(4)
    q = cv2.warpAffine(m.astype(np.float32), A, (61, 61), flags=cv2.INTER_LINEAR)
    q = np.clip(256.0 - q + rng.normal(0, 25.0, q.shape), 1, 255).astype(np.uint8)
    nd = NULL_DEFAULTS
    args = (10.0, 96, nd["block_px"], nd["exclude_px"], nd["tail_k"])
    r = scan(q, 1.0, m, *args)
    bound = nd["log_nfa_max"]
    assert r is not None and r["log10_nfa"] < bound - 2.0
    S, ang, _ = fine_pose(q, 1.0, m, r["S"], r["angle_deg"])
    c = matching.apply_h(S, np.array([[30.0, 30.0]]))[0]
    assert np.hypot(c[0] - 200.0, c[1] - 120.0) < 1.0
    assert abs((ang + theta + 180.0) % 360.0 - 180.0) <= 1.0  # cv2's angle is counter-clockwise
    for seed in range(5):
        other = _field(100 + seed, (61, 61))
        ru = scan(other, 1.0, m, *args)
        assert ru is not None and ru["log10_nfa"] > bound


@needs_data
def test_cfog_null_registers_a_tiny_sentinel2_query_and_rejects_another_city():
    """``register.small.null_test`` on a tiny query of a tuning city (``--set tiny``, 52 px,
    Sentinel-2 SWIR 20 m vs RGB 10 m of another date) that the candidate windows' guided
    re-match rejects (log10 NFA +4.9 to +6.0): the whole map's CFOG peak passes the top-spacing
    test and lands within 5 map px of the truth; the same query against another city's map
    does not pass."""
    import cv2

    bc = _bench()
    from georeg.index.features import merged_conf
    from georeg.register.null_scan import null_conf
    from georeg.register.search import MapSource
    from georeg.register.small import null_register, small_conf

    cv2.setNumThreads(1)
    scenes, qs = bc.build_small_set(5, 11, bc.TINY_SIDES, "tiny_", 600)
    by = {s.name: s for s in scenes}
    name = "tiny_s2_abudhabi_102_2.2um"
    q = next(x for x in qs if x.name == name)
    neg = next(x for x in qs if x.name.startswith(name + "_vs_"))
    conf = bc._deep(bc.workflow_register_conf(), {"small": {"null_test": {"enabled": True}}})
    bound = null_conf(small_conf(conf))["log_nfa_max"]
    out = {}
    for key, qq in (("pos", q), ("neg", neg)):
        sc = by[qq.map_scene]
        g = sc.map_gsd
        mxy, mdesc, mang, msize = bc.map_features(sc, g, merged_conf(bc.FEATURES))
        src = MapSource(mxy, mdesc, g, angle=mang, scale=msize * g)
        rec = null_register(bc.query_stack(qq, "auto"), qq.gsd, src, conf,
                            bc.plain_window_reader(sc))  # fmt: skip
        H = None if rec.get("homography") is None else np.array(rec["homography"])
        out[key] = (rec, bc.judge(qq, sc, {"accepted": rec["accepted"], "H": H}))
    rec, j = out["pos"]
    assert rec["accepted"] and rec["log10_nfa"] < bound, rec
    assert j["outcome"] == "success" and j["error_px"] < 5.0
    assert rec["null_blocks"] > 1000 and rec["gap"] > 0
    assert not out["neg"][0]["accepted"] and out["neg"][0]["log10_nfa"] > bound


def _crop_scene() -> tuple:
    """A 300 px field (map x = col g, y = -row g, g = 10), a 61 px crop of it rotated by 40 deg
    whose centre is map px (150, 170), a plain-array MapSource, a window reader and the crop's
    warp A (map px -> query px)."""
    import cv2

    from georeg.register.search import MapSource

    g = 10.0
    m = _field(5, (300, 300))
    A = cv2.getRotationMatrix2D((150.0, 170.0), -40.0, 1.0)  # query centre = map px (150, 170)
    A[:, 2] += (30.0 - 150.0, 30.0 - 170.0)
    q = cv2.warpAffine(m.astype(np.float32), A, (61, 61), flags=cv2.INTER_LINEAR)
    q = np.clip(q, 1, 255).astype(np.uint8)
    src = MapSource(np.array([[0.0, 0.0], [299 * g, -299 * g]]), np.zeros((2, 128), np.float32), g)

    def read(b):
        c0, c1 = max(0, math.floor(b[0] / g)), min(300, math.ceil(b[2] / g) + 1)
        r0, r1 = max(0, math.floor(-b[3] / g)), min(300, math.ceil(-b[1] / g) + 1)
        win = m[r0:r1, c0:c1].astype(np.float32)
        return win, np.array([[g, 0, c0 * g], [0, -g, -r0 * g], [0, 0, 1.0]])

    return g, q, src, read, A


def test_null_register_accepts_a_synthetic_crop_records_the_evidence_and_skips_large_maps():
    """``small.null_register`` on plain arrays (map x = col g, y = -row g): a rotated crop of
    the map is accepted with its homography within a map pixel of the truth and the evidence in
    the record; with ``max_map_px`` below the map's size the tiled scan finds the same place, and
    with ``max_tiled_map_px`` below it too, the scan is not run."""

    from georeg.register.small import null_register

    g, q, src, read, A = _crop_scene()

    conf = {"small": {"null_test": {"enabled": True}}}
    rec = null_register(q, g, src, conf, read)
    assert rec["accepted"], rec
    c = matching.apply_h(np.array(rec["homography"]), np.array([[30.0, 30.0]]))[0]
    assert np.hypot(c[0] / g - 150.0, -c[1] / g - 170.0) < 1.0
    for k in ("score", "null_max", "gap", "tail_scale", "null_blocks", "log10_p", "statistic"):
        assert k in rec
    assert rec["log10_nfa"] < -3.0 and rec["null_blocks"] >= 30
    # above max_map_px: the tiled scan (null_scan.tiled_scan) gives the same place; above its cap, none
    tiled = null_register(q, g, src, {"small": {"null_test": {"max_map_px": 1000}}}, read)
    assert tiled["accepted"] and tiled["scan"] == "tiled" and rec["scan"] == "whole", tiled
    ct = matching.apply_h(np.array(tiled["homography"]), np.array([[30.0, 30.0]]))[0]
    assert np.hypot(*(ct - c)) < 0.2 * g
    capped = {"small": {"null_test": {"max_map_px": 1000, "max_tiled_map_px": 1000}}}
    small = null_register(q, g, src, capped, read)
    assert not small["accepted"] and "too large for the tiled scan" in small["reason"]


def test_null_check_replaces_a_feature_fit_the_scan_contradicts_and_keeps_one_it_confirms():
    """``small.null_check``: a small query's fused feature fit is compared with the whole-map
    CFOG scan. The true fit agrees and is kept; a fit 12 map px off conflicts with the scan's
    significant peak and is replaced by it (within a map pixel of the truth); switched off, or
    when the registration is the scan's own, nothing is run; above ``max_map_px`` the check
    does not tile."""
    import cv2

    from georeg.register.small import null_check

    g, q, src, read, A = _crop_scene()

    # the truth: query px -> map px (inverse of A) -> map x = col g, y = -row g
    Ai = cv2.invertAffineTransform(A)
    T = np.diag([g, -g, 1.0]) @ np.vstack([Ai, [0, 0, 1.0]])
    conf = {"small": {"null_test": {"enabled": True}}}
    fused = {"status": "registered", "homography": T.tolist(), "inliers": 9}
    out, rec = null_check(q, fused, src, conf, g, read)
    assert rec["outcome"] == "agrees" and not rec["replaced"] and out is fused
    off = np.array([[1, 0, 12 * g], [0, 1, 0], [0, 0, 1.0]]) @ T  # 12 map px east
    out, rec = null_check(q, {**fused, "homography": off.tolist()}, src, conf, g, read)
    assert rec["outcome"] == "conflict" and rec["replaced"], rec
    assert rec["distance_corr_px"] > rec["conflict_px"]
    c = matching.apply_h(np.array(out["homography"]), np.array([[30.0, 30.0]]))[0]
    assert np.hypot(c[0] / g - 150.0, -c[1] / g - 170.0) < 1.0
    assert out["feature_homography"] == off.tolist()
    no = {"small": {"null_test": {"enabled": True, "check": False}}}
    assert null_check(q, fused, src, no, g, read) == (fused, None)
    own = {"cfog_null": {"accepted": True}}
    assert null_check(q, fused, src, conf, g, read, own) == (fused, None)
    # a map above max_map_px: the check does not run the tiled scan (its cost per query)
    big = {"small": {"null_test": {"enabled": True, "max_map_px": 1000}}}
    out, rec = null_check(q, {**fused, "homography": off.tolist()}, src, big, g, read)
    assert out["homography"] == off.tolist() and not rec["replaced"]
    assert "tiled scan" in rec["reason"]


@needs_data
def test_null_check_turns_a_distorted_tiny_feature_fit_into_the_scans_true_place():
    """A tiny query of a tuning city (``--set tiny``, 79 px) whose 12-inlier feature fit is
    7.5 map px off at its centre (a false accept before the check): the whole-map CFOG scan's
    significant peak is 5 correlation px away, so the workflow default replaces the fit and the
    query ends within the success bound of the truth (without the check, the turn of weak
    feature fits does too)."""
    import cv2

    bc = _bench()
    cv2.setNumThreads(1)
    scenes, qs = bc.build_small_set(5, 11, bc.TINY_SIDES, "tiny_", 600)
    by = {s.name: s for s in scenes}
    qi, q = next((i, x) for i, x in enumerate(qs) if x.name == "tiny_s2_saclay_e_103_1.6um")
    sc = by[q.map_scene]
    res = bc.run_method(q, sc, bc.METHODS["wf_default"], 11 + qi)
    assert res["null_check"] == "conflict"
    j = bc.judge(q, sc, res)
    assert j["outcome"] == "success" and j["error_px"] < 3.0, j
    # what the check corrects: without it, and without the turn of weak feature fits
    # (``fuse.turn_weak_fit``, ``rift.turn_deg``), the fit is a false accept; the turn alone
    # brings it within the success bound too
    plain = {"pipeline": {"small": {"null_test": {"check": False}}, "rift": {"turn_deg": 0}}, "bands": "auto"}
    assert bc.judge(q, sc, bc.run_method(q, sc, plain, 11 + qi))["outcome"] == "false_accept"
    turned = bc.judge(q, sc, bc.run_method(q, sc, bc.METHODS["wf_nocheck"], 11 + qi))
    assert turned["outcome"] == "success", turned


def _peaks_view(m: np.ndarray, g: float):
    """A MapView of the uint8 field ``m`` (map x = col g, y = -row g) with a window reader."""
    from georeg.register.search import MapSource, MapView

    h, w = m.shape
    src = MapSource(np.array([[0.0, 0.0], [(w - 1) * g, -(h - 1) * g]]),
                    np.zeros((2, 128), np.float32), g)  # fmt: skip

    def read(b):
        c0, c1 = max(0, math.floor(b[0] / g)), min(w, math.ceil(b[2] / g) + 1)
        r0, r1 = max(0, math.floor(-b[3] / g)), min(h, math.ceil(-b[1] / g) + 1)
        win = m[r0:r1, c0:c1].astype(np.float32)
        return win, np.array([[g, 0, c0 * g], [0, -g, -r0 * g], [0, 0, 1.0]])

    return MapView(src, read)


def test_peaks_source_registers_an_inverted_crop_and_refuses_an_unrelated_query():
    """``small.peaks_source`` (source ``cfog_peaks``) on plain arrays: a 161 px crop of the map,
    rotated, its contrast inverted and noisy (larger than the small-query sources take), is
    accepted at its true place within a map pixel, its dense log10 NFA counting the tests
    before it; a query cut from an unrelated field is refused with every peak checked; with
    ``peaks: 0`` the source does not run, and on a map too large for one FFT neither."""
    import cv2

    from georeg.register.search import QueryInput
    from georeg.register.small import peaks_source

    g = 10.0
    m = _field(7, (420, 420), sigma=2.5)
    A = cv2.getRotationMatrix2D((260.0, 190.0), 33.0, 1.0)  # query centre = map px (260, 190)
    A[:, 2] += (80.0 - 260.0, 80.0 - 190.0)
    rng = np.random.default_rng(8)
    q = cv2.warpAffine(m.astype(np.float32), A, (161, 161), flags=cv2.INTER_LINEAR)
    q = np.clip(256.0 - q + rng.normal(0, 30.0, q.shape), 1, 255).astype(np.uint8)
    view = _peaks_view(m, g)
    conf: dict = {}
    parts, rec = peaks_source(QueryInput(q, None, g, [1.0], 0, tests_before=50), view, [], conf)
    assert rec["ran"] and rec["accepted"] and rec["tests"] == 50 + rec["candidates"], rec
    assert len(parts) == 1 and parts[0]["method"] == "cfog_peaks"
    c = matching.apply_h(np.array(parts[0]["homography"]), np.array([[80.0, 80.0]]))[0]
    assert np.hypot(c[0] / g - 260.0, -c[1] / g - 190.0) < 1.0
    assert parts[0]["log10_nfa"] < -3.0
    other = _field(99, (161, 161), sigma=2.5)
    parts, rec = peaks_source(QueryInput(other, None, g, [1.0], 0, tests_before=50), view, [], conf)
    assert rec["ran"] and not rec["accepted"] and parts == [], rec
    assert len(rec["peaks"]) == rec["candidates"] == 5
    assert min(p["log10_nfa"] for p in rec["peaks"] if p["log10_nfa"] is not None) > -3.0
    off = {"small": {"null_test": {"peaks": 0}}}
    assert not peaks_source(QueryInput(q, None, g, [1.0]), view, [], off)[1]["ran"]
    big = {"small": {"null_test": {"max_map_px": 1000}}}
    parts, rec = peaks_source(QueryInput(q, None, g, [1.0]), view, [], big)
    assert not rec["ran"] and "one FFT" in rec["reason"]


@pytest.mark.skipif(not (DATA / "landsat_pucallpa" / "2000.tif").exists(), reason="Landsat Pucallpa absent")
def test_peaks_source_registers_a_cross_date_crop_the_features_miss_and_not_its_blanked_map():
    """Landsat Pucallpa (``bench_devset``, seed 11, checking half): the 2005 SWIR crop 1 on the
    2000 red/green map, which the feature search and rift do not register (session 45's record):
    one of the CFOG correlation's best places holds 28 % of the tie points against at most 8 %
    elsewhere and passes the dense count over the workflow's 74 tests within 2 map px of the
    truth; on the same map with the crop's place blanked no peak does."""
    import cv2

    bd = benchmark_module.load("bench_devset")
    bx = _bench()
    from georeg.register.search import MapSource, MapView, QueryInput
    from georeg.register.small import peaks_source

    cv2.setNumThreads(1)
    scenes, queries = bd.build_pucallpa(11)
    by = {s.name: s for s in scenes}
    out = {}
    for name in ("puc_2005_on_2000_1_1.6um", "puc_2005_on_2000_1_1.6um_blanked"):
        q = next(x for x in queries if x.name == name)
        sc = by[q.map_scene]
        g = sc.map_gsd
        h, w = sc.map_gray.shape
        src = MapSource(np.array([[0.0, 0.0], [(w - 1) * g, -(h - 1) * g]]),
                        np.zeros((2, 128), np.float32), g)  # fmt: skip
        qi = QueryInput(next(iter(q.bands.values())), None, q.gsd, [1.0], 0, tests_before=69)
        parts, rec = peaks_source(qi, MapView(src, bx.plain_window_reader(sc)), [], {})
        H = np.array(parts[0]["homography"]) if parts else None
        out[name] = (rec, bx.judge(q, sc, {"accepted": bool(parts), "H": H}))
    rec, j = out["puc_2005_on_2000_1_1.6um"]
    assert rec["accepted"] and j["outcome"] == "success" and j["error_px"] < 2.0, (rec, j)
    assert rec["tests"] == 74 and rec["peaks"][rec["peak"]]["log10_nfa"] < -3.0
    rec, j = out["puc_2005_on_2000_1_1.6um_blanked"]
    assert rec["ran"] and not rec["accepted"] and j["outcome"] == "rejected", rec


def test_dense_nfa_counts_a_quarter_of_the_tie_points_and_stays_finite():
    """``small.dense_nfa``: chance support (at the moved poses' rate) is not significant, a
    clear excess is, the count of tests adds its decades, and a perfect match stays a finite
    number (registration.json); a check without moved poses has no figure."""
    from georeg.register.small import NFA_FLOOR, dense_nfa

    chance = {"tie_points": 200, "supported": 0.08, "supported_moved": [0.06, 0.08, 0.05, 0.07]}
    assert dense_nfa(chance, 10) > 0.0
    clear = {**chance, "supported": 0.4}
    assert dense_nfa(clear, 10) < -3.0
    assert math.isclose(dense_nfa(clear, 1000) - dense_nfa(clear, 10), 2.0)
    perfect = {"tie_points": 2000, "supported": 1.0, "supported_moved": [0.0] * 4}
    v = dense_nfa(perfect, 10)
    assert math.isfinite(v) and v == 1.0 + NFA_FLOOR
    assert dense_nfa({"tie_points": 200, "supported": 0.4}, 10) is None
