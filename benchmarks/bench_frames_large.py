"""Frames on large maps: seconds (CPU) and peak memory per frame against the map size.

One thread per process (OMP / OpenBLAS / MKL / OpenCV): on the shared 2-core machine more threads
only spin, and CPU seconds then measure the work. Maps: ``python -m georeg.demo.padmap`` (a real frames_dev case padded into a large map of other
real imagery, built once, e.g. under /work/bigmaps/). Every frame runs in its own process
(``one``), so its peak RSS is its own; CPU = user + system of that process around
``localize_frame`` only (loading the index and imports excluded, reported apart). Frames of the
other case are frames from elsewhere (expected ``not_found``).

    python benchmarks/bench_frames_large.py run --map /work/bigmaps/odm_6 --coarse index \
        --out benchmarks/out/frames_large.jsonl
    python benchmarks/bench_frames_large.py table benchmarks/out/frames_large.jsonl
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import subprocess
import sys
import time
from pathlib import Path

DATA = Path(__file__).resolve().parents[1] / ".." / "shared" / "data" / "frames_dev"
CASES = {"odm": ["0136", "0142"], "ngi": ["0182", "0251"]}
#: coarse search modes: the scalable index search (default) and the plain (pre-index) one
MODES = {"index": {}, "plain": {"coarse": {"mode": "plain"}}}
THREAD_VARS = ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS")


def _cpu() -> float:
    r = resource.getrusage(resource.RUSAGE_SELF)
    return r.ru_utime + r.ru_stime


def one(map_dir: str, case: str, fid: str, mode: str, extra: str | None, index: str = "index",
        threads: int = 1) -> dict:  # fmt: skip
    """Localise one frame of ``case`` on the padded map ``map_dir``; a JSON record."""
    import cv2
    import numpy as np

    from georeg.frames.localize import MapSources, evaluate, localize_frame

    cv2.setNumThreads(threads)

    c0, t0 = _cpu(), time.perf_counter()
    m = Path(map_dir)
    maps = MapSources(m / index, m / "ortho.vrt", m / "dsm.vrt")
    truth = json.loads((DATA / case / "truth" / f"{fid}.json").read_text())
    cam = {k: truth["intrinsics"][k] for k in ("fx", "fy", "cx", "cy")}
    cam["dist"] = truth["intrinsics"].get("dist") or [0, 0, 0, 0, 0]
    conf = {**MODES[mode], **json.loads(extra or "{}")}
    rss0 = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    c1, t1 = _cpu(), time.perf_counter()
    rec, _ = localize_frame(str(DATA / case / "queries" / f"{fid}.png"), cam, maps, conf)
    cpu, wall = _cpu() - c1, time.perf_counter() - t1
    ev = evaluate(rec, {**truth, "status": "registered"})
    man = json.loads((m / "padmap.json").read_text())
    return {"map": m.name, "index": index, "k": maps.index.n_words, "map_case": man["case"], "mpx": man["mpx"], "gsd": man["gsd"],
            "frame": f"{case}/{fid}", "expected": "registered" if case == man["case"] else "not_found",
            "mode": mode, "status": rec["status"], "path": rec.get("path"),
            "h_err_m": (ev.get("final") or {}).get("horizontal_m"),
            "pos_err_m": (ev.get("final") or {}).get("position_m"),
            "cpu_s": cpu, "wall_s": wall, "peak_rss_mb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024,
            "rss_before_mb": rss0, "load_cpu_s": c1 - c0, "load_wall_s": t1 - t0,
            "timings_s": rec.get("timings_s"), "coarse": {k: v for k, v in (rec.get("coarse") or {}).items()
                                                          if k != "candidates"},
            "score": (rec.get("verification") or {}).get("score"), "extra": extra, "threads": threads,
            "loadavg": float(np.round(os.getloadavg()[0], 2))}  # fmt: skip


def _limited(cmd: list[str], env: dict, timeout: float | None, mem_gb: float | None) -> tuple:
    """Run ``cmd`` under an optional wall limit (seconds) and address-space limit (GB): (completed
    process or None when it timed out, wall seconds, child CPU seconds)."""
    if mem_gb:
        cmd = ["prlimit", f"--as={int(mem_gb * 2**30)}", "--", *cmd]
    c0 = resource.getrusage(resource.RUSAGE_CHILDREN)
    t0 = time.perf_counter()
    try:
        r = subprocess.run(cmd, capture_output=True, text=True, env=env, timeout=timeout)
    except subprocess.TimeoutExpired:
        r = None
    c1 = resource.getrusage(resource.RUSAGE_CHILDREN)
    cpu = c1.ru_utime + c1.ru_stime - c0.ru_utime - c0.ru_stime
    return r, time.perf_counter() - t0, cpu


def run(a: argparse.Namespace) -> None:
    out = Path(a.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    frames = [(c, f) for c in a.cases for f in CASES[c] if not a.frames or f in a.frames]
    env = {**os.environ, **{v: str(a.threads) for v in THREAD_VARS}}
    for _ in range(a.repeat):
        for case, fid in frames:
            for mode in a.coarse:
                cmd = [sys.executable, __file__, "one", a.map, case, fid, mode, a.extra or "{}", "--index", a.index,
                       "--threads", str(a.threads)]  # fmt: skip
                r, wall, cpu = _limited(cmd, env, a.timeout, a.mem_gb)
                line = (
                    r.stdout.strip().splitlines()[-1]
                    if r is not None and r.returncode == 0 and r.stdout.strip()
                    else None
                )
                if line is None:
                    # a limit hit (or a crash): recorded, not skipped silently
                    why = (
                        f"> {a.timeout:.0f} s wall (killed)"
                        if r is None
                        else (r.stderr or "")[-600:]
                    )
                    print(f"FAILED {case}/{fid} {mode}: {why}", file=sys.stderr)
                    line = json.dumps({"map": Path(a.map).name, "index": a.index, "frame": f"{case}/{fid}",
                                       "mode": mode, "status": "limit" if r is None else "error", "why": why,
                                       "timeout_s": a.timeout, "mem_gb": a.mem_gb, "wall_s_process": wall,
                                       "cpu_s_process": cpu, "threads": a.threads, "extra": a.extra,
                                       "loadavg": round(os.getloadavg()[0], 2)})  # fmt: skip
                    with out.open("a") as f:
                        f.write(line + "\n")
                    continue
                with out.open("a") as f:
                    f.write(line + "\n")
                d = json.loads(line)
                print(f"{d['map']} {d['frame']} {mode} t{a.threads}: {d['status']} h {d['h_err_m']} "
                      f"wall {d['wall_s']:.1f} s cpu {d['cpu_s']:.1f} s rss {d['peak_rss_mb']:.0f} MB "
                      f"load {d['loadavg']} {d['timings_s']}", flush=True)  # fmt: skip


def _cell(rs: list[dict], key: str, fmt: str = "{:.1f}") -> str:
    """Median of ``key`` over the runs ``rs`` of one frame, with the run count when > 1."""
    import numpy as np

    v = [r[key] for r in rs if r.get(key) is not None]
    if not v:
        return "-"
    return fmt.format(float(np.median(v))) + (f" (x{len(v)})" if len(v) > 1 else "")


def table(a: argparse.Namespace) -> None:
    """One row per (map, index, coarse mode, threads, overrides); per frame: status of every run,
    median error, wall and CPU seconds, peak RSS; a limit hit is shown as such."""
    rows = [json.loads(x) for p in a.files for x in Path(p).read_text().splitlines() if x.strip()]
    groups: dict[tuple, dict[str, list[dict]]] = {}
    for r in rows:
        if r["status"] in ("limit", "error"):  # the whole process's seconds until it was stopped
            r.setdefault("wall_s", r.get("wall_s_process"))
            r.setdefault("cpu_s", r.get("cpu_s_process"))
        key = (
            r["map"],
            r.get("index", "index"),
            r["mode"],
            r.get("threads", 1),
            r.get("extra") or "{}",
        )
        groups.setdefault(key, {}).setdefault(r["frame"], []).append(r)
    print(
        "| map | Mpx | coarse (index, threads) | frame | status (runs) | error m (horizontal / 3-D) | wall s | CPU s | "
        "peak RSS MB | load |"
    )
    print("|---|---:|---|---|---|---:|---:|---:|---:|---|")
    for key in sorted(
        groups, key=lambda k: (k[0].split("_")[0], int(k[0].split("_")[-1]), k[1], k[2], k[3])
    ):
        mp, idx, mode, th, ex = key
        for fr, rs in sorted(groups[key].items()):
            mpx = next((r["mpx"] for r in rs if "mpx" in r), None)
            st = ", ".join(
                sorted(
                    {f"{r['status']} x{sum(q['status'] == r['status'] for q in rs)}" for r in rs}
                )
            )
            lim = [r for r in rs if r["status"] in ("limit", "error")]
            note = f" ({lim[0].get('why', '')[:60].strip()})" if lim else ""
            loads = [r.get("loadavg") for r in rs if r.get("loadavg") is not None]
            load = f"{min(loads):.1f}-{max(loads):.1f}" if loads else "-"
            print(f"| {mp} | {'-' if mpx is None else f'{mpx:.0f}'} | {mode} ({idx}, t{th}"
                  f"{'' if ex == '{}' else ', ' + ex}) | {fr} | {st}{note} | {_cell(rs, 'h_err_m', '{:.2f}')} / {_cell(rs, 'pos_err_m', '{:.2f}')} "
                  f"| {_cell(rs, 'wall_s')} | {_cell(rs, 'cpu_s')} | {_cell(rs, 'peak_rss_mb', '{:.0f}')} "
                  f"| {load} |")  # fmt: skip


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    sub = ap.add_subparsers(dest="cmd", required=True)
    p = sub.add_parser("one")
    p.add_argument("map")
    p.add_argument("case")
    p.add_argument("fid")
    p.add_argument("mode")
    p.add_argument("extra", nargs="?")
    p.add_argument("--index", default="index")
    p.add_argument("--threads", type=int, default=1)
    p = sub.add_parser("run")
    p.add_argument("--map", required=True)
    p.add_argument("--cases", nargs="+", default=["odm", "ngi"])
    p.add_argument("--coarse", nargs="+", default=["index", "plain"])
    p.add_argument("--frames", nargs="+", help="frame ids (default: every frame of the cases)")
    p.add_argument("--extra", help="JSON overrides of frame_loc")
    p.add_argument("--index", default="index", help="index dir of the map (e.g. index_k6400)")
    p.add_argument(
        "--threads", type=int, default=1, help="threads per frame process (OMP / BLAS / OpenCV)"
    )
    p.add_argument(
        "--repeat", type=int, default=1, help="runs of every frame (the table takes medians)"
    )
    p.add_argument(
        "--timeout", type=float, help="wall limit per frame process, seconds (recorded as 'limit')"
    )
    p.add_argument(
        "--mem-gb", type=float, help="address-space limit per frame process (prlimit --as)"
    )
    p.add_argument("--out", required=True)
    p = sub.add_parser("table")
    p.add_argument("files", nargs="+")
    a = ap.parse_args()
    if a.cmd == "one":
        print(json.dumps(one(a.map, a.case, a.fid, a.mode, a.extra, a.index, a.threads)))
    elif a.cmd == "run":
        run(a)
    else:
        table(a)


if __name__ == "__main__":
    main()
