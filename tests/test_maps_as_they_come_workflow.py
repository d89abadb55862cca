"""Maps and queries as users have them, through the real ``snakemake`` command on the tiny demo.

The demo scene of config/test.yaml is made once; from it, inputs a user could hand over:

* run ``pan``: the orthophoto as ONE 16-bit band (panchromatic), heights from a DEM (the demo's
  truth DSM), the demo SWIR query, a 2-band SWIR GeoTIFF (1610 and 2190 nm in the band
  descriptions, no CRS, no 1200 nm band) and a demo drone frame;
* run ``rgbn``: the orthophoto as 4 16-bit bands NIR, R, G, B (names in the descriptions) and NO
  elevation at all (``lidar: []``, ``dem: null``), the demo query.

Both must end with exit status 0; the queries are registered against the dense truth, products
that need what the input lacks are skipped with the reason in products.json and in the report.
"""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import rasterio
import yaml

from georeg.io.query import open_query
from georeg.register.band import nearest_band

REPO = Path(__file__).resolve().parents[1]
TEST_CONFIG = REPO / "config" / "test.yaml"
pytestmark = pytest.mark.slow


def smk(work: Path, *args: str, timeout: int = 1500) -> subprocess.CompletedProcess:
    cmd = [sys.executable, "-m", "snakemake", "-s", str(REPO / "Snakefile"), "-d", str(work)]
    return subprocess.run(cmd + list(args), capture_output=True, text=True, timeout=timeout, cwd=work)


def _derive_inputs(work: Path) -> dict[str, str]:
    """Panchromatic 16-bit and NIR-first 16-bit orthophotos, a 2-band SWIR GeoTIFF query."""
    demo = work / "results" / "demo"
    inp = work / "inputs"
    inp.mkdir()
    with rasterio.open(demo / "orthophoto.tif") as ds:
        rgb = ds.read().astype(np.float64)
        prof = ds.profile | {"dtype": "uint16", "nodata": None, "photometric": None}
    luma = 0.299 * rgb[0] + 0.587 * rgb[1] + 0.114 * rgb[2]
    with rasterio.open(inp / "pan16.tif", "w", **(prof | {"count": 1})) as dst:
        dst.write((luma * 39.0).astype(np.uint16)[None])
    nir = np.clip(1.6 * rgb[1] - 0.5 * rgb[0], 0, 255)  # vegetation bright, roads dark: not a colour
    with rasterio.open(inp / "rgbn16.tif", "w", **(prof | {"count": 4})) as dst:
        dst.write((np.stack([nir, rgb[0], rgb[1], rgb[2]]) * 39.0).astype(np.uint16))
        for i, d in enumerate(["NIR", "Red", "Green", "Blue"], 1):
            dst.set_band_description(i, d)
    cube = open_query(demo / "queries" / "demo.hdr")
    bands = [cube.read_band(nearest_band(cube, w)) for w in (1610.0, 2190.0)]
    with rasterio.open(
        inp / "swir2.tif", "w", driver="GTiff", width=cube.width, height=cube.height, count=2,
        dtype="float32",
    ) as dst:  # fmt: skip
        dst.write(np.stack(bands).astype(np.float32))
        dst.set_band_description(1, "1610 nm")
        dst.set_band_description(2, "2190 nm")
    return {k: str(inp / f"{k}.tif") for k in ("pan16", "rgbn16", "swir2")}


def _ground_height(work: Path) -> float:
    """What a user without elevation data may know: the median ground height of the area."""
    with rasterio.open(work / "results/demo/truth/dtm.tif") as ds:
        return float(np.nanmedian(ds.read(1, masked=True).filled(np.nan)))


@pytest.fixture(scope="module")
def runs(tmp_path_factory) -> dict[str, Path]:
    work = tmp_path_factory.mktemp("as_they_come")
    scene = smk(work, "results/demo/scene.json", "--cores", "2", "--configfile", str(TEST_CONFIG))
    assert scene.returncode == 0, scene.stderr[-3000:]
    inputs = _derive_inputs(work)
    base = yaml.safe_load(TEST_CONFIG.read_text())
    demo_q = base["queries"]["demo"]
    frame_view = {"name": "nadir_110", "off_nadir_deg": 0.0, "agl_m": 110.0, "heading_deg": 30.0}
    pan_frames = {"demo": {
        "images": ["results/demo/frames/nadir_110.png"],
        "camera": {"fx": 700.0, "fy": 700.0, "cx": 403.2, "cy": 297.1,
                   "dist": [-0.06, 0.015, 0.0005, -0.0003, 0.0]},
        "truth": "results/demo/frames/truth.json",
    }}  # fmt: skip
    configs = {
        "pan": base | {
            "map": {"orthophoto": inputs["pan16"], "lidar": [], "dem": "results/demo/truth/dsm.tif"},
            "queries": {
                "demo": demo_q,
                "swir2": {"image": inputs["swir2"], "gsd_m": 0.8,
                          "truth": "results/demo/queries/demo_truth.tif"},
            },
            "frames": pan_frames,
            "frame_loc": {"demo_frames": {"seed": 9, "views": [frame_view]}},
        },
        "rgbn": base | {
            "map": {"orthophoto": inputs["rgbn16"], "lidar": [], "dem": None,
                    "ground_z": _ground_height(work)},
            "queries": {"demo": demo_q},
            "frames": pan_frames,
            "frame_loc": {"demo_frames": {"seed": 9, "views": [frame_view]}},
        },
    }  # fmt: skip
    out = {}
    for name, cfg in configs.items():
        d = work / name
        d.mkdir()
        (d / "results" / "demo").parent.mkdir(parents=True, exist_ok=True)
        (d / "results" / "demo").symlink_to(work / "results" / "demo", target_is_directory=True)
        (d / "inputs").symlink_to(work / "inputs", target_is_directory=True)
        p = d / "config.yaml"
        p.write_text(yaml.safe_dump(cfg))
        proc = smk(d, "--cores", "2", "--configfile", str(p))
        (d / "run.log").write_text(proc.stderr)
        assert proc.returncode == 0, f"{name}: {proc.stderr[-4000:]}"
        out[name] = d
    return out


