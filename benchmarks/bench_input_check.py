"""Cost of the input check that runs before any rule (``register.inputs.check_inputs``).

Real inputs from ../shared/data: each frames_dev case's map (ortho + DEM) and frames, plus the
autzen LAZ, the EnMAP cube and a Landsat ENVI cube as queries; median of ``--repeats``.

    python benchmarks/bench_input_check.py --repeats 5
"""

from __future__ import annotations

import argparse
import statistics
import time
from pathlib import Path

import yaml

from georeg.register.inputs import check_inputs

SHARED = Path(__file__).resolve().parents[2] / "shared" / "data"


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawTextHelpFormatter)
    ap.add_argument("--repeats", type=int, default=5)
    a = ap.parse_args()
    landsat = sorted((SHARED / "swir_dates" / "landsat_nanjing").glob("*.hdr"))[0]
    print("| case | inputs | median s | problems |\n|---|---:|---:|---:|")
    for case in ("ngi", "odm"):
        c = yaml.safe_load((SHARED / "frames_dev" / f"{case}.yaml").read_text())
        c = {k: v.replace("../shared/data", str(SHARED)) if isinstance(v, str) else v
             for k, v in yaml.safe_load(yaml.safe_dump(c).replace("../shared/data", str(SHARED))).items()}  # fmt: skip
        c["map"]["lidar"] = [str(SHARED / "autzen" / "autzen_trim.laz")]
        c["queries"] = {"enmap": {"image": str(SHARED / "enmap_potsdam" / "enmap_potsdam_mosaic_subset.tif")},
                        "landsat": {"image": str(landsat)}}  # fmt: skip
        n = 3 + len(c["queries"]) + sum(len(f.get("images") or []) for f in c["frames"].values())
        times, problems = [], []
        for _ in range(a.repeats):
            t = time.perf_counter()
            problems = check_inputs(c)
            times.append(time.perf_counter() - t)
        print(f"| {case} | {n} | {statistics.median(times):.3f} | {len(problems)} |")


if __name__ == "__main__":
    main()
