"""The optional location prior (georeg.io.prior): parsed and checked, the map clipped to it,
fewer candidates tested, a prior elsewhere ends not found, recorded in the result."""

from __future__ import annotations

import json

import numpy as np
import pytest
from test_register import (
    FEAT,
    error_px,
    reg_conf,
    synthetic_map,  # noqa: F401  (fixture)
    warp_query,
)

from georeg.io.errors import InputError
from georeg.io.prior import check_prior, prior_bounds, prior_record
from georeg.register.fuse import register_query
from georeg.register.search import clip_to_prior, index_candidates, query_features

UTM50 = "EPSG:32650"


def test_prior_forms_and_errors():
    assert prior_bounds(None, UTM50) is None
    assert prior_bounds({"box": [1, 2, 3, 4]}, UTM50) == (1, 2, 3, 4)
    assert prior_bounds([1, 2, 3, 4], None) == (1, 2, 3, 4)
    assert prior_bounds({"centre": [100.0, 200.0], "radius_m": 50}, UTM50) == (50, 150, 150, 250)
    # a map in US survey feet: a radius in metres is more feet
    b = prior_bounds({"centre": [0.0, 0.0], "radius_m": 30.48}, "EPSG:2992")
    assert b is not None and abs(b[2] - 100.0) < 0.1
    # lon/lat: the centre lands where pyproj puts it, the box covers the corners
    from pyproj import Transformer

    x, y = Transformer.from_crs("EPSG:4326", UTM50, always_xy=True).transform(117.0, 32.0)
    c = prior_bounds({"centre": [117.0, 32.0], "radius_m": 1000, "crs": "lonlat"}, UTM50)
    assert c is not None and abs((c[0] + c[2]) / 2 - x) < 1e-6 and abs(c[2] - c[0] - 2000) < 1e-6
    bx = prior_bounds({"box": [116.99, 31.99, 117.01, 32.01], "crs": "lonlat"}, UTM50)
    assert bx is not None and bx[0] < x < bx[2] and bx[1] < y < bx[3]
    bad = [
        {"box": [3, 2, 1, 4]},  # x0 > x1
        {"centre": [1, 2]},  # no radius
        {"centre": [1, 2], "radius_m": -5},
        {"centre": [1, 2], "radius_m": 5, "box": [0, 0, 1, 1]},
        {"box": [0, 0, 1, 1], "crs": "wgs84"},
        {"centre": [200.0, 10.0], "radius_m": 5, "crs": "lonlat"},
        {"box": [0, 0, 1]},
        {"centre": [0, 0], "radius_m": 5, "where": "here"},
    ]
    for p in bad:
        with pytest.raises(ValueError, match="prior"):
            check_prior(p)
    with pytest.raises(InputError, match="band.json: prior.radius_m"):
        prior_bounds({"centre": [1, 2], "radius_m": 0}, UTM50, "band.json")
    assert prior_record(None, None) is None
    assert prior_record({"box": [1, 2, 3, 4]}, (1, 2, 3, 4)) == {
        "given": {"box": [1, 2, 3, 4]}, "bounds": [1.0, 2.0, 3.0, 4.0]}  # fmt: skip


def test_clipped_source_sees_only_the_prior(synthetic_map):  # noqa: F811
    _, _, src = synthetic_map
    box = (430100.0, 3769100.0, 430400.0, 3769400.0)
    v = src.clipped(box)
    assert v.bounds == pytest.approx(box, abs=1.0)
    ids = v.features_in((430000.0, 3768800.0, 431200.0, 3770000.0))
    xy = np.asarray(src.xy)[ids]
    assert len(ids) > 50 and (xy[:, 0] >= box[0]).all() and (xy[:, 0] <= box[2]).all()
    assert len(v.features_in((431000.0, 3769700.0, 431100.0, 3769800.0))) == 0
    # a prior grown by half the query's ground diagonal
    g = clip_to_prior(src, box, 300, 400, 1.0, [1.0])
    assert g.clip == pytest.approx((430100 - 250, 3769100 - 250, 430400 + 250, 3769400 + 250))
    assert clip_to_prior(src, None, 300, 400, 1.0, [1.0]) is src


def _query(img):
    crop = img[700:1000, 150:450]
    q, Minv = warp_query(crop, 1.25, -35.0)  # query at 0.8 m, rotated
    return q, np.array([[1, 0, 150], [0, 1, 700], [0, 0, 1]]) @ Minv


