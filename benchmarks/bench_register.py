"""Registration search strategies `paper` vs `index` on demo maps of growing size (issue 5).

For each map size the demo scene, map and index are built once through the real workflow; then
the registration rules run once per strategy (only they rerun: the map and index do not depend on
`register`). Every figure comes from the run's own registration.json files.

    python benchmarks/bench_register.py --sizes 1024 2048 3072 --out benchmarks/out/register

Writes `<out>/summary.csv` and prints a Markdown table for docs/BENCHMARKS.md.
"""

from __future__ import annotations

import argparse
import csv
import json
import subprocess
import sys
import time
from pathlib import Path

import yaml

REPO = Path(__file__).resolve().parents[1]


def run_workflow(work: Path, cfg: Path, targets: list[str]) -> float:
    cmd = [sys.executable, "-m", "snakemake", "-s", str(REPO / "Snakefile"), "-d", str(work),
           "--cores", "2", *targets, "--configfile", str(cfg)]  # fmt: skip
    t0 = time.perf_counter()
    proc = subprocess.run(cmd, capture_output=True, text=True)
    if proc.returncode:
        sys.exit(f"workflow failed in {work}:\n{proc.stderr[-3000:]}")
    return time.perf_counter() - t0


def config_for(size_m: int, strategy: str, samples: int, lines: int) -> dict:
    demo = {"size_m": size_m, "margin_m": 384, "query": {"samples": samples, "lines": lines}}
    return {
        "demo": demo,
        "map": {"orthophoto": "results/demo/orthophoto.tif",
                "lidar": [f"results/demo/lidar/tile_{i}.laz" for i in range(2)]},
        "queries": {
            name: {"image": f"results/demo/queries/{name}.hdr", "band": "1200nm", "gsd_m": 0.8,
                   "truth": f"results/demo/queries/{name}_truth.tif"}
            for name in ("demo", "outside")
        },
        "register": {"strategy": strategy, "paper": {"max_candidates": 400, "max_seconds": 900}},
    }  # fmt: skip


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--sizes", type=int, nargs="+", default=[1024, 2048, 3072])
    ap.add_argument("--samples", type=int, default=400)
    ap.add_argument("--lines", type=int, default=500)
    ap.add_argument("--out", type=Path, default=REPO / "benchmarks" / "out" / "register")
    args = ap.parse_args()
    rows = []
    for size in args.sizes:
        work = args.out / f"map_{size}"
        work.mkdir(parents=True, exist_ok=True)
        for strategy in ("index", "paper"):
            cfg = work / f"{strategy}.yaml"
            cfg.write_text(yaml.safe_dump(config_for(size, strategy, args.samples, args.lines)))
            targets = [f"results/queries/{q}/registration.json" for q in ("demo", "outside")]
            wall = run_workflow(work, cfg, targets)
            for q in ("demo", "outside"):
                reg = json.loads((work / f"results/queries/{q}/registration.json").read_text())
                ev = (reg.get("evaluation") or {}).get("px") or {}
                t = reg.get("timings_s", {})
                search = sum((t.get("search_parts") or {}).values())
                rows.append({
                    "map_mpx": round((size / 1.0) ** 2 / 1e6, 2), "strategy": strategy, "query": q,
                    "status": reg["status"], "inliers": reg.get("inliers", 0),
                    "candidates_tried": sum(p.get("candidates_tried", 0) for p in reg["parts"]),
                    "search_cpu_s": round(search, 2),
                    "median_px": round(ev["median"], 2) if ev else "",
                    "max_px": round(ev["max"], 2) if ev else "",
                    "workflow_wall_s": round(wall, 1),
                })  # fmt: skip
            print(rows[-2], rows[-1], flush=True)
    with open(args.out / "summary.csv", "w", newline="") as fh:
        w = csv.DictWriter(fh, fieldnames=list(rows[0]))
        w.writeheader()
        w.writerows(rows)
    cols = list(rows[0])
    print("| " + " | ".join(cols) + " |\n|" + "---|" * len(cols))
    for r in rows:
        print("| " + " | ".join(str(r[c]) for c in cols) + " |")


if __name__ == "__main__":
    main()
