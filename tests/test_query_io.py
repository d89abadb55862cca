"""Reading query cubes (ENVI, GeoTIFF with wavelengths, plain images) and choosing the band."""

from __future__ import annotations

import gzip
from pathlib import Path

import numpy as np
import pytest
import rasterio

from georeg.io.errors import InputError
from georeg.io.query import open_query, parse_envi_header
from georeg.register.band import (
    auto_partner,
    parse_band_spec,
    pooled_indices,
    read_query_band,
    read_query_bands,
    select_band,
    stretch_uint8,
    write_query_band,
)

CODES = {"u1": 1, "i2": 2, "i4": 3, "f4": 4, "f8": 5, "u2": 12, "u4": 13, "i8": 14, "u8": 15}


def write_envi(
    base: Path,
    cube: np.ndarray,  # (bands, lines, samples)
    interleave: str = "bsq",
    big_endian: bool = False,
    ext: str = ".bil",
    offset: int = 0,
    extra: str = "",
    hdr_ext: str = ".hdr",
) -> Path:
    """Write ``cube`` as an ENVI file pair and return the header path."""
    b, lines, samples = cube.shape
    arr = {"bsq": cube, "bil": cube.transpose(1, 0, 2), "bip": cube.transpose(1, 2, 0)}[interleave]
    dt = cube.dtype.newbyteorder(">" if big_endian else "<")
    data = Path(f"{base}{ext}")
    data.write_bytes(b"\0" * offset + np.ascontiguousarray(arr).astype(dt).tobytes())
    hdr = Path(f"{base}{hdr_ext}")
    hdr.write_text(
        "ENVI\ndescription = {test cube,\n  written by a test}\n"
        f"samples = {samples}\nlines   = {lines}\nbands = {b}\nheader offset = {offset}\n"
        f"file type = ENVI Standard\ndata type = {CODES[cube.dtype.str[1:]]}\n"
        f"interleave = {interleave}\nbyte order = {int(big_endian)}\n{extra}"
    )
    return hdr


def cube_of(dtype: str, bands: int = 5, lines: int = 7, samples: int = 11) -> np.ndarray:
    rng = np.random.default_rng(3)
    a = rng.integers(0, 120, size=(bands, lines, samples))
    return a.astype(dtype)


@pytest.mark.parametrize("interleave", ["bsq", "bil", "bip"])
@pytest.mark.parametrize("big_endian", [False, True])
@pytest.mark.parametrize("dtype", ["u1", "i2", "i4", "f4", "f8", "u2", "u4", "i8", "u8"])
def test_envi_round_trip(tmp_path, interleave, big_endian, dtype):
    cube = cube_of(dtype)
    hdr = write_envi(
        tmp_path / "q", cube, interleave, big_endian, offset=16 if dtype == "i2" else 0
    )
    c = open_query(hdr)
    assert (c.width, c.height, c.count) == (11, 7, 5)
    for i in range(5):
        np.testing.assert_array_equal(c.read_band(i), cube[i].astype(np.float32))


@pytest.mark.parametrize("ext", ["", ".bsq", ".img", ".dat", ".BIL"])
def test_data_file_extensions_and_upper_case_header(tmp_path, ext):
    cube = cube_of("f4")
    hdr = write_envi(tmp_path / "scene", cube, "bil", ext=ext, hdr_ext=".HDR")
    c = open_query(hdr)
    np.testing.assert_array_equal(c.read_band(3), cube[3])
    # giving the data file instead of the header works too (when it has an extension)
    if ext:
        assert open_query(Path(f"{tmp_path / 'scene'}{ext}")).count == 5


@pytest.mark.parametrize(
    "units,values,expect",
    [
        ("Nanometers", "900, 1200, 1500, 2000, 2500", [900, 1200, 1500, 2000, 2500]),
        ("Micrometers", "0.9, 1.2, 1.5, 2.0, 2.5", [900, 1200, 1500, 2000, 2500]),
        ("um", "0.9, 1.2, 1.5, 2.0, 2.5", [900, 1200, 1500, 2000, 2500]),
        ("micrometers", "0.9, 1.2, 1.5, 2.0, 2.5", [900, 1200, 1500, 2000, 2500]),
        ("Unknown", "0.9, 1.2, 1.5, 2.0, 2.5", [900, 1200, 1500, 2000, 2500]),
    ],
)
def test_wavelength_units(tmp_path, units, values, expect):
    extra = f"wavelength units = {units}\nwavelength = {{\n {values}}}\nfwhm = {{{values}}}\n"
    c = open_query(write_envi(tmp_path / "w", cube_of("u2"), "bsq", extra=extra))
    np.testing.assert_allclose(c.wavelengths_nm, expect)
    _, _, info = select_band(c, "1.25um")
    assert info["index"] == 1 and info["wavelength_nm"] == pytest.approx(1200)


