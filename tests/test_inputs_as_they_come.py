"""Maps and queries as users have them, at library level: orthophotos of any band layout and bit
depth become the map's 8-bit RGB, maps without elevation, `band: auto`, and every input checked
before a run (all problems in one list)."""

from __future__ import annotations

import json
from pathlib import Path

import laspy
import numpy as np
import pytest
import rasterio
from rasterio.enums import ColorInterp
from rasterio.transform import from_origin

from georeg.io.query import open_query
from georeg.map.elevation import LAYERS, make_elevation_tile
from georeg.map.grid import make_ortho_tile, write_grid
from georeg.map.visible import visible_bands
from georeg.register.band import parse_band_spec, resolve_band, select_band
from georeg.register.inputs import check_inputs, utm_hint

UTM = "EPSG:32611"
H = W = 96


def _scene(seed: int = 0) -> dict[str, np.ndarray]:
    """Three distinct smooth 'colour' fields and a NIR that looks like none of them."""
    rng = np.random.default_rng(seed)
    yy, xx = np.mgrid[0:H, 0:W].astype(np.float64)
    return {
        "red": xx / W,
        "green": yy / H,
        "blue": (xx + yy) / (W + H),
        "nir": rng.uniform(0, 1, (H, W)),
    }


def _write(path: Path, bands: list[np.ndarray], dtype: str, crs: str | None = UTM, **kw) -> Path:
    arr = np.stack(bands).astype(dtype)
    with rasterio.open(
        path, "w", driver="GTiff", width=W, height=H, count=len(bands), dtype=dtype, crs=crs,
        transform=from_origin(500000, 3760000, 1, 1), **kw,
    ) as ds:  # fmt: skip
        ds.write(arr)
    return path


def _with_descriptions(path: Path, descs: list[str], interp: list[ColorInterp] | None = None):
    with rasterio.open(path, "r+") as ds:
        for i, d in enumerate(descs, 1):
            ds.set_band_description(i, d)
        if interp:
            ds.colorinterp = interp
    return path


def _tile(tmp: Path, ortho: Path) -> np.ndarray:
    write_grid(tmp / "grid.json", [str(ortho)], 128, 16)
    make_ortho_tile(tmp / "grid.json", "r000_c000", tmp / "t.tif")
    with rasterio.open(tmp / "t.tif") as ds:
        assert ds.count == 3 and ds.dtypes[0] == "uint8"
        return ds.read(), ds.dataset_mask()


def _corr(a: np.ndarray, b: np.ndarray) -> float:
    return float(np.corrcoef(a.ravel().astype(float), b.ravel().astype(float))[0, 1])


def test_panchromatic_16_bit_becomes_grey_rgb(tmp_path):
    s = _scene()
    o = _write(tmp_path / "pan.tif", [s["red"] * 10000], "uint16")
    rgb, mask = _tile(tmp_path, o)
    assert np.array_equal(rgb[0], rgb[1]) and np.array_equal(rgb[0], rgb[2])
    assert _corr(rgb[0], s["red"]) > 0.999
    assert rgb[0].max() == 255 and rgb[0][mask > 0].min() <= 2  # stretched over the 8 bits
    assert json.loads((tmp_path / "grid.json").read_text())["visible"]["how"].startswith("one band")


def test_nir_first_16_bit_takes_red_green_blue_by_description(tmp_path):
    s = _scene()
    o = _write(tmp_path / "nrgb.tif", [s[k] * 10000 for k in ("nir", "red", "green", "blue")], "uint16")
    _with_descriptions(o, ["NIR", "Red", "Green", "Blue"])
    rgb, _ = _tile(tmp_path, o)
    for i, k in enumerate(("red", "green", "blue")):
        assert _corr(rgb[i], s[k]) > 0.99, k
    assert abs(_corr(rgb[0], s["nir"])) < 0.2


def test_bands_by_wavelength_in_descriptions(tmp_path):
    s = _scene()
    o = _write(tmp_path / "wl.tif", [s[k] for k in ("blue", "green", "red", "nir")], "float32")
    _with_descriptions(o, ["490 nm", "560 nm", "665 nm", "842 nm"])
    with rasterio.open(o) as ds:
        assert visible_bands(ds)[0] == [3, 2, 1]


