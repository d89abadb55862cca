"""Large synthetic maps (georeg.demo.largemap): georeferenced chunks, seamless, bounded memory."""

from __future__ import annotations

import json
import tracemalloc

import laspy
import numpy as np
import pyproj
import pytest
import rasterio
import yaml

from georeg.demo.largemap import (
    LargeMapSpec,
    generate_large_map,
    local_layout,
    render_window,
    world_frame,
)
from georeg.demo.raster import Grid
from georeg.demo.scene import MAP_EPSG, ORIGIN
from georeg.io.errors import ConfigError


def _spec(size_m: float, **kw) -> LargeMapSpec:
    return LargeMapSpec(size_m=size_m, chunk_px=256, lidar_density=0.2, **kw)


def _generate(tmp_path, size_m: float) -> tuple[dict, int]:
    tracemalloc.start()
    try:
        m = generate_large_map(tmp_path / f"m{int(size_m)}", _spec(size_m), query=False)
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    return m, peak


@pytest.fixture(scope="module")
def maps(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("largemap")
    small, p_small = _generate(tmp, 256)  # 1 chunk
    big, p_big = _generate(tmp, 512)  # 4 chunks: 4x the pixels, points and files
    return tmp, small, p_small, big, p_big


def test_memory_bounded_while_map_grows_4x(maps):
    _, small, p_small, big, p_big = maps
    assert len(big["chunks"]) == 4 * len(small["chunks"]) == 4
    assert big["megapixels"] == pytest.approx(4 * small["megapixels"])
    pts_small = sum(c["points"] for c in small["chunks"])
    pts_big = sum(c["points"] for c in big["chunks"])
    assert 3.5 * pts_small < pts_big < 4.5 * pts_small
    # peak Python/numpy memory is one chunk's (+ its pad), not the map's
    print(f"traced peak: {p_small / 1e6:.1f} MB (1 chunk), {p_big / 1e6:.1f} MB (4 chunks)")
    assert p_big < 1.3 * p_small, (p_small, p_big)
    assert p_big < 200e6


def test_chunks_georeferenced_and_mosaicked(maps):
    tmp, _, _, big, _ = maps
    out = tmp / "m512"
    with rasterio.open(out / "orthophoto.vrt") as vrt:
        assert vrt.crs.to_epsg() == MAP_EPSG
        assert (vrt.width, vrt.height, vrt.count) == (512, 512, 3)
        assert vrt.transform.c == ORIGIN[0] and vrt.transform.f == ORIGIN[1]
        assert vrt.transform.a == 1.0 and vrt.transform.e == -1.0
        for info in big["chunks"]:
            r, c = info["chunk"]
            with rasterio.open(info["ortho"]) as ds:
                assert ds.crs.to_epsg() == MAP_EPSG
                assert ds.block_shapes[0] == (256, 256)
                assert list(ds.bounds) == pytest.approx(info["bounds"])
                assert ds.transform.c == ORIGIN[0] + 256 * c
                assert ds.transform.f == ORIGIN[1] - 256 * r
                win = vrt.window(*ds.bounds)
                assert np.array_equal(vrt.read(window=win), ds.read())
                assert ds.read().std() > 10  # rendered, not blank


def test_laz_grid_and_config(maps):
    tmp, _, _, big, _ = maps
    out = tmp / "m512"
    cfg = yaml.safe_load((out / "map.yaml").read_text())
    assert cfg["map"]["orthophoto"].endswith("orthophoto.vrt")
    assert len(cfg["map"]["lidar"]) == len(big["chunks"]) == 4
    for info, path in zip(big["chunks"], cfg["map"]["lidar"], strict=True):
        assert info["lidar"].endswith(path.split("/")[-1])
        with laspy.open(path) as f:
            h = f.header
            assert h.point_count == info["points"] > 0
            assert pyproj.CRS(h.parse_crs()).to_epsg() == MAP_EPSG
            x0, y0, x1, y1 = info["bounds"]
            assert h.mins[0] >= x0 - 0.01 and h.maxs[0] <= x1 + 0.01
            assert h.mins[1] >= y0 - 0.01 and h.maxs[1] <= y1 + 0.01
    manifest = json.loads((out / "largemap.json").read_text())
    assert manifest["width"] == 512 and "query" not in manifest


def test_neighbouring_windows_are_seamless():
    """Two overlapping windows rendered separately agree on the overlap (same city, same texture)."""
    spec = LargeMapSpec(size_m=1024, chunk_px=256)
    frame = world_frame(spec)
    x0, y1 = ORIGIN
    a = Grid(x0 + 100, y1 - 100, 1.0, 300, 200)
    b = Grid(x0 + 250, y1 - 150, 1.0, 300, 200)  # overlaps a on 150 x 150 px
    sa, _ = render_window(spec, frame, a, np.random.default_rng(0))
    sb, _ = render_window(spec, frame, b, np.random.default_rng(1))
    ov_a = (slice(50, 200), slice(150, 300))
    ov_b = (slice(0, 150), slice(0, 150))
    assert np.array_equal(sa.label[ov_a], sb.label[ov_b])
    assert np.allclose(sa.dsm[ov_a], sb.dsm[ov_b], atol=1e-3)
    assert np.allclose(sa.c1[ov_a], sb.c1[ov_b], atol=1e-3)
    # block contents depend on the block, not on the window: same rectangles where both reach
    la = local_layout(spec, frame, a.bounds)
    lb = local_layout(spec, frame, b.bounds)
    ids_a, ids_b = set(la.rects["bid"].tolist()), set(lb.rects["bid"].tolist())
    common = sorted(ids_a & ids_b - {-1})
    assert common
    for bid in common[:20]:
        ka, kb = la.rects["bid"] == bid, lb.rects["bid"] == bid
        assert np.array_equal(la.rects["x0"][ka], lb.rects["x0"][kb])


def test_bad_spec():
    with pytest.raises(ConfigError, match="multiple of 256"):
        generate_large_map("/nonexistent", LargeMapSpec(size_m=1024, chunk_px=300))
    with pytest.raises(ConfigError, match="256 px"):
        generate_large_map("/nonexistent", LargeMapSpec(size_m=100))