def test_band_selection_and_nodata(tmp_path):
    cube = cube_of("f4")
    cube[2, 0, :3] = -9999
    extra = (
        "wavelength units = nm\nwavelength = {900,1000,1100,1200,1300}\ndata ignore value = -9999\n"
    )
    c = open_query(write_envi(tmp_path / "n", cube, "bip", extra=extra))
    band, mask, info = select_band(c, "1100nm")
    assert info["index"] == 2 and not mask[0, :3].any() and mask.sum() == mask.size - 3
    band, mask, info = select_band(c, 4)
    np.testing.assert_array_equal(band, cube[4])
    mean, mmask, _ = select_band(c, "mean")
    expect = cube.mean(axis=0)
    expect[0, :3] = cube[[0, 1, 3, 4], 0, :3].mean(axis=0)  # nodata excluded per pixel
    np.testing.assert_allclose(mean, expect, rtol=1e-5)
    u8, st = stretch_uint8(band, mask)
    assert u8.dtype == np.uint8 and u8[mask].min() >= 1 and (u8[~mask] == 0).all()


def test_errors_are_clear(tmp_path):
    extra = "wavelength units = Micrometers\nwavelength = {0.9, 1.2, 1.5, 2.0, 2.5}\n"
    hdr = write_envi(tmp_path / "e", cube_of("i2"), "bil", extra=extra)
    c = open_query(hdr)
    with pytest.raises(InputError, match=r"outside the cube.*900\.0-2500\.0 nm in 5 bands"):
        select_band(c, "650nm")
    with pytest.raises(InputError, match=r"band index 9 does not exist.*0\.\.4"):
        select_band(c, 9)
    with pytest.raises(InputError, match="not understood"):
        parse_band_spec("red")
    # truncated data file
    data = Path(f"{tmp_path / 'e'}.bil")
    data.write_bytes(data.read_bytes()[:-10])
    with pytest.raises(InputError, match=r"e\.bil: data file is \d+ bytes but the header"):
        open_query(hdr)
    # compressed cube: refused with the fix in the message
    hdr2 = write_envi(tmp_path / "z", cube_of("u1"), "bsq", extra="file compression = 1\n")
    raw = Path(f"{tmp_path / 'z'}.bil")
    raw.write_bytes(gzip.compress(raw.read_bytes()))
    with pytest.raises(InputError, match="gzip"):
        open_query(hdr2)
    with pytest.raises(InputError, match="does not exist"):
        open_query(tmp_path / "missing.hdr")
    # no wavelengths and several bands: a wavelength cannot be chosen
    hdr3 = write_envi(tmp_path / "nw", cube_of("u1"), "bsq")
    with pytest.raises(InputError, match="no wavelengths.*index 0..4 or 'mean'"):
        select_band(open_query(hdr3), "1200nm")


def test_header_parser_multiline(tmp_path):
    p = tmp_path / "h.hdr"
    p.write_text("ENVI\nsamples = 3\nband names = {\n a,\n b}\nmap info = {UTM, 1, 1}\nlines=2\n")
    h = parse_envi_header(p)
    assert h["samples"] == "3" and h["lines"] == "2" and h["band names"].replace("\n", "") == "a, b"


def test_geotiff_with_wavelength_descriptions(tmp_path):
    p = tmp_path / "m.tif"
    data = np.arange(3 * 4 * 5, dtype=np.float32).reshape(3, 4, 5)
    with rasterio.open(p, "w", driver="GTiff", width=5, height=4, count=3, dtype="float32") as d:
        d.write(data)
        for i, w in enumerate(("418.24 nm", "1650.5 nm", "2.2 um"), start=1):
            d.set_band_description(i, w)
    c = open_query(p)
    np.testing.assert_allclose(c.wavelengths_nm, [418.24, 1650.5, 2200.0])
    band, _, info = select_band(c, "1600nm")
    assert info["index"] == 1
    np.testing.assert_array_equal(band, data[1])


