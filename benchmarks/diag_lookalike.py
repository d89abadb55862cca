"""Diagnostics of look-alike poses (session 28): three probes of whether a pose accepted by the
map-wide sources (rift, learned) can be told from a look-alike (Pucallpa's visible control, seed
13: the query's river bend laid on another bend of the same river). None was kept; the figures
are in docs/experiments/2026-11-29-session28.md.

    python benchmarks/diag_lookalike.py mirror  RECORDS pucallpa 13 visible
    python benchmarks/diag_lookalike.py cells   RECORDS pucallpa 13 visible
    python benchmarks/diag_lookalike.py beyond  RECORDS pucallpa 11 swir
    python benchmarks/diag_lookalike.py beyond  RECORDS srif oi wide

RECORDS: a ``bench_devset.py`` run's .jsonl of the same set (``pucallpa SEED swir|visible`` or
``srif MODS wide|pair [BLOCK]``, BLOCK the run's ``--block``: the mosaic's layout).

* ``mirror``: the query flipped left-right (no rigid pose can truly match it) searched by rift on
  the same map, its acceptance off: its lowest log10 NFA and where its pose lies (footprint-centre
  distance from the accepted pose, in query sides).
* ``cells``: the query cells whose k nearest map descriptors include one at the pose's place
  (within ``reproj_px``), and in how many of them that one is the most similar.
* ``beyond``: the doubled-angle gradient-orientation correlation (contrast-sign free) of the query
  with the map warped by the pose, as a z-score against 150 random poses (any place and rotation,
  the pose's scale); on every valid query pixel, and without the query's strongest structure (the
  top 15 % of smoothed gradient magnitude, dilated 7 px: Pucallpa's river banks).
"""

from __future__ import annotations

import json
import math
import sys
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import yaml

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "benchmarks"))

import bench_devset as bd  # noqa: E402

from georeg.register import matching, rift  # noqa: E402


def register_conf() -> tuple[dict[str, Any], dict[str, Any]]:
    """config/config.yaml's acceptance section and its rift section (without ``enabled``)."""
    cfg = yaml.safe_load((ROOT / "config" / "config.yaml").read_text())["register"]
    return cfg["acceptance"], {k: v for k, v in (cfg.get("rift") or {}).items() if k != "enabled"}


def poses(records: str, spec: list[str], square_only: bool = True
          ) -> Iterator[tuple[dict, Any, Any, np.ndarray, np.ndarray]]:  # fmt: skip
    """(record, query, map scene, query uint8, H query px -> map px) of every square query whose
    pose a map-wide source (rift, learned) accepted in ``records``."""
    if spec[0] == "srif":
        block = int(spec[3]) if len(spec) > 3 else bd.BLOCK  # the run's --block (mosaic layout)
        scenes, queries = bd.build_srif(spec[1].split(","), spec[2] == "wide", spec[2] == "pair",
                                        block=block)  # fmt: skip
    else:
        scenes, queries = bd.build_pucallpa(int(spec[1]), True, query=spec[2])
    scene = {s.name: s for s in scenes}
    query = {q.name: q for q in queries}
    for line in open(records):
        r = json.loads(line)
        if r.get("pose_source") not in ("rift", "learned") or r["query"] not in query:
            continue
        q = query[r["query"]]
        sc = scene[q.map_scene]
        u8 = next(iter(q.bands.values()))
        if square_only and u8.shape[0] != u8.shape[1]:
            continue
        yield r, q, sc, u8, np.diag([1 / sc.map_gsd, -1 / sc.map_gsd, 1.0]) @ np.array(r["H"])


def mirror(r: dict, q: Any, sc: Any, u8: np.ndarray, H: np.ndarray) -> str:
    acc, rconf = register_conf()
    off = {**rconf, "null_margin": 0, "confirm_log_p_max": 0, "rescue_log_nfa_max": 0,
           "log_nfa_max": 50.0, "reangle": False, "polish": False}  # fmt: skip
    n = u8.shape[0]
    m = rift.register(np.ascontiguousarray(np.fliplr(u8)), sc.map_gray, q.gsd / sc.map_gsd,
                      {**acc, "log_nfa_max": 50.0}, off)  # fmt: skip
    d = None
    if m["H"] is not None:
        Hm = m["H"] @ np.array([[-1.0, 0, n - 1], [0, 1, 0], [0, 0, 1]])  # mirrored px -> map px
        c = np.array([[n / 2, n / 2]])
        d = round(float(np.linalg.norm(matching.apply_h(Hm, c) - matching.apply_h(H, c)))
                  / (n * q.gsd / sc.map_gsd), 2)  # fmt: skip
    return (f"far-rot null {r.get('null_log10_nfa') or math.nan:6.2f} mirror "
            f"{m['lowest_log10_nfa']:6.2f} at {d} sides")  # fmt: skip


_MAP_FEATURES: dict[str, tuple[np.ndarray, np.ndarray]] = {}


