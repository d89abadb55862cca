"""The small-query CFOG null test on maps larger than one FFT: the tiled scan
(``georeg.register.null_scan``) against the whole-map scan, and on a large real mosaic.

``--equiv``: the tuning cities' tiny set (``bench_crossspectral.py --set tiny``, 40-80 px,
``--limit`` positives and unrelated pairs spread over the cities) against their own maps (<= 1 Mpx correlation): the
whole-map scan (``null_scan.scan``, as ``small.null_register``) and the tiled scan with a forced
``--tile-px``; per query the two peaks' distance (map px), rotations and log10 p, and the whole
scan's log10 p on the map less its first row and column (the statistic's own sensitivity to the
phase of the shrink).

``--large``: a mosaic of four real maps (Landsat Nanjing date 2, Landsat Taizhou, Sentinel-2 Abu
Dhabi and Hong Kong RGB luminance; each brought to 800 x 800 px of 30 m, then the whole mosaic
upsampled x ``--upsample``), tiny SWIR queries of Nanjing date 1 (positives, truth known) and of
Saclay / Norcia (unrelated) through ``small.null_register`` with the workflow's config; per query
the path taken (whole / tiled), tiles, log10 p, accepted, error (map px), seconds; the process's
peak RSS at the end (``--whole`` forces the one-FFT path for comparison, as the code before the
tiled scan would have done with ``max_map_px`` raised).

    nice -n 10 python benchmarks/bench_null_tiled.py --equiv --limit 8 --tile-px 320
    nice -n 10 python benchmarks/bench_null_tiled.py --large --upsample 1
    nice -n 10 python benchmarks/bench_null_tiled.py --large --upsample 1 --whole
    nice -n 10 python benchmarks/bench_null_tiled.py --large --upsample 2
    nice -n 10 python benchmarks/bench_null_tiled.py --large --upsample 1 --native
"""

from __future__ import annotations

import argparse
import json
import logging
import math
import resource
import sys
import time
from pathlib import Path
from typing import Any

import cv2
import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
import bench_crossspectral as bc  # noqa: E402

from georeg.register import matching  # noqa: E402
from georeg.register.dense import window_u8  # noqa: E402
from georeg.register.null_scan import (
    scan,  # noqa: E402
    tiled_scan,  # noqa: E402
)
from georeg.register.search import MapSource  # noqa: E402
from georeg.register.small import null_register, small_conf  # noqa: E402


def array_reader(m: np.ndarray, g: float) -> Any:
    """``bench_crossspectral.plain_window_reader`` on a plain array of map px size ``g``."""
    h, w = m.shape

    def read(b: tuple[float, ...]) -> tuple[np.ndarray, np.ndarray] | None:
        c0, c1 = max(0, int(math.floor(b[0] / g))), min(w, int(math.ceil(b[2] / g)) + 1)
        r0, r1 = max(0, int(math.floor(-b[3] / g))), min(h, int(math.ceil(-b[1] / g)) + 1)
        if c1 - c0 < 8 or r1 - r0 < 8:
            return None
        win = m[r0:r1, c0:c1].astype(np.float32)
        win[win == 0] = np.nan
        return win, np.array([[g, 0, c0 * g], [0, -g, -r0 * g], [0, 0, 1.0]])

    return read


def rss_mb() -> float:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0


def centre(H: np.ndarray, q: np.ndarray) -> np.ndarray:
    h, w = q.shape[-2:]
    return matching.apply_h(H, np.array([[(w - 1) / 2, (h - 1) / 2]]))[0]


