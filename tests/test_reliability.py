"""Issue 13, library level: the bad-input matrix, the band-by-band reader, units, stale temporaries.

Each case writes a real malformed file, calls the function the rule's script calls, and checks
the one-line error (names the file, says what is wrong and what to do) and that the failed step
left no output. The same cases through the ``snakemake`` command: test_reliability_workflow.py.
The table of all cases is docs/RELIABILITY.md.
"""

from __future__ import annotations

import gzip
import math
import os
import subprocess
import tracemalloc
from pathlib import Path

import cv2
import numpy as np
import pytest
import rasterio
from pyproj import CRS
from rasterio.transform import from_origin
from test_map_synthetic import UTM, X0, Y0, make_las, make_ortho, run_tile, scene_points
from test_query_io import cube_of, write_envi

from georeg.io.atomic import write_text
from georeg.io.errors import InputError
from georeg.map.grid import make_ortho_tile, write_grid
from georeg.register.band import write_query_band
from georeg.register.search import gsd_in_map_units

WL = "wavelength units = nm\nwavelength = {900, 1100, 1300, 1500, 1700}\n"


def clear_error(exc: pytest.ExceptionInfo, path: Path | str, *words: str) -> str:
    """The message is one line, names the file, says what is wrong and (in brackets) what to do."""
    msg = str(exc.value)
    assert "\n" not in msg, msg
    assert str(path) in msg, msg
    assert msg.rstrip().endswith(")") and " (" in msg, f"no hint: {msg}"
    for w in words:
        assert w.lower() in msg.lower(), (w, msg)
    return msg


def no_files(d: Path) -> None:
    left = [p for p in d.rglob("*") if p.is_file()] if d.exists() else []
    assert not left, left


# ---------------------------------------------------------------- map: orthophoto


def _tiled_ortho(path: Path, nodata: float | None = None, fill: int | None = None) -> Path:
    data = np.random.default_rng(0).integers(1, 255, (3, 400, 400), dtype=np.uint8)
    if fill is not None:
        data[:] = fill
    with rasterio.open(
        path, "w", driver="GTiff", width=400, height=400, count=3, dtype="uint8", crs=UTM,
        transform=from_origin(X0, Y0, 1, 1), compress="deflate", tiled=True, nodata=nodata,
    ) as ds:  # fmt: skip
        ds.write(data)
    return path