def _registered_px(run: Path, name: str) -> dict:
    reg = json.loads((run / f"results/queries/{name}/registration.json").read_text())
    assert reg["status"] == "registered", reg.get("reason")
    ev = json.loads((run / f"results/queries/{name}/evaluation.json").read_text())
    return ev


def test_panchromatic_16_bit_map_registers_the_demo_query(runs):
    grid = json.loads((runs["pan"] / "results/map/grid.json").read_text())
    assert grid["visible"]["bands"] == [1] and grid["visible"]["stretch"] is not None
    ev = _registered_px(runs["pan"], "demo")
    assert ev["outcome"] == "success" and ev["error"]["px"]["median"] < 1.0, ev["error"]


def test_two_band_swir_geotiff_is_registered_with_cube_and_footprint(runs):
    run = runs["pan"]
    reg = json.loads((run / "results/queries/swir2/registration.json").read_text())
    assert reg["status"] == "registered", reg.get("reason")
    band = json.loads((run / "results/queries/swir2/band.json").read_text())
    assert abs(band["band"]["wavelength_nm"] - 1610.0) < 1.0  # auto: the band nearest 1200 nm it has
    ev = json.loads((run / "results/queries/swir2/evaluation.json").read_text())
    assert ev["outcome"] == "success" and ev["error"]["px"]["median"] < 1.5, ev["error"]
    prod = json.loads((run / "results/products/swir2/products.json").read_text())
    assert (run / "results/products/swir2" / prod["files"]["footprint_geojson"]).exists()
    cube = json.loads((run / "results/products/swir2/cube.json").read_text())
    with rasterio.open(run / "results/products/swir2" / cube["files"]["cube_cog"]) as ds:
        assert ds.count == 2 and ds.crs is not None
    assert "no band near" in prod["skipped"]["segmentation"]
    html = (run / "results/report/index.html").read_text()
    assert "no band near" in html


def test_map_without_elevation_registers_and_says_what_lacks_heights(runs):
    run = runs["rgbn"]
    grid = json.loads((run / "results/map/grid.json").read_text())
    assert grid["visible"]["bands"] == [2, 3, 4]
    ev = _registered_px(run, "demo")
    assert ev["outcome"] == "success" and ev["error"]["px"]["median"] < 1.0, ev["error"]
    # no elevation: the LiDAR check is skipped, the registration is the one without it
    reg = json.loads((run / "results/queries/demo/registration.json").read_text())
    assert reg["lidar_check"]["outcome"] == "skipped", reg["lidar_check"]
    prod = json.loads((run / "results/products/demo/products.json").read_text())
    assert prod["heights"]["available"] is False
    assert set(prod["skipped"]) >= {"segmentation", "points_spectra", "elevation heights"}
    assert "points_spectra" not in prod["files"] and "segmentation" not in prod["files"]
    with rasterio.open(run / "results/products/demo/elevation.tif") as ds:
        assert np.isnan(ds.read(1)).all() and np.isfinite(ds.read(4)).any()  # dsm nodata, lon kept
    assert "map without elevation" in (run / "run.log").read_text()
    assert "has no elevation" in (run / "results/report/index.html").read_text()


def test_frame_on_the_panchromatic_map(runs):
    poses = json.loads((runs["pan"] / "results/frames/demo/poses.json").read_text())
    assert poses[0]["status"] == "registered", poses[0]
    # measured 2.1 m / 1.0 deg (a nadir view at 110 m trades tilt for position)
    assert poses[0]["evaluation"]["final"]["position_m"] < 5.0, poses[0]["evaluation"]


def test_frame_on_a_map_without_elevation_uses_the_flat_ground(runs):
    poses = json.loads((runs["rgbn"] / "results/frames/demo/poses.json").read_text())
    p = poses[0]
    assert "flat" in json.dumps(p.get("ground")), p.get("ground")
    assert p["status"] == "registered", p.get("reason")
    assert p["evaluation"]["final"]["position_m"] < 6.0, p["evaluation"]  # measured 3.1 m
