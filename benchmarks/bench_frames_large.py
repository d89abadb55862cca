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


def one(map_dir: str, case: str, fid: str, mode: str, extra: str | None, index: str = "index") -> dict:
    """Localise one frame of ``case`` on the padded map ``map_dir``; a JSON record."""
    import cv2
    import numpy as np

    from georeg.frames.localize import MapSources, evaluate, localize_frame

    cv2.setNumThreads(1)

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
            "score": (rec.get("verification") or {}).get("score"), "extra": extra,
            "loadavg": float(np.round(os.getloadavg()[0], 2))}  # fmt: skip


def run(a: argparse.Namespace) -> None:
    out = Path(a.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    frames = [(c, f) for c in a.cases for f in CASES[c] if not a.frames or f in a.frames]
    for case, fid in frames:
        for mode in a.coarse:
            cmd = [sys.executable, __file__, "one", a.map, case, fid, mode, a.extra or "{}", "--index", a.index]
            env = {**os.environ, **{v: "1" for v in THREAD_VARS}}
            r = subprocess.run(cmd, capture_output=True, text=True, env=env)
            line = r.stdout.strip().splitlines()[-1] if r.returncode == 0 and r.stdout.strip() else None
            if line is None:
                print(f"FAILED {case}/{fid} {mode}: {r.stderr[-2000:]}", file=sys.stderr)
                continue
            with out.open("a") as f:
                f.write(line + "\n")
            d = json.loads(line)
            print(f"{d['map']} {d['frame']} {mode}: {d['status']} h {d['h_err_m']} "
                  f"cpu {d['cpu_s']:.1f} s rss {d['peak_rss_mb']:.0f} MB {d['timings_s']}", flush=True)  # fmt: skip


def table(a: argparse.Namespace) -> None:
    import numpy as np

    rows = [json.loads(x) for p in a.files for x in Path(p).read_text().splitlines() if x.strip()]
    # the last record of each (map, index, frame, mode, extra): a rerun replaces an earlier one
    rows = list({(r["map"], r.get("k", 1000), r["frame"], r["mode"], r.get("extra") or "{}"): r
                 for r in rows}.values())  # fmt: skip
    print("| map | Mpx | coarse | in-map frames registered | errors m | CPU s / in-map frame (median) | "
          "peak RSS MB (in-map) | from elsewhere: status, CPU s, RSS MB |")
    print("|---|---:|---|---|---|---:|---:|---|")
    keys = sorted({(r["map"], r["mpx"], r["mode"], r.get("k", 1000), r.get("extra") or "{}") for r in rows},
                  key=lambda k: (k[0].split("_")[0], k[1], k[2], k[3], k[4]))  # fmt: skip
    for mp, mpx, mode, k, ex in keys:
        rs = [r for r in rows if (r["map"], r["mode"], r.get("k", 1000), r.get("extra") or "{}") == (mp, mode, k, ex)]
        ins = [r for r in rs if r["expected"] == "registered"]
        out = [r for r in rs if r["expected"] != "registered"]
        ok = sum(r["status"] == "registered" for r in ins)
        errs = " / ".join(f"{r['h_err_m']:.2f}" if r["h_err_m"] is not None else "-" for r in ins)
        cpu = " / ".join(f"{r['cpu_s']:.1f}" for r in ins)
        med = f"{np.median([r['cpu_s'] for r in ins]):.1f} ({cpu})" if ins else "-"
        rss = f"{max(r['peak_rss_mb'] for r in ins):.0f}" if ins else "-"
        far = "; ".join(f"{r['status']}, {r['cpu_s']:.1f}, {r['peak_rss_mb']:.0f}" for r in out) or "-"
        print(f"| {mp} | {mpx:.0f} | {mode} (k {k}{'' if ex == '{}' else ', ' + ex}) | {ok}/{len(ins)} | {errs} "
              f"| {med} | {rss} | {far} |")  # fmt: skip


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
    p = sub.add_parser("run")
    p.add_argument("--map", required=True)
    p.add_argument("--cases", nargs="+", default=["odm", "ngi"])
    p.add_argument("--coarse", nargs="+", default=["index", "plain"])
    p.add_argument("--frames", nargs="+", help="frame ids (default: every frame of the cases)")
    p.add_argument("--extra", help="JSON overrides of frame_loc")
    p.add_argument("--index", default="index", help="index dir of the map (e.g. index_k6400)")
    p.add_argument("--out", required=True)
    p = sub.add_parser("table")
    p.add_argument("files", nargs="+")
    a = ap.parse_args()
    if a.cmd == "one":
        print(json.dumps(one(a.map, a.case, a.fid, a.mode, a.extra, a.index)))
    elif a.cmd == "run":
        run(a)
    else:
        table(a)


if __name__ == "__main__":
    main()
