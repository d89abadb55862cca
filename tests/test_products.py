"""Spectral-elevation products (issue 6) on a small generated demo scene.

The registration is replaced by the generator's truth (``demo_truth.tif`` x, y; z sampled from the
truth DSM) and the map mosaics by the truth DSM / DTM / nDSM rasters, so these tests check the
products alone. Points: the demo's LiDAR reprojected to the map CRS as one map tile.
"""

from __future__ import annotations

import contextlib
import json
import os
import shutil
import subprocess
import warnings
import xml.etree.ElementTree as ET
from pathlib import Path

import laspy
import numpy as np
import pyproj
import pytest
import rasterio
from rasterio.errors import NotGeoreferencedWarning
from scipy.ndimage import binary_erosion
from scipy.spatial import cKDTree

from georeg.io.query import open_query
from georeg.map import lidar
from georeg.products import segmentation as seg
from georeg.products.cube_resample import InverseGeolocation, read_band_chunk
from georeg.products.make import make_cube, make_products
from georeg.register.geolocation import map_xy, sample_raster

# seed 11 puts every demo class (incl. a few pool pixels) inside a 160 x 200 query at 1.6 m
SCENE = {
    "seed": 11,
    "size_m": 768,
    "gsd_m": 1.0,
    "margin_m": 200,
    "lidar_density": 2.0,
    "lidar_tiles": 1,
    "lidar_crs": "EPSG:2229",
    "query": {"samples": 160, "lines": 200, "bands": 90, "gsd_m": 1.6, "heading_deg": 35.0},
}
KML = "{http://www.opengis.net/kml/2.2}"


def _read(path: Path, band: int | None = None) -> np.ndarray:
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", NotGeoreferencedWarning)
        with rasterio.open(path) as ds:
            return ds.read(band) if band else ds.read()


def _stand_in_inputs(scene: dict[str, str], out: Path, crs_wkt: str) -> dict[str, Path]:
    """geolocation.tif from the truth, registration.json, map-CRS points as one map tile."""
    x, y = _read(Path(scene["demo_truth"])).astype(np.float64)
    z = sample_raster(scene["dsm"], x, y)
    geo = out / "in" / "geolocation.tif"
    geo.parent.mkdir(parents=True)
    prof = {"driver": "GTiff", "width": x.shape[1], "height": x.shape[0], "count": 3,
            "dtype": "float64", "nodata": float("nan")}  # fmt: skip
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", NotGeoreferencedWarning)
        with rasterio.open(geo, "w", **prof) as ds:
            ds.write(np.stack([x, y, z]))
    reg = out / "in" / "registration.json"
    reg.write_text(json.dumps({"status": "registered", "crs": crs_wkt}))
    mcrs = pyproj.CRS.from_wkt(crs_wkt)
    pts = lidar.Points.concat(list(lidar.iter_chunks(lidar.scan(scene["lidar_0"]), mcrs)))
    tile = out / "in" / "tiles" / "r000_c000" / "points.laz"
    tile.parent.mkdir(parents=True)
    lidar.write_textured_laz(tile, pts, np.full((len(pts), 3), 128, np.uint8), mcrs)
    return {"geolocation": geo, "registration": reg, "tile": tile}


@pytest.fixture(scope="module")
def run(tmp_path_factory):
    from georeg.demo import generate_scene

    root = tmp_path_factory.mktemp("products")
    scene = generate_scene(SCENE, root / "demo")
    crs_wkt = json.loads(Path(scene["scene"]).read_text())["map"]["crs_wkt"]
    inp = _stand_in_inputs(scene, root, crs_wkt)
    out = root / "products" / "demo"
    cube_m = make_cube(inp["registration"], inp["geolocation"], scene["demo_hdr"],
                       out / "cube.json", {}, None, "demo")  # fmt: skip
    mosaics = {k: scene[k] for k in ("dsm", "dtm", "ndsm")}
    prod_m = make_products(inp["registration"], inp["geolocation"], scene["demo_hdr"],
                           None, mosaics, [inp["tile"]], out / "products.json", {},
                           None, "demo", scene["demo_labels"])  # fmt: skip
    return {"scene": scene, "inp": inp, "out": out, "cube_m": cube_m, "m": prod_m, "crs": crs_wkt}