def test_single_band_png_and_write_query_band(tmp_path):
    import cv2

    img = (np.random.default_rng(0).random((40, 30)) * 200 + 20).astype(np.uint8)
    p = tmp_path / "g.png"
    cv2.imwrite(str(p), img)
    c = open_query(p)
    assert c.count == 1 and c.wavelengths_nm is None
    meta = write_query_band(str(p), "1200nm", None, tmp_path / "b.tif", tmp_path / "b.json")
    assert meta["band"]["index"] == 0 and meta["valid_fraction"] == 1.0
    with rasterio.open(tmp_path / "b.tif") as d:
        assert d.read(1).shape == (40, 30) and d.nodata == 0
        assert d.count == 1  # `bands: auto` on one band: nothing to pool
    assert [b["index"] for b in meta["pooled_bands"]] == [0]
    assert read_query_bands(str(tmp_path / "b.tif")).shape == (1, 40, 30)
    # a location prior is checked here and recorded in band.json for the search and fuse jobs
    prior = {"centre": [10.0, 20.0], "radius_m": 50.0}
    meta = write_query_band(str(p), "1200nm", None, tmp_path / "c.tif", tmp_path / "c.json",
                            prior=prior)  # fmt: skip
    assert meta["prior"] == prior
    with pytest.raises(InputError, match=r"g\.png: queries prior: prior.radius_m"):
        write_query_band(str(p), "1200nm", None, tmp_path / "d.tif", tmp_path / "d.json",
                         prior={"centre": [10.0, 20.0], "radius_m": -1})  # fmt: skip
    assert not (tmp_path / "d.tif").exists() and not (tmp_path / "d.json").exists()


def test_auto_partner_pools_the_other_swir_window():
    # a 0.9-2.5 um cube: 1200 nm (band auto) + the band nearest 2200 nm
    wl = np.arange(900.0, 2501.0, 10.0)
    assert wl[auto_partner(wl, 30)] == 2200.0
    # Landsat / Sentinel-2 SWIR pair: band auto -> 1.61 um, pooled with 2.19 um, and back
    pair = np.array([1610.0, 2190.0])
    assert auto_partner(pair, 0) == 1 and auto_partner(pair, 1) == 0
    # a 2200 nm primary pools 1650 nm; a 0.9-1.7 um InGaAs cube pools 1650 nm with 1200 nm
    assert wl[auto_partner(wl, int(np.flatnonzero(wl == 2200.0)[0]))] == 1650.0
    ingaas = np.arange(900.0, 1701.0, 5.0)
    assert ingaas[auto_partner(ingaas, 60)] == 1650.0
    # nothing far enough in a SWIR window, one band, or no wavelengths: no partner
    assert auto_partner(np.array([1200.0, 1300.0, 1400.0]), 0) is None
    assert auto_partner(np.array([1650.0]), 0) is None and auto_partner(None, 0) is None


