"""Where Landsat Pucallpa's misses fail: the hypotheses, or their verification (issue 34).

Per query of ``bench_devset.build_pucallpa`` (positives and blanked maps), rift alone as the
workflow runs it (``rift.register``, default conf), then:

1. **Rift's hypotheses**: every rotation's pose (the poses its rescue re-matches), each judged
   against the truth: is a true pose (<= 5 map px) among the 36 at all, and at what log10 NFA?
2. **A dense hypothesis**: the CFOG correlation of the whole map (``null_scan.scan``, its
   top-spacing log10 p), the peak refined at full resolution (``null_scan.fine_pose``, +-6 px),
   then checked by rift's guided re-match (``rift.confirm`` over all query cells, at the rotation
   with the most hits) against the hit rate of the rift poses >= 25 deg away, times 37 tests:
   the rescue's statistic (``rift.rescue``) for one more pose.

Writes one JSON record per query (``--out``, .jsonl) and prints one line each; ``--analyse``
prints the summary of one or more such files. Diagnostic only: nothing here is in the library.

    nice -n 5 python benchmarks/diag_pucallpa_hypotheses.py --seed 11 --half tuning --out /tmp/h11.jsonl
    python benchmarks/diag_pucallpa_hypotheses.py --analyse /tmp/h11.jsonl /tmp/h13.jsonl
"""

from __future__ import annotations

import argparse
import json
import math
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np
from scipy.spatial import cKDTree
from scipy.stats import binom

sys.path.insert(0, str(Path(__file__).resolve().parent))
import bench_crossspectral as bx  # noqa: E402
import bench_devset as bd  # noqa: E402

from georeg.register import null_scan, rift  # noqa: E402

TRUE_PX = 5.0  # a pose this close to the truth (median, map px) is the true one


def _err(q: Any, sc: Any, H: np.ndarray | None) -> float | None:
    """Median error (map px) of a pose (query px -> map px) at the query's truth grid."""
    if H is None:
        return None
    g = sc.map_gsd
    return bx.judge(q, sc, {"accepted": True, "H": np.diag([g, -g, 1.0]) @ H})["error_px"]


def probe(q: Any, sc: Any, conf: dict[str, Any], feats: tuple[np.ndarray, np.ndarray],
          acc: dict[str, Any]) -> dict[str, Any]:  # fmt: skip
    """The record of one query (see the module docstring)."""
    cap: dict[str, Any] = {}
    orig_rescue, orig_rot = rift.rescue, rift.rotated_features

    def rescue(guided, tests, c):
        cap["guided"] = guided
        return orig_rescue(guided, tests, c)

    def rotated(*a, **k):
        cap["rot"] = list(orig_rot(*a, **k))
        return iter(cap["rot"])

    u8, g = next(iter(q.bands.values())), sc.map_gsd
    t0 = time.perf_counter()
    rift.rescue, rift.rotated_features = rescue, rotated
    try:
        r = rift.register(u8, sc.map_gray, q.gsd / g, acc, conf, feats, q.gsd, g)
    finally:
        rift.rescue, rift.rotated_features = orig_rescue, orig_rot
    nfa = dict(r["per_rotation"])
    poses = [{"angle": o["angle_deg"], "inliers": o["inliers"], "err": _err(q, sc, o["H"]),
              "log10_nfa": nfa.get(o["angle_deg"])} for o in cap.get("guided", [])]  # fmt: skip
    true = [p for p in poses if p["err"] is not None and p["err"] <= TRUE_PX]
    rec: dict[str, Any] = {
        "query": q.name, "half": q.half, "positive": q.truth is not None,
        "rift_accepted": bool(r["accepted"]), "rift_err": _err(q, sc, r["H"]) if r["accepted"] else None,
        "true_rotation_poses": len(true),
        "true_pose_best_log10_nfa": min((p["log10_nfa"] for p in true), default=None),
    }  # fmt: skip
    s = null_scan.scan(u8, q.gsd / g, sc.map_gray)
    if s is not None:
        S, _, _ = null_scan.fine_pose(
            u8, q.gsd / g, sc.map_gray, s["S"], s["angle_deg"], box_px=6.0
        )
        mxy, md = feats
        tree = cKDTree(mxy)
        best: tuple[float, dict[str, Any]] | None = None
        for a, qxy, qd, A in cap.get("rot", []):
            x = rift.confirm(
                S, qxy, qd, A, mxy, md, conf, tree=tree, exclude=np.array([], np.int64)
            )
            if best is None or x["hits"] > best[1]["hits"]:
                best = (a, x)
        guided = cap.get("guided", [])
        lx = None
        if best is not None:
            a, x = best
            far = [o for o in guided if rift._angle_gap(o["angle_deg"], a) >= rift.NULL_FAR_DEG]
            rate = max(rift._disc_ratio(conf),
                       (sum(o["hits"] for o in far) + 1) / (sum(o["cells"] for o in far) + 1))  # fmt: skip
            tail = (
                binom.logsf(x["hits"] - 1, x["cells"], min(rate, 1.0)) / math.log(10)
                if x["hits"]
                else 0.0
            )
            lx = float(tail) + math.log10(len(cap.get("rot", [])) + 1)
            rec.update(scan_hits=x["hits"], scan_cells=x["cells"], scan_hit_rate=rate)
        rec.update(scan_log10_p=s["log10_p"], scan_err=_err(q, sc, S), scan_confirm_log10_nfa=lx)
    rec["seconds"] = time.perf_counter() - t0
    return rec


