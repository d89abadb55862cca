"""An empirical null for the small-query path's CFOG peak (development only: the TUNING cities'
``--set tiny`` / ``--set small`` of bench_crossspectral.py; never the checking half).

Per query (positives and unrelated pairs): the small path's candidate windows
(``register.small.small_windows``, the dense-feature Hough vote), the CFOG peak in each
(``dense.dense_search`` with the region as ``centre_box``, as ``small_register`` does), whether
the true place is in the region and how far the peak lands from it; then the same peak statistic
for the same query in ``--null`` random regions of the same size of the same map, away from the
candidate windows (seeded per query). Writes one JSON record per query (``--out``) and prints one
line per query; ``--analyse FILE`` reads such a file and prints the separation.

    nice -n 10 python benchmarks/diag_small_null.py --set tiny --out /tmp/null_tiny.json
    python benchmarks/diag_small_null.py --analyse /tmp/null_tiny.json
"""

from __future__ import annotations

import argparse
import json
import math
import sys
import time
from pathlib import Path
from typing import Any

import cv2
import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
import bench_crossspectral as bc  # noqa: E402

from georeg.index.features import merged_conf  # noqa: E402
from georeg.register import matching  # noqa: E402
from georeg.register.dense import correlation_surface, dense_search, window_u8  # noqa: E402
from georeg.register.null_scan import block_maxima  # noqa: E402
from georeg.register.search import MapSource, query_features  # noqa: E402
from georeg.register.small import dense_features_conf, small_conf, small_windows  # noqa: E402


