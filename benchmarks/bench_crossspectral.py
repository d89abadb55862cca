"""Cross-spectral, cross-date matching benchmark (issue 11): SWIR of date 1 vs RGB of date 2.

    source /work/venv/bin/activate
    nice -n 10 python benchmarks/bench_crossspectral.py            # all candidates, a few minutes
    nice -n 10 python benchmarks/bench_crossspectral.py --methods paper,cross --per-scene 2

Development set, built the way a user meets it (seeded): from every scene of
../shared/data/swir_dates (Landsat Nanjing + Taizhou, five Sentinel-2 cities) a SWIR band of one
date (1.6 or 2.2 um, chosen at random) is rotated (any angle), rescaled (x0.75-1.3, the query GSD
given accordingly), cropped to half the scene's side and stripped of its geo-referencing; the map
is the RGB luminance of the other date (Landsat: either direction; Sentinel-2: date 2). The truth
comes from the geo-referencing of both dates. Unrelated pairs (a query of one scene against the
map of another) must come out not found. Each candidate matches the query against the whole map
(one candidate region; the search strategy is not what is measured here) and decides with the
project's acceptance (georeg.register.acceptance: NFA + plausibility + collinearity).

Outcome per query: success = accepted with median error <= 5 map pixels over the query; false
accept = accepted with a larger error, or any acceptance of an unrelated pair; missed = not
accepted. Output: a table on stdout and results/benchmark/crossspectral.json.
"""

from __future__ import annotations

import argparse
import glob
import json
import math
import sys
import time
import warnings
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import cv2
import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
SHARED = ROOT.parent / "shared" / "data"
DATES = SHARED / "swir_dates"

from georeg.index.features import detect_and_describe, merged_conf, resample  # noqa: E402
from georeg.register import acceptance, crossspectral, matching  # noqa: E402

SUCCESS_PX = 5.0


# ----------------------------------------------------------------------------- scenes


@dataclass
class Scene:
    """One scene: SWIR bands of the query date (float32, src grid), RGB luminance of the map date,
    and px_to_map(col, row) -> map pixel (col, row) of the truth."""

    name: str
    swir: dict[str, np.ndarray]
    swir_gsd: float
    map_gray: np.ndarray  # uint8, 0 = nodata
    map_gsd: float
    to_map: Any  # (n,2) src px -> (n,2) map px


def _stretch(a: np.ndarray, valid: np.ndarray | None = None, lo=1.0, hi=99.0) -> np.ndarray:
    a = a.astype(np.float32)
    v = np.isfinite(a) if valid is None else valid & np.isfinite(a)
    p0, p1 = np.percentile(a[v], [lo, hi])
    out = np.clip((a - p0) / max(p1 - p0, 1e-6), 0, 1) * 254 + 1
    return np.where(v, out, 0).round().astype(np.uint8)


def _lum(r: np.ndarray, g: np.ndarray, b: np.ndarray) -> np.ndarray:
    return _stretch(0.299 * r.astype(np.float32) + 0.587 * g + 0.114 * b)


def landsat_scene(city: str, query_date: int) -> Scene:
    from georeg.io.query import open_query

    d = DATES / f"landsat_{city}"
    cubes = sorted(p for p in d.iterdir() if p.suffix.lower() not in (".hdr",))
    q, m = open_query(str(cubes[query_date])), open_query(str(cubes[1 - query_date]))
    swir = {"1.6um": q.read_band(4), "2.2um": q.read_band(5)}
    gray = _lum(m.read_band(2), m.read_band(1), m.read_band(0))
    return Scene(f"{city}_d{query_date + 1}", swir, 30.0, gray, 30.0, lambda p: p)


def s2_scene(city: str) -> Scene:
    import rasterio

    d = DATES / "oscd_dev" / city

    def band(date: int, b: str):
        (p,) = glob.glob(str(d / f"imgs_{date}" / f"*_{b}.tif"))
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            with rasterio.open(p) as s:
                return s.read(1).astype(np.float32), s.transform

    b11, t1 = band(1, "B11")
    b12, _ = band(1, "B12")
    r, t2 = band(2, "B04")
    g, _ = band(2, "B03")
    b, _ = band(2, "B02")
    inv2 = ~t2

    def to_map(p: np.ndarray) -> np.ndarray:
        lon, lat = t1 * ((p[:, 0] + 0.5), (p[:, 1] + 0.5))
        c, rr = inv2 * (lon, lat)
        return np.c_[c - 0.5, rr - 0.5]

    return Scene(f"s2_{city}", {"1.6um": b11, "2.2um": b12}, 20.0, _lum(r, g, b), 10.0, to_map)


