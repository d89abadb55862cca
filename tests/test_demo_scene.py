"""The demo scene generator: formats, CRS, truth consistency, spectra, determinism."""

from __future__ import annotations

import hashlib
import json
import re
import warnings
from pathlib import Path

import laspy
import numpy as np
import pyproj
import pytest
import rasterio
from rasterio.errors import NotGeoreferencedWarning

from georeg.demo import classes as C
from georeg.demo import generate_scene
from georeg.demo import spectra as S

SMALL = {
    "seed": 11,
    "size_m": 384,
    "gsd_m": 1.0,
    "margin_m": 256,
    "lidar_density": 2.0,
    "lidar_tiles": 2,
    "lidar_crs": "EPSG:2229",
    "query": {"samples": 160, "lines": 200, "bands": 40, "gsd_m": 0.8, "heading_deg": 35.0},
}
FT = 0.3048006096012192  # US survey foot in metres


@pytest.fixture(scope="module")
def scene(tmp_path_factory) -> tuple[Path, dict[str, str]]:
    out = tmp_path_factory.mktemp("demo")
    return out, generate_scene(SMALL, out)


def _read(path, band: int | None = None):
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", NotGeoreferencedWarning)
        with rasterio.open(path) as src:
            return src.read(band) if band else src.read(), src.profile, src.transform, src.crs


def _parse_hdr(path: Path) -> dict[str, str]:
    text = path.read_text()
    assert text.startswith("ENVI")
    return {
        m.group(1).strip().lower(): m.group(2).strip()
        for m in re.finditer(r"^([^=\n]+?)\s*=\s*(\{[^}]*\}|[^\n]*)", text, re.M)
    }


def _cube_band(hdr_path: Path, wl_nm: float) -> np.ndarray:
    h = _parse_hdr(hdr_path)
    s, lines, b = int(h["samples"]), int(h["lines"]), int(h["bands"])
    wl = np.array([float(v) for v in h["wavelength"].strip("{}").split(",")])
    data = np.fromfile(hdr_path.with_suffix(".bil"), dtype="<i2").reshape(lines, b, s)
    return data[:, int(np.argmin(np.abs(wl - wl_nm))), :].astype(np.float32) / 10000.0


def _changed_mask(x: np.ndarray, y: np.ndarray, scene_json: dict, grow: float = 2.0) -> np.ndarray:
    m = np.zeros(x.shape, bool)
    for ch in scene_json["changes"]:
        x0, y0, x1, y1 = ch["bbox"]
        m |= (x > x0 - grow) & (x < x1 + grow) & (y > y0 - grow) & (y < y1 + grow)
    return m


def test_all_outputs_written(scene):
    out, paths = scene
    for name in ("orthophoto.tif", "truth/dsm.tif", "truth/dtm.tif", "truth/ndsm.tif", "truth/labels.tif",
                 "truth/classes.json", "truth/outliers.npy", "scene.json", "lidar/tile_0.laz", "lidar/tile_1.laz",
                 "queries/demo.hdr", "queries/demo.bil", "queries/demo_truth.tif", "queries/demo_labels.tif",
                 "queries/demo_ndsm.tif", "queries/outside.hdr", "queries/outside.bil",
                 "queries/outside_truth.tif", "queries/outside_labels.tif"):  # fmt: skip
        assert (out / name).is_file(), name
    assert all(Path(p).is_file() for p in paths.values())
    assert not list(out.rglob(".*tmp-*")), "temporary files left behind"


def test_orthophoto_and_truth_grid(scene):
    out, _ = scene
    rgb, prof, tr, crs = _read(out / "orthophoto.tif")
    assert crs.to_epsg() == 32611
    assert rgb.shape == (3, 384, 384) and rgb.dtype == np.uint8
    assert prof["tiled"] and prof["compress"] == "deflate"
    assert (tr.a, tr.e, tr.c, tr.f) == (1.0, -1.0, 384000.0, 3768000.0)
    assert rgb.std() > 20  # structure, not a flat image
    for name in ("dsm", "dtm", "ndsm", "labels"):
        arr, _, t2, c2 = _read(out / "truth" / f"{name}.tif", 1)
        assert arr.shape == (384, 384) and t2 == tr and c2.to_epsg() == 32611
    dsm, dtm, ndsm = (_read(out / "truth" / f"{n}.tif", 1)[0] for n in ("dsm", "dtm", "ndsm"))
    assert dsm.dtype == np.float32
    np.testing.assert_allclose(ndsm, dsm - dtm, atol=1e-3)
    assert 70 < dtm.min() and dtm.max() < 120
    labels = _read(out / "truth" / "labels.tif", 1)[0]
    classes = json.loads((out / "truth" / "classes.json").read_text())
    assert set(np.unique(labels)) <= {int(k) for k in classes}
    assert {classes[str(C.ROAD)]["name"], classes[str(C.TREE)]["name"]} == {"road", "tree"}
    assert ndsm[labels == C.ROAD].max() < 0.5 and np.median(ndsm[labels == C.TREE]) > 4


