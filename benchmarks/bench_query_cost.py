"""Query cost against maps of growing size: `index` vs the paper's random search (`paper`).

For each finished large-map run of ``bench_scaling.py --keep`` (map + index built), the real
workflow registers two queries once per strategy (only the registration rules rerun: the map and
the index do not depend on ``register``):

* ``q0``: the large map's own SWIR query (inside the map, with dense truth);
* ``outside``: a query of another city (the default demo's ``outside`` cube by default), which
  must end ``not_found``.

Time to a decision = query band + the slowest part's search (the parts are parallel jobs) + the
fusion, from the run's ``registration.json`` timings; CPU = the sum over band, parts and fusion.
The outside query's cost is bounded by the candidate budget: ``register.index.top_candidates``
(8) and ``max_seconds``, ``register.paper.max_candidates`` (200) and ``max_seconds`` (600).

    python benchmarks/bench_query_cost.py --runs /work/scale_small/run_2048 ... \
        --outside /path/to/results/demo/queries/outside.hdr
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time
from pathlib import Path

import yaml

REPO = Path(__file__).resolve().parents[1]


def decision(reg: dict) -> tuple[float, float]:
    """(time to a decision with parallel parts, CPU seconds) from registration.json timings."""
    t = reg.get("timings_s") or {}
    parts = [float(v) for v in (t.get("search_parts") or {}).values()]
    band, fuse = float(t.get("query_band") or 0.0), float(t.get("fuse_total") or 0.0)
    return band + (max(parts) if parts else 0.0) + fuse, band + sum(parts) + fuse


def outcome(reg: dict, truth_tif: str, map_px: float, bound_px: float = 5.0) -> str:
    """``success`` when the registration's homography puts the query's pixels within
    ``bound_px`` map pixels of the truth at the median (the evaluation's own error field; the
    run's evaluation.json is not rerun here: it would wait for the products), else ``missed``."""
    from georeg.report.evaluation import error_field, error_stats, map_xy, read_truth

    if reg.get("status") != "registered" or not reg.get("homography"):
        return "missed"
    tx, ty = read_truth(truth_tif)
    x, y = map_xy(reg["homography"], tx.shape[1], tx.shape[0])
    median = error_stats(error_field(x, y, tx, ty), map_px).get("px", {}).get("median")
    return "success" if median is not None and median <= bound_px else "missed"


def run(work: Path, cfg: dict, queries: list[str]) -> float:
    p = work / "query_cost.yaml"
    p.write_text(yaml.safe_dump(cfg))
    targets = [f"results/queries/{q}/registration.json" for q in queries]
    # the workflow copy bench_scaling ran (``<work>/src``), so the map and index stay up to date
    src = work.parent / "src" if (work.parent / "src" / "Snakefile").exists() else REPO
    env = {
        **os.environ,
        "PYTHONPATH": os.pathsep.join([str(src), os.environ.get("PYTHONPATH", "")]),
    }
    cmd = [sys.executable, "-m", "snakemake", "-s", str(src / "Snakefile"), "-d", str(work),
           "--cores", "2", *targets, "--configfile", str(p)]  # fmt: skip
    t0 = time.perf_counter()
    proc = subprocess.run(cmd, capture_output=True, text=True, env=env)
    if proc.returncode:
        sys.exit(f"workflow failed in {work}:\n{proc.stderr[-3000:]}")
    return time.perf_counter() - t0


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawTextHelpFormatter)
    ap.add_argument("--runs", type=Path, nargs="+", required=True, help="bench_scaling run dirs")
    ap.add_argument("--outside", required=True, help="a query cube of another place (.hdr)")
    ap.add_argument("--strategies", nargs="+", default=["index", "paper"])
    ap.add_argument("--out", type=Path, default=REPO / "benchmarks/out/bench_query_cost.jsonl")
    a = ap.parse_args()
    rows = []
    for work in a.runs:
        base = yaml.safe_load((work / "bench.yaml").read_text())
        grid = json.loads((work / "results/map/grid.json").read_text())
        mpx = grid["width"] * grid["height"] / 1e6
        base["queries"]["outside"] = {"image": a.outside, "band": "1200nm", "gsd_m": 0.8}
        for strategy in a.strategies:
            cfg = base | {"register": {"strategy": strategy}}
            wall = run(work, cfg, ["q0", "outside"])
            for q in ("q0", "outside"):
                reg = json.loads((work / f"results/queries/{q}/registration.json").read_text())
                dec, cpu = decision(reg)
                row = {"map_mpx": round(mpx, 1), "strategy": strategy, "query": q,
                       "status": reg["status"], "decision_s": round(dec, 2), "cpu_s": round(cpu, 2),
                       "candidates_tried": reg.get("candidates_tried"), "workflow_wall_s": round(wall, 1)}  # fmt: skip
                truth = base["queries"][q].get("truth") if q == "q0" else None
                row["outcome"] = outcome(reg, truth, abs(grid["transform"][0])) if truth else None
                rows.append(row)
                print(json.dumps(row), flush=True)
    a.out.parent.mkdir(parents=True, exist_ok=True)
    with open(a.out, "a") as f:
        for r in rows:
            f.write(json.dumps(r) + "\n")
    print(
        "\n| map | query | index: decision s (CPU s, tried) | paper: decision s (CPU s, tried) "
        "| paper / index |\n|---:|---|---|---|---:|"
    )
    for mpx in sorted({r["map_mpx"] for r in rows}):
        for q in ("q0", "outside"):
            by = {r["strategy"]: r for r in rows if r["map_mpx"] == mpx and r["query"] == q}
            cells = [f"{by[s]['status']} {by[s]['decision_s']:.1f} ({by[s]['cpu_s']:.1f}, "
                     f"{by[s]['candidates_tried']})" if s in by else "-" for s in ("index", "paper")]  # fmt: skip
            ratio = (by["paper"]["decision_s"] / by["index"]["decision_s"]
                     if "paper" in by and "index" in by and by["index"]["decision_s"] else None)  # fmt: skip
            print(
                f"| {mpx:.0f} Mpx | {q} | {cells[0]} | {cells[1]} | "
                f"{'-' if ratio is None else f'{ratio:.1f}x'} |"
            )


if __name__ == "__main__":
    main()