def all_scenes() -> list[Scene]:
    out = [landsat_scene(c, k) for c in ("nanjing", "taizhou") for k in (0, 1)]
    out += [s2_scene(c) for c in sorted(p.name for p in (DATES / "oscd_dev").iterdir())]
    return out


# ----------------------------------------------------------------------------- queries


@dataclass
class Query:
    name: str
    scene: str
    map_scene: str
    bands: dict[str, np.ndarray]  # stretched uint8 query bands (0 = nodata), first = the chosen one
    gsd: float
    truth: np.ndarray | None  # (k,2) query px sample points, or None for an unrelated pair
    truth_map: np.ndarray | None  # (k,2) map px of those points


def make_query(sc: Scene, rng: np.random.Generator, i: int) -> Query:
    """Rotate, rescale and crop a SWIR band of ``sc`` (seeded); truth on a grid of query pixels."""
    h, w = next(iter(sc.swir.values())).shape
    side = 0.5 * min(h, w)
    s = float(rng.uniform(0.75, 1.3))
    theta = float(rng.uniform(0, 360))
    half = side / math.sqrt(2)
    cx, cy = rng.uniform(half, w - half), rng.uniform(half, h - half)
    n = int(round(side * s))
    # query px (u, v) -> src px: centre + R(theta) (u - n/2, v - n/2) / s
    c, si = math.cos(math.radians(theta)), math.sin(math.radians(theta))
    A = np.array([[c, -si], [si, c]]) / s
    t = np.array([cx, cy]) - A @ np.array([(n - 1) / 2, (n - 1) / 2])
    M = np.c_[A, t]
    names = list(sc.swir)
    first = names[int(rng.integers(len(names)))]
    order = [first] + [b for b in names if b != first]
    bands = {}
    for b in order:
        src = sc.swir[b]
        warped = cv2.warpAffine(
            src, M, (n, n), flags=cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP, borderValue=np.nan
        )
        bands[b] = _stretch(warped)
    uu, vv = np.meshgrid(np.linspace(2, n - 3, 12), np.linspace(2, n - 3, 12))
    qp = np.c_[uu.ravel(), vv.ravel()]
    sp = qp @ A.T + t
    return Query(
        f"{sc.name}_{i}_{first}", sc.name, sc.name, bands, sc.swir_gsd / s, qp, sc.to_map(sp)
    )


# ----------------------------------------------------------------------------- methods


_MAP_CACHE: dict[tuple, tuple[np.ndarray, np.ndarray]] = {}


def gradmag(u8: np.ndarray) -> np.ndarray:
    """Gradient-magnitude structure image (contrast-sign free), stretched to 1..255 (0 = nodata)."""
    g = cv2.GaussianBlur(u8.astype(np.float32), (0, 0), 1.0)
    mag = np.hypot(cv2.Sobel(g, cv2.CV_32F, 1, 0), cv2.Sobel(g, cv2.CV_32F, 0, 1))
    valid = cv2.erode((u8 > 0).astype(np.uint8), np.ones((5, 5), np.uint8)) > 0
    return _stretch(mag, valid)


def map_features(sc: Scene, gsd: float, conf: dict, structure: str = "") -> tuple:
    """Map features (x, y in metres, north-up: x = col * gsd, y = -row * gsd) at feature ``gsd``."""
    key = (sc.name, gsd, json.dumps(conf, sort_keys=True), structure)
    if key not in _MAP_CACHE:
        gray = gradmag(sc.map_gray) if structure == "gradmag" else sc.map_gray
        img, m, (sx, sy) = resample(gray, sc.map_gsd / gsd, sc.map_gray > 0)
        f = detect_and_describe(img, m, conf)
        px = (f.xy.astype(np.float64) + 0.5) * np.array([sx, sy]) - 0.5
        xy = np.c_[px[:, 0] * sc.map_gsd, -px[:, 1] * sc.map_gsd]
        _MAP_CACHE[key] = (xy, f.desc, f.angle.astype(np.float64), f.scale.astype(np.float64))
    return _MAP_CACHE[key]