def test_manifests_list_existing_files(run):
    m = run["m"]
    assert m["status"] == "registered"
    for key in ("elevation", "fused", "segmentation", "segmentation_geo", "segmentation_legend",
                "class_areas", "footprint_geojson", "footprint_kml", "points_spectra"):  # fmt: skip
        assert (run["out"] / m["files"][key]).is_file(), key
    for key in ("cube_cog", "cube_envi_header", "cube_envi_data"):
        assert (run["out"] / run["cube_m"]["files"][key]).is_file(), key


def test_geo_cube_matches_query_spectra_at_map_points(run):
    """At map points in the footprint, the resampled spectrum = the query spectrum of the pixel
    whose true map position is nearest (nearest resampling copies spectra unchanged)."""
    out, scene = run["out"], run["scene"]
    with rasterio.open(out / "cube.tif") as ds:
        assert ds.crs.to_epsg() == 32611
        assert ds.tags(ns="IMAGE_STRUCTURE").get("INTERLEAVE") == "BAND"  # streamed COG copy
        assert ds.descriptions[0] == "900.0 nm" and ds.count == SCENE["query"]["bands"]
        assert float(ds.tags(1)["wavelength"]) == pytest.approx(900.0)
        assert float(ds.tags(1)["fwhm"]) > 0
        geo = ds.read()
        tr, nodata = ds.transform, ds.nodata
    cube = open_query(scene["demo_hdr"])
    q = read_band_chunk(cube, 0, cube.count)  # small test cube: whole
    tx, ty = _read(Path(scene["demo_truth"])).astype(np.float64)
    rng = np.random.default_rng(0)
    rows, cols = np.nonzero(geo[0] != nodata)
    pick = rng.choice(rows.size, 2000, replace=False)
    r, c = rows[pick], cols[pick]
    px, py = tr * (c + 0.5, r + 0.5)
    tree = cKDTree(np.column_stack([tx.ravel(), ty.ravel()]))
    d, k = tree.query(np.column_stack([px, py]), k=2)
    clear = (d[:, 1] - d[:, 0]) > 0.05  # not a near-tie between two query pixels
    qr, qc = np.unravel_index(k[:, 0], tx.shape)
    same = np.all(geo[:, r, c] == q[:, qr, qc], axis=0)
    assert clear.sum() > 1500
    assert same[clear].mean() > 0.995, same[clear].mean()
    # and nodata outside the footprint: no valid pixel farther than a pixel from any query pixel
    rows_o, cols_o = np.nonzero(geo[0] == nodata)
    ox, oy = tr * (cols_o[::50] + 0.5, rows_o[::50] + 0.5)
    d_out, _ = tree.query(np.column_stack([ox, oy]))
    assert d_out.min() > 0.5 * SCENE["query"]["gsd_m"]
    # the ENVI copy: same pixels, CRS, grid, wavelengths
    with rasterio.open(out / "cube.bsq") as ds:
        assert ds.crs.to_epsg() == 32611 and ds.transform.almost_equals(tr)
        assert np.array_equal(ds.read(7), geo[6])
    envi = open_query(out / "cube.hdr")
    np.testing.assert_allclose(envi.wavelengths_nm, cube.wavelengths_nm, atol=1e-3)
    np.testing.assert_allclose(envi.fwhm_nm, cube.fwhm_nm, atol=1e-3)


def test_inverse_geolocation_exact_for_homography_and_respects_nan():
    H = np.array([[0.6, -0.5, 5000.0], [-0.45, -0.62, 9000.0], [1e-5, 2e-5, 1.0]])
    x, y = map_xy(H, 300, 220)
    inv = InverseGeolocation.build(x, y)
    rng = np.random.default_rng(1)
    c = rng.uniform(-0.4, 298.4, 5000)
    r = rng.uniform(-0.4, 218.4, 5000)
    w = H[2, 0] * c + H[2, 1] * r + H[2, 2]
    px = (H[0, 0] * c + H[0, 1] * r + H[0, 2]) / w
    py = (H[1, 0] * c + H[1, 1] * r + H[1, 2]) / w
    ci, ri = inv(px, py)
    # exact at pixel centres, within the bilinear-vs-projective curvature elsewhere
    assert np.nanmax(np.abs(ci - c)) < 1e-3 and np.nanmax(np.abs(ri - r)) < 1e-3
    assert np.isfinite(ci).all()
    far = inv(np.array([x[0, 0] - 50.0]), np.array([y[0, 0] - 50.0]))
    assert np.isnan(far[0]).all()
    x2, y2 = x.copy(), y.copy()
    x2[100:120, 100:120] = np.nan
    inv2 = InverseGeolocation.build(x2, y2)
    ch, _ = inv2(x[110, 110:112], y[110, 110:112])
    assert np.isnan(ch).all()


