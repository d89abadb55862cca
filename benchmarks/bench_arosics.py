"""Issue 12, "Compare with the reference tool": AROSICS vs our local refinement.

NOT a dependency of the workflow. Runs with the python of a separate venv that has AROSICS
(see docs/BENCHMARKS.md "Comparison with AROSICS" for how to create it); it does not import georeg
and reads the workflow outputs with GDAL / numpy / scipy only.

Inputs (a finished workflow run directory RUN, query QUERY, default ``demo``):
- ``RUN/results/queries/QUERY/band.tif``                 the query band (uint8, 0 = nodata)
- ``RUN/results/queries/QUERY/geolocation_global.tif``   GLOBAL map x, y of every query pixel centre
- ``RUN/results/queries/QUERY/registration.json``        our numbers (evaluation / evaluation_global)
- ``RUN/results/map/mosaic/ortho.vrt``                   the orthophoto (reference)
- ``RUN/results/demo/queries/QUERY_truth.tif``           truth: map x, y of every query pixel centre

Method:
1. "Unrefined" geo-referenced target: the query band warped (bilinear) onto a north-up grid at map
   resolution, snapped to the orthophoto grid, with the GLOBAL geolocation. For every output pixel
   centre the query (col, row) is found by Newton iterations on the bilinearly interpolated
   geolocation field (start: least-squares affine fit), i.e. an exact inverse of the raster.
2. Reference: BT.601 luminance of the orthophoto (as our refinement uses), cropped to the target
   extent + a margin, same grid.
3. AROSICS ``COREG`` (one global shift) and ``COREG_LOCAL`` (tie-point grid), then
   ``correct_shifts()`` (included in the timed part, as a user would run it).
4. Per-query-pixel corrected map position, i.e. where the corrected product places query pixel
   (col, row) whose global position is p = G(col, row):
   - COREG: p' = p + (x_shift_map, y_shift_map) (AROSICS moves the target geotransform origin by
     that vector: ``new_origin = imXY2mapXY(shift_px, gt)``).
   - COREG_LOCAL: AROSICS warps the target with GDAL's thin-plate-spline GCP transformer, GCPs =
     (target pixel X_IM, Y_IM) -> (X_MAP + X_SHIFT_M, Y_MAP + Y_SHIFT_M) over the accepted tie
     points (``Tie_Point_Grid.to_GCPList``, ``warp_ndarray(..., tps=True)``). We build the same
     transformer (``gdal.Transformer`` with ``METHOD=GCP_TPS`` on the same GCPs) and apply it to
     p expressed in target pixel coordinates (GDAL corner convention, as AROSICS's X_IM / X_MAP).
   Error = |p' - truth| per query pixel with a truth, in map pixels; median / p90 / max / RMSE.

Usage (arosics venv)::

    /work/arosics-venv/bin/python benchmarks/bench_arosics.py RUN [--query demo] [--out DIR]
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
import warnings
from pathlib import Path

import numpy as np
from osgeo import gdal, osr
from scipy import ndimage

gdal.UseExceptions()


def read_bands(path: Path) -> tuple[list[np.ndarray], gdal.Dataset]:
    ds = gdal.Open(str(path))
    return [ds.GetRasterBand(i + 1).ReadAsArray() for i in range(ds.RasterCount)], ds


def stats(err: np.ndarray, px_m: float) -> dict[str, float]:
    e = err[np.isfinite(err)] / px_m
    return {
        "median": float(np.median(e)),
        "p90": float(np.percentile(e, 90)),
        "max": float(e.max()),
        "rmse": float(np.sqrt(np.mean(e**2))),
        "pixels": int(e.size),
    }


def invert_geolocation(
    gx: np.ndarray, gy: np.ndarray, X: np.ndarray, Y: np.ndarray, iters: int = 8
) -> tuple[np.ndarray, np.ndarray]:
    """(col, row) such that bilinear G(col, row) = (X, Y); NaN outside the query."""
    h, w = gx.shape
    rows, cols = np.mgrid[0:h, 0:w]
    ok = np.isfinite(gx) & np.isfinite(gy)
    A = np.column_stack([gx[ok], gy[ok], np.ones(ok.sum())])
    coef, *_ = np.linalg.lstsq(A, np.column_stack([cols[ok], rows[ok]]), rcond=None)
    c = coef[0, 0] * X + coef[1, 0] * Y + coef[2, 0]
    r = coef[0, 1] * X + coef[1, 1] * Y + coef[2, 1]

    def g(cc: np.ndarray, rr: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        cc = np.clip(cc, 0, w - 1)
        rr = np.clip(rr, 0, h - 1)
        return (
            ndimage.map_coordinates(gx, [rr, cc], order=1, mode="nearest"),
            ndimage.map_coordinates(gy, [rr, cc], order=1, mode="nearest"),
        )

    d = 0.5
    for _ in range(iters):
        x0, y0 = g(c, r)
        xc, yc = g(c + d, r)
        xr, yr = g(c, r + d)
        j11, j21 = (xc - x0) / d, (yc - y0) / d
        j12, j22 = (xr - x0) / d, (yr - y0) / d
        det = j11 * j22 - j12 * j21
        det = np.where(np.abs(det) < 1e-12, np.nan, det)
        ex, ey = X - x0, Y - y0
        c = c + (j22 * ex - j12 * ey) / det
        r = r + (-j21 * ex + j11 * ey) / det
        c = np.clip(c, -2, w + 1)
        r = np.clip(r, -2, h + 1)
    x0, y0 = g(c, r)
    inside = (c >= 0) & (c <= w - 1) & (r >= 0) & (r <= h - 1) & (np.hypot(X - x0, Y - y0) < 1e-3)
    return np.where(inside, c, np.nan), np.where(inside, r, np.nan)


def write_tif(path: Path, arr: np.ndarray, gt: tuple, wkt: str, nodata: float | None) -> None:
    drv = gdal.GetDriverByName("GTiff")
    ds = drv.Create(str(path), arr.shape[1], arr.shape[0], 1, gdal.GDT_Float32)
    ds.SetGeoTransform(gt)
    ds.SetProjection(wkt)
    b = ds.GetRasterBand(1)
    if nodata is not None:
        b.SetNoDataValue(nodata)
    b.WriteArray(arr.astype(np.float32))
    ds.FlushCache()
    ds = None


def build_inputs(run: Path, query: str, out: Path, margin: float) -> dict:
    t0 = time.perf_counter()
    qdir = run / "results" / "queries" / query
    reg = json.loads((qdir / "registration.json").read_text())
    (band,), _ = read_bands(qdir / "band.tif")
    (gx, gy, *_), _ = read_bands(qdir / "geolocation_global.tif")
    ortho = gdal.Open(str(run / "results" / "map" / "mosaic" / "ortho.vrt"))
    ogt = ortho.GetGeoTransform()
    res = ogt[1]
    srs = osr.SpatialReference()
    srs.ImportFromWkt(reg["crs"])
    wkt = srs.ExportToWkt()
    # north-up grid at map resolution, snapped to the orthophoto grid
    x_min = np.floor((np.nanmin(gx) - margin - ogt[0]) / res) * res + ogt[0]
    x_max = np.ceil((np.nanmax(gx) + margin - ogt[0]) / res) * res + ogt[0]
    y_max = ogt[3] - np.floor((ogt[3] - np.nanmax(gy) - margin) / res) * res
    y_min = ogt[3] - np.ceil((ogt[3] - np.nanmin(gy) + margin) / res) * res
    nx, ny = int(round((x_max - x_min) / res)), int(round((y_max - y_min) / res))
    gt = (float(x_min), res, 0.0, float(y_max), 0.0, -res)
    X = x_min + (np.arange(nx) + 0.5) * res
    Y = y_max - (np.arange(ny) + 0.5) * res
    XX, YY = np.meshgrid(X, Y)
    c, r = invert_geolocation(gx.astype(np.float64), gy.astype(np.float64), XX, YY)
    inside = np.isfinite(c)
    cc, rr = np.where(inside, c, 0), np.where(inside, r, 0)
    b = band.astype(np.float64)
    val = ndimage.map_coordinates(b, [rr, cc], order=1, mode="nearest")
    vmask = ndimage.map_coordinates(
        (band > 0).astype(np.float64), [rr, cc], order=1, mode="nearest"
    )
    tgt = np.where(inside & (vmask > 0.999), np.maximum(val, 1e-3), 0.0)
    tgt_path = out / "target_global.tif"
    write_tif(tgt_path, tgt, gt, wkt, 0.0)
    # reference: orthophoto luminance (BT.601) over the target extent + margin, same grid
    pad = 32
    xo = int(round((x_min - ogt[0]) / res)) - pad
    yo = int(round((ogt[3] - y_max) / res)) - pad
    x0c, y0c = max(xo, 0), max(yo, 0)
    x1c = min(xo + nx + 2 * pad, ortho.RasterXSize)
    y1c = min(yo + ny + 2 * pad, ortho.RasterYSize)
    rgb = [
        ortho.GetRasterBand(i + 1).ReadAsArray(x0c, y0c, x1c - x0c, y1c - y0c).astype(np.float64)
        for i in range(min(3, ortho.RasterCount))
    ]
    lum = 0.299 * rgb[0] + 0.587 * rgb[1] + 0.114 * rgb[2] if len(rgb) == 3 else rgb[0]
    ref_gt = (ogt[0] + x0c * res, res, 0.0, ogt[3] - y0c * res, 0.0, -res)
    ref_path = out / "reference_lum.tif"
    write_tif(ref_path, lum, ref_gt, wkt, None)
    return {
        "reg": reg,
        "gx": gx.astype(np.float64),
        "gy": gy.astype(np.float64),
        "tgt": tgt_path,
        "ref": ref_path,
        "tgt_gt": gt,
        "tgt_shape": (ny, nx),
        "wkt": wkt,
        "res": res,
        "prep_s": time.perf_counter() - t0,
    }


def tps_positions(gcps: list, x: np.ndarray, y: np.ndarray, gt: tuple, shape: tuple, wkt: str):
    """Map positions of target-grid map points (x, y) after AROSICS's TPS GCP warp."""
    mem = gdal.GetDriverByName("MEM").Create("", shape[1], shape[0], 1, gdal.GDT_Byte)
    mem.SetGCPs(gcps, wkt)
    tr = gdal.Transformer(mem, None, ["METHOD=GCP_TPS"])
    px = (x - gt[0]) / gt[1]
    py = (y - gt[3]) / gt[5]
    pts = np.column_stack([px.ravel(), py.ravel()])
    res, ok = tr.TransformPoints(0, pts.tolist())
    res = np.asarray(res, dtype=np.float64)
    ok = np.asarray(ok, dtype=bool)
    res[~ok] = np.nan
    return res[:, 0].reshape(x.shape), res[:, 1].reshape(x.shape)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("run", type=Path, help="workflow run directory (snakemake -d)")
    ap.add_argument("--query", default="demo")
    ap.add_argument("--out", type=Path, default=None, help="work dir (default RUN/arosics_bench)")
    ap.add_argument("--grid-res", type=float, default=12, help="COREG_LOCAL grid (target px)")
    ap.add_argument("--window", type=int, default=32, help="COREG_LOCAL window (target px)")
    ap.add_argument("--global-window", type=int, default=128, help="COREG window (target px)")
    ap.add_argument("--cpus", type=int, default=2)
    ap.add_argument("--margin", type=float, default=8.0, help="map units around the footprint")
    a = ap.parse_args(argv)
    out = a.out or a.run / "arosics_bench"
    out.mkdir(parents=True, exist_ok=True)
    warnings.simplefilter("ignore")
    os.environ.setdefault("MPLBACKEND", "Agg")
    from arosics import COREG, COREG_LOCAL, __version__

    inp = build_inputs(a.run, a.query, out, a.margin)
    reg, gx, gy, res = inp["reg"], inp["gx"], inp["gy"], inp["res"]
    px_m = float(reg.get("map_px_m") or res)
    (tx, ty), _ = read_bands(a.run / "results" / "demo" / "queries" / f"{a.query}_truth.tif")
    valid = np.isfinite(tx) & np.isfinite(ty)

    def err(x: np.ndarray, y: np.ndarray) -> dict:
        return stats(np.hypot(x - tx, y - ty)[valid], px_m)

    rows: dict[str, dict] = {}
    rows["global (ours, input to AROSICS)"] = {"error_px": err(gx, gy)}

    # AROSICS COREG: one global shift
    t0 = time.perf_counter()
    cr = COREG(
        str(inp["ref"]), str(inp["tgt"]), ws=(a.global_window, a.global_window),
        nodata=(-9999, 0), path_out=str(out / "coreg.tif"), fmt_out="GTIFF",
        CPUs=a.cpus, q=True,
    )  # fmt: skip
    cr.calculate_spatial_shifts()
    cr.correct_shifts()
    t_coreg = time.perf_counter() - t0
    info = cr.coreg_info
    sx, sy = info["corrected_shifts_map"]["x"], info["corrected_shifts_map"]["y"]
    rows["AROSICS COREG (global shift)"] = {
        "error_px": err(gx + sx, gy + sy),
        "seconds": t_coreg,
        "shift_map": [sx, sy],
        "success": bool(info["success"]),
    }

    # AROSICS COREG_LOCAL: tie-point grid + TPS warp
    t0 = time.perf_counter()
    crl = COREG_LOCAL(
        str(inp["ref"]), str(inp["tgt"]), grid_res=a.grid_res, window_size=(a.window, a.window),
        nodata=(-9999, 0), path_out=str(out / "coreg_local.tif"), fmt_out="GTIFF",
        CPUs=a.cpus, progress=False, q=True,
    )  # fmt: skip
    crl.calculate_spatial_shifts()
    t_tie = time.perf_counter() - t0
    crl.correct_shifts()
    t_local = time.perf_counter() - t0
    table = crl.CoRegPoints_table
    gcps = crl.tiepoint_grid.GCPList
    measured = table[table.ABS_SHIFT != -9999]
    row = {
        "seconds": t_local,
        "tie_points_seconds": t_tie,
        "grid_points": int(len(table)),
        "measured": int(len(measured)),
        "accepted_gcps": int(len(gcps)),
        "grid_res": a.grid_res,
        "window": a.window,
    }
    if gcps:
        x2, y2 = tps_positions(gcps, gx, gy, inp["tgt_gt"], inp["tgt_shape"], inp["wkt"])
        row["error_px"] = err(x2, y2)
    rows["AROSICS COREG_LOCAL"] = row

    ev, evg, tm = reg.get("evaluation") or {}, reg.get("evaluation_global") or {}, reg["timings_s"]
    g_s = sum(v for k, v in tm.items() if k in ("query_band", "fuse_total", "geolocation"))
    g_s += sum((tm.get("search_parts") or {}).values())
    rows["ours: global (registration.json evaluation_global)"] = {
        "error_px": evg.get("px"), "seconds": g_s,
    }  # fmt: skip
    rows["ours: refined (registration.json evaluation)"] = {
        "error_px": ev.get("px"), "seconds": tm.get("refine"),
        "model": (reg.get("refine") or {}).get("model"),
        "tie_points": (reg.get("refine") or {}).get("tie_points"),
        "grid_points": (reg.get("refine") or {}).get("grid_points"),
    }  # fmt: skip
    result = {
        "run": str(a.run),
        "query": a.query,
        "arosics": __version__,
        "gdal": gdal.__version__,
        "query_shape": list(gx.shape),
        "target_shape": list(inp["tgt_shape"]),
        "prep_warp_s": inp["prep_s"],
        "rows": rows,
    }
    (out / "result.json").write_text(json.dumps(result, indent=2))
    print(f"arosics {__version__}, gdal {gdal.__version__}; query {gx.shape}, "
          f"target grid {inp['tgt_shape']}, warp {inp['prep_s']:.1f} s")  # fmt: skip
    print("| method | median | p90 | max | RMSE | time (s) | notes |")
    print("|---|---:|---:|---:|---:|---:|---|")
    for name, r in rows.items():
        e = r.get("error_px") or {}
        f = [f"{e[k]:.3f}" if k in e else "-" for k in ("median", "p90", "max", "rmse")]
        s = f"{r['seconds']:.1f}" if r.get("seconds") is not None else ""
        notes = {k: v for k, v in r.items() if k not in ("error_px", "seconds")}
        print(f"| {name} | {' | '.join(f)} | {s} | {notes or ''} |")
    return 0


if __name__ == "__main__":
    sys.exit(main())