def query_feats(band: np.ndarray, factor: float, conf: dict):
    img, m, (sx, sy) = resample(band, factor, band > 0)
    f = detect_and_describe(img, m, conf)
    xy = (f.xy.astype(np.float64) + 0.5) * np.array([sx, sy]) - 0.5
    return (
        xy,
        f.desc,
        f.response.astype(np.float64),
        f.angle.astype(np.float64),
        f.scale.astype(np.float64),
    )


METHODS: dict[str, dict[str, Any]] = {
    # the paper: one band brought to the map's GSD, SIFT/RootSIFT, ratio 0.7, Nt = 100
    "paper": {},
    "paper_all_matches": {"max_matches": 0},
    "coarse": {"coarse": True},
    "low_contrast": {"query_sift": {"contrast_threshold": 0.01}},
    "two_bands": {"bands": 2},
    "polarity": {"polarity": True},
    "polarity_all": {"polarity": True, "max_matches": 0},
    "polarity_coarse": {"polarity": True, "coarse": True},
    "polarity_2bands": {"polarity": True, "bands": 2},
    "gradmag": {"structure": "gradmag"},
    "gradmag_vote": {"structure": "gradmag", "vote": {"ratio": 0.9}},
    "vote_r0.8": {"vote": {"ratio": 0.8}},
    "vote_r0.9_pol_2bands": {"vote": {"ratio": 0.9}, "polarity": True, "bands": 2},
    "vote_r0.9_pol_lowcontrast": {
        "vote": {"ratio": 0.9},
        "polarity": True,
        "query_sift": {"contrast_threshold": 0.01},
    },
    "vote_guided": {"vote": {"ratio": 0.9}, "guided": 8},
    # the workflow's default: guided re-match only refines an accepted hypothesis (fuse stage)
    "vote_refine": {"vote": {"ratio": 0.9}, "guided": 8, "rescue": False},
    "vote_pol_refine": {"vote": {"ratio": 0.9}, "polarity": True, "guided": 8, "rescue": False},
    "vote_2bands_guided": {"vote": {"ratio": 0.9}, "bands": 2, "guided": 8},
    "vote_pol_guided": {"vote": {"ratio": 0.9}, "polarity": True, "guided": 8},
    "vote_pol_2bands_guided": {"vote": {"ratio": 0.9}, "polarity": True, "bands": 2, "guided": 8},
    "vote_pol_coarse_guided": {
        "vote": {"ratio": 0.9},
        "polarity": True,
        "coarse": True,
        "guided": 8,
    },
    "vote_r0.9": {"vote": {"ratio": 0.9}},
    "vote_r0.9_pol": {"vote": {"ratio": 0.9}, "polarity": True},
    "vote_r0.9_coarse": {"vote": {"ratio": 0.9}, "coarse": True},
    "vote_r0.9_pol_coarse": {"vote": {"ratio": 0.9}, "polarity": True, "coarse": True},
    "vote_r0.95_pol_coarse": {"vote": {"ratio": 0.95}, "polarity": True, "coarse": True},
}

FEATURES = {"rootsift": True, "max_features_per_mpx": 8000}
REG = {
    "ratio": 0.7,
    "max_matches": 100,
    "ransac": {"method": "magsac", "reproj_px": 3.0, "max_seconds": 2.0, "rounds": 3},
    "acceptance": {"mode": "nfa", "log_nfa_max": 0.0},
}


