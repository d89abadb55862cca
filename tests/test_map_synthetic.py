"""Map preparation on small synthetic inputs: grid, COG tiles, LiDAR units, outliers, bad inputs.

The helpers ``make_ortho`` / ``make_las`` / ``make_scene`` are reused by test_map_workflow.py.
"""

from __future__ import annotations

import json
from pathlib import Path

import laspy
import numpy as np
import pytest
import rasterio
import rasterio.shutil
from pyproj import CRS, Transformer
from rasterio.transform import from_origin
from rasterio.vrt import WarpedVRT

from georeg.io.errors import InputError
from georeg.io.raster import ELEV_NODATA, is_cog, open_raster
from georeg.map import lidar
from georeg.map.elevation import LAYERS, Grid, make_elevation_tile
from georeg.map.grid import MapGrid, make_ortho_tile, tile_layout, write_grid, write_mosaic

UTM = "EPSG:32611"
X0, Y0 = 500_000.0, 3_760_000.0  # top-left of the synthetic orthophoto (UTM 11N, metres)
W, H = 200, 160  # orthophoto size at 1 m
GROUND_M = 100.0
ROOF_M = 112.0  # building of known height 12 m
BUILDING = (60.0, 90.0, 50.0, 70.0)  # x0, x1, y0, y1 offsets from (X0, Y0 - H) in metres
FTUS = 1200.0 / 3937.0


def make_ortho(
    path: Path, crs: str | None = UTM, width: int = W, height: int = H, x0: float = X0
) -> Path:
    """RGB uint8 orthophoto with a texture, 1 m pixels, top-left at (X0, Y0)."""
    rng = np.random.default_rng(0)
    img = rng.integers(40, 220, size=(3, height, width), dtype=np.uint8)
    with rasterio.open(
        path,
        "w",
        driver="GTiff",
        width=width,
        height=height,
        count=3,
        dtype="uint8",
        crs=crs,
        transform=from_origin(x0, Y0, 1.0, 1.0),
    ) as ds:
        ds.write(img)
    return path


def scene_points(density: float = 4.0, seed: int = 1) -> dict[str, np.ndarray]:
    """UTM points: ground (class 2) at GROUND_M, a flat-roof building (class 6) at ROOF_M,
    plus 6 birds 60 m up and 6 low points 25 m down (class 1). Heights in metres."""
    rng = np.random.default_rng(seed)
    n = int(W * H * density)
    ex = rng.uniform(0, W, n)
    ny = rng.uniform(0, H, n)
    bx0, bx1, by0, by1 = BUILDING
    inb = (ex >= bx0) & (ex < bx1) & (ny >= by0) & (ny < by1)
    z = np.where(inb, ROOF_M, GROUND_M) + rng.normal(0, 0.03, n)
    cls = np.where(inb, 6, 2).astype(np.uint8)
    bird_e = rng.uniform(10, W - 10, 6)
    bird_n = rng.uniform(10, H - 10, 6)
    low_e = rng.uniform(10, W - 10, 6)
    low_n = rng.uniform(10, H - 10, 6)
    low_e[:2] = bx0 - 8.0  # two low points near the building
    ex = np.concatenate([ex, bird_e, low_e])
    ny = np.concatenate([ny, bird_n, low_n])
    z = np.concatenate([z, np.full(6, GROUND_M + 60.0), np.full(6, GROUND_M - 25.0)])
    cls = np.concatenate([cls, np.ones(12, np.uint8)])
    kind = np.concatenate([np.zeros(n, np.int8), np.ones(6, np.int8), np.full(6, 2, np.int8)])
    return {"e": X0 + ex, "n": Y0 - H + ny, "z": z, "cls": cls, "kind": kind}