def cells(r: dict, q: Any, sc: Any, u8: np.ndarray, H: np.ndarray) -> str:
    c = rift.rift_conf(register_conf()[1])
    if sc.name not in _MAP_FEATURES:
        _MAP_FEATURES[sc.name] = rift.map_features(sc.map_gray, c)
    mxy, md = _MAP_FEATURES[sc.name]
    kc = rift.n_candidates(len(md), c)
    best = None  # the query's features at the rotation nearest the pose's
    for _, qxy, qd, A in rift.rotated_features(u8, q.gsd / sc.map_gsd, c):
        M = (H @ np.linalg.inv(A))[:2, :2]
        err = abs(math.degrees(math.atan2(M[1, 0], M[0, 0])))
        if best is None or err < best[0]:
            best = (err, qxy, qd, A)
    _, qxy, qd, A = best
    idx = rift.MapMatcher(md, c).nearest(qd, kc)
    sims = np.einsum("nd,nkd->nk", qd, md[idx])
    pred = matching.apply_h(H @ np.linalg.inv(A), qxy)
    at_pose = np.linalg.norm(mxy[idx] - pred[:, None, :], axis=2) <= c["reproj_px"]
    rank = (sims > np.where(at_pose, sims, -np.inf).max(1)[:, None]).sum(1)
    cell = rift.cell_key(qxy, c["thin_px"])
    ranks: dict[int, int] = {}
    for i in np.flatnonzero(at_pose.any(1)):
        ranks[int(cell[i])] = min(ranks.get(int(cell[i]), kc), int(rank[i]))
    rk = np.array(list(ranks.values()))
    return (f"cells {len(np.unique(cell)):3d} at the pose {len(rk):3d} of which best there "
            f"{int((rk == 0).sum()):3d} (k {kc})")  # fmt: skip


def _orientation(u8: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Unit doubled-angle gradient (complex) and the gradient magnitude."""
    g = cv2.GaussianBlur(u8.astype(np.float32), (0, 0), 1.5)
    z = (cv2.Sobel(g, cv2.CV_32F, 1, 0) + 1j * cv2.Sobel(g, cv2.CV_32F, 0, 1)) ** 2
    m = np.abs(z) + 1e-6
    return z / np.sqrt(m), np.sqrt(m)


def _correlation(zq: np.ndarray, mp: np.ndarray, H: np.ndarray, n: int, mask: np.ndarray) -> float:
    """The query's orientation (``zq``) against the map warped by ``H`` over ``mask``; NaN when
    less than a fifth of the mask is covered."""
    warped = cv2.warpPerspective(mp, H, (n, n), flags=cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP)
    inside = cv2.warpPerspective(np.ones_like(mp), H, (n, n), flags=cv2.INTER_NEAREST | cv2.WARP_INVERSE_MAP) > 0
    valid = inside & (warped > 0) & mask
    if valid.sum() < 0.2 * mask.sum():
        return math.nan
    a, b = zq[valid], _orientation(warped)[0][valid]
    return float(np.real(np.sum(a * np.conj(b))) / np.sqrt(np.sum(np.abs(a) ** 2) * np.sum(np.abs(b) ** 2)))


def _z_score(zq: np.ndarray, mp: np.ndarray, H: np.ndarray, n: int, mask: np.ndarray,
             rng: np.random.Generator, draws: int = 150) -> float:  # fmt: skip
    s = float(np.sqrt(abs(np.linalg.det(H[:2, :2]))))
    h, w = mp.shape
    null = []
    for _ in range(draws):
        a = rng.uniform(0, 2 * np.pi)
        R = np.array([[math.cos(a), -math.sin(a)], [math.sin(a), math.cos(a)]]) * s
        t = np.array([rng.uniform(0, w), rng.uniform(0, h)]) - R @ np.array([n / 2, n / 2])
        v = _correlation(zq, mp, np.r_[np.c_[R, t], [[0, 0, 1]]], n, mask)
        if np.isfinite(v):
            null.append(v)
    if len(null) < 10:
        return math.nan
    return (_correlation(zq, mp, H, n, mask) - float(np.mean(null))) / float(np.std(null))


_RNG = np.random.default_rng(0)


def beyond(r: dict, q: Any, sc: Any, u8: np.ndarray, H: np.ndarray) -> str:
    n = u8.shape[0]
    zq, mag = _orientation(u8)
    valid = u8 > 0
    strong = cv2.GaussianBlur(mag, (0, 0), 3)
    dominant = cv2.dilate((strong >= np.percentile(strong[valid], 85)).astype(np.uint8),
                          np.ones((7, 7), np.uint8)) > 0  # fmt: skip
    z_all = _z_score(zq, sc.map_gray, H, n, valid, _RNG)
    z_rest = _z_score(zq, sc.map_gray, H, n, valid & ~dominant, _RNG)
    return f"z all {z_all:6.2f} z without the strongest 15 % {z_rest:6.2f}"


def structure(r: dict, q: Any, sc: Any, u8: np.ndarray, H: np.ndarray) -> str:
    """``georeg.register.rift.structure_check`` at the pose, as the workflow's rift source runs
    it (the map read through ``bench_crossspectral.plain_window_reader``)."""
    g = sc.map_gsd
    got = rift.structure_check(u8, np.diag([g, -g, 1.0]) @ H, bd.bx.plain_window_reader(sc), q.gsd,
                               register_conf()[1])  # fmt: skip
    return f"structure z {got['z'] if got else math.nan:6.2f}"


PROBES = {"mirror": mirror, "cells": cells, "beyond": beyond, "structure": structure}


def main() -> int:
    if len(sys.argv) < 5 or sys.argv[1] not in PROBES:
        print(__doc__, file=sys.stderr)
        return 2
    probe = PROBES[sys.argv[1]]
    for r, q, sc, u8, H in poses(sys.argv[2], sys.argv[3:], probe is not structure):
        print(f"{r['query']:34s} {r['outcome']:12s} log10 NFA {r['log10_nfa']:7.2f} "
              f"{probe(r, q, sc, u8, H)}", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