def test_float_nan_is_masked_and_alpha_is_not_a_colour(tmp_path):
    s = _scene()
    red = s["red"].copy()
    red[:10] = np.nan
    o = _write(tmp_path / "f.tif", [red, s["green"], s["blue"]], "float32")
    _, mask = _tile(tmp_path, o)
    assert (mask[:10] == 0).all() and (mask[10:] > 0).all()
    a = _write(tmp_path / "rgba.tif", [s["red"] * 255, s["green"] * 255, s["blue"] * 255,
                                       np.full((H, W), 255.0)], "uint8")  # fmt: skip
    _with_descriptions(a, ["", "", "", ""], [ColorInterp.red, ColorInterp.green, ColorInterp.blue,
                                             ColorInterp.alpha])  # fmt: skip
    with rasterio.open(a) as ds:
        assert visible_bands(ds)[0] == [1, 2, 3]


def test_8_bit_rgb_tiles_are_unchanged(tmp_path):
    s = _scene()
    o = _write(tmp_path / "rgb.tif", [s[k] * 250 for k in ("red", "green", "blue")], "uint8")
    rgb, _ = _tile(tmp_path, o)
    with rasterio.open(o) as ds:
        assert np.array_equal(rgb, ds.read())


def test_map_without_elevation_writes_nodata_heights_and_no_points(tmp_path):
    s = _scene()
    o = _write(tmp_path / "rgb.tif", [s[k] * 250 for k in ("red", "green", "blue")], "uint8")
    outs = {k: str(tmp_path / f"{k}.tif") for k in LAYERS} | {"points": str(tmp_path / "p.laz")}
    make_elevation_tile(str(o), outs, [], None)
    for k in ("dsm", "dtm", "ndsm"):
        with rasterio.open(outs[k]) as ds:
            assert (ds.read(1, masked=True).mask).all(), k
    with rasterio.open(outs["density"]) as ds:
        assert (ds.read(1) == 0).all()
    assert laspy.read(outs["points"]).header.point_count == 0


def _two_band_swir(path: Path, descs=("1610 nm", "2190 nm")) -> Path:
    s = _scene()
    o = _write(path, [s["red"] * 3000, s["green"] * 2000], "uint16", crs=None)
    return _with_descriptions(o, list(descs))


def test_band_auto_takes_the_band_nearest_1200_nm(tmp_path):
    cube = open_query(_two_band_swir(tmp_path / "swir2.tif"))
    assert list(cube.wavelengths_nm) == [1610.0, 2190.0]
    assert resolve_band(cube, parse_band_spec("auto")) == 0
    _, _, info = select_band(cube, "auto")
    assert info["wavelength_nm"] == 1610.0
    with pytest.raises(Exception, match="outside the cube"):
        resolve_band(cube, parse_band_spec("1200nm"))  # an explicit wavelength stays strict
    nowl = open_query(_two_band_swir(tmp_path / "nowl.tif", ("band a", "band b")))
    assert nowl.wavelengths_nm is None and resolve_band(nowl, parse_band_spec("auto")) == 0


def test_three_broken_inputs_in_one_list(tmp_path):
    s = _scene()
    bad = tmp_path / "corrupt.tif"
    bad.write_bytes(b"not a tiff at all")
    good = _write(tmp_path / "ok.tif", [s["red"] * 250] * 3, "uint8")
    config = {
        "map": {"orthophoto": [str(good), str(bad)], "lidar": [str(tmp_path / "gone.laz")]},
        "queries": {"q": {"image": str(_two_band_swir(tmp_path / "q.tif")), "band": "900nm"}},
        "frames": {"f": {"images": [str(good)]}},
    }
    problems = check_inputs(config)
    assert len(problems) == 3, problems
    assert any("corrupt.tif" in p and "not a readable raster" in p for p in problems)
    assert any("gone.laz" in p and "file not found" in p for p in problems)
    assert any(p.startswith("queries.q:") and "900 nm is outside" in p for p in problems)


def test_geographic_map_crs_is_refused_with_the_utm_zone(tmp_path):
    s = _scene()
    with rasterio.open(
        tmp_path / "geo.tif", "w", driver="GTiff", width=W, height=H, count=1, dtype="uint8",
        crs="EPSG:4326", transform=from_origin(13.0, 52.5, 1e-4, 1e-4),
    ) as ds:  # fmt: skip
        ds.write((s["red"] * 250).astype("uint8")[None])
    problems = check_inputs({"map": {"orthophoto": str(tmp_path / "geo.tif")}})
    assert len(problems) == 1 and "EPSG:32633" in problems[0], problems
    assert check_inputs({"map": {"orthophoto": str(tmp_path / "geo.tif"), "crs": "EPSG:32633"}}) == []
    assert utm_hint(-117.0, 34.0).startswith("EPSG:32611")


