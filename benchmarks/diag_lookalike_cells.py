"""Diagnostic: at each accepted rift pose of a Pucallpa run, the query cells whose k nearest map
descriptors include one at the pose's place (within reproj_px), and how many of the k score
higher there (other places that look more alike): look-alike poses against true ones.

    python benchmarks/diag_lookalike_cells.py benchmarks/out/s28/puc13_visible.jsonl 13 visible
"""

from __future__ import annotations

import json
import math
import sys
from pathlib import Path

import numpy as np
import yaml

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "benchmarks"))

import bench_devset as bd  # noqa: E402

from georeg.register import rift  # noqa: E402


def nearest_rotation(u8: np.ndarray, scale: float, H: np.ndarray, c: dict) -> tuple:
    """The query's rift features at the rotation nearest the pose's (keypoints, descriptors, A)."""
    best = None
    for _, qxy, qd, A in rift.rotated_features(u8, scale, c):
        M = (H @ np.linalg.inv(A))[:2, :2]
        err = abs(math.degrees(math.atan2(M[1, 0], M[0, 0])))
        if best is None or err < best[0]:
            best = (err, qxy, qd, A)
    return best[1:]


def main() -> int:
    records, seed, kind = sys.argv[1], int(sys.argv[2]), sys.argv[3]
    cfg = yaml.safe_load((ROOT / "config" / "config.yaml").read_text())["register"]
    c = rift.rift_conf({k: v for k, v in (cfg.get("rift") or {}).items() if k != "enabled"})
    scenes, queries = bd.build_pucallpa(seed, True, query=kind)
    scene = {s.name: s for s in scenes}
    query = {q.name: q for q in queries}
    feats: dict[str, tuple] = {}
    for line in open(records):
        r = json.loads(line)
        if r.get("pose_source") != "rift" or r["query"] not in query:
            continue
        q = query[r["query"]]
        sc = scene[q.map_scene]
        u8 = next(iter(q.bands.values()))
        if sc.name not in feats:
            feats[sc.name] = rift.map_features(sc.map_gray, c)
        mxy, md = feats[sc.name]
        kc = rift.n_candidates(len(md), c)
        H = np.diag([1 / sc.map_gsd, -1 / sc.map_gsd, 1.0]) @ np.array(r["H"])
        qxy, qd, A = nearest_rotation(u8, q.gsd / sc.map_gsd, H, c)
        Hc = H @ np.linalg.inv(A)
        idx = rift.MapMatcher(md, c).nearest(qd, kc)
        sims = np.einsum("nd,nkd->nk", qd, md[idx])
        pred = (np.c_[qxy, np.ones(len(qxy))] @ Hc.T)[:, :2]
        at_pose = np.linalg.norm(mxy[idx] - pred[:, None, :], axis=2) <= c["reproj_px"]
        s_pose = np.where(at_pose, sims, -np.inf).max(1)
        rank = (sims > s_pose[:, None]).sum(1)
        cell = rift.cell_key(qxy, c["thin_px"])
        ranks: dict[int, int] = {}
        for i in np.flatnonzero(at_pose.any(1)):
            ranks[int(cell[i])] = min(ranks.get(int(cell[i]), kc), int(rank[i]))
        rk = np.array(list(ranks.values()))
        print(f"{r['query']:34s} {r['outcome']:12s} log10 NFA {r['log10_nfa']:7.2f} cells "
              f"{len(np.unique(cell)):3d} at the pose {len(rk):3d} of which best there "
              f"{int((rk == 0).sum()):3d} (k {kc})", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
