"""Issue 34's unseen SRIF case's stand-in, as a user runs it: ``snakemake`` on JPEGs.

    . /work/main/.venv/bin/activate
    nice -n 5 python benchmarks/bench_srif_big_workflow.py --work /tmp/srifbig --half tuning \\
        --out benchmarks/out/srif_big_workflow.json [--gsd] [--limit N]

The map is ``bench_devset.build_srif_big``'s mosaic (100 SRIF optical-infrared references,
every 10th left out, 40 optical-depth optical references as filler; 1 m pixels, UTM 33N) written
as a GeoTIFF orthophoto without LiDAR; the queries are SRIF's own ``pair<i>_2.jpg`` files, as
delivered (no nodata: their black fill is whatever the workflow makes of it), each with no
``gsd_m`` (a JPEG states none; ``--gsd``: 1 m over the truth's scale, the GSD known). One
``snakemake --cores 2`` run registers them all; each query is judged from its
``geolocation.tif`` at the truth grid (``bench_devset.judge``: within 8 query px or 5 map px of
its reference or of an overlapping one; a left-out query must end ``not_found`` unless it lands
on a reference overlapping its own). Session 33 ran this from /tmp (31/90, 0 false, no GSD).
"""

from __future__ import annotations

import argparse
import json
import shutil
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
import bench_devset as bd  # noqa: E402

ROOT = bd.ROOT


def write_map(sc: Any, path: Path) -> None:
    """The mosaic as a 3-band GeoTIFF orthophoto (EPSG:32633, 0 = nodata)."""
    import rasterio
    from rasterio.transform import Affine

    g = bd.mosaic_geotransform(sc)
    prof = {"driver": "GTiff", "width": sc.map_gray.shape[1], "height": sc.map_gray.shape[0],
            "count": 3, "dtype": "uint8", "crs": "EPSG:32633", "nodata": 0, "compress": "deflate",
            "tiled": True, "transform": Affine(g[1], g[2], g[0], g[4], g[5], g[3])}  # fmt: skip
    with rasterio.open(path, "w", **prof) as dst:
        for k in (1, 2, 3):
            dst.write(sc.map_gray, k)


