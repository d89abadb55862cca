"""Where the default run's time goes: per-rule CPU, wall and memory, and its critical path.

    python benchmarks/bench_default_run.py run --dir /tmp/default_run [--rev HEAD] [--nice 5]
    python benchmarks/bench_default_run.py table /tmp/default_run [--json out.json]

``run`` clones the repository at ``--rev`` into ``--dir`` (a fresh clone, as a new user has) and
runs ``snakemake --cores 2`` there under ``/usr/bin/time -v`` (wall, peak RSS of any process),
noting the load average before and after; then prints the table. ``table`` reads a finished
run: the Snakemake ``benchmark:`` file of every job (``benchmarks/<stage>/<rule>[/<wildcards>].tsv``:
wall ``s``, ``cpu_time``, ``max_rss``) and the run's Snakemake log (job start and end times, each
job's inputs and outputs). The critical path is walked back from the job that finished last: at
each step the job that made one of its inputs and finished last; a gap between a job's start
and the end of that input's job is time the job waited for a core.
"""

from __future__ import annotations

import argparse
import csv
import json
import os
import re
import subprocess
import sys
import time
from datetime import datetime
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parents[1]

_STAMP = re.compile(r"^\[(\w{3} \w{3} +\d+ \d\d:\d\d:\d\d \d{4})\]$")
_HEAD = re.compile(r"^(?:local)?(?:rule|checkpoint) (\w+):$")
_DONE = re.compile(r"^Finished jobid: (\d+) \(Rule: (\w+)\)")


def _stamp(text: str) -> float:
    return datetime.strptime(text, "%a %b %d %H:%M:%S %Y").timestamp()


def parse_log(path: Path) -> dict[int, dict[str, Any]]:
    """Jobs of a Snakemake log: rule, start, end (epoch s), inputs, outputs, wildcards."""
    jobs: dict[int, dict[str, Any]] = {}
    stamp = None
    cur: dict[str, Any] | None = None
    for line in path.read_text(errors="replace").splitlines():
        m = _STAMP.match(line.strip())
        if m:
            stamp = _stamp(m[1])
            cur = None
            continue
        m = _HEAD.match(line.strip())
        if m and stamp is not None:
            cur = {"rule": m[1], "start": stamp, "inputs": [], "outputs": [], "wildcards": ""}
            continue
        m = _DONE.match(line.strip())
        if m and stamp is not None:
            jobs.setdefault(int(m[1]), {"rule": m[2]})["end"] = stamp
            continue
        if cur is not None:
            s = line.strip()
            if s.startswith("input:"):
                cur["inputs"] = [x.strip() for x in s[6:].split(",") if x.strip()]
            elif s.startswith("output:"):
                cur["outputs"] = [x.strip() for x in s[7:].split(",") if x.strip()]
            elif s.startswith("wildcards:"):
                cur["wildcards"] = s[10:].strip()
            elif s.startswith("threads:"):
                cur["threads"] = int(s[8:])
            elif s.startswith("jobid:"):
                jid = int(s[6:])
                cur.update(jobs.get(jid, {}))
                jobs[jid] = cur  # later lines (wildcards) still land in it
    return {j: v for j, v in jobs.items() if "start" in v and "end" in v}


def read_benchmarks(run: Path) -> list[dict[str, Any]]:
    """One row per benchmark file: rule, wildcards, wall s, CPU s, max RSS MB."""
    rows = []
    for p in sorted((run / "benchmarks").rglob("*.tsv")):
        rel = p.relative_to(run / "benchmarks").parts
        rule = rel[1] if len(rel) > 2 else p.stem
        with p.open() as f:
            recs = list(csv.DictReader(f, delimiter="\t"))
        if not recs:
            continue
        r = recs[-1]

        rows.append(
            {
                "stage": rel[0],
                "rule": rule,
                "wildcards": p.stem if len(rel) > 2 else "",
                "wall_s": _num(r, "s"),
                "cpu_s": _num(r, "cpu_time"),
                "max_rss_mb": _num(r, "max_rss"),
            }
        )
    return rows


def _num(rec: dict[str, str], key: str) -> float:
    try:
        return float(rec.get(key, "nan"))
    except ValueError:
        return float("nan")


def per_rule(rows: list[dict[str, Any]]) -> list[dict[str, Any]]:
    """Rows summed by rule (CPU and wall), max RSS over its jobs; largest CPU first."""
    acc: dict[str, dict[str, Any]] = {}
    for r in rows:
        a = acc.setdefault(
            r["rule"], {"rule": r["rule"], "jobs": 0, "cpu_s": 0.0, "wall_s": 0.0, "max_rss_mb": 0.0}
        )
        a["jobs"] += 1
        a["cpu_s"] += r["cpu_s"]
        a["wall_s"] += r["wall_s"]
        a["max_rss_mb"] = max(a["max_rss_mb"], r["max_rss_mb"])
    return sorted(acc.values(), key=lambda a: -a["cpu_s"])


