"""GeoPackage writing (issue 33): sqlite3 by hand (georeg.export.gpkg) vs GDAL through pyogrio
(not in requirements.txt: measured from a side install), on N random tie points.

    PYTHONPATH=.:/path/to/pyogrio/site python benchmarks/bench_gpkg.py [--n 20000] [--out DIR]

Prints CPU seconds (import, write x3), file sizes and whether GDAL reads the sqlite3-written file.
"""

from __future__ import annotations

import argparse
import struct
import sys
import time
from pathlib import Path

import numpy as np


def main(argv: list[str]) -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--n", type=int, default=20000)
    ap.add_argument("--out", default="/tmp/bench_gpkg")
    a = ap.parse_args(argv)
    out = Path(a.out)
    out.mkdir(parents=True, exist_ok=True)
    rng = np.random.default_rng(0)
    n = a.n
    xyz = np.c_[rng.uniform(4e5, 4.1e5, n), rng.uniform(5.8e6, 5.81e6, n), rng.uniform(0, 50, n)]
    cols = {k: rng.random(n) for k in ("query_col", "query_row", "residual_px", "score")}
    cols["accepted"] = rng.random(n) > 0.5
    t0 = time.process_time()
    from georeg.export.gpkg import write_points

    imp = time.process_time() - t0
    ts = []
    for i in range(3):
        t = time.process_time()
        write_points(out / f"sqlite3_{i}.gpkg", "tie_points", xyz, cols, "EPSG:32633")
        ts.append(time.process_time() - t)
    print(f"| sqlite3 by hand | {imp:.3f} | {min(ts):.3f} | {(out / 'sqlite3_0.gpkg').stat().st_size / 1e6:.2f} |")
    try:
        t0 = time.process_time()
        import pyogrio
        from pyogrio.raw import write

        imp = time.process_time() - t0
    except ImportError:
        print("pyogrio not importable: GDAL half skipped")
        return
    wkb = np.array([struct.pack("<BIddd", 1, 1001, *p) for p in xyz], dtype=object)
    ts = []
    for i in range(3):
        t = time.process_time()
        write(str(out / f"pyogrio_{i}.gpkg"), wkb, [cols[k] for k in cols], list(cols), driver="GPKG",
              layer="tie_points", crs="EPSG:32633", geometry_type="Point Z")  # fmt: skip
        ts.append(time.process_time() - t)
    print(f"| pyogrio (GDAL {pyogrio.__gdal_version_string__}) | {imp:.3f} | {min(ts):.3f} | "
          f"{(out / 'pyogrio_0.gpkg').stat().st_size / 1e6:.2f} |")
    info = pyogrio.read_info(out / "sqlite3_0.gpkg", layer="tie_points")
    print(f"GDAL reads the sqlite3-written file: {info['features']} features, {info['geometry_type']}, {info['crs']}")


if __name__ == "__main__":
    main(sys.argv[1:])
