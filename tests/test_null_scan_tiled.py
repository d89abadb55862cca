"""The tiled CFOG null scan (georeg.register.null_scan) on synthetic maps: the same peak and
statistic as the whole-map scan (null_scan.scan), a query found in a map larger than one FFT
through ``small.null_register``'s default config, reads never larger than a tile, and the cap."""

from __future__ import annotations

import math

import cv2
import numpy as np

from georeg.register import matching
from georeg.register.dense import window_u8
from georeg.register.null_scan import query_geometry, scan, tiled_scan
from georeg.register.search import MapSource
from georeg.register.small import null_register

G = 10.0  # map px size (map x = col G, y = -row G)


def _field(seed: int, shape: tuple[int, int], sigma: float) -> np.ndarray:
    rng = np.random.default_rng(seed)
    m = cv2.GaussianBlur(rng.random(shape).astype(np.float32), (0, 0), sigma)
    return (1 + 254 * (m - m.min()) / (m.max() - m.min())).astype(np.uint8)


def _query(m: np.ndarray, centre: tuple[float, float], theta: float, f: float, n: int,
           seed: int = 1) -> np.ndarray:  # fmt: skip
    """An n x n query of GSD f x the map's, centred on map px ``centre`` (col, row), rotated by
    ``theta`` degrees, contrast-inverted and noisy."""
    A = cv2.getRotationMatrix2D(centre, theta, 1.0 / f)
    A[:, 2] += ((n - 1) / 2 - centre[0], (n - 1) / 2 - centre[1])
    q = cv2.warpAffine(m.astype(np.float32), A, (n, n), flags=cv2.INTER_AREA)
    q = 256.0 - q + np.random.default_rng(seed).normal(0, 20.0, q.shape)
    return np.clip(q, 1, 255).astype(np.uint8)


def _reader(m: np.ndarray, asked: list[tuple[int, int]] | None = None):
    """The plain-array window reader of the benchmarks, recording the shape of every read."""
    H, W = m.shape

    def read(b):
        c0, c1 = max(0, math.floor(b[0] / G)), min(W, math.ceil(b[2] / G) + 1)
        r0, r1 = max(0, math.floor(-b[3] / G)), min(H, math.ceil(-b[1] / G) + 1)
        if c1 - c0 < 8 or r1 - r0 < 8:
            return None
        if asked is not None:
            asked.append((r1 - r0, c1 - c0))
        win = m[r0:r1, c0:c1].astype(np.float32)
        return win, np.array([[G, 0, c0 * G], [0, -G, -r0 * G], [0, 0, 1.0]])

    return read


def _bounds(m: np.ndarray, pad: float) -> tuple[float, float, float, float]:
    H, W = m.shape
    return (-pad, -(H - 1) * G - pad, (W - 1) * G + pad, pad)


def test_tiled_scan_gives_the_whole_maps_peak_and_statistic():
    """A query of GSD 2.3 x the map's (correlation shrink s ~ 0.28) in a 900 x 1000 px map:
    whole-map scan vs the tiled scan with forced small tiles (4 and 12 tiles): same rotation,
    peak within a correlation px, same block count, log10 p within 3 % and the same null max;
    a query with s = 1 (61 px at the map's GSD, 500 x 700 px map, 12 tiles): identical to
    1e-4."""
    m0 = _field(5, (900, 1000), 6.0)
    cases = ((2.3, 150, (400, 250), 0.03, m0), (1.0, 61, (300,), 1e-4, m0[:500, :700]))
    for f, n, tiles, tol, m in cases:
        q = _query(m, (600.0, 360.0), -40.0, f, n)
        b = _bounds(m, 0.5 * math.hypot(n, n) * f * G)
        read = _reader(m)
        gray, A = read(b)
        whole = scan(q, f, window_u8(gray), 10.0, 96, 16, 12.0, 30)
        cw = (A @ whole["S"] @ [(n - 1) / 2, (n - 1) / 2, 1.0])[:2]
        assert np.hypot(cw[0] / G - 600.0, -cw[1] / G - 360.0) < 2.0  # the truth, first
        s, _, _ = query_geometry(q, f, 96)
        for tile_px in tiles:
            t = tiled_scan(q, f * G, b, read, G, tile_px=tile_px)
            assert t["tiles"] > 1 and "reason" not in t, t
            assert t["angle_deg"] == whole["angle_deg"]
            ct = (t["A"] @ t["S"] @ [(n - 1) / 2, (n - 1) / 2, 1.0])[:2]
            assert np.hypot(*(ct - cw)) / G <= 1.0 / s + 1e-6
            assert t["blocks"] == whole["blocks"] and t["null_blocks"] == whole["null_blocks"]
            assert abs(t["log10_p"] - whole["log10_p"]) <= tol * abs(whole["log10_p"])
            assert abs(t["null_max"] - whole["null_max"]) <= 0.02 * abs(whole["null_max"])


