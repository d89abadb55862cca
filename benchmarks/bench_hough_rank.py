"""Where the true place ranks among the Hough vote's candidate regions, by vote setting.

The feature search verifies the first ``register.index.top_candidates`` (8) regions of the vote
(georeg.register.hough); a query whose true place is not among them can only be found by a later
source. For each query with a truth, of the chosen set and half, and for the whole query and
its two halves (the split plan's parts), the rank of the first candidate region that holds the
true centre is recorded for every combination of ``--knn``, ``--bin-deg`` and ``--max-octaves``
(the map's nearest features are searched once, at the largest knn, and cut per setting).

    python benchmarks/bench_hough_rank.py --set srif_wide_oo --half tuning --knn 1 2 3 5 10 \\
        --bin-deg 15 30 --out benchmarks/out/hough_rank_oo_tuning.json

Sets: ``srif_wide_oo`` / ``_oi`` / ``_od`` (bench_devset's 40-reference mosaics, ``--block``
50), ``pucallpa`` (bench_devset, ``--seed``), ``xs_small`` (bench_crossspectral's small
queries, seed 11). Prints one line a setting: queries whose true place is in the first 8 for
the whole query or a part, for the whole query, parts in the first 8, the median best rank.
"""

from __future__ import annotations

import argparse
import itertools
import json
import sys
from pathlib import Path
from typing import Any

import cv2
import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import bench_crossspectral as bx  # noqa: E402
import bench_devset as bd  # noqa: E402

from georeg.io.atomic import write_json  # noqa: E402
from georeg.register.hough import hough_regions  # noqa: E402
from georeg.register.matching import flip_polarity  # noqa: E402
from georeg.register.search import (  # noqa: E402
    MapSource,
    footprint_diagonal_m,
    part_rows,
    plain_nearest,
    query_features,
)

TOP = 64  # candidate regions ranked (the search verifies the first 8)


class CutNearest:
    """The map's ``kmax`` nearest features of each query descriptor, searched once; ``knn_words``
    returns the first ``k`` of them (the same as searching with ``k``)."""

    def __init__(self, nn: Any, desc: np.ndarray, kmax: int) -> None:
        self.xy, self.angle, self.scale = nn.xy, nn.angle, nn.scale
        self.cq, self.cf, self.d = nn.knn_words(desc, kmax, 0)
        starts = np.r_[0, np.flatnonzero(np.diff(self.cq)) + 1]
        first = np.repeat(starts, np.diff(np.r_[starts, len(self.cq)]))
        self.rank = np.arange(len(self.cq)) - first

    def knn_words(self, desc: np.ndarray, k: int, nprobe: int = 0) -> tuple[np.ndarray, ...]:
        keep = self.rank < k
        return self.cq[keep], self.cf[keep], self.d[keep]


def build(name: str, block: int, seed: int) -> tuple[dict[str, bx.Scene], list[Any], Any]:
    """Scenes by name, the queries with a truth, and a query -> half function."""
    if name.startswith("srif_wide_"):
        scenes, queries = bd.build_srif([name.split("_")[-1]], True, False, 0, block, False)
    elif name == "pucallpa":
        scenes, queries = bd.build_pucallpa(seed, True, 0, 2)
    elif name == "xs_small":
        scenes, queries = bx.build_small_set(6, 11)
    else:
        raise SystemExit(f"unknown --set {name!r} (srif_wide_oo|_oi|_od, pucallpa, xs_small)")
    by = {s.name: s for s in scenes}

    def half(q: Any) -> str:
        return getattr(q, "half", None) or bx.half_of(by[q.scene].city)

    return by, [q for q in queries if q.truth is not None], half


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--set", required=True)
    ap.add_argument("--half", default="tuning", choices=["tuning", "checking"])
    ap.add_argument("--knn", type=int, nargs="+", default=[1, 10])
    ap.add_argument("--bin-deg", type=float, nargs="+", default=[30.0])
    ap.add_argument("--max-octaves", type=float, nargs="+", default=[1.0])
    ap.add_argument("--block", type=int, default=50)
    ap.add_argument("--seed", type=int, default=11, help="pucallpa's draw")
    ap.add_argument("--out", required=True)
    a = ap.parse_args(argv)
    if not bd.SRIF.is_dir() or not bd.PUCALLPA.is_dir():
        print(f"no development data at {bd.SRIF} / {bd.PUCALLPA}", file=sys.stderr)
        return 1
    cv2.setNumThreads(1)
    by, queries, half = build(a.set, a.block, a.seed)
    settings = [{"knn": k, "bin_deg": b, "max_octaves": o}
                for k, b, o in itertools.product(a.knn, a.bin_deg, a.max_octaves)]  # fmt: skip
    ranks: dict[str, dict[str, list[int | None]]] = {json.dumps(s): {} for s in settings}
    for q in (q for q in queries if half(q) == a.half):
        sc = by[q.map_scene]
        mxy, mdesc, mang, msize = bx.map_features(sc, sc.map_gsd, bx.merged_conf(bx.FEATURES))
        src = MapSource(mxy, mdesc, sc.map_gsd, angle=mang, scale=msize * sc.map_gsd)
        u8 = next(iter(q.bands.values()))
        h = u8.shape[-2]
        places = getattr(q, "alts", None) or [q.truth_map]
        centres = [np.mean(p, axis=0) * np.array([sc.map_gsd, -sc.map_gsd]) for p in places]
        for rows in ((0, h), part_rows(h, 2, 0), part_rows(h, 2, 1)):
            qf = query_features(u8, rows, [q.gsd / sc.map_gsd], src.features_conf)
            nn = None
            if len(qf):
                desc = np.concatenate([qf.desc, flip_polarity(qf.desc)]).astype(np.float32)
                nn = CutNearest(plain_nearest(src), desc, max(a.knn))
            diag = footprint_diagonal_m(qf, sc.map_gsd, q.gsd)
            for s in settings:
                cands = (
                    []
                    if nn is None
                    else hough_regions(qf, nn, src.bounds, sc.map_gsd, diag, TOP, s)
                )
                hit = [i for i, (b, _v) in enumerate(cands)
                       if any(b[0] <= x <= b[2] and b[1] <= y <= b[3] for x, y in centres)]  # fmt: skip
                ranks[json.dumps(s)].setdefault(q.name, []).append(hit[0] if hit else None)
        short = {f"knn {t['knn']} bin {t['bin_deg']:g} oct {t['max_octaves']:g}": ranks[json.dumps(t)][q.name]
                 for t in settings}  # fmt: skip
        print(q.name, short, flush=True)
    summary = []
    for s in settings:
        r = ranks[json.dumps(s)]
        best = [min((k for k in v if k is not None), default=TOP) for v in r.values()]
        row = {**s, "queries": len(r),
               "any_in_8": sum(b < 8 for b in best),
               "whole_in_8": sum(v[0] is not None and v[0] < 8 for v in r.values()),
               "parts_in_8": sum(k is not None and k < 8 for v in r.values() for k in v[1:]),
               "median_best_rank": float(np.median(best)) if best else None}  # fmt: skip
        summary.append(row)
        print(row)
    write_json(a.out, {"set": a.set, "half": a.half, "summary": summary, "ranks": ranks})
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
