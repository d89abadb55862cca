"""Map preparation on real data: Autzen (JPEG ortho with .aux.xml CRS, LiDAR in international feet).

Skipped when ../shared/data (beside the repo) is absent.
"""

from __future__ import annotations

from pathlib import Path

import laspy
import numpy as np
import pytest
import rasterio

from georeg.io.errors import InputError
from georeg.map import lidar
from georeg.map.elevation import LAYERS, make_elevation_tile
from georeg.map.grid import MapGrid, make_ortho_tile, write_grid

DATA = Path(__file__).parents[1].parent / "shared" / "data" / "autzen"
pytestmark = pytest.mark.shared

ORTHO = DATA / "autzen.jpg"
TRIM = DATA / "autzen_trim.laz"
THIN = DATA / "autzen-thin.las"
FT = 0.3048


@pytest.fixture(scope="module")
def autzen(tmp_path_factory):
    if not ORTHO.exists():
        pytest.skip(f"{DATA} not available")
    tmp = tmp_path_factory.mktemp("autzen")
    write_grid(tmp / "grid.json", [str(ORTHO)], 1024, 64)
    return tmp, MapGrid.load(tmp / "grid.json")


def _elevation(tmp: Path, tile: str, las: Path, lidar_crs: str | None = None) -> dict[str, str]:
    tdir = tmp / tile / las.stem
    make_ortho_tile(tmp / "grid.json", tile, tdir / "ortho.tif")
    outs = {k: str(tdir / f"{k}.tif") for k in LAYERS} | {"points": str(tdir / "points.laz")}
    make_elevation_tile(str(tdir / "ortho.tif"), outs, [str(las)], lidar_crs=lidar_crs)
    return outs


def test_grid_covers_orthophoto(autzen):
    _, grid = autzen
    with rasterio.open(ORTHO) as ds:
        assert ds.crs is not None  # from the .aux.xml side-car
        assert grid.crs == ds.crs and grid.transform == ds.transform
        assert (grid.width, grid.height) == (ds.width, ds.height)
    cover = np.zeros((grid.height, grid.width), bool)
    for t in grid.tiles.values():
        w = t.window
        cover[w.row_off : w.row_off + w.height, w.col_off : w.col_off + w.width] = True
    assert cover.all()
    assert len(grid.tiles) == 4 * 5


def test_dsm_in_metres_and_trees_bridge_above_river(autzen):
    tmp, grid = autzen
    # the LiDAR (south edge) falls mostly in the bottom row of tiles
    info = lidar.scan(TRIM)
    assert info.z_to_m == pytest.approx(FT)
    tile = "r004_c001"
    outs = _elevation(tmp, tile, TRIM)
    with rasterio.open(outs["dsm"]) as dsm, rasterio.open(outs["ndsm"]) as nd:
        assert dsm.crs == grid.crs and dsm.transform == grid.tile_transform(tile)
        d = dsm.read(1, masked=True)
        n = nd.read(1, masked=True)
    assert d.count() > 50_000
    # header z is 406..521 ft: in metres 123.8..158.8 (feet values would be > 400)
    assert 120.0 < d.min() and d.max() < 160.0
    assert np.ma.median(d) == pytest.approx(130.0, abs=6.0)
    # open ground dominates, trees/bridge stand well above it
    assert np.ma.median(n) < 1.0
    assert np.percentile(n.compressed(), 99) > 5.0
    pts = laspy.read(outs["points"])
    assert pts.header.point_format.id == 7 and len(pts) > 20_000
    assert np.asarray(pts.red).max() > 0  # coloured from the orthophoto
    high = np.asarray(pts.z) > np.percentile(pts.z, 99)  # treetops / bridge deck
    with rasterio.open(outs["ndsm"]) as nd:
        vals = np.array([v[0] for v in nd.sample(zip(pts.x[high], pts.y[high], strict=True))])
    assert np.median(vals) > 5.0


def test_thin_las_without_crs(autzen):
    tmp, _ = autzen
    with pytest.raises(InputError, match=r"autzen-thin\.las.*no CRS.*lidar_crs"):
        lidar.scan(THIN)
    with pytest.raises(InputError, match=r"autzen-thin\.las"):
        _elevation(tmp, "r002_c001", THIN)
    outs = _elevation(tmp, "r002_c001", THIN, lidar_crs="EPSG:2994")  # Oregon Lambert (ft)
    with rasterio.open(outs["dsm"]) as dsm, rasterio.open(outs["density"]) as den:
        d = dsm.read(1, masked=True)
        assert den.read(1).max() > 0
    assert d.count() > 0 and 115.0 < np.ma.median(d) < 180.0