def test_write_query_band_pools_bands_primary_first(tmp_path):
    wl = np.arange(1000.0, 2401.0, 100.0)  # 15 bands
    rng = np.random.default_rng(5)
    cube = (rng.random((15, 20, 24)) * 1000 + 10).astype("f4")
    cube[12, :3] = -1.0  # nodata in the 2200 nm band only
    wls = ", ".join(f"{w:g}" for w in wl)
    hdr = write_envi(
        tmp_path / "q", cube, extra=f"wavelength = {{{wls}}}\ndata ignore value = -1\n"
    )
    meta = write_query_band(str(hdr), "auto", 2.0, tmp_path / "b.tif", tmp_path / "b.json")
    got = [(b["index"], b["wavelength_nm"]) for b in meta["pooled_bands"]]
    assert got == [(2, 1200.0), (12, 2200.0)]
    stack = read_query_bands(str(tmp_path / "b.tif"))
    assert stack.shape == (2, 20, 24)
    # each plane is its own band stretched on its own valid pixels; 0 = that band's nodata
    for plane, k in zip(stack, (2, 12), strict=True):
        m = cube[k] != -1.0
        np.testing.assert_array_equal(plane, stretch_uint8(cube[k], m)[0])
    assert (stack[1, :3] == 0).all() and (stack[0] > 0).all()
    assert meta["pooled_bands"][1]["valid_fraction"] == pytest.approx(17 / 20)
    # readers of the primary band (refinement, figures) see band 1
    np.testing.assert_array_equal(read_query_band(str(tmp_path / "b.tif")), stack[0])
    # `one`: the primary only; a list: the primary, then those bands, duplicates dropped
    meta = write_query_band(str(hdr), "auto", 2.0, tmp_path / "c.tif", tmp_path / "c.json",
                            bands_spec="one")  # fmt: skip
    assert [b["index"] for b in meta["pooled_bands"]] == [2]
    with rasterio.open(tmp_path / "c.tif") as d:
        assert d.count == 1
    c = open_query(hdr)
    assert pooled_indices(c, 2, ["1.6um", 0, "1200nm"]) == [2, 6, 0]
    assert pooled_indices(c, None, "auto") == [None]  # the mean is not pooled with anything
    with pytest.raises(InputError, match="not understood"):
        pooled_indices(c, 2, "all")
    with pytest.raises(InputError, match="cannot be pooled"):
        pooled_indices(c, 2, ["mean"])


def test_enmap_geotiff(shared_data):
    c = open_query(shared_data / "enmap_potsdam" / "enmap_potsdam_mosaic_subset.tif")
    assert c.count == 224 and c.wavelengths_nm.min() == pytest.approx(418.24)
    band, mask, info = select_band(c, "1.65um")
    assert abs(info["wavelength_nm"] - 1650) < 10 and 0.1 < mask.mean() < 0.9


def test_gsd_from_the_files_own_georeferencing(tmp_path):
    """Without ``gsd_m`` the query's GSD is the pixel size its file states (a GeoTIFF's
    geotransform, in metres or feet; on the ground for longitude/latitude; an ENVI ``map info``),
    recorded as ``gsd_source: geotransform``; a given ``gsd_m`` wins; a plain image has none."""
    from georeg.io.query import georeferenced_gsd_m

    a = np.full((1, 20, 30), 50, np.uint16)

    def tif(name: str, crs: str | None, t: rasterio.Affine) -> Path:
        p = tmp_path / name
        with rasterio.open(p, "w", driver="GTiff", width=30, height=20, count=1, dtype="uint16",
                           **({"crs": crs, "transform": t} if crs else {})) as d:  # fmt: skip
            d.write(a)
        return p

    utm = tif("utm.tif", "EPSG:32633", rasterio.Affine(30.0, 0, 500000, 0, -30.0, 5800000))
    assert georeferenced_gsd_m(open_query(utm)) == pytest.approx(30.0)
    feet = tif("ft.tif", "EPSG:2229", rasterio.Affine(10.0, 0, 6e6, 0, -10.0, 2e6))  # US survey feet
    assert georeferenced_gsd_m(open_query(feet)) == pytest.approx(3.048, abs=1e-3)
    deg = 1e-4  # square degrees at 60 N: 5.6 x 11.1 m on the ground
    geo = tif("geo.tif", "EPSG:4326", rasterio.Affine(deg, 0, 10.0, 0, -deg, 60.001))
    assert georeferenced_gsd_m(open_query(geo)) == pytest.approx(7.87, abs=0.05)
    assert georeferenced_gsd_m(open_query(tif("plain.tif", None, rasterio.Affine.identity()))) is None
    hdr = write_envi(tmp_path / "env", cube_of("u1"), extra="map info = {UTM, 1.000, 1.000, 660585.0, "
                     "3551295.0, 2.5e+001, 2.5e+001, 50, North, WGS-84, units=Meters}\n")  # fmt: skip
    assert georeferenced_gsd_m(open_query(hdr)) == pytest.approx(25.0)
    meta = write_query_band(str(utm), "auto", None, tmp_path / "b.tif", tmp_path / "b.json")
    assert meta["gsd_m"] == pytest.approx(30.0) and meta["gsd_source"] == "geotransform"
    meta = write_query_band(str(utm), "auto", 28.0, tmp_path / "c.tif", tmp_path / "c.json")
    assert meta["gsd_m"] == 28.0 and meta["gsd_source"] == "config"