def test_building_ndsm_per_query_pixel_matches_true_height(run):
    """Roof pixels (eroded, unchanged between map and query epochs): sampled nDSM = true height."""
    scene, out = run["scene"], run["out"]
    elev = _read(out / "elevation.tif")
    ndsm = elev[2]
    true_h = _read(Path(scene["demo_ndsm"]), 1).astype(np.float64)
    lab = _read(Path(scene["demo_labels"]), 1)
    tx, ty = _read(Path(scene["demo_truth"])).astype(np.float64)
    map_lab = sample_raster_nearest(scene["labels"], tx, ty)
    for cls in (7, 8):  # houses, tall buildings
        roof = binary_erosion(lab == cls, iterations=2) & (map_lab == cls)
        assert roof.sum() > 100, cls
        err = np.abs(ndsm[roof] - true_h[roof])
        assert np.median(err) < 0.25, (cls, np.median(err))
        assert np.mean(err < 1.0) > 0.9, (cls, np.mean(err < 1.0))
    # longitude / latitude bands = pyproj of the geolocation
    lon, lat = pyproj.Transformer.from_crs(run["crs"], "EPSG:4326", always_xy=True).transform(
        tx, ty
    )
    np.testing.assert_allclose(elev[3], lon, atol=1e-9)
    np.testing.assert_allclose(elev[4], lat, atol=1e-9)
    with rasterio.open(out / "fused.tif") as ds:
        n = SCENE["query"]["bands"]
        assert ds.count == n + 3 and ds.descriptions[n] == "dsm (m)"
        assert ds.descriptions[n + 2].startswith("ndsm")
        np.testing.assert_allclose(ds.read(n + 3), ndsm.astype(np.float32), equal_nan=True)


def sample_raster_nearest(path: str, x: np.ndarray, y: np.ndarray) -> np.ndarray:
    with rasterio.open(path) as ds:
        a = ds.read(1)
        c, r = ~ds.transform * (x, y)
    ci = np.clip(np.floor(c).astype(int), 0, a.shape[1] - 1)
    ri = np.clip(np.floor(r).astype(int), 0, a.shape[0] - 1)
    return a[ri, ci]


def test_segmentation_agrees_with_generator_labels(run):
    acc = run["m"]["segmentation"]["accuracy"]
    per = acc["classes"]
    report = {k: (v["truth_pixels"], v["recall"], v["precision"])
              for k, v in per.items()}  # fmt: skip
    print("segmentation OA", round(acc["overall"], 4), report)
    assert acc["overall"] > 0.74  # measured 0.776 (map-epoch nDSM, 90 bands)
    for k, rec in (("tall_building", 0.85), ("low_building", 0.75), ("tree", 0.75), ("grass", 0.75),
                   ("road_bare", 0.60)):  # fmt: skip
        assert per[k]["recall"] > rec, (k, per[k])
    cm = np.array(acc["confusion"])
    T, L, TR, G = seg.TALL_BUILDING, seg.LOW_BUILDING, seg.TREE, seg.GRASS
    # tall vs low buildings and trees vs grass are separated, as the paper intends
    assert cm[L, T] < 0.05 * cm[L].sum() and cm[T, L] < 0.10 * cm[T].sum()
    assert cm[TR, G] < 0.10 * cm[TR].sum() and cm[G, TR] < 0.05 * cm[G].sum()
    # products: colour table, nodata, geo copy, csv sums
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", NotGeoreferencedWarning)
        with rasterio.open(run["out"] / "segmentation.tif") as ds:
            assert ds.dtypes[0] == "uint8" and ds.nodata == 0
            assert ds.colormap(1)[seg.TREE][:3] == seg.CLASSES[seg.TREE]["color"]
            assert len(ds.gcps[0]) > 10
    with rasterio.open(run["out"] / "segmentation_geo.tif") as ds:
        assert ds.crs.to_epsg() == 32611 and ds.nodata == 0
        assert set(np.unique(ds.read(1))) <= set(range(8))
        with rasterio.open(run["out"] / "cube.tif") as cube:  # made apart, on the same grid
            assert (ds.transform, ds.shape) == (cube.transform, cube.shape)
    lines = (run["out"] / "class_areas.csv").read_text().splitlines()
    assert lines[0] == "class,name,pixels,area_m2,fraction" and len(lines) == 8
    total = sum(float(v.split(",")[3]) for v in lines[1:])
    n_px = SCENE["query"]["samples"] * SCENE["query"]["lines"]
    assert total == pytest.approx(n_px * SCENE["query"]["gsd_m"] ** 2, rel=0.02)