def run_method(q: Query, sc_map: Scene, spec: dict[str, Any], seed: int) -> dict[str, Any]:
    t0 = time.perf_counter()
    fgsd = max(sc_map.map_gsd, q.gsd) if spec.get("coarse") else sc_map.map_gsd
    fconf = merged_conf(FEATURES)
    structure = spec.get("structure", "")
    mxy, mdesc, mang, msize = map_features(sc_map, fgsd, fconf, structure)
    qconf = merged_conf(FEATURES)
    qconf["sift"].update(spec.get("query_sift", {}))
    xs, ds, rs, angs, sizes = [], [], [], [], []
    for b in list(q.bands)[: int(spec.get("bands", 1))]:
        band = gradmag(q.bands[b]) if structure == "gradmag" else q.bands[b]
        xy, d, r, ang, size = query_feats(band, q.gsd / fgsd, qconf)
        if spec.get("polarity"):
            xy, d, r = crossspectral.add_polarity(xy, d, r)
            ang, size = np.r_[ang, (ang + 180.0) % 360.0], np.r_[size, size]
        xs.append(xy), ds.append(d), rs.append(r), angs.append(ang), sizes.append(size)
    qxy, qd, qr = np.concatenate(xs), np.concatenate(ds), np.concatenate(rs)
    qang, qsize = np.concatenate(angs), np.concatenate(sizes)
    knn = matching.knn2(mdesc)
    if spec.get("vote"):
        hyps = crossspectral.rotation_hypotheses(
            qxy, qd, qang, qsize, mxy, mang, msize, knn, spec["vote"]
        )
    else:
        nt = spec.get("max_matches", REG["max_matches"])
        hyps = [(matching.ratio_matches(qxy, qd, qr, mxy, knn, REG["ratio"], nt), 1)]
    ext = mxy.max(axis=0) - mxy.min(axis=0)
    area = float(ext[0] * ext[1]) / fgsd**2
    n = next(iter(q.bands.values())).shape[0]
    out: dict[str, Any] = {"matches": 0, "inliers": 0, "accepted": False, "H": None}
    best = None
    for m, ntests in hyps:
        if len(m) < 4:
            out["matches"] = max(out["matches"], len(m))
            continue
        fit = matching.fit_homography(m.q_xy, m.m_xy, fgsd, REG["ransac"], seed)
        dec = acceptance.decide(
            fit.H, fit.residual_px, fit.n_inliers, area, n, n, q.gsd, REG["acceptance"],
            n_candidates=ntests, inlier_q_xy=None if fit.H is None else m.q_xy[fit.inliers],
        )  # fmt: skip
        nfa = dec.get("log10_nfa", np.inf)
        key = (bool(dec["accepted"]), -nfa if np.isfinite(nfa) else -np.inf)
        if best is None or key > best[0]:
            best = (key, len(m), fit, dec)
    if best is not None and spec.get("guided") and best[2].H is not None:
        # guided re-match around the best hypothesis (accepted or not), refit, decide again
        fit0 = best[2]
        radius = float(spec["guided"]) * fgsd
        gm = crossspectral.guided_matches(qxy, qd, fit0.H, mxy, mdesc, radius, 0.8, knn)
        if len(gm) >= 4:
            fit = matching.fit_homography(gm.q_xy, gm.m_xy, fgsd, REG["ransac"], seed)
            if fit.H is not None:
                # the NFA of the guided set: matches can only land within the radius, but the
                # prior hypothesis was chosen among len(hyps) x bins tests on the whole map
                dec = acceptance.decide(
                    fit.H, fit.residual_px, fit.n_inliers, math.pi * (radius / fgsd) ** 2, n, n,
                    q.gsd, REG["acceptance"], n_candidates=max(t for _, t in hyps) * len(hyps),
                    inlier_q_xy=gm.q_xy[fit.inliers],
                )  # fmt: skip
                if best[0][0] and fit.n_inliers > fit0.n_inliers:
                    # a refinement of an accepted detection: keep its decision, take the fit
                    best = (best[0], len(gm), fit, {**best[3], "refined": True})
                elif dec["accepted"] and spec.get("rescue", True):
                    best = (best[0], len(gm), fit, dec)
    if best is not None:
        _, nm, fit, dec = best
        out.update(matches=nm, inliers=fit.n_inliers, accepted=bool(dec["accepted"]),
                   log10_nfa=dec.get("log10_nfa"), H=fit.H)  # fmt: skip
    out["seconds"] = time.perf_counter() - t0
    return out