def test_a_small_prior_is_one_candidate_and_a_large_one_caps_the_count(synthetic_map):  # noqa: F811
    img, tr, src = synthetic_map
    q, _ = _query(img)
    qf = query_features(q, (0, q.shape[0]), [0.8], FEAT)
    diag = float(np.hypot(*q.shape)) * 0.8
    near = clip_to_prior(src, (430250.0, 3769100.0, 430350.0, 3769200.0), q.shape[1], q.shape[0],
                         0.8, [0.8])  # fmt: skip
    cands = index_candidates(qf, near, diag, {"top_candidates": 8})
    assert len(cands) == 1 and cands[0][0] == near.bounds
    wide = clip_to_prior(src, (430000.0, 3768800.0, 431200.0, 3770000.0), 10, 10, 0.8, [0.8])
    assert len(index_candidates(qf, wide, 300.0, {"top_candidates": 8})) <= 8


def test_register_query_with_a_prior_registers_with_fewer_tests_and_one_elsewhere_is_refused(
    synthetic_map,  # noqa: F811
):
    img, tr, src = synthetic_map
    q, Minv = _query(img)
    conf = reg_conf(parts=1)
    free = register_query(q, src, conf, 0.8, [0.8], seed=2)
    # the truth's centre (map x 430300, y 3769150) inside a 200 m box, in map coordinates
    prior = {"centre": [430310.0, 3769140.0], "radius_m": 100.0}
    res = register_query(q, src, conf, 0.8, [0.8], seed=2, prior=prior)
    assert free["status"] == res["status"] == "registered"
    err = error_px(np.array(res["homography"]), Minv, tr, q)
    assert np.median(err) < 0.5 and err.max() < 1.5
    p0 = res["parts"][0]
    assert p0["candidates_available"] == 1 < free["parts"][0]["candidates_available"]
    assert res["prior"]["bounds"] == [430210.0, 3769040.0, 430410.0, 3769240.0]
    assert json.loads(json.dumps(res["prior"]))["given"] == prior
    assert [s["name"] for s in res["sources"]][0] == "features" and res["sources"][0]["accepted"]
    # a prior 600 m away from the truth: nothing there, not found
    away = register_query(q, src, conf, 0.8, [0.8], seed=2,
                          prior={"centre": [430900.0, 3769700.0], "radius_m": 50.0})  # fmt: skip
    assert away["status"] == "not_found"


def test_sources_run_in_order_only_while_nothing_is_accepted(monkeypatch):
    """fuse.run_sources: a source is one function + one entry of fuse.SOURCES; it runs only while
    no candidate is accepted, and the record says which ran, what each tried, which accepted."""
    from georeg.register import fuse
    from georeg.register.search import MapView, QueryInput

    calls, seen = [], []

    def make(name, accept):
        def source(q, view, parts, conf):
            calls.append(name)
            seen.append(q.tests_before)
            part = {"part": len(parts), "accepted": accept, "candidates_tried": 2}
            return [*parts, part], {"ran": True, "candidates": 2}

        return source

    def whole(q, view, parts, conf):
        return parts, {"ran": False, "plan": {"parts": 1}}

    monkeypatch.setattr(fuse, "SOURCES", (("whole_query", whole), ("small_windows", make("a", False)),
                                          ("cfog_null", make("b", True)), ("new", make("c", True))))  # fmt: skip
    parts0 = [{"part": 0, "accepted": False, "candidates_tried": 8}]
    q = QueryInput(np.arange(1, 65, dtype=np.uint8).reshape(8, 8), None, 1.0, [1.0])  # type: ignore[arg-type]
    parts, split, ran, _ = fuse.run_sources(q, MapView(None), parts0, {})  # type: ignore[arg-type]
    assert calls == ["a", "b"]  # "c" after an accepted source: not run
    assert seen == [8, 10]  # one a-contrario count: each source sees the tests run before it
    assert [(r["name"], r["accepted"], r["candidates"]) for r in ran] == [
        ("features", False, 8), ("small_windows", False, 2), ("cfog_null", True, 2)]  # fmt: skip
    assert len(parts) == 3 and parts[-1]["accepted"]
    assert split["parts"] == 1 and split["small"]["ran"] and split["small"]["cfog_null"]["ran"]
    # an accepted feature search: no other source runs
    calls.clear()
    _, _, ran, _ = fuse.run_sources(q, MapView(None), [{**parts0[0], "accepted": True}], {})  # type: ignore[arg-type]
    assert calls == [] and [r["name"] for r in ran] == ["features"]


