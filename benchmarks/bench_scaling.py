"""Scaling benchmark: map preparation, index build and query registration on growing maps.

For each map side, ``georeg.demo.largemap`` writes a large synthetic map (chunked orthophoto +
VRT, one LAZ per chunk, one SWIR query), then the **real workflow** runs on it::

    snakemake -s Snakefile --cores N -d <work>/run_<size> --configfile <work>/map_<size>/map.yaml \
        <map, index and registration targets>

Every job is measured by a ``sitecustomize`` hook put on ``PYTHONPATH`` (nothing in the workflow
changes): at exit, each Python process that runs a rule script (``.snakemake/scripts/tmp*.<rule>.py``)
or a Snakemake job wrapper (``--target-jobs <rule>:...``, e.g. on a cluster) appends its wall time, user+system CPU
(``resource.getrusage(RUSAGE_SELF)``) and peak RSS (``ru_maxrss``; of its own children too) to a
JSON-lines file. Per stage we report: jobs, wall span (first job start to last job end), summed
job wall and CPU, the largest peak RSS of any job, and per-tile / per-Mpx costs.

    source /work/venv/bin/activate
    nice -n 10 python benchmarks/bench_scaling.py --sizes-m 2048 4096 8192 --cores 2
    python benchmarks/bench_scaling.py --table benchmarks/out/bench_scaling.jsonl   # table only

Results are appended to ``benchmarks/out/bench_scaling.jsonl`` (one record per map size) and
printed as the Markdown table of docs/SCALING.md. Generated maps and runs are deleted after each
size unless ``--keep``. A long run that was stopped (the 1 Gpx map takes hours) continues where it
stopped with ``--resume`` (same ``--work``): the map is not generated again, Snakemake keeps its
finished jobs, and the rusage log and the wall time add up over the sessions.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import platform
import shutil
import subprocess
import sys
import time
from collections import defaultdict
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
OUT = ROOT / "benchmarks" / "out" / "bench_scaling.jsonl"

STAGES = {
    "map": ("map_grid", "map_tile_ortho", "map_tile_elevation", "map_mosaic", "map_overview"),
    "index": ("tile_features", "vocabulary", "word_quantizer", "tile_words", "build_index"),
    "register": (
        "query_band",
        "search_part",
        "fuse_parts",
        "refine_registration",
        "evaluate_query",
    ),
}
PER_TILE = ("map_tile_ortho", "map_tile_elevation", "tile_features", "tile_words")
#: the per-tile rules of the Slurm group `tiles` (tile_words is modelled apart, at k = 100,000)
TILE_CHAIN = ("map_tile_ortho", "map_tile_elevation", "tile_features")
SCRIPT_RULE = {  # scripts/<name>.py -> rule name, where they differ
    "index_tile_features": "tile_features",
    "index_vocabulary": "vocabulary",
    "index_build": "build_index",
    "index_word_quantizer": "word_quantizer",
    "index_tile_words": "tile_words",
    "register_query_band": "query_band",
    "register_search_part": "search_part",
    "register_fuse_parts": "fuse_parts",
    "register_refine": "refine_registration",
}

HOOK = r"""
import atexit, json, os, resource, sys, time
_LOG = os.environ.get("GEOREG_RUSAGE_LOG")
_T0 = time.time()
def _georeg_rusage_dump():
    argv = list(sys.argv)
    kind = rule = None
    a0 = os.path.basename(argv[0]) if argv else ""
    if ".snakemake" in (argv[0] if argv else "") and a0.startswith("tmp") and a0.endswith(".py"):
        kind, rule = "script", a0.split(".")[-2]  # mapped to the rule name by SCRIPT_RULE
    elif "--target-jobs" in argv:
        i = argv.index("--target-jobs")
        kind, rule = "wrapper", argv[i + 1].split(":")[0] if i + 1 < len(argv) else "?"
    elif os.environ.get("GEOREG_RUSAGE_STAGE"):
        kind, rule = "step", os.environ["GEOREG_RUSAGE_STAGE"]
    if kind is None:
        return
    s, c = resource.getrusage(resource.RUSAGE_SELF), resource.getrusage(resource.RUSAGE_CHILDREN)
    rec = {"kind": kind, "rule": rule, "pid": os.getpid(), "start": _T0, "end": time.time(),
           "cpu_s": s.ru_utime + s.ru_stime, "child_cpu_s": c.ru_utime + c.ru_stime,
           "maxrss_mb": s.ru_maxrss / 1024, "child_maxrss_mb": c.ru_maxrss / 1024}
    with open(_LOG, "a") as f:
        f.write(json.dumps(rec) + "\n")
