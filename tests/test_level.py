"""A map level near the query's GSD for queries much coarser than the map (issue 34 item 5)."""

from __future__ import annotations

import benchmark_module
import cv2
import numpy as np
import pytest
import rasterio
from rasterio.transform import from_origin

from georeg.index.features import detect_and_describe, rgb_to_gray
from georeg.register import level
from georeg.register.search import MapSource, map_for_query


def test_level_only_for_queries_much_coarser_than_the_map():
    assert level.level_gsd(30.0, 3.6, {}) == 30.0  # 8x: the level at the query's GSD
    assert level.level_gsd(2.0, 1.0, {}) is None  # 2x: the index at the feature GSD
    assert level.level_gsd(None, 1.0, {}) is None  # unknown GSD: the guesses of the index search
    assert level.level_gsd(30.0, 3.6, {"min_ratio": 0}) is None  # switched off


def _ortho(path, rgb: np.ndarray, x0: float, y1: float, g: float, nodata_box=None) -> None:
    prof = {"driver": "GTiff", "width": rgb.shape[2], "height": rgb.shape[1], "count": 3,
            "dtype": "uint8", "crs": "EPSG:32633", "transform": from_origin(x0, y1, g, g)}  # fmt: skip
    with rasterio.open(path, "w", **prof) as ds:
        ds.write(rgb)
        if nodata_box is not None:
            m = np.full(rgb.shape[1:], 255, np.uint8)
            r0, r1, c0, c1 = nodata_box
            m[r0:r1, c0:c1] = 0
            ds.write_mask(m)


def test_orthophoto_level_is_the_block_average_at_the_right_place(tmp_path):
    rng = np.random.default_rng(3)
    rgb = rng.integers(20, 230, (3, 96, 128)).astype(np.uint8)
    x0, y1, g = 500000.0, 5000000.0, 0.5
    _ortho(tmp_path / "o.tif", rgb, x0, y1, g, nodata_box=(0, 8, 0, 8))
    read = level.read_ortho_level(str(tmp_path / "o.tif"))
    gray, A = read((x0, y1 - 96 * g, x0 + 128 * g, y1), 4 * g)  # 4 x 4 blocks
    assert gray.shape == (24, 32)
    want = rgb_to_gray(rgb).astype(np.float64).reshape(24, 4, 32, 4).mean(axis=(1, 3))
    assert np.abs(gray[3:, 3:].astype(float) - want[3:, 3:]).max() <= 1.0
    assert (gray[:2, :2] == 0).all()  # the masked corner stays nodata
    # level pixel (col 5, row 7) centre = centre of its 4 x 4 block of orthophoto pixels
    x, y, _ = A @ np.array([5.0, 7.0, 1.0])
    assert (x, y) == pytest.approx((x0 + (5 * 4 + 2) * g, y1 - (7 * 4 + 2) * g))
    # as the sources' window reader: float, NaN = nodata, the same place
    win, A2 = level.window_reader(read, 4 * g)((x0, y1 - 96 * g, x0 + 128 * g, y1))
    assert np.isnan(win[:2, :2]).all() and np.array_equal(win[3:, 3:], gray[3:, 3:])
    assert np.array_equal(A2, A)
    assert read((x0 - 900, y1 + 100, x0 - 800, y1 + 200), 4 * g) is None  # off the orthophoto


def _map_source(gray: np.ndarray, g: float) -> MapSource:
    f = detect_and_describe(gray, gray > 0, {})
    xy = np.c_[f.xy[:, 0] * g, -f.xy[:, 1] * g].astype(np.float64)
    return MapSource(xy, f.desc, g, angle=f.angle.astype(np.float64), scale=f.scale * g)


def test_a_level_too_large_is_refused_with_the_reason_and_the_index_is_kept():
    rng = np.random.default_rng(0)
    gray = cv2.GaussianBlur(rng.integers(1, 255, (400, 400)).astype(np.uint8), (0, 0), 2)
    src = _map_source(gray, 1.0)
    view, factors, rec = map_for_query(src, None, 50, 50, 8.0, [8.0],
                                       {"level": {"max_mpx": 1e-4}}, None, lambda b, g: None)  # fmt: skip
    assert view.source is src and factors == [8.0]
    assert "max_mpx" in rec["reason"] and "prior" in rec["reason"]


def test_a_level_without_features_leaves_the_index_to_search_with_the_reason():
    """A map a few query pixels wide (or featureless) has no SIFT features at the query's GSD:
    the level is not used (the record says why) and the index's features are searched, instead
    of an empty map failing further on (found by the map-inside scale-gap set, session 55)."""
    rng = np.random.default_rng(0)
    gray = cv2.GaussianBlur(rng.integers(1, 255, (400, 400)).astype(np.uint8), (0, 0), 2)
    src = _map_source(gray, 1.0)
    flat = np.full((400, 400), 128, np.uint8)

    def read_level(b, g):  # the map averaged to g: a flat image
        n = max(1, round(400 / g))
        return cv2.resize(flat, (n, n), interpolation=cv2.INTER_AREA), np.array(
            [[g, 0, b[0] + g / 2], [0, -g, b[3] - g / 2], [0, 0, 1.0]])

    view, factors, rec = map_for_query(src, None, 50, 50, 8.0, [8.0], {}, None, read_level)
    assert view.source is src and factors == [8.0] and view.read_gsd is None
    assert rec is not None and "no features" in rec["reason"]