def make_las(
    path: Path, pts: dict[str, np.ndarray], crs: str | None = "EPSG:2229", z_unit_m: float = FTUS
) -> Path:
    """Write the UTM points as LAS 1.4 in ``crs`` (z divided by ``z_unit_m``); no CRS if None."""
    header = laspy.LasHeader(point_format=6, version="1.4")
    header.scales = np.array([0.01, 0.01, 0.01])
    if crs is not None:
        tr = Transformer.from_crs(UTM, crs, always_xy=True)
        x, y = tr.transform(pts["e"], pts["n"])
        header.add_crs(CRS.from_user_input(crs))
    else:
        x, y = pts["e"], pts["n"]
    if len(x):
        header.offsets = np.array([np.floor(np.min(x)), np.floor(np.min(y)), 0.0])
    las = laspy.LasData(header)
    las.x, las.y, las.z = x, y, pts["z"] / z_unit_m
    las.classification = pts["cls"]
    las.return_number = np.ones(len(x), np.uint8)
    las.number_of_returns = np.ones(len(x), np.uint8)
    las.write(str(path))
    return path


def make_scene(tmp: Path) -> tuple[Path, Path, dict[str, np.ndarray]]:
    pts = scene_points()
    return make_ortho(tmp / "ortho.tif"), make_las(tmp / "lidar.laz", pts), pts


def run_tile(tmp: Path, ortho: Path, las: list[Path], tile_size: int = 256, **settings):
    """Grid + tile r000_c000 (whole scene) + elevation; returns the output paths."""
    write_grid(tmp / "grid.json", [str(ortho)], tile_size, 16)
    tdir = tmp / "tiles" / "r000_c000"
    make_ortho_tile(tmp / "grid.json", "r000_c000", tdir / "ortho.tif")
    outs = {k: str(tdir / f"{k}.tif") for k in LAYERS}
    outs["points"] = str(tdir / "points.laz")
    make_elevation_tile(str(tdir / "ortho.tif"), outs, [str(p) for p in las], settings=settings)
    return outs


def _pixel(ds, e: float, n: float) -> tuple[int, int]:
    return ds.index(e, n)


# ---------------------------------------------------------------- grid and tiles


def test_tile_layout_covers_with_overlap():
    size, ov = 100, 10
    tiles = tile_layout(333, 251, size, ov)
    cover = np.zeros((251, 333), np.int32)
    core = np.zeros_like(cover)
    for t in tiles:
        w, c = t.window, t.core
        assert w.width <= size and w.height <= size
        cover[w.row_off : w.row_off + w.height, w.col_off : w.col_off + w.width] += 1
        core[c.row_off : c.row_off + c.height, c.col_off : c.col_off + c.width] += 1
    assert cover.min() >= 1  # full coverage
    assert (core == 1).all()  # cores partition the map
    by_pos = {(t.row, t.col): t for t in tiles}
    a, b = by_pos[(0, 0)].window, by_pos[(0, 1)].window
    assert a.col_off + a.width - b.col_off == ov  # neighbours share exactly `ov` pixels
    assert by_pos[(1, 0)].window.row_off == size - ov


def test_grid_covers_orthophoto_and_skips_empty(tmp_path):
    ortho = make_ortho(tmp_path / "o.tif", width=300, height=200)
    # blank out the right third: tiles there have no valid pixel
    with rasterio.open(ortho, "r+") as ds:
        ds.nodata = 0
        a = ds.read()
        a[:, :, 200:] = 0
        ds.write(a)
    g = write_grid(tmp_path / "grid.json", [str(ortho)], 100, 10)
    assert (g["width"], g["height"]) == (300, 200)
    grid = MapGrid.load(tmp_path / "grid.json")
    assert grid.transform == from_origin(X0, Y0, 1, 1)
    cols = {t.col for t in grid.tiles.values()}
    assert cols == {0, 1, 2}  # col 3 (x >= 270) holds only blanked pixels
    b = grid.tile_bounds("r000_c000")
    assert b[0] == X0 and b[3] == Y0


