"""Diagnostic: does a rift pose hold beyond the query's dominant structure?

    python benchmarks/diag_support_beyond.py benchmarks/out/s28/puc13_visible.jsonl 13 visible
    python benchmarks/diag_support_beyond.py benchmarks/out/s27/wide_oi_tuning.jsonl srif oi wide

For each pose accepted by rift in a Pucallpa run's records: the doubled-angle gradient-orientation
correlation (contrast-sign free) of the query with the map warped by the pose, as a z-score
against the same query at 150 random poses (any place, any rotation, the pose's scale) on the
same map; once on every valid query pixel and once without its strongest structure (the top
15 % of smoothed gradient magnitude, dilated 7 px: on Pucallpa, the river's banks).
"""

from __future__ import annotations

import json
import math
import sys
from pathlib import Path

import cv2
import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "benchmarks"))

import bench_devset as bd  # noqa: E402


def orientation(u8: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Unit doubled-angle gradient (complex) weighted by sqrt |g|^2, and that weight."""
    g = cv2.GaussianBlur(u8.astype(np.float32), (0, 0), 1.5)
    z = (cv2.Sobel(g, cv2.CV_32F, 1, 0) + 1j * cv2.Sobel(g, cv2.CV_32F, 0, 1)) ** 2
    m = np.abs(z) + 1e-6
    return z / np.sqrt(m), np.sqrt(m)


def correlation(zq: np.ndarray, mp: np.ndarray, H: np.ndarray, n: int, mask: np.ndarray) -> float:
    """The orientation correlation of the query (``zq``) with the map warped by ``H`` over
    ``mask``; NaN when less than a fifth of the mask is covered."""
    warped = cv2.warpPerspective(mp, H, (n, n), flags=cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP)
    inside = cv2.warpPerspective(np.ones_like(mp), H, (n, n),
                                 flags=cv2.INTER_NEAREST | cv2.WARP_INVERSE_MAP) > 0  # fmt: skip
    valid = inside & (warped > 0) & mask
    if valid.sum() < 0.2 * mask.sum():
        return math.nan
    a, b = zq[valid], orientation(warped)[0][valid]
    return float(np.real(np.sum(a * np.conj(b))) / np.sqrt(np.sum(np.abs(a) ** 2) * np.sum(np.abs(b) ** 2)))


def z_score(zq: np.ndarray, mp: np.ndarray, H: np.ndarray, n: int, mask: np.ndarray,
            rng: np.random.Generator, draws: int = 150) -> float:  # fmt: skip
    """The pose's correlation against ``draws`` random poses at its scale."""
    s = float(np.sqrt(abs(np.linalg.det(H[:2, :2]))))
    h, w = mp.shape
    null = []
    for _ in range(draws):
        a = rng.uniform(0, 2 * np.pi)
        R = np.array([[math.cos(a), -math.sin(a)], [math.sin(a), math.cos(a)]]) * s
        t = np.array([rng.uniform(0, w), rng.uniform(0, h)]) - R @ np.array([n / 2, n / 2])
        v = correlation(zq, mp, np.r_[np.c_[R, t], [[0, 0, 1]]], n, mask)
        if np.isfinite(v):
            null.append(v)
    if len(null) < 10:
        return math.nan
    return (correlation(zq, mp, H, n, mask) - float(np.mean(null))) / float(np.std(null))


def main() -> int:
    records = sys.argv[1]
    if sys.argv[2] == "srif":  # srif MODS wide|pair: the SRIF sets of bench_devset
        scenes, queries = bd.build_srif(sys.argv[3].split(","), sys.argv[4] == "wide", sys.argv[4] == "pair")
    else:  # SEED swir|visible: Landsat Pucallpa
        scenes, queries = bd.build_pucallpa(int(sys.argv[2]), True, query=sys.argv[3])
    scene = {s.name: s for s in scenes}
    query = {q.name: q for q in queries}
    rng = np.random.default_rng(0)
    for line in open(records):
        r = json.loads(line)
        if r.get("pose_source") not in ("rift", "learned") or r["query"] not in query:
            continue
        q = query[r["query"]]
        sc = scene[q.map_scene]
        u8 = next(iter(q.bands.values()))
        n = u8.shape[0]
        if u8.shape[1] != n:
            continue  # square queries only
        H = np.diag([1 / sc.map_gsd, -1 / sc.map_gsd, 1.0]) @ np.array(r["H"])
        zq, wq = orientation(u8)
        valid = u8 > 0
        strong = cv2.GaussianBlur(wq, (0, 0), 3)
        dominant = cv2.dilate((strong >= np.percentile(strong[valid], 85)).astype(np.uint8),
                              np.ones((7, 7), np.uint8)) > 0  # fmt: skip
        z_all = z_score(zq, sc.map_gray, H, n, valid, rng)
        z_rest = z_score(zq, sc.map_gray, H, n, valid & ~dominant, rng)
        print(f"{r['query']:34s} {r['outcome']:12s} log10 NFA {r['log10_nfa']:7.2f} z all "
              f"{z_all:6.2f} z without the strongest 15 % {z_rest:6.2f}", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
