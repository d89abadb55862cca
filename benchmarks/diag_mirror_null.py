"""Diagnostic: a measured null for look-alike structure, the query MIRRORED (no rigid pose can
truly match it) searched by rift on the same map; its best pose at another place than the
accepted one is what look-alike structure alone reaches for this query.

    python benchmarks/diag_mirror_null.py --records benchmarks/out/s27/puc13.jsonl --seed 13
    python benchmarks/diag_mirror_null.py --records benchmarks/out/s28/puc13_visible.jsonl --seed 13 --puc-query visible

For each record accepted by rift (true poses, and false accepts), prints the pose's log10 NFA,
the mirrored query's lowest log10 NFA over all rotations (rift's own acceptance off) and where
its pose lies (footprint-centre distance in query sides from the accepted pose)."""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np
import yaml

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "benchmarks"))

import bench_devset as bd  # noqa: E402

from georeg.register import matching, rift  # noqa: E402


def main() -> int:
    ap = argparse.ArgumentParser()
    ap.add_argument("--records", required=True)
    ap.add_argument("--seed", type=int, default=11)
    ap.add_argument("--puc-query", default="swir")
    a = ap.parse_args()
    cfg = yaml.safe_load((ROOT / "config" / "config.yaml").read_text())["register"]
    acc = cfg["acceptance"]
    rconf = {k: v for k, v in (cfg.get("rift") or {}).items() if k != "enabled"}
    scenes, queries = bd.build_pucallpa(a.seed, True, query=a.puc_query)
    S = {s.name: s for s in scenes}
    Q = {q.name: q for q in queries}
    for line in open(a.records):
        r = json.loads(line)
        if r.get("pose_source") != "rift" or r["query"] not in Q:
            continue
        q = Q[r["query"]]
        sc = S[q.map_scene]
        u8 = next(iter(q.bands.values()))
        n = u8.shape[0]
        H = np.diag([1 / sc.map_gsd, -1 / sc.map_gsd, 1.0]) @ np.array(r["H"])
        off = {**rconf, "null_margin": 0, "confirm_log_p_max": 0, "rescue_log_nfa_max": 0,
               "log_nfa_max": 50.0, "reangle": False, "polish": False}
        m = rift.register(np.ascontiguousarray(np.fliplr(u8)), sc.map_gray, q.gsd / sc.map_gsd,
                          {**acc, "log_nfa_max": 50.0}, off)
        c = np.array([[n / 2, n / 2]])
        d = None
        if m["H"] is not None:
            Hm = m["H"] @ np.array([[-1.0, 0, n - 1], [0, 1, 0], [0, 0, 1]])  # mirrored px -> map px
            d = float(np.linalg.norm(matching.apply_h(Hm, c) - matching.apply_h(H, c))) / (n * q.gsd / sc.map_gsd)
        print(f"{r['query']:36s} {r['outcome']:12s} pose {r['log10_nfa']:7.2f} far-rot null "
              f"{r.get('null_log10_nfa') or float('nan'):6.2f} mirror {m['lowest_log10_nfa']:6.2f} "
              f"at {d if d is None else round(d, 2)} sides", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