def test_footprint_kml_and_geojson_corners(run):
    tx, ty = _read(Path(run["scene"]["demo_truth"])).astype(np.float64)
    h, w = tx.shape
    rc = [(0, 0), (0, w - 1), (h - 1, w - 1), (h - 1, 0)]
    to_ll = pyproj.Transformer.from_crs(run["crs"], "EPSG:4326", always_xy=True)
    want = np.array([to_ll.transform(tx[r, c], ty[r, c]) for r, c in rc])
    root = ET.parse(run["out"] / "footprint.kml").getroot()
    assert root.tag == f"{KML}kml"
    marks = root.findall(f".//{KML}Placemark")
    pts = [m for m in marks if m.find(f"{KML}Point") is not None]
    got = np.array(
        [[float(v) for v in m.find(f".//{KML}coordinates").text.split(",")[:2]] for m in pts]
    )
    np.testing.assert_allclose(got, want, atol=1e-8)
    ring_txt = root.find(f".//{KML}LinearRing/{KML}coordinates").text.split()
    ring = np.array([[float(v) for v in p.split(",")[:2]] for p in ring_txt])
    assert len(ring) >= 5 and np.allclose(ring[0], ring[-1])
    # every corner is a vertex of the outline (within a metre ~ 1e-5 deg)
    dist = np.abs(ring[None, :, :] - want[:, None, :]).max(axis=2).min(axis=1)
    assert dist.max() < 1e-5
    gj = json.loads((run["out"] / "footprint.geojson").read_text())
    assert gj["crs"]["properties"]["name"] == "urn:ogc:def:crs:EPSG::32611"
    coords = np.array(gj["features"][0]["geometry"]["coordinates"][0])
    assert coords[:, 0].min() == pytest.approx(tx.min(), abs=0.01)
    assert coords[:, 1].max() == pytest.approx(ty.max(), abs=0.01)


def test_points_carry_the_spectrum_of_their_pixel(run):
    scene, out = run["scene"], run["out"]
    las = laspy.read(out / "points_spectra.laz")
    cube = open_query(scene["demo_hdr"])
    names = [f"b{w:.0f}nm" for w in cube.wavelengths_nm]
    dims = set(las.point_format.extra_dimension_names)
    assert set(names) <= dims and {"query_col", "query_row"} <= dims
    assert str(las.header.version) == "1.4" and len(las) > 1000
    q = read_band_chunk(cube, 0, cube.count)
    rng = np.random.default_rng(2)
    k = rng.choice(len(las), 3000, replace=False)
    r = np.asarray(las["query_row"])[k].astype(int)
    c = np.asarray(las["query_col"])[k].astype(int)
    spec = np.stack([np.asarray(las[n])[k] for n in names])
    assert np.array_equal(spec, q[:, r, c])
    # each point lies in its pixel: within half a diagonal of the pixel's true centre
    tx, ty = _read(Path(scene["demo_truth"])).astype(np.float64)
    d = np.hypot(np.asarray(las.x)[k] - tx[r, c], np.asarray(las.y)[k] - ty[r, c])
    assert d.max() < 0.75 * SCENE["query"]["gsd_m"]