if _LOG:
    atexit.register(_georeg_rusage_dump)
"""


def _env(hook_dir: Path, log: Path, src: Path, stage: str | None = None) -> dict[str, str]:
    env = dict(os.environ)
    env["PYTHONPATH"] = os.pathsep.join(
        [str(hook_dir), str(src), env.get("PYTHONPATH", "")]
    ).rstrip(os.pathsep)
    env["GEOREG_RUSAGE_LOG"] = str(log)
    env.pop("GEOREG_RUSAGE_STAGE", None)
    if stage:
        env["GEOREG_RUSAGE_STAGE"] = stage
    return env


def _targets() -> list[str]:
    return [
        *(f"results/map/mosaic/{lyr}.vrt" for lyr in ("ortho", "dsm", "dtm", "ndsm", "density")),
        "results/map/overview.png",
        "results/index/map/meta.json",
        "results/queries/q0/registration.json",
        "results/queries/q0/geolocation.tif",
        "results/queries/q0/evaluation.json",
    ]


def _du_mb(path: Path) -> float:
    return sum(f.stat().st_size for f in path.rglob("*") if f.is_file()) / 1e6


def summarise(recs: list[dict], n_tiles: int, mpx: float) -> dict:
    """Per rule and per stage: jobs, wall span, summed wall and CPU, peak RSS, per-tile costs."""
    by_rule: dict[str, list[dict]] = defaultdict(list)
    wrappers: dict[str, list[dict]] = defaultdict(list)
    for r in recs:
        r["rule"] = SCRIPT_RULE.get(r["rule"], r["rule"])
        (by_rule if r["kind"] in ("script", "step") else wrappers)[r["rule"]].append(r)
    rules = {}
    for rule, rs in by_rule.items():
        w = wrappers.get(rule, [])
        rules[rule] = {
            "jobs": len(rs),
            "wall_sum_s": round(sum(r["end"] - r["start"] for r in rs), 2),
            "cpu_s": round(sum(r["cpu_s"] + r["child_cpu_s"] for r in rs), 2),
            "peak_rss_mb": round(max(max(r["maxrss_mb"], r["child_maxrss_mb"]) for r in rs), 1),
            "wrapper_cpu_s": round(sum(r["cpu_s"] for r in w), 2),
            "wrapper_peak_rss_mb": round(max((r["maxrss_mb"] for r in w), default=0.0), 1),
            "start": min(r["start"] for r in rs),
            "end": max(r["end"] for r in rs),
        }
        if rule in PER_TILE and n_tiles:
            rules[rule]["cpu_per_tile_s"] = round(rules[rule]["cpu_s"] / n_tiles, 3)
    stages = {}
    for stage, names in {"generate": ("generate",), **STAGES}.items():
        rs = [rules[n] for n in names if n in rules]
        if not rs:
            continue
        st = {
            "jobs": sum(r["jobs"] for r in rs),
            "span_s": round(max(r["end"] for r in rs) - min(r["start"] for r in rs), 1),
            "wall_sum_s": round(sum(r["wall_sum_s"] for r in rs), 1),
            "cpu_s": round(sum(r["cpu_s"] for r in rs), 1),
            "peak_rss_mb": max(r["peak_rss_mb"] for r in rs),
            "cpu_per_mpx_s": round(sum(r["cpu_s"] for r in rs) / mpx, 2),
        }
        stages[stage] = st
    for r in rules.values():
        r.pop("start"), r.pop("end")
    return {"rules": rules, "stages": stages}


def snapshot(work: Path) -> Path:
    """Copy the workflow and the library to ``work/src``: the run is immune to concurrent edits."""
    src = work / "src"
    shutil.rmtree(src, ignore_errors=True)
    src.mkdir(parents=True)
    ignore = shutil.ignore_patterns("__pycache__", "*.pyc")
    for name in ("workflow", "scripts", "config", "georeg"):
        shutil.copytree(ROOT / name, src / name, ignore=ignore)
    shutil.copy2(ROOT / "Snakefile", src / "Snakefile")
    return src


def run_size(size_m: float, args) -> dict:
    work = Path(args.work)
    src = Path(args.src)
    tag = f"{int(size_m)}"
    mapdir, rundir = work / f"map_{tag}", work / f"run_{tag}"
    hook_dir = work / "hook"
    hook_dir.mkdir(parents=True, exist_ok=True)
    (hook_dir / "sitecustomize.py").write_text(HOOK)
    log = work / f"rusage_{tag}.jsonl"
    gen_done = mapdir / "generate_wall_s.txt"
    resume = args.resume and gen_done.exists()
    if not resume:  # a fresh start; with --resume after a stop, the map and the run are kept
        log.unlink(missing_ok=True)
        for d in (mapdir, rundir):
            shutil.rmtree(d, ignore_errors=True)
        t0 = time.time()
        gen = [sys.executable, "-m", "georeg.demo.largemap", "--out", str(mapdir),
               "--size-m", str(size_m), "--workers", str(args.cores), "--chunk-px", str(args.chunk_px),
               "--lidar-density", str(args.lidar_density)]  # fmt: skip
        subprocess.run(gen, check=True, env=_env(hook_dir, log, src, "generate"), cwd=src,
                       stdout=subprocess.DEVNULL)  # fmt: skip
        # the generator's worker processes exit via os._exit (no atexit): the parent's record
        # holds them as RUSAGE_CHILDREN (CPU summed, peak RSS = the largest child)
        gen_done.write_text(f"{time.time() - t0:.1f}\n")
    t_gen = float(gen_done.read_text())
    cfg = rundir / "bench.yaml"
    rundir.mkdir(parents=True, exist_ok=True)
    cfg.write_text((mapdir / "map.yaml").read_text()
                   + f"vocabulary:\n  k: {args.k}\n  sample_size: {args.sample_size}\n")  # fmt: skip
    smk = [sys.executable, "-m", "snakemake", *_targets(), "-s", str(src / "Snakefile"),
           "--cores", str(args.cores), "-d", str(rundir), "--configfile", str(cfg)]  # fmt: skip
    if resume:  # a stopped run: release its lock, redo its incomplete jobs, keep the finished ones
        subprocess.run(
            [*smk, "--unlock"], cwd=src, capture_output=True, env=_env(hook_dir, log, src)
        )
        smk.append("--rerun-incomplete")
    t1 = time.time()
    p = subprocess.run(smk, env=_env(hook_dir, log, src), cwd=src, capture_output=True, text=True)
    t_smk = time.time() - t1
    wall_file = rundir / "snakemake_wall_s.txt"  # summed over the sessions a resumed run took
    t_smk += float(wall_file.read_text()) if resume and wall_file.exists() else 0.0
    wall_file.write_text(f"{t_smk:.1f}\n")
    if p.returncode:
        sys.stderr.write(p.stdout[-4000:] + p.stderr[-4000:])
        raise SystemExit(f"snakemake failed for size {size_m}")
    recs = [json.loads(line) for line in log.read_text().splitlines() if line.strip()]
    grid = json.loads((rundir / "results/map/grid.json").read_text())
    manifest = json.loads((mapdir / "largemap.json").read_text())
    n_tiles, mpx = len(grid["tiles"]), manifest["megapixels"]
    summ = summarise(recs, n_tiles, mpx)
    reg = json.loads((rundir / "results/queries/q0/registration.json").read_text())
    ev_path = rundir / "results/queries/q0/evaluation.json"
    ev = json.loads(ev_path.read_text()) if ev_path.exists() else {}
    idx_meta = json.loads((rundir / "results/index/map/meta.json").read_text())
    rec = {
        "date": time.strftime("%Y-%m-%d %H:%M"),
        "host": platform.node(),
        "cores": args.cores,
        "load_start": os.getloadavg()[0],
        "size_m": size_m,
        "megapixels": round(mpx, 2),
        "chunks": len(manifest["chunks"]),
        "laz_files": len(manifest["chunks"]),
        "points": sum(c.get("points") or 0 for c in manifest["chunks"]),
        "tiles": n_tiles,
        "features": idx_meta.get("n_features"),
        "vocabulary_k": args.k,
        "generate_wall_s": round(t_gen, 1),
        "snakemake_wall_s": round(t_smk, 1),
        "map_input_mb": {d: round(_du_mb(mapdir / d), 1) for d in ("ortho", "lidar", "queries")},
        "results_mb": {
            d: round(_du_mb(rundir / "results" / d), 1) for d in ("map", "index", "queries")
        },
        "registration": {k: reg.get(k) for k in ("status", "found", "accepted") if k in reg},
        "evaluation": {"outcome": ev.get("outcome"), "error": ev.get("error")},
        **summ,
    }
    if not args.keep:
        shutil.rmtree(mapdir, ignore_errors=True)
        shutil.rmtree(rundir, ignore_errors=True)
    return rec


def table(recs: list[dict]) -> str:
    """Markdown: one row per (map size, stage)."""
    lines = [
        "| map | tiles | stage | jobs | wall span | CPU | CPU / tile | peak RSS (any job) |",
        "|---|---:|---|---:|---:|---:|---:|---:|",
    ]
    for r in recs:
        for stage, s in r["stages"].items():
            per_tile = s["cpu_s"] / r["tiles"] if stage != "generate" else s["cpu_s"] / r["chunks"]
            unit = "" if stage != "generate" else " (chunk)"
            lines.append(
                f"| {r['megapixels']:.0f} Mpx | {r['tiles']} | {stage} | {s['jobs']} | {s['span_s']:.0f} s "
                f"| {s['cpu_s']:.0f} s | {per_tile:.2f} s{unit} | {s['peak_rss_mb']:.0f} MB |"
            )
    lines += ["", "| map | rule | jobs | CPU | CPU / job | wall / job | peak RSS |",
              "|---|---|---:|---:|---:|---:|---:|"]  # fmt: skip
    for r in recs:
        for rule, s in r["rules"].items():
            lines.append(
                f"| {r['megapixels']:.0f} Mpx | {rule} | {s['jobs']} | {s['cpu_s']:.1f} s "
                f"| {s['cpu_s'] / s['jobs']:.2f} s | {s['wall_sum_s'] / s['jobs']:.1f} s "
                f"| {s['peak_rss_mb']:.0f} MB |"
            )
    return "\n".join(lines)


# County-scale model (docs/SCALING.md). Fixed inputs that are not measured here come from
# docs/BENCHMARKS.md "Feature index": k-means k = 100,000 on 10^6 descriptors = 201 s per
# iteration on 2 cores (402 core-s), HNSW word assignment at k = 100,000 = 0.5-1.0 ms per feature
# per core, HNSW graph of the 100,000 words (rule word_quantizer, once) 52 s; features per Mpx:
# 1,030 on the real autzen orthophoto, measured here on the synthetic city (capped by
# features.max_features_per_mpx = 8000). Word assignment runs in the per-tile `tile_words` jobs
# (Slurm group `words`, 64 tiles per job, `group_cores` wide), each paying a process start-up
# (Python, faiss, reading the saved quantizer: WORDS_STARTUP_S, measured in "Feature index").
KMEANS_CORE_S_PER_ITER = 402.0
ASSIGN_MS = (0.5, 1.0)
HNSW_BUILD_S = 52.0
WORDS_GROUP = 64
WORDS_STARTUP_S = 1.5


def estimate(recs: list[dict], gpx: float = 10.0, nodes=(1, 10, 50), cores_per_node: int = 32,
             group: int = 16, group_cores: int = 8, latency_s: float = 30.0,
             kmeans_iters: int = 20, kmeans_threads: int = 8) -> str:  # fmt: skip
    """Markdown: county-scale (``gpx`` gigapixels) cost on N nodes from the largest measured map."""
    r = max(recs, key=lambda x: x["megapixels"])
    rules = r["rules"]
    # per FULL tile: the map's pixels over the 960 x 960 px a full tile adds (edge tiles of a
    # small map are partial, so CPU / tile count would under-estimate a county's full tiles)
    full_tiles = r["megapixels"] * 1e6 / 960**2
    tile_cpu = sum(rules[n]["cpu_s"] for n in TILE_CHAIN if n in rules) / full_tiles
    tile_rss = max(rules[n]["peak_rss_mb"] for n in TILE_CHAIN if n in rules)
    side = math.sqrt(gpx * 1e9)
    per_side = math.ceil((side - 64) / 960)
    tiles = per_side**2
    mpx = gpx * 1e3
    feat_per_mpx_synth = r["features"] / r["megapixels"]
    build_cpu_per_feat = rules["build_index"]["cpu_s"] / r["features"]
    reg_cpu = sum(rules[n]["cpu_s"] for n in STAGES["register"] if n in rules)
    gen_cpu_per_mpx = rules["generate"]["cpu_s"] / r["megapixels"] if "generate" in rules else 0
    kmeans_core_s = KMEANS_CORE_S_PER_ITER * kmeans_iters
    inp = ""
    if isinstance(r["map_input_mb"], dict):  # orthophoto + LiDAR input (records before: a total)
        m_in = r["map_input_mb"]["ortho"] + r["map_input_mb"]["lidar"]
        inp = f"map input (ortho + LAZ) {m_in / r['megapixels'] * mpx / 1e3:,.0f} GB, "
    out = [
        f"Model inputs (largest measured map: {r['megapixels']:.0f} Mpx, {r['tiles']} tiles): "
        f"{tile_cpu:.2f} CPU-s per full 1024 px tile (ortho + elevation + features), peak RSS of a tile job "
        f"{tile_rss:.0f} MB; county = {gpx:.0f} Gpx = {per_side} x {per_side} = {tiles:,} tiles "
        f"of 1024 px (960 px stride); group jobs of {group} tiles on {group_cores} cores, "
        f"{latency_s:.0f} s Slurm latency per job; k-means k = 100,000, {kmeans_iters} "
        f"iterations = {kmeans_core_s / 3600:.1f} core-h on {kmeans_threads} threads.",
        "",
        "| nodes (x 32 cores) | tile stages (map + features) | vocabulary (k = 100,000) "
        "| word assignment, tile_words (1,030 / 8,000 features per Mpx) "
        "| build_index merge, 1 thread | total |",
        "|---:|---:|---:|---:|---:|---:|",
    ]
    for n in nodes:
        concurrent = max(1, n * cores_per_node // group_cores)
        jobs = math.ceil(tiles / group)
        job_wall = group * tile_cpu / group_cores + latency_s
        t_tiles = math.ceil(jobs / concurrent) * job_wall
        t_kmeans = kmeans_core_s / min(kmeans_threads, cores_per_node)
        # word assignment: per tile, in group jobs of WORDS_GROUP tiles, + the HNSW graph once
        w_jobs = math.ceil(tiles / WORDS_GROUP)
        words = []
        for fpm, ms in ((1030, ASSIGN_MS[0]), (8000, ASSIGN_MS[1])):
            per_tile = 0.9216 * fpm * ms / 1e3 + WORDS_STARTUP_S  # a full tile: 960 x 960 px new
            w_job = WORDS_GROUP * per_tile / group_cores + latency_s
            words.append(HNSW_BUILD_S + math.ceil(w_jobs / concurrent) * w_job)
        # the merge (build_index): measured CPU per feature (it included the k = 1000 flat
        # word assignment in the records before tile_words: an upper bound)
        merge = (mpx * 1030 * build_cpu_per_feat, mpx * 8000 * build_cpu_per_feat)
        lo = t_tiles + t_kmeans + words[0] + merge[0]
        hi = t_tiles + t_kmeans + words[1] + merge[1]
        out.append(
            f"| {n} | {t_tiles / 60:.0f} min | {t_kmeans / 60:.0f} min "
            f"| {words[0] / 60:.0f} - {words[1] / 60:.0f} min "
            f"| {merge[0] / 60:.1f} - {merge[1] / 60:.0f} min "
            f"| {lo / 3600:.1f} - {hi / 3600:.1f} h |"
        )
    out += [
        "",
        f"CPU totals: tiles {tiles * tile_cpu / 3600:,.0f} core-h; k-means "
        f"{kmeans_core_s / 3600:.1f} core-h; word assignment {mpx * 1030 * ASSIGN_MS[0] / 1e3 / 3600:.1f}"
        f" - {mpx * 8000 * ASSIGN_MS[1] / 1e3 / 3600:.0f} core-h (+ {tiles * WORDS_STARTUP_S / 3600:.1f} "
        f"core-h of tile_words process start-ups); one query {reg_cpu:.0f} CPU-s "
        f"(measured at k = {r['vocabulary_k']}); generating the synthetic county "
        f"{gen_cpu_per_mpx * mpx / 3600:.0f} core-h. Features per Mpx on the synthetic city: "
        f"{feat_per_mpx_synth:,.0f}. Disk per county (measured MB per Mpx x {mpx:,.0f} Mpx): "
        f"{inp}results/map "
        f"{r['results_mb']['map'] / r['megapixels'] * mpx / 1e3:,.0f} GB, results/index "
        f"{r['results_mb']['index'] / r['megapixels'] * mpx / 1e3:,.0f} GB.",
    ]
    return "\n".join(out)


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--sizes-m", type=float, nargs="+", default=[2048, 4096, 8192])
    p.add_argument("--cores", type=int, default=2)
    p.add_argument("--work", default="/tmp/georeg_scaling")
    p.add_argument("--chunk-px", type=int, default=2048)
    p.add_argument("--lidar-density", type=float, default=0.5)
    p.add_argument("--k", type=int, default=1000, help="vocabulary size (workflow default)")
    p.add_argument("--sample-size", type=int, default=500000)
    p.add_argument("--keep", action="store_true", help="keep the generated maps and runs")
    p.add_argument(
        "--resume",
        action="store_true",
        help="continue a stopped run in --work (same map, same workflow snapshot)",
    )
    p.add_argument("--out", default=str(OUT))
    p.add_argument("--table", help="only print the tables and the estimate of this JSON-lines file")
    p.add_argument("--nodes", type=int, nargs="+", default=[1, 10, 50])
    a = p.parse_args(argv)
    if a.table:
        recs = [json.loads(x) for x in Path(a.table).read_text().splitlines() if x.strip()]
        print(table(recs))
        print()
        print(estimate(recs, nodes=a.nodes))
        return 0
    src = Path(a.work) / "src"
    a.src = str(src if a.resume and (src / "Snakefile").exists() else snapshot(Path(a.work)))
    recs = []
    for size in a.sizes_m:
        rec = run_size(size, a)
        recs.append(rec)
        Path(a.out).parent.mkdir(parents=True, exist_ok=True)
        with open(a.out, "a") as f:
            f.write(json.dumps(rec) + "\n")
        print(table([rec]), flush=True)
    print(table(recs))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
