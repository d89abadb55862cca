"""Evaluation against the truth: error statistics, outcomes, parts, segmentation accuracy."""

from __future__ import annotations

import json
import warnings
from pathlib import Path

import numpy as np
import pytest
import rasterio
from rasterio.transform import Affine

from georeg.report.evaluation import (
    classify,
    error_field,
    error_stats,
    evaluate_query,
    inside_fraction,
    map_truth_labels,
    products_segmentation,
    run_evaluate_query,
    segmentation_accuracy,
)

W, H_ = 60, 80
# query pixel (col, row) -> map (x, y): 0.8 m pixels, rotated 30 deg, inside a 1 km map
A = np.deg2rad(30.0)
H_TRUE = np.array(
    [
        [0.8 * np.cos(A), -0.8 * np.sin(A), 500_400.0],
        [-0.8 * np.sin(A), -0.8 * np.cos(A), 5_800_600.0],
        [0.0, 0.0, 1.0],
    ]
)
MAP_TRANSFORM = Affine(0.5, 0, 500_000.0, 0, -0.5, 5_801_000.0)  # 2000 x 2000 px at 0.5 m


def shifted(H: np.ndarray, dx: float, dy: float = 0.0) -> np.ndarray:
    return np.array([[1, 0, dx], [0, 1, dy], [0, 0, 1.0]]) @ H


def write_truth(path: Path, H: np.ndarray, width: int = W, height: int = H_) -> Path:
    from georeg.register.geolocation import map_xy

    x, y = map_xy(H, width, height)
    x[:2, :2] = np.nan  # a few pixels without truth
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        with rasterio.open(
            path, "w", driver="GTiff", width=width, height=height, count=2, dtype="float64"
        ) as ds:
            ds.write(np.stack([x, y]))
    return path


def write_grid(path: Path) -> Path:
    from rasterio.crs import CRS

    data = {
        "crs": CRS.from_epsg(32633).to_wkt(),
        "transform": list(MAP_TRANSFORM)[:6],
        "width": 2000,
        "height": 2000,
        "tiles": {},
    }
    path.write_text(json.dumps(data))
    return path


def registration(H: np.ndarray | None, parts: list[np.ndarray | None]) -> dict:
    rows = np.linspace(0, H_, len(parts) + 1).round().astype(int)
    return {
        "status": "registered" if H is not None else "not_found",
        "homography": None if H is None else H.tolist(),
        "inliers": 40 if H is not None else 0,
        "map_px_m": 0.5,
        "reason": None if H is not None else "part 0: 3 candidate(s) tried, none accepted",
        "fuse": {"method": "fused"},
        "parts": [
            {
                "part": i,
                "rows": [int(rows[i]), int(rows[i + 1])],
                "accepted": p is not None,
                "candidates_tried": 2,
                "inliers": 20 if p is not None else 0,
                "homography": None if p is None else p.tolist(),
            }
            for i, p in enumerate(parts)
        ],
    }


def test_error_stats_and_field() -> None:
    tx = np.array([[0.0, 1.0], [np.nan, 3.0]])
    ty = np.zeros_like(tx)
    e = error_field(tx + 3.0, ty + 4.0, tx, ty)
    assert np.isnan(e[1, 0]) and np.allclose(e[~np.isnan(e)], 5.0)
    s = error_stats(e, map_px=0.5, m_per_unit=1.0)
    assert s["pixels"] == 3
    assert s["m"] == {"median": 5.0, "p90": 5.0, "max": 5.0, "rmse": 5.0}
    assert s["px"]["median"] == 10.0
    # an estimate missing where truth exists is an infinite error, written as null
    e2 = error_field(np.full((2, 2), np.nan), ty, tx, ty)
    assert error_stats(e2, 1.0)["px"]["max"] is None


@pytest.mark.parametrize(
    ("registered", "median", "inside", "outcome"),
    [
        (True, 1.0, 1.0, "success"),
        (True, 50.0, 1.0, "false_accept"),
        (True, 1.0, 0.0, "success"),
        (False, None, 0.0, "correct_not_found"),
        (False, None, 0.2, "correct_not_found"),
        (False, None, 0.9, "missed"),
        (False, None, None, "no_truth"),
    ],
)
def test_classify(registered: bool, median, inside, outcome: str) -> None:
    stats = {"px": {"median": median}} if median is not None else None
    conf = {"success_error_px": 5.0, "success_stat": "median", "min_inside_fraction": 0.5}
    assert classify(registered, stats, inside, conf) == outcome


def test_inside_fraction() -> None:
    tx = np.array([0.0, 5.0, 20.0, np.nan])
    ty = np.array([0.0, 5.0, 5.0, 1.0])
    assert inside_fraction(tx, ty, (0, 0, 10, 10)) == pytest.approx(2 / 3)
    assert inside_fraction(tx, ty, None) is None


def test_evaluate_success_and_parts(tmp_path: Path) -> None:
    truth = write_truth(tmp_path / "truth.tif", H_TRUE)
    grid = write_grid(tmp_path / "grid.json")
    # fused: 0.3 m off; part 0 right on its rows but rotated slightly (grows away from them)
    rot = np.array([[1, -0.01, 0], [0.01, 1, 0], [0, 0, 1.0]])
    p0 = H_TRUE @ rot
    p1 = shifted(H_TRUE, 2.0)
    reg = registration(shifted(H_TRUE, 0.3), [p0, p1])
    ev = evaluate_query(reg, None, truth, grid, {"success_error_px": 2.0})
    assert ev["outcome"] == "success"
    assert ev["map_px"] == 0.5 and ev["inside_fraction"] == 1.0
    assert ev["error"]["m"]["median"] == pytest.approx(0.3)
    assert ev["error"]["px"]["median"] == pytest.approx(0.6)
    assert ev["truth_pixels"] == W * H_ - 4
    parts = {p["part"]: p for p in ev["parts"]}
    assert parts[1]["error_whole"]["m"]["median"] == pytest.approx(2.0)
    assert parts[1]["outcome"] == "false_accept"  # 4 px > 2 px bound
    # part 0's own homography is worse over the whole query than over its own rows
    assert parts[0]["error_whole"]["m"]["max"] > parts[0]["error_own_rows"]["m"]["max"]
    assert ev["fusion_gain"]["improvement_px"] > 0


