"""A query whose GSD the user does not know (no ``gsd_m``), through ``snakemake``: SRIF
optical-infrared references laid side by side in one geo-referenced map, the published query
JPEG as it is. The feature search finds nothing across the spectral gap; rift searches each
guess of ``unknown_gsd_factors`` (``georeg.register.rift.source``) and registers it."""

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
    assert [g["gsd"] for g in rift["gsd_guesses"]] == pytest.approx([1.0, 0.5, 0.25])
    assert rift["gsd"] == pytest.approx(1.0)
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