def test_null_register_finds_a_small_query_in_a_map_beyond_one_fft_and_reads_only_tiles():
    """A 3600 x 3600 px map and a 100 px query at 3 x its GSD (1.4 M correlation px, above the
    default ``max_map_px``): ``null_register`` scans it tile by tile (``tile_px`` 768, 4 tiles),
    accepts the true place (within a map px); an unrelated query is not accepted; no read is
    larger than a tile (``tile_px`` + 2 x 64 shrunk px, / s) and under half the map."""
    m = _field(7, (3600, 3600), 8.0)
    src = MapSource(np.array([[0.0, 0.0], [3599 * G, -3599 * G]]), np.zeros((2, 128), np.float32),
                    G)  # fmt: skip
    asked: list[tuple[int, int]] = []
    read = _reader(m, asked)
    q = _query(m, (2300.0, 900.0), 65.0, 3.0, 100, seed=3)
    conf = {"small": {"null_test": {"enabled": True, "tile_px": 768}}}
    rec = null_register(q, 3.0 * G, src, conf, read)
    assert rec["scan"] == "tiled" and rec["tiles"] == 4 and rec["accepted"], rec
    c = matching.apply_h(np.array(rec["homography"]), np.array([[49.5, 49.5]]))[0]
    assert np.hypot(c[0] / G - 2300.0, -c[1] / G - 900.0) < 1.0
    s, _, _ = query_geometry(q, 3.0, 96)
    side = (768 + 2 * 64 + 8) / s  # the tile, moved out by <= 64 shrunk px to keep the phase
    assert max(h for h, _ in asked) <= side and max(w for _, w in asked) <= side
    assert max(h * w for h, w in asked) < 0.5 * m.size
    other = _field(100, (100, 100), 8.0 / 3.0)
    ru = null_register(other, 3.0 * G, src, conf, read)
    assert ru["scan"] == "tiled" and not ru["accepted"] and ru["log10_p"] > -3.0, ru


def test_tiled_scan_refuses_above_its_cap_with_tiles_smaller_than_the_query_or_a_rotated_grid():
    m = _field(9, (400, 400), 4.0)
    q = _query(m, (200.0, 200.0), 10.0, 1.0, 61)
    b = _bounds(m, 450.0)
    capped = tiled_scan(q, G, b, _reader(m), G, max_map_px=1e5)
    assert "S" not in capped and "too large for the tiled scan" in capped["reason"]
    tiny = tiled_scan(q, G, b, _reader(m), G, tile_px=120)
    assert "S" not in tiny and "too small for the query" in tiny["reason"]
    read = _reader(m)

    def rotated(bb):  # a reader whose windows are not north-up
        gray, A = read(bb)
        return gray, A @ np.array([[0.99, -0.14, 0], [0.14, 0.99, 0], [0, 0, 1.0]])

    src = MapSource(np.array([[0.0, 0.0], [399 * G, -399 * G]]), np.zeros((2, 128), np.float32), G)
    rec = null_register(q, G, src, {"small": {"null_test": {"max_map_px": 1000}}}, rotated)
    assert rec["scan"] == "tiled" and not rec["accepted"] and "north-up" in rec["reason"]


def test_tiled_scan_through_the_workflows_orthophoto_reader(tmp_path):
    """The workflow's GeoTIFF window reader (``fuse.ortho_window_reader``: rasterio windows,
    pixel-centre affine): ``null_register`` forced to tiles (``max_map_px`` 1000, ``tile_px``
    300) gives the whole-map scan's peak, score and log10 p on a 500 x 700 px orthophoto."""
    import rasterio
    from rasterio.transform import from_origin

    from georeg.register.fuse import ortho_window_reader

    m = _field(11, (500, 700), 5.0)
    path = tmp_path / "ortho.tif"
    with rasterio.open(path, "w", driver="GTiff", width=700, height=500, count=1, dtype="uint8",
                       transform=from_origin(0.0, 0.0, G, G), crs="EPSG:32633") as ds:  # fmt: skip
        ds.write(m, 1)
    read = ortho_window_reader(str(path))
    q = _query(m, (420.0, 180.0), 120.0, 1.0, 61, seed=5)
    src = MapSource(np.array([[0.5 * G, -0.5 * G], [699.5 * G, -499.5 * G]]),
                    np.zeros((2, 128), np.float32), G)  # fmt: skip
    whole = null_register(q, G, src, {"small": {"null_test": {"enabled": True}}}, read)
    conf = {"small": {"null_test": {"max_map_px": 1000, "tile_px": 300}}}
    tiled = null_register(q, G, src, conf, read)
    assert whole["scan"] == "whole" and tiled["scan"] == "tiled" and tiled["tiles"] > 4
    assert whole["accepted"] and tiled["accepted"], (whole, tiled)
    cw = matching.apply_h(np.array(whole["homography"]), np.array([[30.0, 30.0]]))[0]
    ct = matching.apply_h(np.array(tiled["homography"]), np.array([[30.0, 30.0]]))[0]
    assert np.hypot(cw[0] / G - 420.5, -cw[1] / G - 180.5) < 1.0  # pixel centres at +0.5
    assert np.hypot(*(ct - cw)) < 0.05 * G
    assert abs(tiled["log10_p"] - whole["log10_p"]) < 1e-3 * abs(whole["log10_p"])
    assert abs(tiled["score"] - whole["score"]) < 1e-5 and tiled["null_blocks"] == whole["null_blocks"]
