"""Peak memory and time of the products' cube COG: streaming band copy vs GDAL's COG driver.

The geo-referenced cube (the paper's 829 x 1163 x 260 query on the default demo) is staged as a
band-interleaved tiled GeoTIFF, then made a COG. ``stream`` is the library's
``copy_band_interleaved_cog`` (overviews band by band, ``COPY_SRC_OVERVIEWS`` + ``INTERLEAVE=BAND``,
128 MB GDAL cache); ``cog_driver`` is the baseline written here: GDAL's COG driver as the products
stage used it before (pixel interleave, default cache). Each run is a fresh subprocess calling
``make_cube`` on a finished default run; peak RSS and CPU of each child from ``os.wait4``,
alternating methods, median of ``--repeats``.

    python benchmarks/bench_products_memory.py --run /path/to/a/default/run --repeats 3
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
CHILD = r"""
import json, os, sys, time
import rasterio
from georeg.products import cube_resample
from georeg.products.make import make_cube

method, out = sys.argv[1], sys.argv[2]
os.chdir(sys.argv[3])  # the run's relative paths; imported from this checkout, not the run's
if method == "cog_driver":
    def cog_driver(stage, dst, overview_resampling="nearest", threads=1, cache_mb=None):
        rasterio.shutil.copy(stage, dst, driver="COG", compress="DEFLATE", predictor="YES",
                             blocksize=256, overviews="AUTO", overview_resampling=overview_resampling,
                             BIGTIFF="IF_SAFER", num_threads=str(max(1, threads)))
    cube_resample.copy_band_interleaved_cog = cog_driver
t = time.perf_counter()
m = make_cube("results/queries/demo/registration.json", "results/queries/demo/geolocation.tif",
              "results/demo/queries/demo.hdr", out + "/cube.json", {}, "results/map/mosaic/ortho.vrt",
              "demo", 1)
print(json.dumps({"wall_s": time.perf_counter() - t, "bands": m["cube"]["bands"],
                  "georeg": cube_resample.__file__}))
"""


def run_once(run_dir: Path, method: str) -> dict:
    with tempfile.TemporaryDirectory() as tmp:
        out_f = Path(tmp) / "stdout.txt"
        with open(out_f, "w") as fh:
            p = subprocess.Popen(
                [sys.executable, "-c", CHILD, method, tmp, str(run_dir.resolve())], cwd=REPO,
                stdout=fh,
            )
            _, status, ru = os.wait4(p.pid, 0)  # this child's own rusage
        p.returncode = os.waitstatus_to_exitcode(status)
        if p.returncode:
            raise SystemExit(f"{method}: child failed ({p.returncode})")
        size = (Path(tmp) / "cube.tif").stat().st_size
        r = json.loads(out_f.read_text().strip().splitlines()[-1])
    return {"method": method, "wall_s": r["wall_s"], "cpu_s": ru.ru_utime + ru.ru_stime,
            "peak_rss_mb": ru.ru_maxrss / 1024, "cog_mb": size / 1e6}  # fmt: skip


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawTextHelpFormatter)
    ap.add_argument("--run", required=True, help="directory of a finished default run")
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--out", default="benchmarks/out/bench_products_memory.jsonl")
    a = ap.parse_args()
    rows: dict[str, list[dict]] = {"stream": [], "cog_driver": []}
    for _ in range(a.repeats):
        for method in rows:
            rows[method].append(run_once(Path(a.run), method))
            print(rows[method][-1], flush=True)
    Path(a.out).parent.mkdir(parents=True, exist_ok=True)
    with open(a.out, "a") as f:
        f.write(json.dumps({"time": time.time(), "runs": rows}) + "\n")
    print("| method | wall (s) | CPU (s) | peak RSS (MB) | COG (MB) |\n|---|---:|---:|---:|---:|")
    for method, rs in rows.items():
        med = {k: statistics.median(r[k] for r in rs) for k in rs[0] if k != "method"}
        print(f"| {method} | {med['wall_s']:.1f} | {med['cpu_s']:.1f} | {med['peak_rss_mb']:.0f} "
              f"| {med['cog_mb']:.0f} |")


if __name__ == "__main__":
    main()