def test_evaluate_false_accept_and_not_found(tmp_path: Path) -> None:
    truth = write_truth(tmp_path / "truth.tif", H_TRUE)
    grid = write_grid(tmp_path / "grid.json")
    ev = evaluate_query(registration(shifted(H_TRUE, 300.0), [None]), None, truth, grid, {})
    assert ev["outcome"] == "false_accept"
    ev = evaluate_query(registration(None, [None, None]), None, truth, grid, {})
    assert ev["outcome"] == "missed" and "error" not in ev
    # a query that lies wholly outside the map: not finding it is correct
    far = write_truth(tmp_path / "far.tif", shifted(H_TRUE, 5000.0))
    ev = evaluate_query(registration(None, [None]), None, far, grid, {})
    assert ev["outcome"] == "correct_not_found" and ev["inside_fraction"] == 0.0


def test_evaluate_without_truth_and_run(tmp_path: Path) -> None:
    ev = evaluate_query(registration(H_TRUE, [H_TRUE]), None, None)
    assert ev == {
        "status": "registered",
        "registered": True,
        "inliers": 40,
        "method": "fused",
        "reason": None,
        "outcome": "no_truth",
    }
    reg_path = tmp_path / "registration.json"
    reg_path.write_text(json.dumps(registration(H_TRUE, [H_TRUE])))
    out = tmp_path / "evaluation.json"
    run_evaluate_query(reg_path, None, None, None, {}, out)
    assert json.loads(out.read_text())["outcome"] == "no_truth"


def test_evaluate_uses_geolocation_raster(tmp_path: Path) -> None:
    from georeg.register.geolocation import write_geolocation

    truth = write_truth(tmp_path / "truth.tif", H_TRUE)
    geo = tmp_path / "geolocation.tif"
    write_geolocation(geo, shifted(H_TRUE, 0.0, 1.0), W, H_, None, None)
    # the homography in the JSON is ignored when the geolocation raster is given
    ev = evaluate_query(registration(shifted(H_TRUE, 99.0), [None]), geo, truth, None, {})
    assert ev["error"]["m"]["median"] == pytest.approx(1.0)


def test_segmentation_accuracy() -> None:
    truth = np.array([[1, 1, 2, 2], [1, 1, 2, 0]])
    pred = np.array([[1, 2, 2, 2], [1, 1, 2, 3]])
    acc = segmentation_accuracy(pred, truth, {1: "road", 2: "grass"})
    assert acc["pixels"] == 7
    assert acc["overall_accuracy"] == pytest.approx(6 / 7)
    assert acc["classes"]["1"]["name"] == "road"
    assert acc["classes"]["1"]["iou"] == pytest.approx(3 / 4)
    assert acc["classes"]["2"]["iou"] == pytest.approx(3 / 4)
    assert acc["mean_iou"] == pytest.approx(0.75)
    assert map_truth_labels(np.array([[1, 9]]), {1: 5, 9: 6}).tolist() == [[5, 6]]
    assert map_truth_labels(np.array([[1, 42]]), {1: 5}).tolist() == [[1, 42]]


def test_segmentation_from_products_manifest(tmp_path: Path) -> None:
    truth = write_truth(tmp_path / "truth.tif", H_TRUE)
    seg = np.ones((H_, W), np.uint8) * 2
    seg[:10] = 1
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        with rasterio.open(
            tmp_path / "segmentation.tif",
            "w",
            driver="GTiff",
            width=W,
            height=H_,
            count=1,
            dtype="uint8",
            nodata=0,
        ) as ds:
            ds.write(seg, 1)
            ds.write_colormap(1, {1: (200, 40, 40, 255), 2: (20, 110, 30, 255)})
        lab = np.full((H_, W), 6, np.uint8)  # demo class 6 = tree
        with rasterio.open(
            tmp_path / "labels.tif",
            "w",
            driver="GTiff",
            width=W,
            height=H_,
            count=1,
            dtype="uint8",
            nodata=0,
        ) as ds:
            ds.write(lab, 1)
    manifest = {
        "status": "registered",
        "files": {"segmentation": "segmentation.tif"},
        "segmentation": {"classes": {"1": "tall building", "2": "trees"}, "accuracy": {"x": 1}},
    }
    (tmp_path / "products.json").write_text(json.dumps(manifest))
    ps = products_segmentation(tmp_path / "products.json")
    assert ps is not None and ps.names[2] == "trees" and ps.colours[1] == (200, 40, 40)
    reg = registration(H_TRUE, [H_TRUE])
    lut = {6: 2}
    ev = evaluate_query(
        reg, None, truth, None, {}, tmp_path / "labels.tif", tmp_path / "products.json"
    )
    seg_ev = ev["segmentation"]
    assert seg_ev["products_accuracy"] == {"x": 1}
    # with the demo mapping (tree -> class 3 of georeg.products.segmentation), or unmapped otherwise
    assert seg_ev["pixels"] == W * H_
    assert map_truth_labels(lab, lut).max() == 2
    assert products_segmentation(tmp_path / "absent.json") is None