def test_ortho_tiles_are_cogs_and_match_source(tmp_path):
    ortho = make_ortho(tmp_path / "o.tif", width=700, height=600)
    write_grid(tmp_path / "grid.json", [str(ortho)], 512, 32)
    out = tmp_path / "t.tif"
    make_ortho_tile(tmp_path / "grid.json", "r001_c000", out)
    assert is_cog(out)
    with rasterio.open(out) as t, rasterio.open(ortho) as s:
        assert t.block_shapes[0] == (256, 256) and t.overviews(1)
        assert t.crs == s.crs
        assert t.profile["blockxsize"] == 256
        win = rasterio.windows.from_bounds(*t.bounds, transform=s.transform)
        assert np.array_equal(t.read(), s.read(window=win))


def test_two_orthophotos_in_two_crs_mosaic(tmp_path):
    a = make_ortho(tmp_path / "a.tif", width=120, height=100)
    east = make_ortho(tmp_path / "east.tif", width=120, height=100, x0=X0 + 100)
    b = tmp_path / "b.tif"  # the eastern one, reprojected to WGS84
    with rasterio.open(east) as src, WarpedVRT(src, crs="EPSG:4326", nodata=0) as vrt:
        rasterio.shutil.copy(vrt, b, driver="GTiff")
    g = write_grid(tmp_path / "grid.json", [str(a), str(b)], 128, 8)
    assert g["crs_epsg"] == 32611 and g["width"] >= 219
    make_ortho_tile(tmp_path / "grid.json", "r000_c001", tmp_path / "t.tif")
    with rasterio.open(tmp_path / "t.tif") as ds:
        m = ds.dataset_mask()
        assert m[:, -20:].mean() > 200  # the eastern part comes from the WGS84 source


# ---------------------------------------------------------------- LiDAR


def test_feet_conversion_us_survey_vs_international(tmp_path):
    """10000 ft: US survey -> 3048.0061 m, international -> 3048.0000 m."""
    pts = {
        "e": np.array([X0 + 5.0]),
        "n": np.array([Y0 - 5.0]),
        "z": np.array([10_000.0]),
        "cls": np.array([2], np.uint8),
    }
    us = make_las(tmp_path / "us.las", pts, "EPSG:2229", z_unit_m=1.0)  # ftUS state plane
    intl = make_las(tmp_path / "ft.las", pts, "EPSG:2994", z_unit_m=1.0)  # Oregon Lambert ft
    i_us, i_ft = lidar.scan(us), lidar.scan(intl)
    assert i_us.z_to_m == pytest.approx(1200 / 3937, abs=1e-12)
    assert i_ft.z_to_m == pytest.approx(0.3048, abs=1e-12)
    m = CRS(UTM)
    z_us = next(lidar.iter_chunks(i_us, m)).z[0]
    z_ft = next(lidar.iter_chunks(i_ft, m)).z[0]
    assert z_us == pytest.approx(3048.0061, abs=1e-4)
    assert z_ft == pytest.approx(3048.0, abs=1e-4)
    # horizontal: both come back to the same UTM position
    p_us = next(lidar.iter_chunks(i_us, m))
    assert p_us.x[0] == pytest.approx(X0 + 5.0, abs=0.02)
    assert p_us.y[0] == pytest.approx(Y0 - 5.0, abs=0.02)


def test_compound_crs_vertical_unit_wins(tmp_path):
    """Horizontal in ftUS but heights in metres (NAVD88 height, m): z is not scaled."""
    pts = {
        "e": np.array([X0 + 5.0]),
        "n": np.array([Y0 - 5.0]),
        "z": np.array([123.0]),
        "cls": np.array([2], np.uint8),
    }
    f = make_las(tmp_path / "c.las", pts, "EPSG:2229+5703", z_unit_m=1.0)
    info = lidar.scan(f)
    assert info.z_to_m == 1.0
    assert next(lidar.iter_chunks(info, CRS(UTM))).z[0] == pytest.approx(123.0, abs=1e-3)