def peak_in(u8q, q_gsd, reader, b, grow, sc_conf) -> dict[str, Any] | None:
    """The small path's CFOG peak for region ``b`` (map x0, y0, x1, y1) grown by ``grow``."""
    got = reader((b[0] - grow, b[1] - grow, b[2] + grow, b[3] + grow))
    if got is None:
        return None
    gray, A = got
    win = window_u8(gray)
    win_px = float(np.sqrt(abs(np.linalg.det(A[:2, :2]))))
    inv = np.linalg.inv(A)
    cr = matching.apply_h(inv, np.array([[b[0], b[1]], [b[2], b[3]]]))
    box = (cr[:, 0].min(), cr[:, 1].min(), cr[:, 0].max(), cr[:, 1].max())
    q0 = u8q if u8q.ndim == 2 else u8q[0]
    r = dense_search(q0, q_gsd / win_px, win, float(sc_conf["step_deg"]), int(sc_conf["max_side"]),
                     centre_box=box)  # fmt: skip
    if r is None:
        return None
    return {"score": r.score, "ratio": r.second_ratio, "z": r.z, "H": (A @ r.S).tolist()}


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser()
    ap.add_argument("--set", choices=("tiny", "small"), default="tiny")
    ap.add_argument("--null", type=int, default=24, help="random null regions per query")
    ap.add_argument("--limit", type=int, default=0, help="first N positives and N unrelated")
    ap.add_argument("--out", default="/tmp/null_diag.json")
    ap.add_argument("--analyse", default=None)
    ap.add_argument("--map-only", action="store_true", help="skip the candidate windows")
    a = ap.parse_args(argv)
    if a.analyse:
        return analyse(json.loads(Path(a.analyse).read_text()),
                       Path(a.analyse).with_suffix("").as_posix())
    cv2.setNumThreads(1)
    if a.set == "tiny":
        scenes, qs = bc.build_small_set(5, 11, bc.TINY_SIDES, "tiny_", 600)
    else:
        scenes, qs = bc.build_small_set(6, 11)
    if a.limit:
        qs = [q for q in qs if q.truth is not None][: a.limit] + [
            q for q in qs if q.truth is None][: a.limit]  # fmt: skip
    by = {s.name: s for s in scenes}
    conf = bc.workflow_register_conf()
    sc_conf = small_conf(conf)
    out = []
    for q in qs:
        t0 = time.perf_counter()
        sc = by[q.map_scene]
        g = sc.map_gsd
        u8 = bc.query_stack(q, "auto")
        h, w = u8.shape[-2:]
        mxy, mdesc, mang, msize = bc.map_features(sc, g, merged_conf(bc.FEATURES))
        src = MapSource(mxy, mdesc, g, angle=mang, scale=msize * g)
        fconf = dense_features_conf(src.features_conf, sc_conf)
        qf = query_features(u8, (0, h), [q.gsd / g], fconf)
        wins = [] if a.map_only else small_windows(qf, src, [], conf, q.gsd)
        grow = 0.5 * math.hypot(w, h) * q.gsd
        reader = bc.plain_window_reader(sc)
        c_true = None
        if q.truth is not None:
            txy = np.c_[q.truth_map[:, 0] * g, -q.truth_map[:, 1] * g]
            Ht, _ = cv2.findHomography(q.truth, txy, 0)
            c_true = matching.apply_h(Ht, np.array([[(w - 1) / 2, (h - 1) / 2]]))[0]
        rec_w = []
        for b in wins:
            p = peak_in(u8, q.gsd, reader, b, grow, sc_conf)
            inside = c_true is not None and b[0] <= c_true[0] <= b[2] and b[1] <= c_true[1] <= b[3]
            err = None
            if p is not None and c_true is not None:
                pc = matching.apply_h(np.array(p["H"]), np.array([[(w - 1) / 2, (h - 1) / 2]]))
                err = float(np.linalg.norm(pc[0] - c_true) / g)
            rec_w.append({"bounds": list(b), "true_inside": bool(inside), "err_px": err,
                          **({k: p[k] for k in ("score", "ratio", "z")} if p else {})})  # fmt: skip
        # the whole map's surface (max over rotations) for the offline null analysis
        t1 = time.perf_counter()
        q0 = u8 if u8.ndim == 2 else u8[0]
        sf = correlation_surface(q0, q.gsd / g, sc.map_gray, float(sc_conf["step_deg"]),
                                 int(sc_conf["max_side"]))  # fmt: skip
        best_k = np.argmax(sf.scores, axis=0).astype(np.uint8)
        surf = sf.scores.max(axis=0)
        D = int(math.ceil(math.hypot(*sf.query_shape))) + 2
        off = (D - 1) / 2 - sf.pd  # offset d -> query centre at map px (d + off + 0.5) / s - 0.5
        dt_map = time.perf_counter() - t1
        np.savez_compressed(Path(a.out).with_suffix("").as_posix() + f"_{q.name}.npz",
                            surf=surf.astype(np.float32), rot=best_k)
        dt = time.perf_counter() - t0
        rec = {"query": q.name, "positive": q.truth is not None, "side": int(max(h, w)),
               "windows": rec_w, "s": sf.s, "off": off, "g": g,
               "truth_centre": None if c_true is None else c_true.tolist(),
               "seconds": dt, "seconds_map": dt_map}  # fmt: skip
        out.append(rec)
        print(f"{q.name:46s} n {max(h, w):3d} wins "
              + " ".join(f"[{x.get('score', float('nan')):.3f} {'T' if x['true_inside'] else '-'}"
                         f" {'' if x['err_px'] is None else round(x['err_px'], 1)}]"
                         for x in rec_w)
              + f" map max {float(surf[np.isfinite(surf)].max()):.3f} map {dt_map:.1f}s "
              f"{dt:.1f}s", flush=True)  # fmt: skip
        Path(a.out).write_text(json.dumps(out, default=float))
    return 0


def gumbel_log10_nfa(peak: float, null: np.ndarray, n_blocks: int) -> float:
    """Gumbel law fitted to every null block maximum by moments, tested at the peak, x blocks."""
    beta = max(float(np.std(null)) * math.sqrt(6) / math.pi, 1e-12)
    mu = float(np.mean(null)) - 0.5772 * beta
    z = (peak - mu) / beta
    lp = -z / math.log(10) if z > 30 else math.log10(max(-math.expm1(-math.exp(-z)), 1e-300))
    return lp + math.log10(n_blocks)