def test_lidar_crs_units_and_truth(scene):
    out, _ = scene
    dsm, _, tr, _ = _read(out / "truth" / "dsm.tif", 1)
    labels = _read(out / "truth" / "labels.tif", 1)[0]
    to_map = pyproj.Transformer.from_crs("EPSG:2229", "EPSG:32611", always_xy=True)
    for i in range(2):
        las = laspy.read(out / "lidar" / f"tile_{i}.laz")
        assert las.header.version.major == 1 and las.header.version.minor == 4
        assert las.header.point_format.id in (6, 7)
        assert las.header.parse_crs().to_epsg() == 2229
        assert las.x.min() > 6.0e6  # state-plane feet, not UTM metres
        cls = np.asarray(las.classification)
        bld = cls == 6
        x, y = to_map.transform(np.asarray(las.x)[bld], np.asarray(las.y)[bld])
        col = ((x - tr.c) / tr.a).astype(int)
        row = ((y - tr.f) / tr.e).astype(int)
        ok = (col >= 0) & (col < 384) & (row >= 0) & (row < 384)
        assert ok.mean() > 0.99
        lab = labels[row[ok], col[ok]]
        assert np.isin(lab, (C.HOUSE, C.TALL_BUILDING)).mean() > 0.97
        dz = np.asarray(las.z)[bld][ok] * FT - dsm[row[ok], col[ok]]
        assert np.median(np.abs(dz)) < 0.08 and np.percentile(np.abs(dz), 99) < 0.3
        # trees: multiple returns, canopy first and ground last
        multi = np.asarray(las.number_of_returns) > 1
        assert multi.sum() > 100
        rn = np.asarray(las.return_number)
        assert (cls[multi & (rn == 1)] == 5).mean() > 0.95
        assert (cls[multi & (rn == np.asarray(las.number_of_returns))] == 2).mean() > 0.6
        assert {3, 4, 5, 2, 6}.issubset(set(np.unique(cls)))


def test_outliers_recorded_and_in_the_clouds(scene):
    out, _ = scene
    sj = json.loads((out / "scene.json").read_text())
    outl = np.load(out / "truth" / "outliers.npy")
    assert outl.shape == (sj["outliers"]["high"] + sj["outliers"]["low"], 3) and outl.shape[0] > 0
    dsm = _read(out / "truth" / "dsm.tif", 1)[0]
    dtm = _read(out / "truth" / "dtm.tif", 1)[0]
    high = outl[: sj["outliers"]["high"]]
    low = outl[sj["outliers"]["high"] :]
    assert (high[:, 2] > dsm.max() + 10).all() and (low[:, 2] < dtm.max()).all()
    zs = np.concatenate(
        [np.asarray(laspy.read(out / "lidar" / f"tile_{i}.laz").z) * FT for i in range(2)]
    )
    assert (zs > dsm.max() + 10).sum() == high.shape[0]