def test_not_found_writes_only_a_manifest(tmp_path):
    reg = tmp_path / "registration.json"
    reg.write_text(json.dumps({"status": "not_found", "reason": "no part accepted"}))
    out = tmp_path / "products" / "q"
    m1 = make_cube(reg, tmp_path / "missing.tif", tmp_path / "missing.hdr", out / "cube.json")
    m2 = make_products(reg, tmp_path / "missing.tif", tmp_path / "missing.hdr", None,
                       {}, [], out / "products.json")  # fmt: skip
    assert m1["status"] == m2["status"] == "not_found" and m2["files"] == {}
    assert sorted(p.name for p in out.iterdir()) == ["cube.json", "products.json"]
    assert json.loads((out / "products.json").read_text())["reason"] == "no part accepted"


def test_band_interleaved_cog_copy_keeps_pixels_and_is_a_cog(tmp_path):
    """The products' cube COG is copied band by band (bounded memory): same pixels as the stage,
    tiled, band interleaved, overviews down to about one block."""
    from georeg.io.raster import is_cog, tiled_profile
    from georeg.products.cube_resample import copy_band_interleaved_cog

    rng = np.random.default_rng(3)
    data = rng.integers(0, 4000, (12, 700, 530)).astype(np.uint16)
    stage = tmp_path / "stage.tif"
    prof = tiled_profile(530, 700, 12, "uint16", 0) | {
        "crs": "EPSG:32611", "transform": rasterio.Affine(1, 0, 500000, 0, -1, 3760000)}
    with rasterio.open(stage, "w", **prof) as ds:
        ds.write(data)
        ds.set_band_description(3, "1200.0 nm")
    copy_band_interleaved_cog(stage, tmp_path / "cog.tif", cache_mb=8)
    with rasterio.open(tmp_path / "cog.tif") as ds:
        assert np.array_equal(ds.read(), data)
        assert ds.interleaving.name == "band" and ds.block_shapes[0] == (256, 256)
        assert ds.overviews(1) == [2, 4] and ds.descriptions[2] == "1200.0 nm"
        assert ds.crs.to_epsg() == 32611 and ds.nodata == 0
    assert is_cog(tmp_path / "cog.tif")


@contextlib.contextmanager
def small_filesystem(where: Path, size_bytes: int):
    """A tmpfs of ``size_bytes`` mounted at ``where`` (root only; the test skips otherwise)."""
    where.mkdir(parents=True)
    if os.geteuid() != 0 or not shutil.which("mount"):
        pytest.skip("mounting a small filesystem needs root")
    r = subprocess.run(["mount", "-t", "tmpfs", "-o", f"size={size_bytes}", "tmpfs", str(where)],
                       capture_output=True, text=True)  # fmt: skip
    if r.returncode != 0:
        pytest.skip(f"cannot mount a tmpfs here: {r.stderr.strip()}")
    try:
        yield where
    finally:
        subprocess.run(["umount", "-l", str(where)], capture_output=True)


def _files(d: Path) -> list[str]:
    return sorted(str(p.relative_to(d)) for p in d.rglob("*") if p.is_file())


def test_disk_full_while_writing_products_then_rerun(run, tmp_path):
    """Issue 30: ENOSPC in the middle of the products: one error naming the file and the full
    disk, nothing half-written left (no output, no temporary), and after space is freed the same
    call completes with the same cube."""
    from georeg.io.errors import GeoregError

    scene, inp = run["scene"], run["inp"]
    need = sum(p.stat().st_size for p in run["out"].glob("cube.*"))
    with small_filesystem(tmp_path / "disk", need // 2) as disk:
        out = disk / "products" / "demo"
        args = (inp["registration"], inp["geolocation"], scene["demo_hdr"], out / "cube.json", {},
                None, "demo")  # fmt: skip
        with pytest.raises(GeoregError) as e:
            make_cube(*args)
        msg = str(e.value)
        assert "\n" not in msg and str(out) in msg and "no space left" in msg.lower(), msg
        assert _files(disk) == [], _files(disk)  # no partial output, no temporary
        subprocess.run(["mount", "-o", f"remount,size={need * 3}", "tmpfs", str(disk)], check=True)
        m = make_cube(*args)
        assert _files(out) == ["cube.bsq", "cube.hdr", "cube.json", "cube.tif"]
        assert np.array_equal(_read(out / "cube.tif"), _read(run["out"] / "cube.tif"))
        assert m["cube"]["bands"] == run["cube_m"]["cube"]["bands"]