def test_building_height_in_metres_at_right_place(tmp_path):
    ortho, las, _ = make_scene(tmp_path)
    outs = run_tile(tmp_path, ortho, [las])
    bx0, bx1, by0, by1 = BUILDING
    ce, cn = X0 + (bx0 + bx1) / 2, Y0 - H + (by0 + by1) / 2
    with (
        rasterio.open(outs["dsm"]) as dsm,
        rasterio.open(outs["ndsm"]) as nd,
        rasterio.open(outs["dtm"]) as dtm,
    ):
        assert dsm.nodata == ELEV_NODATA and dsm.dtypes[0] == "float32"
        assert dsm.crs.to_epsg() == 32611
        r, c = _pixel(dsm, ce, cn)
        d, n, t = dsm.read(1), nd.read(1), dtm.read(1)
        roof = d[r - 5 : r + 6, c - 8 : c + 9]
        assert np.median(roof) == pytest.approx(ROOF_M, abs=0.1)
        assert np.median(n[r - 5 : r + 6, c - 8 : c + 9]) == pytest.approx(
            ROOF_M - GROUND_M, abs=0.2
        )
        assert np.median(t[r - 5 : r + 6, c - 8 : c + 9]) == pytest.approx(GROUND_M, abs=0.2)
        # building edges where they should be: 3 m outside the footprint is ground
        r2, c2 = _pixel(dsm, X0 + bx0 - 3.0, cn)
        assert d[r2, c2] == pytest.approx(GROUND_M, abs=0.2)
        r3, c3 = _pixel(dsm, X0 + bx0 + 3.0, cn)
        assert d[r3, c3] == pytest.approx(ROOF_M, abs=0.2)
        tall = n > 6
        rr, cc = np.nonzero(tall)
        xs, ys = rasterio.transform.xy(dsm.transform, rr, cc)
        assert np.min(xs) > X0 + bx0 - 1.5 and np.max(xs) < X0 + bx1 + 1.5
        assert np.min(ys) > Y0 - H + by0 - 1.5 and np.max(ys) < Y0 - H + by1 + 1.5
    with rasterio.open(outs["density"]) as den:
        assert 2.0 < np.median(den.read(1)) < 8.0  # ~4 points per m2


def test_outlier_removal_drops_birds_and_low_points_keeps_building():
    pts = scene_points()
    xyz = np.column_stack([pts["e"] - X0, pts["n"] - Y0, pts["z"]])
    keep = lidar.remove_outliers(xyz, 16, 3.0)
    assert not keep[pts["kind"] == 1].any()  # birds gone
    assert not keep[pts["kind"] == 2].any()  # low points gone
    roof = pts["cls"] == 6
    assert keep[roof].mean() > 0.99
    assert keep[pts["kind"] == 0].mean() > 0.98