def test_query_truth_maps_onto_the_same_objects(scene):
    out, _ = scene
    sj = json.loads((out / "scene.json").read_text())
    truth = _read(out / "queries" / "demo_truth.tif")[0]
    qlab = _read(out / "queries" / "demo_labels.tif", 1)[0]
    assert truth.shape == (2, 200, 160) and truth.dtype == np.float64 and qlab.shape == (200, 160)
    labels, _, tr, _ = _read(out / "truth" / "labels.tif", 1)
    x, y = truth[0], truth[1]
    col = np.floor((x - tr.c) / tr.a).astype(int)
    row = np.floor((y - tr.f) / tr.e).astype(int)
    assert col.min() >= 0 and row.min() >= 0 and col.max() < 384 and row.max() < 384
    mlab = labels[row, col]
    keep = ~_changed_mask(x, y, sj)
    assert keep.mean() > 0.6
    agree = (mlab == qlab)[keep].mean()
    assert agree > 0.9, agree
    # the changed objects really changed somewhere
    assert (mlab != qlab)[~keep].mean() > 0.1
    # pixels are ~gsd apart along and across track
    step_s = np.hypot(*np.diff(truth[:, 100, :], axis=1)).mean()
    step_l = np.hypot(*np.diff(truth[:, :, 80], axis=1)).mean()
    assert abs(step_s - 0.8) < 0.02 and abs(step_l - 0.8) < 0.02
    # proper rotation, not a mirror image: det of d(map x, map row)/d(sample, line) > 0
    j = np.array(
        [[x[0, 1] - x[0, 0], x[1, 0] - x[0, 0]], [-(y[0, 1] - y[0, 0]), -(y[1, 0] - y[0, 0])]]
    )
    assert np.linalg.det(j) > 0


def test_swir_band_looks_like_the_scene(scene):
    out, _ = scene
    b = _cube_band(out / "queries" / "demo.hdr", 1200.0)
    qlab = _read(out / "queries" / "demo_labels.tif", 1)[0]
    med = {k: np.median(b[qlab == k]) for k in np.unique(qlab)}
    assert med[C.TREE] > med[C.ROAD] * 2
    assert med[C.GRASS] > med[C.ROAD]
    if C.WATER in med:
        assert med[C.WATER] == min(med.values())
    # the library itself: vegetation bright, asphalt dark, water darkest at 1.2 um
    M, _ = S.swir_library(np.array([1200.0, 1450.0, 1650.0]))
    assert M[S.LEAF, 0] > M[S.ASPHALT, 0] and M[:, 0].argmin() == S.WATER
    assert M[S.LEAF, 1] < 0.6 * M[S.LEAF, 0] and M[S.LEAF, 2] > M[S.LEAF, 1]  # 1.45 um leaf water
    assert b.std() > 0.03  # spatial structure for SIFT


def test_envi_header(scene):
    out, _ = scene
    for name, size in (("demo", (160, 200)), ("outside", None)):
        h = _parse_hdr(out / "queries" / f"{name}.hdr")
        assert h["interleave"] == "bil" and h["byte order"] == "0" and h["header offset"] == "0"
        assert h["data type"] == "2" and h["wavelength units"].lower() == "nanometers"
        assert "map info" not in h
        bands = int(h["bands"])
        wl = [float(v) for v in h["wavelength"].strip("{}").split(",")]
        fwhm = [float(v) for v in h["fwhm"].strip("{}").split(",")]
        assert bands == 40 and len(wl) == bands == len(fwhm)
        assert wl[0] == 900.0 and wl[-1] == 2500.0 and np.all(np.diff(wl) > 0)
        nbytes = (out / "queries" / f"{name}.bil").stat().st_size
        assert nbytes == int(h["samples"]) * int(h["lines"]) * bands * 2
        if size:
            assert (int(h["samples"]), int(h["lines"])) == size


def test_outside_query_is_outside_the_map(scene):
    out, _ = scene
    truth = _read(out / "queries" / "outside_truth.tif")[0]
    labels = _read(out / "queries" / "outside_labels.tif", 1)[0]
    assert truth.shape[1:] == labels.shape
    x, y = truth[0], truth[1]
    inside = (x >= 384000) & (x <= 384000 + 384) & (y >= 3768000 - 384) & (y <= 3768000)
    assert not inside.any()
    assert len(np.unique(labels)) >= 4  # still a city


def test_deterministic_by_seed(scene, tmp_path):
    out, _ = scene
    generate_scene(SMALL, tmp_path / "same")
    generate_scene({**SMALL, "seed": SMALL["seed"] + 1}, tmp_path / "other")

    def digest(root: Path) -> dict[str, str]:
        return {
            str(p.relative_to(root)): hashlib.sha256(p.read_bytes()).hexdigest()
            for p in sorted(root.rglob("*"))
            if p.is_file()
        }

    a, b, c = digest(out), digest(tmp_path / "same"), digest(tmp_path / "other")
    assert a == b
    differ = [k for k in a if a[k] != c.get(k)]
    assert (
        "orthophoto.tif" in differ and "queries/demo.bil" in differ and "lidar/tile_0.laz" in differ
    )