def _stub_second_pass(monkeypatch, late) -> None:
    """fuse.decide's collaborators stubbed: the whole-query plan, the small-query sources off,
    ``late`` as rift; the fusion registers when every accepted part is ``good``; the terms pass."""
    from georeg.register import fuse

    def whole(q, view, parts, conf):
        return parts, {"ran": False, "plan": {"parts": 1}}

    def off(q, view, parts, conf):
        return parts, {"ran": False, "reason": "not for this query"}

    def fake_fuse(full, source, parts, conf, gsd, seed):
        ok = [p for p in parts if p.get("accepted")]
        good = bool(ok) and all(p.get("good") for p in ok)
        return {"status": "registered" if good else "not_found",
                "reason": None if good else "part 0's pose does not hold over the whole query"}  # fmt: skip

    monkeypatch.setattr(fuse, "SOURCES", (("whole_query", whole), ("small_windows", off),
                                          ("cfog_null", off), ("rift", late)))  # fmt: skip
    monkeypatch.setattr(fuse, "fuse", fake_fuse)
    monkeypatch.setattr(fuse.small, "null_check", lambda u8, fused, *a: (fused, None))
    monkeypatch.setattr(fuse.ortho_check, "apply", lambda u8, fused, *a: (fused, None))
    monkeypatch.setattr(fuse.lidar_check, "run_check", lambda *a: None)


def test_sources_skipped_for_a_refused_candidate_run_in_a_second_pass(monkeypatch):
    """fuse.decide: the feature search's accepted part is refused by the fusion (a pose that does
    not hold over the whole query, SRIF optical-optical 7); the sources skipped because of it run
    after it, counting its tests, and their candidate is fused and judged as any other."""
    from georeg.register import fuse
    from georeg.register.search import MapView, QueryInput

    seen = []

    def late(q, view, parts, conf):
        seen.append(q.tests_before)
        return [*parts, {"part": len(parts), "accepted": True, "candidates_tried": 3, "good": True}], {
            "ran": True, "candidates": 3}  # fmt: skip

    _stub_second_pass(monkeypatch, late)
    q = QueryInput(np.arange(1, 65, dtype=np.uint8).reshape(8, 8), None, 1.0, [1.0])  # type: ignore[arg-type]
    parts0 = [{"part": 0, "accepted": True, "candidates_tried": 9}]
    fused, rec = fuse.decide(q, MapView(None), parts0, {})  # type: ignore[arg-type]
    assert fused["status"] == "registered" and seen == [9]
    assert rec["second_pass"]["sources"] == ["small_windows", "cfog_null", "rift"]
    assert rec["parts"][0]["accepted"] is False and "does not hold" in rec["parts"][0]["refused"]
    assert [r["name"] for r in rec["sources"]] == ["features", "rift"]
    # a fused result the verifier keeps: no second pass
    seen.clear()
    fused, rec = fuse.decide(q, MapView(None), [{**parts0[0], "good": True}], {})  # type: ignore[arg-type]
    assert fused["status"] == "registered" and rec["second_pass"] is None and seen == []


def test_second_pass_candidate_at_another_place_than_the_refused_one_is_refused(monkeypatch):
    """fuse.decide: the second pass's candidate must lie where a refused candidate lay (both
    passed their own a-contrario test; Landsat Pucallpa red/green 2015 on 2005, crop 1: rift's
    look-alike meander 186 px from the vetoed feature pose); at the same place it is kept."""
    from georeg.register import fuse
    from georeg.register.search import MapView, QueryInput

    def shift(dx):
        return [[1.0, 0.0, 1000.0 + dx], [0.0, -1.0, 5000.0], [0.0, 0.0, 1.0]]

    def late_at(dx):
        def late(q, view, parts, conf):
            return [*parts, {"part": len(parts), "accepted": True, "candidates_tried": 3, "good": True,
                             "homography": shift(dx)}], {"ran": True, "candidates": 3}  # fmt: skip
        return late

    q = QueryInput((np.arange(10_000) % 250 + 1).astype(np.uint8).reshape(100, 100), None, 1.0, [1.0])  # type: ignore[arg-type]
    parts0 = [{"part": 0, "accepted": True, "candidates_tried": 9, "homography": shift(0.0)}]
    for dx, registered in ((120.0, False), (-120.0, False), (30.0, True), (0.0, True)):
        _stub_second_pass(monkeypatch, late_at(dx))
        fused, rec = fuse.decide(q, MapView(None), parts0, {})  # type: ignore[arg-type]
        assert (fused["status"] == "registered") is registered, dx
        far = rec["second_pass"].get("elsewhere")
        assert (far is None) is registered
        if far:
            assert far["distance_m"] == abs(dx) and far["side_m"] == 100.0
            assert "ambiguous" in fused["reason"] and not rec["parts"][-1]["accepted"]