def test_outputs_of_the_workflow_are_not_checked(tmp_path):
    """Paths under results/ are made by rules: not opened before the run. The relative paths
    resolve in this test's own directory (conftest), never in a checkout where the demo ran."""
    assert Path.cwd() == tmp_path and not (tmp_path / "results").exists()
    cfg = {"map": {"orthophoto": "results/demo/orthophoto.tif", "lidar": ["results/demo/l.laz"]},
           "queries": {"d": {"image": "results/demo/queries/demo.hdr", "band": "1200nm"}}}  # fmt: skip
    assert check_inputs(cfg, generated="results") == []
    assert len(check_inputs(cfg, generated=None)) == 3


@pytest.mark.shared
def test_real_enmap_cube_as_orthophoto_takes_its_visible_bands(shared_data, tmp_path):
    """224 float bands, NaN nodata, wavelengths in the descriptions ('647.34 nm')."""
    src = shared_data / "enmap_potsdam" / "enmap_potsdam_mosaic_subset.tif"
    with rasterio.open(src) as ds:
        bands, how = visible_bands(ds)
        wl = [float(ds.descriptions[b - 1].split()[0]) for b in bands]
        valid = np.isfinite(ds.read(bands[0]))
    assert "wavelength" in how and abs(wl[0] - 650) < 10 and abs(wl[1] - 550) < 10
    assert abs(wl[2] - 470) < 10
    write_grid(tmp_path / "grid.json", [str(src)], 256, 16)
    make_ortho_tile(tmp_path / "grid.json", "r000_c000", tmp_path / "t.tif")
    with rasterio.open(tmp_path / "t.tif") as ds:
        mask = ds.dataset_mask() > 0
        rgb = ds.read()
    assert np.array_equal(mask, valid[: mask.shape[0], : mask.shape[1]])  # NaN -> masked
    assert rgb[:, mask].std(axis=1).min() > 5  # stretched into the 8 bits, not flat


@pytest.mark.shared
def test_real_sentinel2_band_in_lon_lat_is_refused_with_its_utm_zone(shared_data):
    b04 = sorted((shared_data / "swir_dates" / "oscd_dev" / "abudhabi" / "imgs_1").glob("*B04.tif"))[0]
    problems = check_inputs({"map": {"orthophoto": str(b04)}})
    assert len(problems) == 1 and b04.name in problems[0], problems
    assert "EPSG:32640" in problems[0]  # Abu Dhabi, 54.4 deg E: UTM zone 40N


def test_a_location_prior_is_checked_and_must_overlap_the_map(tmp_path):
    """queries.<name>.prior: malformed or off the map -> one clear line each; fine -> none."""
    s = _scene()
    ortho = _write(tmp_path / "ok.tif", [s["red"] * 250] * 3, "uint8")  # 96 m at 500000, 3760000
    q = str(_two_band_swir(tmp_path / "q.tif"))

    def problems(prior):
        cfg = {"map": {"orthophoto": str(ortho)}, "queries": {"q": {"image": q, "prior": prior}}}
        return check_inputs(cfg)

    assert problems({"centre": [500050.0, 3759950.0], "radius_m": 30}) == []
    assert problems({"box": [499000.0, 3759000.0, 500010.0, 3759910.0]}) == []
    off = problems({"centre": [600000.0, 3759950.0], "radius_m": 30})
    assert len(off) == 1 and off[0].startswith("queries.q.prior:") and "does not overlap" in off[0]
    bad = problems({"box": [500100.0, 3759950.0, 500000.0, 3760000.0]})
    assert len(bad) == 1 and bad[0].startswith("queries.q.prior.box") and "x0 < x1" in bad[0]
    ll = problems({"centre": [-117.0, 200.0], "radius_m": 30, "crs": "lonlat"})
    assert len(ll) == 1 and "out of range" in ll[0]
    # lon/lat of the map's centre (UTM 11N): fine
    from pyproj import Transformer

    lon, lat = Transformer.from_crs(UTM, "EPSG:4326", always_xy=True).transform(500048, 3759952)
    assert problems({"centre": [lon, lat], "radius_m": 20, "crs": "lonlat"}) == []