def test_rift_searches_a_level_at_its_windows_gsd_unless_the_map_is_too_large_there():
    """A map level's windows are read 2x finer than the query: on a map no larger than the
    query's footprint rift works there (the query enlarged 2x), at the level's own GSD when the
    map is larger than the query or the map at the finer GSD exceeds ``rift.max_map_px``;
    without a level at the map's GSD or ``max_upsample`` finer than the query's."""
    from georeg.register import rift
    from georeg.register.search import MapView

    xy = np.array([[0.0, 0.0], [6000.0, -6000.0]])  # 6 km a side
    src = MapSource(xy, np.zeros((2, 128), np.float32), 30.0)
    c = rift.rift_conf({})
    level_view = MapView(src, read_gsd=15.0)
    assert rift.working_gsd(30.0, level_view, c, 200 * 200) == 15.0  # 6 km of query
    assert rift.working_gsd(30.0, level_view, c, 199 * 199) == 30.0  # a map larger than it
    assert rift.working_gsd(30.0, level_view, {**c, "max_map_px": 100_000}, 200 * 200) == 30.0
    plain = MapView(MapSource(xy, np.zeros((2, 128), np.float32), 3.75))
    assert rift.working_gsd(30.0, plain, c) == pytest.approx(12.0)
    assert rift.working_gsd(7.5, plain, c) == 3.75


def _bench():
    return benchmark_module.load("bench_scale_gap")


def test_landsat_swir_30m_on_a_map_8x_finer_registers_and_not_on_another_city(shared_data):
    """Taizhou: Landsat SWIR of one date (30 m, rotated, rescaled x0.9-1.1) against the other
    date's visible map at 3.75 m (the scale gap of EnMAP on an airborne orthophoto): found
    within one query pixel through the level; against another city's map at 3.75 m: not
    found."""
    sg = _bench()
    bx = sg.bx
    sc = sg.upsampled(bx.landsat_scene("taizhou", 1), 8.0)
    q = bx.make_query(sc, np.random.default_rng(11), 0, 0.5)
    q.tol_px = 8.0
    assert q.gsd / sc.map_gsd > 7
    spec = {"pipeline": {}, "bands": "auto"}
    res = bx.run_method(q, sc, spec, 11)
    j = sg.dv.judge(q, sc, res)
    assert j["outcome"] == "success", j
    assert j["error_px"] <= 8.0  # map px: one query pixel
    assert res["level"]["gsd"] == pytest.approx(q.gsd) and res["level"]["features"] > 100
    other = bx.s2_scene("abudhabi")
    f = 3.75 / other.map_gsd
    m = cv2.resize(other.map_gray, None, fx=1 / f, fy=1 / f, interpolation=cv2.INTER_CUBIC)
    neg_map = bx.Scene("abudhabi_375", {}, 30.0, np.clip(m, 1, 255), 3.75, lambda p: p, "abudhabi")
    neg = bx.Query(q.name + "_vs_abudhabi", sc.name, neg_map.name, q.bands, q.gsd, None, None)
    assert not bx.run_method(neg, neg_map, spec, 11)["accepted"]


def test_a_map_smaller_than_the_query_is_found_by_rift_at_twice_the_level(shared_data):
    """Hong Kong: a Sentinel-2 SWIR query (20 m band, rescaled) whose map is a 1.6 km window of
    the other date's visible image upsampled to 2.5 m (8x finer than the band), inside the
    query's footprint (a fifth of it): rift's source on the map level's view searches the map
    at half the level's GSD (the query enlarged 2x: ``MapView.read_gsd``), where the overlap
    holds enough of its cells, and finds the place within one query pixel where the map is; at
    the level's GSD it found nothing (session 54). The source alone: in the workflow the feature
    search now finds this query first, on the level of the whole map (session 56)."""
    from georeg.register import rift
    from georeg.register.search import QueryInput

    sg = _bench()
    bx = sg.bx
    sc = bx.s2_scene("hongkong")
    q = bx.make_query(sc, np.random.default_rng(11), 0, 0.6)
    up = sg.map_inside(sc, q, 0.3, 8.0)
    q.tol_px = 8.0
    conf = bx.workflow_register_conf()
    g = up.map_gsd
    mxy, mdesc, mang, msize = bx.map_features(up, g, bx.merged_conf(bx.FEATURES))
    h, w = up.map_gray.shape
    src = MapSource(mxy, mdesc, g, angle=mang, scale=msize * g,
                    extent=(-0.5 * g, -(h - 0.5) * g, (w - 0.5) * g, 0.5 * g))  # fmt: skip
    u8 = bx.query_stack(q, "auto")
    view, factors, lrec = map_for_query(src, None, u8.shape[-1], u8.shape[-2], q.gsd, [q.gsd / g], conf,
                                        bx.plain_window_reader(up), bx.plain_level_reader(up))  # fmt: skip
    assert lrec["gsd"] == pytest.approx(q.gsd) and view.read_gsd == pytest.approx(q.gsd / 2)
    parts, rec = rift.source(QueryInput(u8, None, q.gsd, factors, 11), view, [], conf)  # type: ignore[arg-type]
    assert rec["accepted"] and rec["working_gsd"] == pytest.approx(q.gsd / 2), rec.get("reason")
    j = sg.dv.judge(q, up, {"accepted": True, "H": np.asarray(parts[-1]["homography"])})
    assert j["outcome"] == "success" and j["error_px"] <= 8.0, j