def equiv(limit: int, tile_px: int) -> int:
    """Whole-map scan vs tiled scan on the tuning cities' tiny set."""
    scenes, qs = bc.build_small_set(5, 11, bc.TINY_SIDES, "tiny_", 600)
    by = {s.name: s for s in scenes}
    pos = [q for q in qs if q.truth is not None]
    neg = [q for q in qs if q.truth is None]
    pos, neg = (x[:: max(1, len(x) // limit)][:limit] for x in (pos, neg))  # spread over cities
    sc_conf = small_conf(bc.workflow_register_conf())
    args = (float(sc_conf["step_deg"]), int(sc_conf["max_side"]))
    nc = {"block_px": 16, "exclude_px": 12.0, "tail_k": 30}
    out = []
    for q in pos + neg:
        sc = by[q.map_scene]
        g = sc.map_gsd
        u8 = bc.query_stack(q, "auto")
        q0 = u8 if u8.ndim == 2 else u8[0]
        h, w = q0.shape
        read = bc.plain_window_reader(sc)
        mh, mw = sc.map_gray.shape
        pad = 0.5 * math.hypot(w, h) * q.gsd
        b = (-pad, -(mh - 1) * g - pad, (mw - 1) * g + pad, pad)
        t0 = time.perf_counter()
        gray, A = read(b)
        r = scan(q0, q.gsd / g, window_u8(gray), *args, *nc.values())
        t1 = time.perf_counter()
        t = tiled_scan(q0, q.gsd, b, read, g, *args, *nc.values(), tile_px=tile_px)
        t2 = time.perf_counter()
        # the whole-map scan's own sensitivity to the shrink's phase: the map less its first px
        r1 = scan(q0, q.gsd / g, window_u8(gray[1:, 1:]), *args, *nc.values())
        if r is None or "S" not in t:
            print(q.name, "skipped", None if r is None else t.get("reason"), flush=True)
            continue
        d = float(np.linalg.norm(centre(A @ r["S"], q0) - centre(t["A"] @ t["S"], q0)) / g)
        rec = {"query": q.name, "positive": q.truth is not None, "side": max(h, w),
               "shrink": r["shrink"], "tiles": t["tiles"], "peak_dist_px": d,
               "angle_whole": r["angle_deg"], "angle_tiled": t["angle_deg"],
               "log10_p_whole": r["log10_p"], "log10_p_tiled": t["log10_p"],
               "log10_p_whole_shifted": None if r1 is None else r1["log10_p"],
               "null_max_whole": r["null_max"], "null_max_tiled": t["null_max"],
               "blocks_whole": r["null_blocks"], "blocks_tiled": t["null_blocks"],
               "s_whole": t1 - t0, "s_tiled": t2 - t1}  # fmt: skip
        out.append(rec)
        print(f"{q.name:46s} n {max(h, w):3d} s {r['shrink']:.2f} tiles {t['tiles']:3d} "
              f"peak d {d:5.2f} px ang {r['angle_deg']:5.0f} {t['angle_deg']:5.0f} "
              f"log10 p {r['log10_p']:7.2f} {t['log10_p']:7.2f} "
              f"(1 px shift {float('nan') if r1 is None else r1['log10_p']:7.2f}) "
              f"blocks {r['null_blocks']} {t['null_blocks']} "
              f"{t1 - t0:5.1f} s {t2 - t1:5.1f} s", flush=True)  # fmt: skip
    Path("/tmp/null_tiled_equiv.json").write_text(json.dumps(out, default=float))
    return 0


def mosaic(up: float, native: bool = False) -> tuple[np.ndarray, float, bc.Scene]:
    """Nanjing (date 2 map) | Taizhou / Abu Dhabi | Hong Kong, each 800 x 800 px of 30 m, the
    mosaic upsampled x ``up``: (map uint8, map GSD, the Nanjing date-1 scene); ``native``: the
    Nanjing map alone."""
    nj = bc.landsat_scene("nanjing", 0)
    if native:
        m = nj.map_gray if up == 1 else cv2.resize(nj.map_gray, None, fx=up, fy=up,
                                                    interpolation=cv2.INTER_CUBIC)  # fmt: skip
        return np.clip(m, 0, 255).astype(np.uint8), 30.0 / up, nj
    tz = bc.landsat_scene("taizhou", 0)
    ab, hk = bc.s2_scene("abudhabi"), bc.s2_scene("hongkong")
    tiles = [cv2.resize(s.map_gray, (800, 800), interpolation=cv2.INTER_LINEAR)
             if s.map_gray.shape != (800, 800) else s.map_gray for s in (nj, tz, ab, hk)]  # fmt: skip
    m = np.block([[tiles[0], tiles[1]], [tiles[2], tiles[3]]])
    if up != 1:
        m = cv2.resize(m, None, fx=up, fy=up, interpolation=cv2.INTER_CUBIC)
    return np.clip(m, 0, 255).astype(np.uint8), 30.0 / up, nj


def large(up: float, n_pos: int, n_neg: int, whole: bool, seed: int, native: bool) -> int:
    """Tiny queries through ``null_register`` on the mosaic (or Nanjing's map alone)."""
    logging.basicConfig(level=logging.WARNING)
    m, g, nj = mosaic(up, native)
    base = rss_mb()
    H, W = m.shape
    src = MapSource(np.array([[0.0, 0.0], [(W - 1) * g, -(H - 1) * g]]),
                    np.zeros((2, 128), np.float32), g)  # fmt: skip
    read = array_reader(m, g)
    conf = bc.workflow_register_conf()
    if whole:
        conf = bc._deep(conf, {"small": {"null_test": {"max_map_px": 1e12}}})
    rng = np.random.default_rng(seed)
    qs = []
    for i in range(n_pos):
        qs.append(bc.make_query(nj, rng, i, side_px=int(rng.integers(40, 81))))
    others = [bc.s2_scene("saclay_e"), bc.s2_scene("saclay_w"), bc.s2_scene("norcia")]
    for i in range(n_neg):
        o = others[i % len(others)]
        n = int(rng.integers(40, 81 if o.city != "norcia" else 56))  # Norcia: 121 px at 20 m
        qq = bc.make_query(o, rng, 100 + i, side_px=n)
        qs.append(bc.Query(qq.name + "_vs_mosaic", qq.scene, "mosaic", qq.bands, qq.gsd, None, None))
    print(f"mosaic {W} x {H} px at {g:.1f} m, baseline RSS {base:.0f} MB", flush=True)
    out = []
    for q in qs:
        u8 = bc.query_stack(q, "auto")
        t0 = time.perf_counter()
        rec = null_register(u8, q.gsd, src, conf, read)
        dt = time.perf_counter() - t0
        err = None
        if rec.get("homography") is not None and q.truth is not None:
            est = matching.apply_h(np.array(rec["homography"]), q.truth) / np.array([g, -g])
            err = float(np.median(np.linalg.norm(est - q.truth_map * up, axis=1)))
        r = {"query": q.name, "positive": q.truth is not None, "side": max(u8.shape[-2:]),
             "scan": rec.get("scan"), "tiles": rec.get("tiles"), "map_px": rec.get("map_px"),
             "log10_p": rec.get("log10_p"), "accepted": rec["accepted"], "err_px": err,
             "reason": rec.get("reason"), "seconds": dt, "rss_mb": rss_mb(),
             "shrink": rec.get("shrink"), "null_blocks": rec.get("null_blocks")}  # fmt: skip
        out.append(r)
        lp = r["log10_p"]
        print(f"{q.name:40s} n {r['side']:3d} {r['scan']} tiles {r['tiles']} "
              f"log10 p {'-' if lp is None else round(lp, 2)} acc {r['accepted']} "
              f"err {'-' if err is None else round(err, 2)} {dt:6.1f} s "
              f"RSS {r['rss_mb']:.0f} MB {r['reason'] or ''}", flush=True)  # fmt: skip
    tag = f"{up:g}{'_whole' if whole else ''}{'_native' if native else ''}"
    Path(f"/tmp/null_tiled_large_{tag}.json").write_text(json.dumps(out, default=float))
    neg = [r["log10_p"] for r in out if not r["positive"] and r["log10_p"] is not None]
    print(f"peak RSS {rss_mb():.0f} MB (baseline {base:.0f}); unrelated accepted "
          f"{sum(r['accepted'] for r in out if not r['positive'])}/{n_neg}, lowest log10 p "
          f"{min(neg) if neg else None}; positives accepted "
          f"{sum(r['accepted'] for r in out if r['positive'])}/{n_pos}", flush=True)  # fmt: skip
    return 0


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser()
    ap.add_argument("--equiv", action="store_true")
    ap.add_argument("--large", action="store_true")
    ap.add_argument("--limit", type=int, default=8)
    ap.add_argument("--tile-px", type=int, default=320)
    ap.add_argument("--upsample", type=float, default=1.0)
    ap.add_argument("--pos", type=int, default=6)
    ap.add_argument("--neg", type=int, default=6)
    ap.add_argument("--whole", action="store_true")
    ap.add_argument("--native", action="store_true", help="Nanjing's map alone")
    ap.add_argument("--seed", type=int, default=20)
    a = ap.parse_args(argv)
    cv2.setNumThreads(1)
    if a.equiv:
        return equiv(a.limit, a.tile_px)
    if a.large:
        return large(a.upsample, a.pos, a.neg, a.whole, a.seed, a.native)
    ap.error("--equiv or --large")
    return 2


if __name__ == "__main__":
    raise SystemExit(main())