def analyse(paths: list[str]) -> None:
    """Summary: per half, the misses' true rift poses and scan poses; the lowest chance figures."""
    rows = [json.loads(line) for p in paths for line in Path(p).read_text().splitlines()]
    for half in ("tuning", "checking"):
        hs = [r for r in rows if r["half"] == half]
        if not hs:
            continue
        pos = [r for r in hs if r["positive"]]
        miss = [r for r in pos if not (r["rift_accepted"] and (r["rift_err"] or 1e9) <= TRUE_PX)]
        has_true = [r for r in miss if r["true_rotation_poses"]]
        scan_true = [r for r in miss if (r.get("scan_err") or 1e9) <= TRUE_PX]
        neg = [r for r in hs if not r["positive"]]
        wrong_scan = [r.get("scan_confirm_log10_nfa") for r in pos + neg
                      if r.get("scan_confirm_log10_nfa") is not None
                      and (not r["positive"] or (r.get("scan_err") or 1e9) > 20)]  # fmt: skip
        print(f"{half}: {len(pos)} positives, rift alone misses {len(miss)}; of them a true pose among "
              f"rift's rotation poses: {len(has_true)}; the CFOG scan's refined peak true: "
              f"{len(scan_true)} (confirm log10 NFA "
              f"{sorted(round(r['scan_confirm_log10_nfa'], 1) for r in scan_true if r.get('scan_confirm_log10_nfa') is not None)}); "
              f"lowest confirm log10 NFA of a wrong scan pose (blanked maps incl., {len(wrong_scan)}): "
              f"{min(wrong_scan) if wrong_scan else None}")  # fmt: skip


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawTextHelpFormatter)
    ap.add_argument("--seed", type=int, default=11)
    ap.add_argument("--half", choices=("tuning", "checking", "both"), default="tuning")
    ap.add_argument("--out", help="records (.jsonl)")
    ap.add_argument("--analyse", nargs="+", metavar="FILE", help="summarise records instead")
    a = ap.parse_args(argv)
    if a.analyse:
        analyse(a.analyse)
        return 0
    if not a.out:
        ap.error("--out is required unless --analyse")
    scenes, queries = bd.build_pucallpa(a.seed)
    by_name = {s.name: s for s in scenes}
    conf, acc = rift.rift_conf({}), bx.workflow_register_conf()["acceptance"]
    feats: dict[str, Any] = {}
    out = Path(a.out)
    out.write_text("")
    for q in queries:
        if a.half != "both" and q.half != a.half:
            continue
        sc = by_name[q.map_scene]
        if sc.name not in feats:
            feats.clear()
            feats[sc.name] = rift.map_features(sc.map_gray, conf)
        rec = probe(q, sc, conf, feats[sc.name], acc)
        with out.open("a") as f:
            f.write(json.dumps(rec, default=float) + "\n")
        print(
            " ".join(
                f"{k}={v:.2f}" if isinstance(v, float) else f"{k}={v}" for k, v in rec.items()
            ),
            flush=True,
        )
    analyse([a.out])
    return 0


if __name__ == "__main__":
    sys.exit(main())