def judge(q: Query, sc_map: Scene, res: dict[str, Any]) -> dict[str, Any]:
    err = None
    if res["H"] is not None and q.truth is not None:
        est = matching.apply_h(res["H"], q.truth) / np.array([sc_map.map_gsd, -sc_map.map_gsd])
        err = float(np.median(np.linalg.norm(est - q.truth_map, axis=1)))
    if not res["accepted"]:
        outcome = "missed" if q.truth is not None else "rejected"
    elif q.truth is None or err is None or err > SUCCESS_PX:
        outcome = "false_accept"
    else:
        outcome = "success"
    return {"outcome": outcome, "error_px": err}


# ----------------------------------------------------------------------------- main


def build_set(per_scene: int, seed: int) -> tuple[list[Scene], list[Query]]:
    scenes = all_scenes()
    rng = np.random.default_rng(seed)
    qs = [make_query(sc, rng, i) for sc in scenes for i in range(per_scene)]
    # unrelated pairs: every query against the map of another scene
    neg = []
    for k, sc in enumerate(scenes):
        other = scenes[(k + 2) % len(scenes)]  # +2: never the other date of the same Landsat city
        for q in (x for x in qs if x.scene == sc.name):
            name = q.name + "_vs_" + other.name
            neg.append(Query(name, sc.name, other.name, q.bands, q.gsd, None, None))
    return scenes, qs + neg


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawTextHelpFormatter)
    ap.add_argument("--methods", default=",".join(METHODS))
    ap.add_argument("--per-scene", type=int, default=3)
    ap.add_argument("--seed", type=int, default=11)
    ap.add_argument("--out", default=str(ROOT / "results" / "benchmark" / "crossspectral.json"))
    ap.add_argument("-v", action="store_true", help="one line per query and method")
    a = ap.parse_args(argv)
    if not DATES.is_dir():
        print(f"no development data at {DATES}", file=sys.stderr)
        return 1
    cv2.setNumThreads(1)
    scenes, queries = build_set(a.per_scene, a.seed)
    by = {s.name: s for s in scenes}
    methods = a.methods.split(",")
    rows: dict[str, list[dict[str, Any]]] = {m: [] for m in methods}
    for qi, q in enumerate(queries):
        for name in methods:
            res = run_method(q, by[q.map_scene], METHODS[name], a.seed + qi)
            j = judge(q, by[q.map_scene], res)
            rec = {"query": q.name, "positive": q.truth is not None, **j,
                   "inliers": res["inliers"], "matches": res["matches"],
                   "log10_nfa": res.get("log10_nfa"), "seconds": res["seconds"]}  # fmt: skip
            rows[name].append(rec)
            if a.v:
                e = "-" if j["error_px"] is None else f"{j['error_px']:.2f}"
                print(f"{q.name:34s} {name:18s} {j['outcome']:12s} err {e:>8s} "
                      f"inl {res['inliers']:3d}/{res['matches']:3d}", flush=True)  # fmt: skip
    n_pos = sum(q.truth is not None for q in queries)
    n_neg = len(queries) - n_pos
    print(f"\n{n_pos} queries + {n_neg} unrelated pairs, seed {a.seed}")
    print(
        "| method | registered | false accepts | unrelated accepted | median error px | s/query |"
    )
    print("|---|---|---|---|---|---|")
    summary = {}
    for name in methods:
        r = rows[name]
        ok = [x for x in r if x["outcome"] == "success"]
        fa = sum(x["outcome"] == "false_accept" and x["positive"] for x in r)
        fneg = sum(x["outcome"] == "false_accept" and not x["positive"] for x in r)
        med = float(np.median([x["error_px"] for x in ok])) if ok else float("nan")
        sec = float(np.mean([x["seconds"] for x in r]))
        summary[name] = {"success": len(ok), "positives": n_pos, "false_accept": fa,
                         "unrelated_accepted": fneg, "negatives": n_neg,
                         "median_error_px": med, "seconds_per_query": sec}  # fmt: skip
        print(f"| {name} | {len(ok)}/{n_pos} | {fa} | {fneg}/{n_neg} | {med:.2f} | {sec:.2f} |")
    Path(a.out).parent.mkdir(parents=True, exist_ok=True)
    Path(a.out).write_text(json.dumps({"summary": summary, "rows": rows}, indent=1, default=float))
    return 0


if __name__ == "__main__":
    sys.exit(main())
