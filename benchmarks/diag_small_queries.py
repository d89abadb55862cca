"""Small queries (45-100 px): what the true candidate region gives, by feature settings and by
the dense CFOG search (development only; the TUNING cities' small-query subset of
bench_crossspectral.py ``--set small``; never run on the checking half).

Per positive query, in a square region of 1.5 footprint diagonals centred on the true place:
``verify`` with the workflow's features (the map index's capped density), with features dense on
both sides (no per-Mpx cap, lower contrast threshold; the map window re-detected), and the dense
CFOG peak (offset error to the truth, score, score of the mirrored query = a null).

    nice -n 10 python benchmarks/diag_small_queries.py
"""

from __future__ import annotations

import argparse
import math
import sys
from pathlib import Path
from typing import Any

import cv2
import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
import bench_crossspectral as bc  # noqa: E402

from georeg.index.features import detect_and_describe, merged_conf  # noqa: E402
from georeg.register import matching  # noqa: E402
from georeg.register.dense import dense_search  # noqa: E402
from georeg.register.search import MapSource, query_features, verify  # noqa: E402


def truth_h(q: bc.Query, g: float) -> np.ndarray:
    """Query px -> map x, y (x = col g, y = -row g) from the truth points."""
    mxy = np.c_[q.truth_map[:, 0] * g, -q.truth_map[:, 1] * g]
    H, _ = cv2.findHomography(q.truth.astype(np.float64), mxy, 0)
    return H


def window_source(sc: bc.Scene, b: tuple, conf: dict) -> tuple[MapSource, np.ndarray, np.ndarray]:
    """Features re-detected in the map window ``b`` (map x, y bounds) with ``conf``."""
    g = sc.map_gsd
    h, w = sc.map_gray.shape
    c0, c1 = max(0, int(math.floor(b[0] / g))), min(w, int(math.ceil(b[2] / g)) + 1)
    r0, r1 = max(0, int(math.floor(-b[3] / g))), min(h, int(math.ceil(-b[1] / g)) + 1)
    win = sc.map_gray[r0:r1, c0:c1]
    f = detect_and_describe(win, win > 0, conf)
    xy = np.c_[(f.xy[:, 0] + c0) * g, -(f.xy[:, 1] + r0) * g].astype(np.float64)
    src = MapSource(xy, f.desc, g, angle=f.angle.astype(np.float64),
                    scale=f.scale.astype(np.float64) * g)  # fmt: skip
    A = np.array([[g, 0, c0 * g], [0, -g, -r0 * g], [0, 0, 1.0]])
    return src, win, A


def run_verify(qf, src, b, conf, q, H_true, g) -> dict[str, Any]:
    rec, m, fit = verify(qf, src, b, conf, q.gsd, n_candidates=24, seed=1)
    good = 0
    if fit is not None and m is not None:
        e = np.linalg.norm(matching.apply_h(H_true, m.q_xy) - m.m_xy, axis=1) / g
        good = int((e[fit.inliers] < 3).sum())
        rec["true_matches"] = int((e < 3).sum())
    return {"inl": rec["inliers"], "good": good, "tm": rec.get("true_matches", 0),
            "m": rec["matches"], "nfa": rec.get("log10_nfa"), "qf": len(qf),
            "mf": rec["map_features"]}  # fmt: skip


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser()
    ap.add_argument("--per-scene", type=int, default=6)
    ap.add_argument("--seed", type=int, default=11)
    ap.add_argument("--contrast", type=float, default=0.02)
    a = ap.parse_args(argv)
    cv2.setNumThreads(1)
    scenes, queries = bc.build_small_set(a.per_scene, a.seed)
    by = {s.name: s for s in scenes}
    conf = bc.workflow_register_conf()
    dense_f = merged_conf({"rootsift": True, "max_features_per_mpx": 0,
                           "sift": {"contrast_threshold": a.contrast}})  # fmt: skip
    for q in (x for x in queries if x.truth is not None):
        sc = by[q.map_scene]
        g = sc.map_gsd
        H = truth_h(q, g)
        u8 = bc.query_stack(q, "auto")
        n = u8.shape[-1]
        c = matching.apply_h(H, np.array([[(n - 1) / 2, (n - 1) / 2]]))[0]
        half = 0.75 * math.hypot(n, n) * q.gsd
        b = (c[0] - half, c[1] - half, c[0] + half, c[1] + half)
        fac = [q.gsd / g]
        mxy, mdesc, mang, msize = bc.map_features(sc, g, merged_conf(bc.FEATURES))
        src = MapSource(mxy, mdesc, g, angle=mang, scale=msize * g)
        r_def = run_verify(query_features(u8, (0, n), fac, None), src, b, conf, q, H, g)
        wsrc, win, A = window_source(sc, b, dense_f)
        r_den = run_verify(query_features(u8, (0, n), fac, dense_f), wsrc, b, conf, q, H, g)
        q0 = u8 if u8.ndim == 2 else u8[0]
        d = dense_search(q0, q.gsd / g, win)
        derr = z = sc0 = scm = None
        if d is not None:
            pc = matching.apply_h(A @ d.S, np.array([[(n - 1) / 2, (n - 1) / 2]]))[0]
            derr = float(np.linalg.norm(pc - c) / g)
            z, sc0 = d.z, d.score
            dm = dense_search(np.ascontiguousarray(q0[:, ::-1]), q.gsd / g, win)
            scm = None if dm is None else dm.score
        print(f"{q.name:34s} n {n:3d} default inl {r_def['inl']:2d} good {r_def['good']:2d} "
              f"tm {r_def['tm']:2d}/{r_def['m']:3d} nfa {r_def['nfa'] if r_def['nfa'] is None else round(r_def['nfa'], 1)} "
              f"qf {r_def['qf']} mf {r_def['mf']} | dense-f inl {r_den['inl']:2d} good {r_den['good']:2d} "
              f"tm {r_den['tm']:2d}/{r_den['m']:3d} nfa {r_den['nfa'] if r_den['nfa'] is None else round(r_den['nfa'], 1)} "
              f"qf {r_den['qf']} mf {r_den['mf']} | cfog err {derr if derr is None else round(derr, 1)} "
              f"z {z if z is None else round(z, 1)} score {sc0 if sc0 is None else round(sc0, 3)} "
              f"mirror {scm if scm is None else round(scm, 3)}", flush=True)  # fmt: skip
    return 0


if __name__ == "__main__":
    sys.exit(main())