def judge_geolocation(q: Any, sc: Any, geo: Path, status: str) -> dict[str, Any]:
    """bench_devset.judge of the query's geolocation.tif (map x, y per query px)."""
    import rasterio

    accepted = status == "registered"
    res: dict[str, Any] = {"accepted": accepted, "H": None}
    if accepted:
        with rasterio.open(geo) as src:
            x, y = src.read(1).astype(np.float64), src.read(2).astype(np.float64)
        x0, y0 = bd.MOSAIC_ORIGIN
        res["xy"] = (x - x0, y - y0)
        n_r, n_c = x.shape
        uu, vv = np.meshgrid(np.linspace(2, n_c - 3, 12), np.linspace(2, n_r - 3, 12))
        qp = np.c_[uu.ravel(), vv.ravel()]
        est = np.c_[res["xy"][0][qp[:, 1].astype(int), qp[:, 0].astype(int)],
                    res["xy"][1][qp[:, 1].astype(int), qp[:, 0].astype(int)]]  # fmt: skip
        ok = np.isfinite(est).all(1)
        if ok.sum() >= 4:  # an H for where the pose lands (the overlapping references)
            A = np.linalg.lstsq(np.c_[qp[ok], np.ones(ok.sum())], est[ok], rcond=None)[0]
            res["H"] = np.vstack([A.T, [0, 0, 1.0]])
    return bd.judge(q, sc, res)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawTextHelpFormatter)
    ap.add_argument("--work", default="/tmp/srifbig")
    ap.add_argument("--half", choices=("tuning", "checking", "both"), default="both")
    ap.add_argument("--gsd", action="store_true", help="give each query its gsd_m")
    ap.add_argument("--limit", type=int, default=0)
    ap.add_argument("--only", default="", help="pair indices, comma-separated")
    ap.add_argument("--out", default=str(ROOT / "benchmarks" / "out" / "srif_big_workflow.json"))
    a = ap.parse_args(argv)
    if not bd.SRIF.is_dir():
        print(f"no development data at {bd.SRIF}", file=sys.stderr)
        return 1
    import yaml

    scenes, queries = bd.build_srif_big()
    sc = scenes[0]
    if a.half != "both":
        queries = [q for q in queries if q.half == a.half]  # type: ignore[attr-defined]
    if a.only:
        keep = {f"big_oi_{i}" for i in a.only.split(",")}
        queries = [q for q in queries if q.name.removesuffix("_leftout") in keep]
    if a.limit:
        queries = queries[: a.limit]
    work = Path(a.work)
    work.mkdir(parents=True, exist_ok=True)
    ortho = work / "map.tif"
    if not ortho.exists():
        write_map(sc, ortho)
    entries = {}
    for q in queries:
        i = int(q.name.split("_")[2])
        jpg = work / "queries" / f"{q.name}.jpg"
        jpg.parent.mkdir(exist_ok=True)
        shutil.copyfile(bd.SRIF / bd.MODALITIES["oi"] / f"pair{i}_2.jpg", jpg)
        entries[q.name] = {"image": str(jpg), "band": "auto", "bands": "auto",
                           "gsd_m": round(float(q.gsd), 6) if a.gsd else None}  # fmt: skip
    cfg = work / "config.yaml"
    cfg.write_text(yaml.safe_dump({"map": {"orthophoto": str(ortho), "crs": "EPSG:32633", "lidar": []},
                                   "queries": entries, "frames": {}}))  # fmt: skip
    t0 = time.perf_counter()
    cmd = [sys.executable, "-m", "snakemake", "-s", str(ROOT / "Snakefile"), "-d", str(work),
           *[f"results/queries/{q}/geolocation.tif" for q in entries],
           "--cores", "2", "--configfile", str(cfg), "--keep-going"]  # fmt: skip
    proc = subprocess.run(cmd, capture_output=True, text=True, cwd=work)
    secs = time.perf_counter() - t0
    (work / "snakemake.log").write_text(proc.stdout + proc.stderr)
    rows = []
    for q in queries:
        d = work / "results" / "queries" / q.name
        if not (d / "registration.json").exists():
            rows.append({"query": q.name, "half": q.half, "outcome": "error"})  # type: ignore[attr-defined]
            continue
        reg = json.loads((d / "registration.json").read_text())
        j = judge_geolocation(q, sc, d / "geolocation.tif", reg["status"])
        rift = (reg.get("split") or {}).get("rift") or {}
        rows.append({"query": q.name, "half": q.half, "positive": q.truth is not None,  # type: ignore[attr-defined]
                     **j, "status": reg["status"], "reason": reg.get("reason"),
                     "rift_log10_nfa": rift.get("log10_nfa"), "rift_reason": rift.get("reason"),
                     "sources": [s["name"] for s in reg.get("sources") or [] if s.get("accepted")]})  # fmt: skip
    summary = {}
    for half in ("tuning", "checking"):
        r = [x for x in rows if x["half"] == half]
        if not r:
            continue
        pos = [x for x in r if x.get("positive")]
        summary[half] = {"registered": sum(x["outcome"] == "success" for x in pos), "positives": len(pos),
                         "false_accepts": sum(x["outcome"] == "false_accept" for x in r),
                         "left_out_not_found": sum(not x.get("positive") and x["outcome"] == "rejected" for x in r),
                         "left_out": sum(not x.get("positive") for x in r),
                         "errors": sum(x["outcome"] == "error" for x in r)}  # fmt: skip
    out = {"seconds": secs, "queries": len(queries), "gsd_given": a.gsd, "returncode": proc.returncode,
           "summary": summary, "rows": rows}  # fmt: skip
    Path(a.out).parent.mkdir(parents=True, exist_ok=True)
    Path(a.out).write_text(json.dumps(out, indent=1, default=float))
    print(json.dumps({"seconds": round(secs), "per_query": round(secs / max(1, len(queries)), 1),
                      "summary": summary}, indent=1))  # fmt: skip
    return 0 if proc.returncode == 0 else 1


if __name__ == "__main__":
    sys.exit(main())
