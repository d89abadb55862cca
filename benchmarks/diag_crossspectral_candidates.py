"""Where the protocol's misses are lost: ranking (the true place is not among the candidate
regions) or verification/acceptance (it is, and the NFA test rejects it).

For every positive query of a half (default: checking, the protocol's set of
bench_crossspectral.py, same seed), the workflow default (``wf_default``) is run with each
``register.index.rank`` given, and every candidate region of every search (parts and the
whole-query fallback) is compared with the truth: the region holds the true centre of the query
(the mean of its truth points) or not. One line per query and rank: outcome, candidates, the
rank of the first true region in its search, its votes / the best votes, its matches, inliers,
log10 NFA and why it was rejected.

    nice -n 5 python benchmarks/diag_crossspectral_candidates.py --half checking --misses
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path
from typing import Any

import cv2
import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
import bench_crossspectral as bc  # noqa: E402


def true_regions(res: dict[str, Any], centre: np.ndarray) -> list[dict[str, Any]]:
    """Per search of the result: its candidates and the first one holding ``centre``."""
    out = []
    searches = []
    for p in res.get("parts") or []:
        allc = p.get("candidates") or []
        # a small query's part 0 searches the whole query, then each part, and concatenates
        # their candidates (``search_one_part``): one search per run of ranks from 0
        starts = [i for i, c in enumerate(allc) if c["rank"] == 0] + [len(allc)]
        names = [x.get("rows") for x in p.get("searched") or []] or [p.get("rows")]
        for j, (a, b) in enumerate(zip(starts[:-1], starts[1:], strict=False)):
            searches.append((names[j] if j < len(names) else p.get("rows"), p, allc[a:b]))
    for name, p, cands in searches:
        hit = next(
            (c for c in cands
             if c["bounds"][0] <= centre[0] <= c["bounds"][2]
             and c["bounds"][1] <= centre[1] <= c["bounds"][3]),
            None,
        )  # fmt: skip
        best = max((c.get("score") or 0.0 for c in cands), default=0.0)
        out.append({
            "search": name, "available": p.get("candidates_available"),
            "tried": len(cands), "accepted": bool(p.get("accepted")),
            "true_rank": None if hit is None else hit["rank"],
            "true_score": None if hit is None else hit.get("score"), "best_score": best,
            "true_matches": None if hit is None else hit.get("matches"),
            "true_inliers": None if hit is None else hit.get("inliers"),
            "true_log10_nfa": None if hit is None else hit.get("log10_nfa"),
            "true_reason": None if hit is None else hit.get("reason"),
        })  # fmt: skip
    return out


def _f(v: float | None) -> str:
    return "-" if v is None else f"{v:.1f}"


def main(argv: list[str] | None = None) -> int:
    from georeg.register.fuse import register_query
    from georeg.register.search import MapSource

    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawTextHelpFormatter)
    ap.add_argument("--half", choices=("tuning", "checking"), default="checking")
    ap.add_argument("--ranks", default="hough,tiles")
    ap.add_argument("--misses", action="store_true", help="only queries wf_default misses")
    ap.add_argument("--seed", type=int, default=11)
    ap.add_argument("--out", default="")
    a = ap.parse_args(argv)
    cv2.setNumThreads(1)
    scenes, queries = bc.build_set(3, a.seed, 1)
    by = {s.name: s for s in scenes}
    records = []
    for qi, q in enumerate(queries):
        if q.truth is None or bc.half_of(by[q.scene].city) != a.half:
            continue
        sc = by[q.map_scene]
        fgsd = sc.map_gsd
        mxy, mdesc, mang, msize = bc.map_features(sc, fgsd, bc.merged_conf(bc.FEATURES))
        centre = np.asarray(q.truth_map, np.float64).mean(axis=0) * np.array([fgsd, -fgsd])
        u8 = bc.query_stack(q, "auto")
        lines = []
        for rank in a.ranks.split(","):
            conf = bc._deep(bc.workflow_register_conf(), {"index": {"rank": rank}})
            src = MapSource(mxy, mdesc, fgsd, angle=mang, scale=msize * fgsd)
            res = register_query(u8, src, conf, q.gsd, [q.gsd / fgsd], a.seed + qi)
            H = None if res.get("homography") is None else np.array(res["homography"])
            j = bc.judge(q, sc, {"accepted": res["status"] == "registered", "H": H})
            searches = true_regions(res, centre)
            records.append({"query": q.name, "rank": rank, "outcome": j["outcome"],
                            "size_px": next(iter(q.bands.values())).shape[0],
                            "map_features": len(mxy), "searches": searches})  # fmt: skip
            lines.append((rank, j["outcome"], searches))
        if a.misses and all(o == "success" for _r, o, _s in lines if _r == "hough"):
            continue
        for rank, outcome, searches in lines:
            s = "; ".join(
                f"[{x['search']}] {x['tried']} tried "
                + ("true: none" if x["true_rank"] is None else
                   f"true #{x['true_rank']} votes {x['true_score'] or 0:.0f}/{x['best_score']:.0f}"
                   f" inl {x['true_inliers']}/{x['true_matches']} nfa {_f(x['true_log10_nfa'])}"
                   f" {x['true_reason'] or ''}")
                for x in searches
            )  # fmt: skip
            print(f"{q.name:34s} {q.gsd:5.1f}m {records[-1]['size_px']:4d}px {rank:6s} "
                  f"{outcome:8s} {s}", flush=True)  # fmt: skip
    if a.out:
        Path(a.out).write_text(json.dumps(records, indent=1, default=float))
    return 0


if __name__ == "__main__":
    sys.exit(main())
