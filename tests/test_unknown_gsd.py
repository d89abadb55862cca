"""Queries without ``gsd_m``, through ``snakemake``. A plain JPEG states no pixel size: SRIF
optical-infrared references laid side by side in one geo-referenced map, the published query
JPEG as it is; the feature search finds nothing across the spectral gap, and rift searches each
guess of ``unknown_gsd_factors`` (``georeg.register.rift.source``) and registers it. A
georeferenced file states its pixel size: the EnMAP cube as released is taken at its 30 m
(``georeg.io.query.georeferenced_gsd_m``)."""

from __future__ import annotations

import json
import sys
from pathlib import Path

import numpy as np
import pytest
import rasterio

REPO = Path(__file__).resolve().parents[1]
REFS = (5, 7, 11, 15)  # tuning-half pairs of bench_devset (256 x 256 px references)
GAP = 16  # nodata px between the references
ORIGIN = (500000.0, 5000000.0)  # UTM 33N, 1 m pixels


def _mosaic(oi: Path, out: Path) -> Path:
    import cv2

    refs = [cv2.imread(str(oi / f"pair{i}_1.jpg"), cv2.IMREAD_GRAYSCALE) for i in REFS]
    m = np.zeros((256, len(refs) * (256 + GAP)), np.uint8)
    for k, r in enumerate(refs):
        m[:, k * (256 + GAP) : k * (256 + GAP) + 256] = np.maximum(r, 1)
    with rasterio.open(out, "w", driver="GTiff", width=m.shape[1], height=m.shape[0], count=1,
                       dtype="uint8", nodata=0, crs="EPSG:32633",
                       transform=rasterio.Affine(1.0, 0, ORIGIN[0], 0, -1.0, ORIGIN[1])) as ds:  # fmt: skip
        ds.write(m[None])
    return out


@pytest.mark.slow
def test_srif_infrared_query_without_gsd_registers_through_the_workflow(shared_data, tmp_path):
    """Pair 11's infrared query (rotated by SRIF) without ``gsd_m`` on a 4-reference map:
    registered by rift within 8 map px of SRIF's hand-picked truth (its own accuracy is 3-5 px),
    every guess recorded; an optical-depth query (no reference in the map) ends ``not_found``."""
    oi, od = shared_data / "srif_dev" / "Optical-Infrared", shared_data / "srif_dev" / "Optical-Depth"
    if not all((oi / f"pair{i}_1.jpg").exists() for i in REFS) or not (od / "pair1_2.jpg").exists():
        pytest.skip("SRIF pairs absent")
    sys.path.insert(0, str(REPO / "benchmarks"))
    import bench_s2_cities as bs

    ortho = _mosaic(oi, tmp_path / "map.tif")
    res = bs.run_workflow(tmp_path / "run", {"orthophoto": str(ortho), "lidar": []},
                          {"ir": {"image": str(oi / "pair11_2.jpg")}, "other": {"image": str(od / "pair1_2.jpg")}})  # fmt: skip
    assert res["ir"]["status"] == "registered" and res["ir"]["sources"] == ["rift"], res["ir"]
    assert res["other"]["status"] == "not_found", res["other"]
    reg = json.loads((tmp_path / "run/results/queries/ir/registration.json").read_text())
    rift = reg["split"]["rift"]
    assert rift["gsd_guesses"][0]["guess"] == pytest.approx(1.0)  # the map's own GSD first
    assert rift["gsd"] == pytest.approx(1.0, rel=0.05)  # the similarity's scale
    # SRIF's truth: [gt; 0 0 1] maps reference px to query px, 1-based
    one = np.array([[1, 0, 1], [0, 1, 1], [0, 0, 1.0]])
    A = np.linalg.inv(one) @ np.vstack([np.loadtxt(oi / "gt_11.txt"), [0, 0, 1.0]]) @ one
    uu, vv = np.meshgrid(np.linspace(40, 215, 8), np.linspace(40, 215, 8))
    ref_px = np.c_[uu.ravel(), vv.ravel(), np.ones(64)]
    q_px = ref_px @ A.T
    xy = q_px @ np.array(reg["homography"]).T
    xy = xy[:, :2] / xy[:, 2:]
    col0 = REFS.index(11) * (256 + GAP)
    want = np.c_[ORIGIN[0] + col0 + ref_px[:, 0] + 0.5, ORIGIN[1] - ref_px[:, 1] - 0.5]
    assert np.median(np.linalg.norm(xy - want, axis=1)) < 8.0