def test_outliers_not_in_dsm_and_textured_points(tmp_path):
    ortho, las, pts = make_scene(tmp_path)
    outs = run_tile(tmp_path, ortho, [las])
    with rasterio.open(outs["dsm"]) as ds:
        d = ds.read(1, masked=True)
        assert d.max() < ROOF_M + 0.5  # no bird
        assert d.min() > GROUND_M - 0.5  # no low point
    out = laspy.read(outs["points"])
    assert out.header.version.minor == 4 and out.header.point_format.id == 7
    crs = out.header.parse_crs()
    assert crs is not None and lidar.split_crs(crs)[0].to_epsg() == 32611
    assert abs(len(out) - int((pts["kind"] == 0).sum())) < 0.02 * len(out)
    assert out.z.max() < ROOF_M + 0.5 and out.z.min() > GROUND_M - 0.5
    # colours are the orthophoto pixel under each point
    with rasterio.open(ortho) as ds:
        img = ds.read()
        r, c = rasterio.transform.rowcol(
            ds.transform, np.asarray(out.x[:200]), np.asarray(out.y[:200])
        )
        assert np.array_equal(np.asarray(out.red[:200]) // 257, img[0, r, c])


def test_no_ground_class_uses_lowest_surface(tmp_path):
    ortho = make_ortho(tmp_path / "ortho.tif")
    pts = scene_points()
    pts["cls"] = np.ones_like(pts["cls"])  # unclassified
    las = make_las(tmp_path / "l.laz", pts)
    outs = run_tile(tmp_path, ortho, [las])
    with rasterio.open(outs["dtm"]) as dtm, rasterio.open(outs["ndsm"]) as nd:
        t, n = dtm.read(1), nd.read(1)
        r, c = dtm.index(X0 + 75, Y0 - H + 60)
        assert t[r, c] == pytest.approx(GROUND_M, abs=0.3)
        assert n[r, c] == pytest.approx(ROOF_M - GROUND_M, abs=0.3)


def test_lidar_not_overlapping_warns_and_empty_coverage(tmp_path, caplog):
    ortho = make_ortho(tmp_path / "ortho.tif")
    pts = scene_points(density=0.2)
    pts["e"] = pts["e"] + 5000.0  # 5 km east
    las = make_las(tmp_path / "far.laz", pts)
    outs = run_tile(tmp_path, ortho, [las])
    assert "no LiDAR file overlaps" in caplog.text
    with rasterio.open(outs["density"]) as den, rasterio.open(outs["dsm"]) as dsm:
        assert den.read(1).max() == 0
        assert (dsm.read(1) == ELEV_NODATA).all()
    assert len(laspy.read(outs["points"])) == 0


def test_dem_mode(tmp_path):
    ortho = make_ortho(tmp_path / "ortho.tif")
    dem = tmp_path / "dem.tif"
    z = np.full((40, 50), 328.084, np.float32)  # 100 m in international feet
    with rasterio.open(
        dem,
        "w",
        driver="GTiff",
        width=50,
        height=40,
        count=1,
        dtype="float32",
        crs=UTM,
        transform=from_origin(X0 - 100, Y0 + 100, 10, 10),
    ) as ds:
        ds.write(z, 1)
        ds.units = ("ft",)
    write_grid(tmp_path / "grid.json", [str(ortho)], 256, 16)
    tdir = tmp_path / "t"
    make_ortho_tile(tmp_path / "grid.json", "r000_c000", tdir / "ortho.tif")
    outs = {k: str(tdir / f"{k}.tif") for k in LAYERS} | {"points": str(tdir / "p.laz")}
    make_elevation_tile(str(tdir / "ortho.tif"), outs, [], dem=str(dem))
    with rasterio.open(outs["dsm"]) as d, rasterio.open(outs["ndsm"]) as n:
        assert np.allclose(d.read(1), 100.0, atol=1e-3)
        assert np.allclose(n.read(1), 0.0)
    assert len(laspy.read(outs["points"])) == W * H


def test_vrt_mosaic_reads_like_tiles(tmp_path):
    ortho = make_ortho(tmp_path / "o.tif", width=300, height=220)
    write_grid(tmp_path / "grid.json", [str(ortho)], 128, 16)
    grid = MapGrid.load(tmp_path / "grid.json")
    files = []
    for tid in grid.tiles:
        f = tmp_path / "tiles" / tid / "ortho.tif"
        make_ortho_tile(tmp_path / "grid.json", tid, f)
        files.append(str(f))
    write_mosaic(tmp_path / "grid.json", "ortho", files, tmp_path / "mosaic" / "ortho.vrt")
    with rasterio.open(tmp_path / "mosaic" / "ortho.vrt") as v, rasterio.open(ortho) as s:
        assert v.crs == s.crs and v.transform == s.transform and v.shape == s.shape
        assert np.array_equal(v.read(), s.read())
        assert v.read(1, out_shape=(55, 75)).shape == (55, 75)  # decimated read works


# ---------------------------------------------------------------- bad inputs


def test_las_without_crs_needs_lidar_crs(tmp_path):
    f = make_las(tmp_path / "nocrs.las", scene_points(density=0.1), crs=None)
    with pytest.raises(InputError, match="nocrs.las.*no CRS.*lidar_crs"):
        lidar.scan(f)
    info = lidar.scan(f, lidar_crs=UTM)
    assert info.crs.to_epsg() == 32611 and info.z_to_m == 1.0


def test_orthophoto_without_crs(tmp_path):
    o = make_ortho(tmp_path / "nocrs.tif", crs=None)
    with pytest.raises(InputError, match="nocrs.tif.*no CRS"):
        write_grid(tmp_path / "grid.json", [str(o)], 128, 8)
    assert not (tmp_path / "grid.json").exists()


def test_missing_and_corrupt_raster(tmp_path):
    with pytest.raises(InputError, match="missing.tif.*not found"):
        with open_raster(tmp_path / "missing.tif"):
            pass
    bad = tmp_path / "bad.tif"
    bad.write_bytes(b"II*\x00garbage" * 10)
    with pytest.raises(InputError, match="bad.tif"):
        write_grid(tmp_path / "grid.json", [str(bad)], 128, 8)


def test_truncated_raster_data(tmp_path):
    o = tmp_path / "o.tif"
    with rasterio.open(
        o,
        "w",
        driver="GTiff",
        width=400,
        height=400,
        count=3,
        dtype="uint8",
        crs=UTM,
        transform=from_origin(X0, Y0, 1, 1),
        compress="deflate",
        tiled=True,
    ) as ds:
        ds.write(np.random.default_rng(0).integers(0, 255, (3, 400, 400), dtype=np.uint8))
    data = o.read_bytes()
    o.write_bytes(data[: len(data) // 2])
    with pytest.raises(InputError, match="o.tif"):
        write_grid(tmp_path / "grid.json", [str(o)], 512, 8)
        make_ortho_tile(tmp_path / "grid.json", "r000_c000", tmp_path / "t.tif")
    assert not (tmp_path / "t.tif").exists()


def test_truncated_and_empty_laz(tmp_path):
    good = make_las(tmp_path / "g.laz", scene_points(density=1.0))
    data = good.read_bytes()
    bad = tmp_path / "trunc.laz"
    bad.write_bytes(data[: len(data) // 2])
    with pytest.raises(InputError, match="trunc.laz"):
        info = lidar.scan(bad)
        for _ in lidar.iter_chunks(info, CRS(UTM), chunk_points=5000):
            pass
    empty = make_las(tmp_path / "empty.laz", {k: v[:0] for k, v in scene_points(0.01).items()})
    with pytest.raises(InputError, match="empty.laz.*0 points"):
        lidar.scan(empty)


def test_bad_lidar_in_tile_leaves_no_outputs(tmp_path):
    ortho = make_ortho(tmp_path / "ortho.tif")
    las = make_las(tmp_path / "nocrs.laz", scene_points(density=0.2), crs=None)
    with pytest.raises(InputError, match="nocrs.laz"):
        run_tile(tmp_path, ortho, [las])
    tdir = tmp_path / "tiles" / "r000_c000"
    assert sorted(p.name for p in tdir.iterdir()) == ["ortho.tif"]


def test_grid_json_is_plain_json(tmp_path):
    ortho = make_ortho(tmp_path / "o.tif")
    write_grid(tmp_path / "grid.json", [str(ortho)], 128, 16)
    data = json.loads((tmp_path / "grid.json").read_text())
    assert set(data["tiles"]) == {"r000_c000", "r000_c001", "r001_c000", "r001_c001"}
    assert Grid.of(ortho).cell_area_m2() == pytest.approx(1.0)