def dependencies(jobs: dict[int, dict[str, Any]]) -> dict[int, set[int]]:
    """Job -> the jobs that made its inputs (exact paths, else directory / prefix matches)."""
    producer = {o: j for j, v in jobs.items() for o in v.get("outputs", [])}
    deps: dict[int, set[int]] = {}
    for j, v in jobs.items():
        d = {producer[i] for i in v.get("inputs", []) if i in producer and producer[i] != j}
        for i in v.get("inputs", []):
            if i in producer:
                continue
            d |= {
                pj
                for o, pj in producer.items()
                if pj != j and (i.startswith(o.rstrip("/") + "/") or o.startswith(i.rstrip("/") + "/"))
            }
        deps[j] = d
    return deps


def schedule(jobs: dict[int, dict[str, Any]], cost: dict[int, float], cores: int = 2) -> dict[str, float]:
    """Wall of the run on ``cores`` idle cores if every job took its measured CPU seconds.

    List scheduling, longest remaining chain first; a job asking for N threads holds N cores for
    CPU / N seconds (perfect scaling: optimistic for it). Also the two lower bounds: the longest
    chain of CPU seconds and the summed CPU over the cores.
    """
    deps = dependencies(jobs)
    users: dict[int, list[int]] = {j: [] for j in jobs}
    for j, d in deps.items():
        for p in d:
            users[p].append(j)
    thr = {j: max(1, min(cores, int(jobs[j].get("threads", 1)))) for j in jobs}
    dur = {j: cost.get(j, 0.0) / thr[j] for j in jobs}
    tail: dict[int, float] = {}

    def chain(j: int) -> float:
        if j not in tail:
            tail[j] = dur[j] + max((chain(u) for u in users[j]), default=0.0)
        return tail[j]

    for j in jobs:
        chain(j)
    done: dict[int, float] = {}
    running: list[tuple[float, int]] = []
    free, now = cores, 0.0
    waiting = set(jobs)
    while waiting or running:
        ready = sorted((j for j in waiting if deps[j] <= done.keys()), key=lambda j: -tail[j])
        started = False
        for j in ready:
            if thr[j] <= free:
                free -= thr[j]
                running.append((now + dur[j], j))
                waiting.discard(j)
                started = True
        if started:
            continue
        if not running:
            break  # unsatisfiable dependencies (should not happen)
        running.sort()
        now, j = running.pop(0)
        free += thr[j]
        done[j] = now
    return {
        "estimated_wall_s": now,
        "longest_chain_s": max(tail.values(), default=0.0),
        "cpu_over_cores_s": sum(cost.values()) / cores,
    }


def critical_path(jobs: dict[int, dict[str, Any]]) -> list[dict[str, Any]]:
    """The chain of jobs that ended the run: from the last job back through its latest input."""
    if not jobs:
        return []
    producer = {o: j for j, v in jobs.items() for o in v.get("outputs", [])}
    real = {j: v for j, v in jobs.items() if v["rule"] != "all"}
    last = max(real or jobs, key=lambda j: jobs[j]["end"])
    chain = []
    j: int | None = last
    while j is not None:
        v = jobs[j]
        chain.append({"jobid": j, **{k: v[k] for k in ("rule", "wildcards", "start", "end")}})
        prev = [producer[i] for i in v.get("inputs", []) if i in producer and producer[i] != j]
        # directory outputs and checkpoint-added inputs: fall back to prefix matches
        if not prev:
            prev = [
                pj
                for i in v.get("inputs", [])
                for o, pj in producer.items()
                if pj != j and (i.startswith(o.rstrip("/") + "/") or o.startswith(i.rstrip("/") + "/"))
            ]
        j = max(prev, key=lambda p: jobs[p]["end"]) if prev else None
    return chain[::-1]