@pytest.mark.slow
def test_enmap_cube_without_gsd_takes_its_geotransforms_pixel_size(shared_data, tmp_path):
    """The EnMAP Potsdam cube as released (UTM, 30 m pixels) without ``gsd_m``, against a 3.6 m
    RGB map of part of it (its own 665/560/490 nm bands, bicubic): the query's GSD is read from
    its geotransform (its position is not used), so the scale gap's level search runs;
    registered within 5 map px of the truth (the cube's geotransform). With the guesses of an
    unknown GSD (3.6, 1.8, 0.9 m) it ended ``not_found``."""
    import cv2

    cube = shared_data / "enmap_potsdam" / "enmap_potsdam_mosaic_subset.tif"
    if not cube.exists():
        pytest.skip("EnMAP Potsdam absent")
    sys.path.insert(0, str(REPO / "benchmarks"))
    import bench_s2_cities as bs

    r0, r1, c0, c1, gm = 100, 180, 40, 140, 3.6  # the map: 80 x 100 EnMAP px of the cube's 192 x 160
    with rasterio.open(cube) as ds:
        wl = np.array([float(d.split()[0]) for d in ds.descriptions])
        T = ds.transform
        rgb = np.stack([ds.read(int(np.argmin(abs(wl - w))) + 1)[r0:r1, c0:c1] for w in (665, 560, 490)])
    valid = np.isfinite(rgb).all(0)
    lo, hi = np.nanpercentile(rgb[:, valid], [1, 99])
    u8 = np.where(valid, np.clip(1 + 254 * (rgb - lo) / (hi - lo), 1, 255), 0).astype(np.float32)
    w, h = round((c1 - c0) * 30 / gm), round((r1 - r0) * 30 / gm)
    up = np.stack([cv2.resize(b, (w, h), interpolation=cv2.INTER_CUBIC) for b in u8])
    up = np.where(cv2.resize(valid.astype(np.uint8), (w, h), interpolation=cv2.INTER_NEAREST) > 0,
                  np.clip(up, 1, 255), 0).astype(np.uint8)  # fmt: skip
    ortho = tmp_path / "map.tif"
    with rasterio.open(ortho, "w", driver="GTiff", width=w, height=h, count=3, dtype="uint8", nodata=0,
                       crs="EPSG:32633", transform=rasterio.Affine(gm, 0, T.c + c0 * 30.0, 0, -gm, T.f - r0 * 30.0)) as d:  # fmt: skip
        d.write(up)
    res = bs.run_workflow(tmp_path / "run", {"orthophoto": str(ortho), "lidar": []}, {"enmap": {"image": str(cube)}})
    assert res["enmap"]["status"] == "registered", res["enmap"]
    run = tmp_path / "run/results/queries/enmap"
    assert json.loads((run / "band.json").read_text())["gsd_source"] == "geotransform"
    reg = json.loads((run / "registration.json").read_text())
    assert reg["level"]["gsd"] == pytest.approx(30.0)
    uu, vv = np.meshgrid(np.arange(5, 160, 10.0), np.arange(5, 192, 10.0))
    inside = (vv >= r0 + 5) & (vv < r1 - 5) & (uu >= c0 + 5) & (uu < c1 - 5)  # over the map
    q = np.c_[uu[inside], vv[inside], np.ones(inside.sum())]
    xy = q @ np.array(reg["homography"]).T
    xy = xy[:, :2] / xy[:, 2:]
    want = np.c_[T.c + (q[:, 0] + 0.5) * 30.0, T.f - (q[:, 1] + 0.5) * 30.0]
    assert np.median(np.linalg.norm(xy - want, axis=1)) / gm < 5.0
