"""The map view (results/report/map.html): is what it draws where the workflow says it is?

A workflow run (the demo, or any run directory with results/):

    python benchmarks/bench_map_view.py run DIR [--out benchmarks/out/map_view_DIRNAME.json]

per registered query, the drawing error of its image in the map view (map px): the distance
between each drawn pixel's centre and the delivered geolocation of the query pixel it shows, for
the view's lookup (fixed-point inverse of the geolocation, 4 iterations) and for the plain
baseline (the homography alone, what the report's static checkerboard uses); and, with a truth
raster, the distance to the true position of that query pixel (= what a user judges by eye). Plus
the CPU seconds and the bytes of the whole map view (built into a temporary directory).

Real data (../shared/data/frames_dev: the ngi and odm cases' surveyed frames):

    python benchmarks/bench_map_view.py real

the look direction drawn for each surveyed camera (the optical axis's horizontal direction) vs
the direction from the camera to the true ground point of the image centre, in degrees, against
the plain baseline (camera -> centroid of the ground footprint); and a query cut from the real
ODM orthophoto through a known wobbling geolocation, drawn by the view's lookup vs by H alone
(drawing error, high-pass correlation of the drawn image with the orthophoto under it).
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from georeg.report.map_data import (  # noqa: E402
    MapFrame,
    look_end,
    lookup_residual,
    query_lookup,
    read_raster,
)
from georeg.report.map_view import run_map_view  # noqa: E402

FRAMES_DEV = REPO.parent / "shared" / "data" / "frames_dev"


def _stats(v: np.ndarray) -> dict[str, float]:
    v = np.asarray(v, float)
    return {"n": int(v.size), "median": float(np.median(v)), "p90": float(np.percentile(v, 90)),
            "max": float(v.max())} if v.size else {"n": 0}  # fmt: skip


def truth_residual(lk: Any, truth_xy: tuple[np.ndarray, np.ndarray], frame: MapFrame) -> np.ndarray:
    """Distance (map px) between each drawn pixel's centre and the TRUE position of the query
    pixel it shows (truth bilinear at the lookup's query position)."""
    import cv2

    k = lk.k
    t = frame.to_px(np.c_[truth_xy[0][::k, ::k].ravel(), truth_xy[1][::k, ::k].ravel()])
    h, w = lk.gc.shape
    g = np.dstack([t[:, 0].reshape(h, w), t[:, 1].reshape(h, w)])
    ok = np.isfinite(g).all(axis=2).astype(np.float32)
    mx, my = lk.qc.astype(np.float32), lk.qr.astype(np.float32)
    at = cv2.remap(np.nan_to_num(g), mx, my, cv2.INTER_LINEAR, borderValue=0)
    inside = cv2.remap(ok, mx, my, cv2.INTER_LINEAR, borderValue=0) > 0.999
    mc, mr = lk.centres()
    return np.hypot(at[..., 0] - mc, at[..., 1] - mr)[inside]


def bench_run(run: Path) -> dict[str, Any]:

    res = run / "results"
    frame = MapFrame.from_grid(res / "map/grid.json")
    out: dict[str, Any] = {"run": str(run), "queries": {}}
    names = sorted(p.name for p in (res / "queries").iterdir() if (p / "registration.json").exists())
    for name in names:
        q = res / "queries" / name
        reg = json.loads((q / "registration.json").read_text())
        if reg.get("status") != "registered":
            out["queries"][name] = {"status": reg.get("status")}
            continue
        geo = read_raster(q / "geolocation.tif")
        geo_xy = (geo[0], geo[1])
        row: dict[str, Any] = {"status": "registered", "size": [int(geo.shape[2]), int(geo.shape[1])]}
        truth_path = next(iter(sorted((res / "demo/queries").glob(f"{name}_truth.tif"))), None) \
            if (res / "demo/queries").is_dir() else None  # fmt: skip
        truth = read_raster(truth_path) if truth_path else None
        for label, it in (("view_lookup", 4), ("baseline_H_only", 0)):
            t0 = time.process_time()
            lk = query_lookup(geo.shape[1:], geo_xy, reg["homography"], frame, 1024, it)
            cpu = time.process_time() - t0
            row[label] = {"drawing_error_px": _stats(lookup_residual(lk)), "cpu_s": round(cpu, 3),
                          "overlay_px": list(lk.qc.shape[::-1])}  # fmt: skip
            if truth is not None:
                row[label]["vs_truth_px"] = _stats(truth_residual(lk, (truth[0], truth[1]), frame))
        ev = q / "evaluation.json"
        if ev.exists():
            row["evaluation_error_px"] = (json.loads(ev.read_text()).get("error") or {}).get("px")
        out["queries"][name] = row
    # the whole view: CPU and bytes
    sets = sorted(p.name for p in (res / "frames").iterdir()) if (res / "frames").is_dir() else []
    with tempfile.TemporaryDirectory() as tmp:
        t0 = time.process_time()
        run_map_view(
            Path(tmp) / "map.html", Path(tmp) / "map", res / "map/grid.json",
            res / "map/mosaic/ortho.vrt", names,
            [str(res / f"queries/{n}/registration.json") for n in names],
            [str(res / f"queries/{n}/evaluation.json") for n in names],
            [str(res / f"queries/{n}/band.tif") for n in names],
            [str(res / f"queries/{n}/geolocation.tif") for n in names],
            [str(res / f"demo/queries/{n}_truth.tif")
             if (res / f"demo/queries/{n}_truth.tif").exists() else None for n in names],
            sets, [str(res / f"frames/{s}/poses.json") for s in sets],
            [None] * len(sets),
            [s for s in sets if (res / f"frames/{s}/trajectory.json").exists()],
        )  # fmt: skip
        cpu = time.process_time() - t0
        files = [p for p in Path(tmp).rglob("*") if p.is_file()]
        out["view"] = {"cpu_s": round(cpu, 2), "bytes": sum(p.stat().st_size for p in files),
                       "html_bytes": (Path(tmp) / "map.html").stat().st_size,
                       "ortho_bytes": (Path(tmp) / "map/ortho.jpg").stat().st_size,
                       "leaflet_bytes": sum(p.stat().st_size for p in files if "leaflet" in p.parts)}  # fmt: skip
    return out


def _angle(a: np.ndarray, b: np.ndarray) -> float:
    d = np.degrees(np.arctan2(a[0], a[1]) - np.arctan2(b[0], b[1]))
    return float(abs((d + 180) % 360 - 180))


def bench_real() -> dict[str, Any]:
    if not FRAMES_DEV.is_dir():
        raise SystemExit(f"{FRAMES_DEV} is absent")
    out: dict[str, Any] = {}
    for case in ("ngi", "odm"):
        for t in sorted((FRAMES_DEV / case / "truth").glob("*.json")):
            tr = json.loads(t.read_text())
            C = np.asarray(tr["camera_center_xyz"], float)
            pose = {"camera_center_xyz": tr["camera_center_xyz"], "R_world_to_cam": tr["R_world_to_cam"],
                    "footprint_xy": [v[:2] for v in tr["footprint_xyz"]]}  # fmt: skip
            true_dir = np.asarray(tr["ground_point_of_image_centre"][:2]) - C[:2]
            ours = look_end(pose) - C[:2]
            base = np.asarray(pose["footprint_xy"], float).mean(axis=0) - C[:2]
            axis = np.asarray(tr["R_world_to_cam"])[2]
            off = float(np.degrees(np.arccos(-axis[2])))
            row: dict[str, Any] = {"off_nadir_deg": round(off, 1)}
            if off < 5:  # no look direction to speak of: the view draws the image's "up" instead
                row["note"] = "nadir: the view draws a tick towards the image top, not compared"
            else:
                row["view_axis_error_deg"] = round(_angle(ours, true_dir), 2)
                row["baseline_footprint_centroid_error_deg"] = round(_angle(base, true_dir), 2)
            out[f"{case}/{t.stem}"] = row
    return out


def _hp_ncc(gray: np.ndarray, rgba: np.ndarray, bounds: list[float]) -> float:
    """High-pass correlation of a drawn query image with the orthophoto under it."""
    import cv2

    c0, r0, c1, r1 = bounds
    h, w = rgba.shape[:2]
    mc, mr = np.meshgrid(c0 + (np.arange(w) + 0.5) * (c1 - c0) / w,
                         r0 + (np.arange(h) + 0.5) * (r1 - r0) / h)  # fmt: skip
    under = cv2.remap(gray, (mc - 0.5).astype(np.float32), (mr - 0.5).astype(np.float32),
                      cv2.INTER_LINEAR)  # fmt: skip
    a, b = (x - cv2.GaussianBlur(x, (0, 0), 3) for x in (rgba[..., 0].astype(np.float32), under))
    m = cv2.erode((rgba[..., 3] > 0).astype(np.uint8), np.ones((9, 9), np.uint8)) > 0
    a, b = a[m] - a[m].mean(), b[m] - b[m].mean()
    return float((a * b).sum() / np.sqrt((a * a).sum() * (b * b).sum()))


def bench_real_query(wobble_m: float = 2.0) -> dict[str, Any]:
    """A query cut from the real ODM orthophoto (green band) through a known geolocation: H (0.5 m
    pixels, 30 deg) plus a cross-track wobble; drawn by the view's lookup vs by H alone."""
    import cv2
    import rasterio

    from georeg.report.map_data import warp_query

    path = FRAMES_DEV / "odm" / "map_ortho.tif"
    with rasterio.open(path) as ds:
        green, T = ds.read(2).astype(np.float32), ds.transform
    frame = MapFrame(tuple(T)[:6], green.shape[1], green.shape[0])
    a = np.deg2rad(-30.0)
    H = np.array([[0.5 * np.cos(a), 0.5 * np.sin(a), T.c + 120.0],
                  [0.5 * np.sin(a), -0.5 * np.cos(a), T.f - 60.0], [0, 0, 1.0]])  # fmt: skip
    qw, qh = 220, 300
    c, r = np.meshgrid(np.arange(qw, dtype=float), np.arange(qh, dtype=float))
    p = np.stack([c, r, np.ones_like(c)], -1) @ H.T
    x = p[..., 0] / p[..., 2] + wobble_m * np.sin(r / qh * 2 * np.pi)
    y = p[..., 1] / p[..., 2]
    col = ((x - T.c) / T.a - 0.5).astype(np.float32)
    row = ((y - T.f) / T.e - 0.5).astype(np.float32)
    b = cv2.remap(green, col, row, cv2.INTER_LINEAR, borderValue=0)
    band = np.clip(b, 1, 255).astype(np.uint8) * (b > 0)
    out: dict[str, Any] = {"wobble_map_px": wobble_m / abs(T.a)}
    for label, it in (("view_lookup", 4), ("baseline_H_only", 0)):
        img, bounds = warp_query(band, (x, y), H, frame, iterations=it)
        lk = query_lookup(band.shape, (x, y), H, frame, iterations=it)
        out[label] = {"drawing_error_px": _stats(lookup_residual(lk)),
                      "highpass_ncc_with_ortho": round(_hp_ncc(green, img, bounds), 3)}  # fmt: skip
    return out


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    sub = ap.add_subparsers(dest="cmd", required=True)
    r = sub.add_parser("run")
    r.add_argument("dir", type=Path)
    r.add_argument("--out", type=Path)
    sub.add_parser("real").add_argument("--out", type=Path)
    a = ap.parse_args(argv)
    res = bench_run(a.dir) if a.cmd == "run" else {"look_directions": bench_real(),
                                                    "odm_query": bench_real_query()}
    text = json.dumps(res, indent=1)
    print(text)
    if a.out:
        a.out.parent.mkdir(parents=True, exist_ok=True)
        a.out.write_text(text + "\n")


if __name__ == "__main__":
    main()