def spacing_log10_p(peak: float, null: np.ndarray, k: int) -> float:
    """Top spacing: gap to the null's largest over the tail scale of its top k (as null_scan)."""
    top = np.sort(null)[::-1]
    k = min(k, len(top) - 1)
    return -(peak - top[0]) / max(float(np.mean(top[:k] - top[k])), 1e-12) / math.log(10)


def analyse(recs: list[dict[str, Any]], stem: str) -> int:
    """The whole map's best peak tested against the map's block maxima farther than 12 map px:
    by a Gumbel fit of all block maxima (x the number of blocks) and by the top spacing; per
    block size. Groups: positives whose best peak is within 3 map px of the truth, positives
    whose best peak is elsewhere, unrelated pairs. Plus how often the candidate windows hold the
    true place (when they were computed)."""
    pos = [r for r in recs if r["positive"]]
    n_in = sum(any(w["true_inside"] for w in r["windows"]) for r in pos)
    n_at = sum(any(w["true_inside"] and w["err_px"] is not None and w["err_px"] <= 3
                   for w in r["windows"]) for r in pos)  # fmt: skip
    print(f"positives {len(pos)}, unrelated {len(recs) - len(pos)}; candidate windows: true place "
          f"in one {n_in}, a window's peak within 3 px of it {n_at}")  # fmt: skip
    f = lambda v: np.round(np.sort(v), 1).tolist()  # noqa: E731
    for b in (4, 8, 16):
        tests = {"gumbel x blocks": lambda pk, nl, n: gumbel_log10_nfa(pk, nl, n)}
        for k in (10, 30, 100):
            tests[f"spacing k {k}"] = lambda pk, nl, n, k=k: spacing_log10_p(pk, nl, k)
        for name, test in tests.items():
            groups: dict[str, list[float]] = {"true": [], "wrong": [], "unrelated": []}
            for r in recs:
                surf = np.load(f"{stem}_{r['query']}.npz")["surf"]
                s, off, g = r["s"], r["off"], r["g"]
                vals, br, bcol = block_maxima(surf, b)
                pr, pc = np.unravel_index(int(np.argmax(np.where(np.isfinite(surf), surf, -np.inf))),
                                          surf.shape)  # fmt: skip
                far = (br - pr) ** 2 + (bcol - pc) ** 2 > (12 * s + b) ** 2
                v = test(float(surf[pr, pc]), vals[far], len(vals))
                if r["truth_centre"] is None:
                    groups["unrelated"].append(v)
                    continue
                tc = (r["truth_centre"][0] / g + 0.5) * s - 0.5 - off
                tr = (-r["truth_centre"][1] / g + 0.5) * s - 0.5 - off
                groups["true" if math.hypot(tc - pc, tr - pr) / s <= 3.0 else "wrong"].append(v)
            tv, wv, uv = (np.array(groups[x]) for x in ("true", "wrong", "unrelated"))
            lowest_wrong = min(np.r_[wv, uv]) if len(wv) + len(uv) else float("nan")
            print(f"b {b:2d} {name:15s}: best peak at the truth {len(tv)}/{len(pos)}; below -2 / -3 "
                  f"/ -4: true {(tv < -2).sum()} / {(tv < -3).sum()} / {(tv < -4).sum()}, wrong + "
                  f"unrelated {((wv < -2).sum() + (uv < -2).sum())} / {((wv < -3).sum() + (uv < -3).sum())}"
                  f" / {((wv < -4).sum() + (uv < -4).sum())} (lowest {lowest_wrong:.1f})")  # fmt: skip
            print(f"     true {f(tv)}\n     wrong {f(wv)}\n     unrelated {f(uv)}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
