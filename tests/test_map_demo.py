"""Map preparation against the demo scene's truth, on a small demo scene generated for the module."""

from __future__ import annotations

from pathlib import Path

import laspy
import numpy as np
import pytest
import rasterio
from scipy import ndimage
from scipy.spatial import cKDTree

from georeg.demo import generate_scene
from georeg.map.elevation import LAYERS, make_elevation_tile
from georeg.map.grid import MapGrid, make_ortho_tile, write_grid

HOUSE, TALL_BUILDING = 7, 8  # georeg.demo.classes
SMALL = {
    "seed": 7, "size_m": 640, "gsd_m": 1.0, "margin_m": 128, "lidar_density": 2.0,
    "lidar_tiles": 2, "lidar_crs": "EPSG:2229",
    "query": {"samples": 64, "lines": 64, "bands": 8, "gsd_m": 0.8, "heading_deg": 35.0},
}  # fmt: skip


@pytest.fixture(scope="module")
def demo_tile(tmp_path_factory):
    demo = tmp_path_factory.mktemp("scene")
    generate_scene(SMALL, demo)
    lidar = sorted((demo / "lidar").glob("tile_*.laz"))
    tmp = tmp_path_factory.mktemp("demo")
    write_grid(tmp / "grid.json", [str(demo / "orthophoto.tif")], 1024, 64)
    grid = MapGrid.load(tmp / "grid.json")
    tile = "r000_c000"
    tdir = tmp / tile
    make_ortho_tile(tmp / "grid.json", tile, tdir / "ortho.tif")
    outs = {k: str(tdir / f"{k}.tif") for k in LAYERS} | {"points": str(tdir / "points.laz")}
    make_elevation_tile(str(tdir / "ortho.tif"), outs, [str(p) for p in lidar])
    return demo, grid, grid.tiles[tile], outs


def _truth(demo: Path, name: str, win) -> np.ndarray:
    with rasterio.open(demo / "truth" / f"{name}.tif") as ds:
        return ds.read(1, window=win)


def test_building_heights_match_truth(demo_tile):
    demo, grid, t, outs = demo_tile
    with rasterio.open(outs["dsm"]) as ds, rasterio.open(outs["ndsm"]) as nd:
        dsm, ndsm = ds.read(1, masked=True), nd.read(1, masked=True)
    labels = _truth(demo, "labels", t.window)
    roofs = ndimage.binary_erosion(np.isin(labels, [HOUSE, TALL_BUILDING]), iterations=2)
    assert roofs.sum() > 500
    ok = roofs & ~np.ma.getmaskarray(dsm)
    err = np.abs(dsm.data[ok] - _truth(demo, "dsm", t.window)[ok])
    assert np.median(err) < 0.15  # LiDAR range noise is 5 cm; pixel-centre vs point offsets
    assert np.percentile(err, 90) < 1.0
    nerr = np.abs(ndsm.data[ok] - _truth(demo, "ndsm", t.window)[ok])
    assert np.median(nerr) < 0.3


def test_outliers_removed_buildings_kept(demo_tile):
    demo, grid, t, outs = demo_tile
    pts = laspy.read(outs["points"])
    xyz = np.column_stack([pts.x, pts.y, pts.z])
    out_path = demo / "truth" / "outliers.npy"
    if out_path.exists():
        outl = np.load(out_path)
        b = grid.tile_bounds(t)
        inside = (
            (outl[:, 0] >= b[0]) & (outl[:, 0] < b[2]) & (outl[:, 1] > b[1]) & (outl[:, 1] <= b[3])
        )
        if inside.any():
            d, _ = cKDTree(xyz).query(outl[inside])
            assert (d > 0.05).all(), "an injected outlier survived"
    with rasterio.open(outs["dsm"]) as ds:
        dsm = ds.read(1, masked=True)
    truth = _truth(demo, "dsm", t.window)
    assert dsm.max() < truth.max() + 1.0  # no bird in the DSM
    labels = _truth(demo, "labels", t.window)
    tall = labels == TALL_BUILDING
    if tall.any():
        assert np.ma.median(dsm[tall]) == pytest.approx(np.median(truth[tall]), abs=1.0)
