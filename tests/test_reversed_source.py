"""The reversed source: a map smaller than the query's footprint searched the other way round
(``georeg.register.rift.reversed_source``; issue 34 item 5)."""

from __future__ import annotations

import math

import benchmark_module
import cv2
import numpy as np
import pytest

from georeg.register import rift
from georeg.register.search import MapSource, MapView, QueryInput

CONF = {"rift": {"enabled": True}, "acceptance": {"log_nfa_max": 0.0}}


def _texture(seed: int, side: int) -> np.ndarray:
    """A smooth random texture (uint8, 1..255): blobs of several sizes."""
    rng = np.random.default_rng(seed)
    img = np.zeros((side, side), np.float32)
    for s in (2.0, 5.0, 11.0):
        img += cv2.GaussianBlur(rng.normal(0, 1, (side, side)).astype(np.float32), (0, 0), s) * s
    img = (img - img.min()) / (img.max() - img.min())
    return np.clip(img * 254 + 1, 1, 255).astype(np.uint8)


def _view(gray: np.ndarray, g: float) -> MapView:
    """A plain map array as the sources see it (x = col g, y = -row g; no features needed)."""
    bx = benchmark_module.load("bench_crossspectral")
    sc = bx.Scene("map", {}, g, gray, g, lambda p: p, "test")
    h, w = gray.shape
    ext = (-0.5 * g, -(h - 0.5) * g, (w - 0.5) * g, 0.5 * g)
    src = MapSource(np.zeros((0, 2)), np.zeros((0, 128), np.float32), g, extent=ext)
    return MapView(src, bx.plain_window_reader(sc))


def _query_on_map(seed: int = 1, angle: float = 35.0):
    """A 300 px query (GSD 4) of a texture and a map (GSD 1: 4x finer) of 60 x 60 query px
    inside it, rotated by ``angle``; returns (query, map view, query px -> map x, y truth)."""
    q = _texture(seed, 300)
    c0, r0, side, f = 130, 110, 60, 4.0
    crop = cv2.resize(q[r0 : r0 + side, c0 : c0 + side].astype(np.float32), None, fx=f, fy=f,
                      interpolation=cv2.INTER_CUBIC)  # fmt: skip
    n = crop.shape[0]
    R = cv2.getRotationMatrix2D(((n - 1) / 2, (n - 1) / 2), angle, 1.0)
    big = int(math.ceil(n * 1.5))
    R[:, 2] += (big - n) / 2
    m = cv2.warpAffine(crop, R, (big, big), flags=cv2.INTER_LINEAR, borderValue=0)
    ok = cv2.warpAffine(np.ones_like(crop), R, (big, big), flags=cv2.INTER_NEAREST, borderValue=0) > 0
    gray = np.where(ok, np.clip(m, 1, 255), 0).astype(np.uint8)
    A = np.vstack([R, [0, 0, 1.0]])  # crop px -> map px
    C = np.array([[f, 0, 0.5 * f - 0.5 - f * c0], [0, f, 0.5 * f - 0.5 - f * r0], [0, 0, 1.0]])

    def truth(p: np.ndarray) -> np.ndarray:  # query px -> map x, y (x = col, y = -row; g = 1)
        mp = (np.c_[p, np.ones(len(p))] @ (A @ C).T)[:, :2]
        return mp * [1.0, -1.0]

    return q, _view(gray, 1.0), truth


def _run(q: np.ndarray, view: MapView, tests_before: int = 0):
    qi = QueryInput(q, None, 4.0, [4.0], 7, tests_before)  # type: ignore[arg-type]
    return rift.reversed_source(qi, view, [], CONF)


def test_a_map_inside_the_query_is_found_the_other_way_round_at_the_right_place():
    q, view, truth = _query_on_map()
    parts, rec = _run(q, view)
    assert rec["ran"] and rec["accepted"], rec.get("reason")
    assert len(parts) == 1 and parts[0]["method"] == "reversed" and parts[0]["whole_query"]
    H = np.asarray(parts[0]["homography"])
    p = np.array([[c, r] for c in range(140, 181, 10) for r in range(120, 161, 10)], float)
    got = (np.c_[p, np.ones(len(p))] @ H.T)[:, :2]
    err = np.linalg.norm(got - truth(p), axis=1)
    assert np.median(err) < 4.0  # map px: one query px
    assert rec["candidates"] >= 1 and rec["searches"][0]["search"] == "cfog"


def test_an_unrelated_map_is_not_accepted_and_every_search_is_counted():
    q, _, _ = _query_on_map()
    _, view, _ = _query_on_map(seed=2)  # a map of another texture
    parts, rec = _run(q, view, tests_before=40)
    assert rec["ran"] and not rec["accepted"] and parts == []
    assert [s["search"] for s in rec["searches"]] == ["cfog", "dense", "rift"]
    assert rec["candidates"] == sum(int(s.get("candidates", 0)) for s in rec["searches"])
    assert rec["searches"][-1]["tests_before"] >= 40 + rec["searches"][0]["candidates"]


def test_not_run_on_a_map_larger_than_the_query_or_without_the_query_gsd():
    q = _texture(1, 100)  # 400 x 400 map units at GSD 4
    view = _view(_texture(3, 600), 1.0)  # 600 x 600 map units: larger
    _, rec = _run(q, view)
    assert not rec["ran"] and "larger than the query's footprint" in rec["reason"]
    _, rec = rift.reversed_source(QueryInput(q, None, None, [4.0]), view, [], CONF)  # type: ignore[arg-type]
    assert not rec["ran"] and "GSD unknown" in rec["reason"]
    _, rec = rift.reversed_source(QueryInput(q, None, 4.0, [4.0]), view, [], {"rift": {"enabled": False}})  # type: ignore[arg-type]
    assert not rec["ran"] and "disabled" in rec["reason"]


@pytest.mark.parametrize("seed", [1])
def test_the_map_level_extent_is_the_maps_not_its_features(seed):
    """A level's features span less than the map (a few features on a small map): the level's
    MapSource keeps the map's extent (``MapSource.extent``), which the reversed source reads."""
    src = MapSource(np.array([[10.0, -10.0], [12.0, -11.0]]), np.zeros((2, 128), np.float32), 1.0,
                    extent=(-0.5, -99.5, 99.5, 0.5))  # fmt: skip
    assert src.bounds == (-0.5, -99.5, 99.5, 0.5)
    assert MapSource(src.xy, src.desc, 1.0).bounds == (10.0, -11.0, 12.0, -10.0)