def test_truncated_geotiff(tmp_path):
    o = _tiled_ortho(tmp_path / "ortho.tif")
    o.write_bytes(o.read_bytes()[: o.stat().st_size // 2])
    out = tmp_path / "results"
    with pytest.raises(InputError) as e:
        write_grid(out / "grid.json", [str(o)], 512, 8)
        make_ortho_tile(out / "grid.json", "r000_c000", out / "tiles" / "ortho.tif")
    clear_error(e, o, "truncated")
    assert not (out / "tiles").exists() or not list((out / "tiles").iterdir())


def test_orthophoto_without_crs(tmp_path):
    o = make_ortho(tmp_path / "ortho.tif", crs=None)
    with pytest.raises(InputError) as e:
        write_grid(tmp_path / "out" / "grid.json", [str(o)], 128, 8)
    clear_error(e, o, "no CRS", "map.crs")
    no_files(tmp_path / "out")


def test_orthophoto_all_nodata(tmp_path):
    o = _tiled_ortho(tmp_path / "ortho.tif", nodata=0, fill=0)
    with pytest.raises(InputError) as e:
        write_grid(tmp_path / "out" / "grid.json", [str(o)], 128, 8)
    clear_error(e, o, "no valid pixels", "nodata")
    no_files(tmp_path / "out")


# ---------------------------------------------------------------- map: LiDAR


def _elevation_outputs(tmp: Path) -> list[str]:
    return sorted(p.name for p in (tmp / "tiles" / "r000_c000").iterdir())


def test_las_without_crs_without_and_with_lidar_crs(tmp_path):
    ortho = make_ortho(tmp_path / "ortho.tif")
    las = make_las(tmp_path / "nocrs.las", scene_points(density=0.2), crs=None)
    with pytest.raises(InputError) as e:
        run_tile(tmp_path, ortho, [las])
    clear_error(e, las, "no CRS", "map.lidar_crs")
    assert _elevation_outputs(tmp_path) == ["ortho.tif"]
    # the same file with map.lidar_crs: runs
    from georeg.map.elevation import LAYERS, make_elevation_tile

    tdir = tmp_path / "tiles" / "r000_c000"
    outs = {k: str(tdir / f"{k}.tif") for k in LAYERS} | {"points": str(tdir / "points.laz")}
    make_elevation_tile(str(tdir / "ortho.tif"), outs, [str(las)], lidar_crs=UTM)
    with rasterio.open(outs["density"]) as d:
        assert d.read(1).max() > 0


def test_laz_with_zero_points(tmp_path):
    ortho = make_ortho(tmp_path / "ortho.tif")
    empty = make_las(tmp_path / "empty.laz", {k: v[:0] for k, v in scene_points(0.01).items()})
    with pytest.raises(InputError) as e:
        run_tile(tmp_path, ortho, [empty])
    clear_error(e, empty, "empty", "0 points", "remove it")
    assert _elevation_outputs(tmp_path) == ["ortho.tif"]


def test_lidar_not_overlapping_warns_and_runs_on(tmp_path, caplog):
    ortho = make_ortho(tmp_path / "ortho.tif")
    pts = scene_points(density=0.1)
    pts["e"] = pts["e"] + 5000.0
    las = make_las(tmp_path / "far.laz", pts)
    run_tile(tmp_path, ortho, [las])
    assert "no LiDAR file overlaps this tile" in caplog.text and "far.laz" in caplog.text
    assert "dsm.tif" in _elevation_outputs(tmp_path)


# ---------------------------------------------------------------- query cube


def _band(tmp: Path, hdr: Path, spec) -> tuple[Path, Path]:
    out = tmp / "out"
    return out, write_query_band(str(hdr), spec, 0.8, str(out / "band.tif"), str(out / "band.json"))


@pytest.mark.parametrize(
    "case,spec,extra,words",
    [
        ("no_wavelength", "1200nm", "", ["no wavelengths", "index 0..4 or 'mean'"]),
        ("index_out_of_range", 7, WL, ["band index 7 does not exist", "0..4"]),
        ("wavelength_outside", "2400nm", WL, ["outside the cube", "900.0-1700.0 nm"]),
        ("gzip", 1, "file compression = 1\n", ["gzip", "gunzip"]),
        ("short_data", 1, WL, ["data file is", "truncated"]),
        ("all_nodata", 1, WL + "data ignore value = 0\n", ["no valid pixel", "data ignore value"]),
    ],
)
def test_bad_query_cube(tmp_path, case, spec, extra, words):
    cube = cube_of("u2")
    if case == "all_nodata":
        cube[:] = 0
    hdr = write_envi(tmp_path / "q", cube, "bil", extra=extra)
    data = Path(f"{tmp_path / 'q'}.bil")
    if case == "gzip":
        data.write_bytes(gzip.compress(data.read_bytes()))
    if case == "short_data":
        data.write_bytes(data.read_bytes()[:-100])
    with pytest.raises(InputError) as e:
        _band(tmp_path, hdr, spec)
    clear_error(e, data if case == "short_data" else hdr, *words)
    no_files(tmp_path / "out")


def test_constant_query_band_is_written(tmp_path):
    """A one-value cube is a valid input: the band is written (registration: not_found, in the
    workflow test), never a division by zero in the stretch."""
    hdr = write_envi(tmp_path / "flat", np.full((5, 30, 40), 7, np.uint16), "bsq", extra=WL)
    meta = write_query_band(
        str(hdr), "1200nm", 0.8, str(tmp_path / "b.tif"), str(tmp_path / "b.json")
    )
    assert meta["valid_fraction"] == 1.0
    with rasterio.open(tmp_path / "b.tif") as b:
        assert np.unique(b.read(1)).size == 1


def test_query_larger_than_memory_is_read_band_by_band(tmp_path):
    """A 2.4 GB cube (sparse file: no disk used) costs the memory of one band, not the cube."""
    bands, lines, samples = 400, 1500, 2000
    base = tmp_path / "big"
    data = Path(f"{base}.bil")
    with open(data, "wb") as f:
        f.truncate(bands * lines * samples * 2)
    wl = ", ".join(f"{900 + 4 * i}" for i in range(bands))
    Path(f"{base}.hdr").write_text(
        f"ENVI\nsamples = {samples}\nlines = {lines}\nbands = {bands}\ndata type = 12\n"
        f"interleave = bil\nbyte order = 0\nwavelength units = nm\nwavelength = {{{wl}}}\n"
    )
    mm = np.memmap(data, np.uint16, "r+", shape=(lines, bands, samples))
    mm[::25, 75, ::7] = 1000  # a few real values in the band asked for
    mm[::25, 325, ::5] = 500  # ... and in the 2200 nm band pooled with it (`bands: auto`)
    mm.flush()
    del mm
    band_bytes = lines * samples * 4  # one float32 band
    tracemalloc.start()
    try:
        meta = write_query_band(
            str(Path(f"{base}.hdr")),
            "1200nm",
            0.8,
            str(tmp_path / "b.tif"),
            str(tmp_path / "b.json"),
        )
        _, peak = tracemalloc.get_traced_memory()
    finally:
        tracemalloc.stop()
    assert meta["band"]["index"] == 75
    assert [b["index"] for b in meta["pooled_bands"]] == [75, 325]
    assert peak < 8 * band_bytes, peak  # the whole cube: 200 band-sizes (measured: ~6)
    assert data.stat().st_blocks * 512 < 50e6  # still sparse: the test used little disk
    data.unlink()


# ---------------------------------------------------------------- units, paths


def test_query_gsd_in_metres_meets_map_in_feet():
    """The query's gsd_m is metres; a map in US feet is searched at gsd / 0.3048006 ft."""
    ftus = CRS.from_epsg(2229).to_wkt()
    assert gsd_in_map_units(0.8, ftus) == pytest.approx(0.8 / 0.3048006096, rel=1e-9)
    assert gsd_in_map_units(0.8, CRS.from_epsg(32611).to_wkt()) == 0.8
    assert gsd_in_map_units(None, ftus) is None


def test_query_gsd_meets_a_web_mercator_map_at_its_latitude():
    """A Web Mercator map's metre is 1 / cos(latitude) ground metres: at 48.7 N a 20 m query
    pixel spans 30.3 map units (searched at 20 it was `not_found`: session 30, Saclay);
    UTM's scale (< 0.1 % from 1) is left out, so UTM runs are unchanged."""
    from pyproj import Transformer

    def at(epsg: str) -> tuple[float, float]:
        return Transformer.from_crs("EPSG:4326", epsg, always_xy=True).transform(2.2, 48.7)

    merc = CRS.from_epsg(3857).to_wkt()
    assert gsd_in_map_units(20.0, merc, at("EPSG:3857")) == pytest.approx(20.0 / math.cos(math.radians(48.7)), rel=3e-3)
    assert gsd_in_map_units(20.0, merc) == 20.0  # no centre: the unit alone
    utm = CRS.from_epsg(32631).to_wkt()
    assert gsd_in_map_units(20.0, utm, at("EPSG:32631")) == 20.0


def test_lidar_in_feet_under_a_metre_map(tmp_path):
    """Horizontal and vertical US feet LiDAR (EPSG:2229) under a UTM map: heights in metres."""
    from test_map_synthetic import GROUND_M

    ortho = make_ortho(tmp_path / "ortho.tif")
    las = make_las(tmp_path / "feet.laz", scene_points(density=0.5), crs="EPSG:2229")
    outs = run_tile(tmp_path, ortho, [las])
    with rasterio.open(outs["dtm"]) as d:
        assert np.median(d.read(1, masked=True)) == pytest.approx(GROUND_M, abs=0.3)


def test_paths_with_spaces_and_non_ascii(tmp_path):
    d = tmp_path / "Données d'été ü"
    d.mkdir()
    hdr = write_envi(d / "cube é 1", cube_of("u2"), "bil", extra=WL)
    meta = write_query_band(
        str(hdr), "1300nm", 0.8, str(d / "out ß" / "b.tif"), str(d / "out ß" / "b.json")
    )
    assert meta["band"]["index"] == 2
    o = make_ortho(d / "ortho ñ.tif")
    write_grid(d / "res ø" / "grid.json", [str(o)], 256, 16)
    make_ortho_tile(d / "res ø" / "grid.json", "r000_c000", d / "res ø" / "t.tif")
    # and the errors still name the file exactly
    with pytest.raises(InputError) as e:
        write_grid(d / "x.json", [str(d / "nö such.tif")], 256, 16)
    assert str(d / "nö such.tif") in str(e.value)


# ---------------------------------------------------------------- atomic writes


def test_killed_writer_leaves_only_a_hidden_temporary_that_the_next_write_removes(tmp_path):
    dead = subprocess.Popen(["true"])
    dead.wait()
    stale = tmp_path / f".grid.tmp-{dead.pid}.json"
    stale.write_text('{"half": ')  # what a SIGKILLed writer leaves: never under the real name
    alive = tmp_path / f".grid.tmp-{os.getppid()}.json"  # a live writer's temporary is kept
    alive.write_text("{}")
    write_text(tmp_path / "grid.json", "{}\n")
    assert not stale.exists() and alive.exists()
    assert (tmp_path / "grid.json").read_text() == "{}\n"


# ---------------------------------------------------------------- faults (issue 30)


@pytest.mark.parametrize("where", [0.01, 0.2, 0.5, 0.9, -4])
def test_laz_truncated_anywhere_is_named_truncated_before_the_run(tmp_path, where):
    """A LAZ cut in its CRS records, in the middle of its points or in its chunk table (the last
    bytes): the header check (before any rule) says truncated, never "no CRS"."""
    from georeg.map.lidar import scan
    from georeg.register.inputs import check_inputs

    good = make_las(tmp_path / "good.laz", scene_points(density=1.0))
    data = good.read_bytes()
    bad = tmp_path / "cut.laz"
    bad.write_bytes(data[: int(len(data) * where) if where > 0 else len(data) + where])
    with pytest.raises(InputError) as e:
        scan(bad)
    clear_error(e, bad, "truncated", f"{bad.stat().st_size} bytes")
    ortho = make_ortho(tmp_path / "ortho.tif")
    problems = check_inputs({"map": {"orthophoto": str(ortho), "lidar": [str(bad)]}})
    assert len(problems) == 1 and str(bad) in problems[0] and "truncated" in problems[0], problems
    scan(good)  # the whole file is fine


def _jpeg(path: Path, keep: float = 1.0) -> Path:
    rng = np.random.default_rng(5)
    img = cv2.GaussianBlur(rng.integers(0, 255, (240, 320, 3), dtype=np.uint8), (0, 0), 2)
    data = cv2.imencode(".jpg", img)[1].tobytes()
    path.write_bytes(data[: int(len(data) * keep)])
    return path


def test_truncated_jpeg_frame_is_refused_naming_it(tmp_path):
    """A JPEG cut short decodes in OpenCV (grey bottom, a libjpeg warning only): it must be an
    error naming the file, at the input check before the run and where the frame is read."""
    from georeg.frames.localize import check_frame
    from georeg.register.inputs import check_inputs

    good, cut = _jpeg(tmp_path / "good.jpg"), _jpeg(tmp_path / "cut frame.jpg", 0.6)
    assert check_frame(good).shape == (240, 320, 3)
    with pytest.raises(InputError) as e:
        check_frame(cut)
    clear_error(e, cut, "truncated")
    ortho = make_ortho(tmp_path / "ortho.tif")
    cfg = {"map": {"orthophoto": str(ortho)}, "frames": {"f": {"images": [str(good), str(cut)]}}}
    problems = check_inputs(cfg)
    assert len(problems) == 1 and str(cut) in problems[0] and "truncated" in problems[0], problems


def test_all_nan_cube_is_refused_saying_nan_and_all_zero_cube_is_a_constant_query(tmp_path):
    """An all-NaN float cube: one error naming it that says NaN (it used to point at the 'data
    ignore value', which it has none of), nothing written. An all-zero cube is a valid, constant
    query: its band is the one a constant cube gives (the workflow test of a constant query:
    not_found with its reason, products not_found)."""
    nan = write_envi(tmp_path / "nan", np.full((5, 30, 40), np.nan, np.float32), "bil", extra=WL)
    with pytest.raises(InputError) as e:
        _band(tmp_path, nan, "1200nm")
    clear_error(e, nan, "no valid pixel", "NaN")
    no_files(tmp_path / "out")
    bands = {}
    for name, value in (("zero", 0), ("flat", 500)):
        hdr = write_envi(tmp_path / name, np.full((5, 30, 40), value, np.uint16), "bil", extra=WL)
        write_query_band(str(hdr), "1200nm", 0.8, str(tmp_path / f"{name}.tif"),
                         str(tmp_path / f"{name}.json"))  # fmt: skip
        with rasterio.open(tmp_path / f"{name}.tif") as ds:
            bands[name] = ds.read()
    assert np.array_equal(bands["zero"], bands["flat"])