def table(run: Path) -> dict[str, Any]:
    logs = sorted((run / ".snakemake" / "log").glob("*.snakemake.log"))
    jobs = parse_log(logs[-1]) if logs else {}
    rows = read_benchmarks(run)
    rules = per_rule(rows)
    t0 = min((v["start"] for v in jobs.values()), default=0.0)
    t1 = max((v["end"] for v in jobs.values()), default=0.0)
    chain = critical_path(jobs)
    bench = {(r["rule"], r["wildcards"]): r for r in rows}
    cost = {}
    for j, v in jobs.items():
        b = bench.get((v["rule"], _wc_stem(v.get("wildcards", ""))))
        cost[j] = b["cpu_s"] if b else 0.0
    for c in chain:
        b = bench.get((c["rule"], _wc_stem(c["wildcards"])))
        c["cpu_s"] = b["cpu_s"] if b else float("nan")
    out = {
        "run": str(run),
        "log_wall_s": t1 - t0,
        "cpu_total_s": sum(r["cpu_s"] for r in rows),
        "jobs": len(rows),
        "rules": rules,
        "idle_estimate": schedule(jobs, cost, 2),
        "critical_path": [{**c, "t_start": c["start"] - t0, "t_end": c["end"] - t0} for c in chain],
    }
    time_file = Path(str(run) + ".time")
    if time_file.exists():
        out["time_v"] = time_file.read_text()
    return out


def _wc_stem(wc: str) -> str:
    """The benchmark file stem of a job's wildcards (``name=demo, part=0`` -> ``demo_0``)."""
    return "_".join(x.split("=", 1)[1] for x in wc.split(", ") if "=" in x)


def print_table(t: dict[str, Any]) -> None:
    print(f"run {t['run']}: {t['jobs']} jobs, CPU {t['cpu_total_s']:.1f} s summed over jobs, "
          f"wall {t['log_wall_s']:.0f} s (first job start to last job end, 1 s resolution)\n")
    e = t["idle_estimate"]
    print(f"idle 2-core estimate from the per-job CPU: wall {e['estimated_wall_s']:.0f} s "
          f"(lower bounds: longest chain {e['longest_chain_s']:.0f} s, CPU / 2 cores "
          f"{e['cpu_over_cores_s']:.0f} s)\n")
    print("| rule | jobs | CPU s | wall s (sum) | max RSS MB |")
    print("|---|---:|---:|---:|---:|")
    for r in t["rules"]:
        print(f"| {r['rule']} | {r['jobs']} | {r['cpu_s']:.1f} | {r['wall_s']:.1f} | {r['max_rss_mb']:.0f} |")
    print("\ncritical path (start-end s from the first job; CPU s of the job):\n")
    print("| rule | wildcards | start | end | wall | CPU s |")
    print("|---|---|---:|---:|---:|---:|")
    for c in t["critical_path"]:
        print(f"| {c['rule']} | {c['wildcards']} | {c['t_start']:.0f} | {c['t_end']:.0f} | "
              f"{c['t_end'] - c['t_start']:.0f} | {c['cpu_s']:.1f} |")


def run_fresh(dest: Path, rev: str, nice: int, cores: int) -> None:
    """A fresh clone at ``rev`` and ``snakemake --cores N`` in it, timed by /usr/bin/time -v."""
    if dest.exists():
        raise SystemExit(f"{dest} exists: give a new --dir")
    subprocess.run(["git", "clone", "-q", str(ROOT), str(dest)], check=True)
    subprocess.run(["git", "-C", str(dest), "checkout", "-q", rev], check=True)
    env = {**os.environ, "PYTHONPATH": str(dest)}
    load0 = os.getloadavg()
    t0 = time.time()
    cmd = ["/usr/bin/time", "-v", "-o", f"{dest}.time", "nice", "-n", str(nice),
           "snakemake", "--cores", str(cores)]
    with open(f"{dest}.log", "w") as log:
        rc = subprocess.run(cmd, cwd=dest, env=env, stdout=log, stderr=subprocess.STDOUT).returncode
    wall = time.time() - t0
    load1 = os.getloadavg()
    Path(f"{dest}.load").write_text(
        json.dumps({"rc": rc, "wall_s": wall, "load_before": load0, "load_after": load1})
    )
    print(f"rc {rc}, wall {wall:.0f} s, load {load0[0]:.1f} -> {load1[0]:.1f}", file=sys.stderr)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    sub = ap.add_subparsers(dest="cmd", required=True)
    r = sub.add_parser("run")
    r.add_argument("--dir", type=Path, required=True)
    r.add_argument("--rev", default="HEAD")
    r.add_argument("--nice", type=int, default=5)
    r.add_argument("--cores", type=int, default=2)
    r.add_argument("--json", type=Path)
    t = sub.add_parser("table")
    t.add_argument("run", type=Path)
    t.add_argument("--json", type=Path)
    a = ap.parse_args()
    if a.cmd == "run":
        run_fresh(a.dir, a.rev, a.nice, a.cores)
        run = a.dir
    else:
        run = a.run
    tab = table(run)
    print_table(tab)
    if a.json:
        a.json.write_text(json.dumps(tab, indent=1))


if __name__ == "__main__":
    main()
