"""Issue 20 "accuracy over the whole footprint": where does the p90 error of the registered
cross-spectral queries come from? (global fit, refinement, truth).

    nice -n 10 python benchmarks/diag_p90.py run --half tuning --out /tmp/p90/tuning.pkl
    nice -n 10 python benchmarks/diag_p90.py analyse /tmp/p90/tuning.pkl

``run`` registers every positive query of the half with the workflow default (``wf_default``)
and keeps the homography; ``analyse`` compares, per registered query, the global fit's error
field with the truth, the local refinement's and the final dense fit's, and measures the truth's
own consistency (CFOG shifts of the map rendered through the truth).
"""

from __future__ import annotations

import argparse
import pickle
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "benchmarks"))

import bench_crossspectral as bc  # noqa: E402


def build(which: str, seed: int = 11) -> tuple[list, list]:
    """The benchmark's query set: ``protocol`` (both halves), ``small`` or ``tiny`` (tuning
    cities only, as ``bench_crossspectral.py --set``)."""
    if which == "small":
        return bc.build_small_set(6, seed)
    if which == "tiny":
        return bc.build_small_set(5, seed, bc.TINY_SIDES, "tiny_", 600)
    return bc.build_set(3, seed, 1)


def run(half: str, out: str, seed: int = 11, which: str = "protocol") -> None:
    import cv2

    cv2.setNumThreads(1)
    scenes, queries = build(which, seed)
    by = {s.name: s for s in scenes}
    recs = []
    for qi, q in enumerate(queries):
        if q.truth is None or (which == "protocol" and bc.half_of(by[q.scene].city) != half):
            continue
        res = bc.run_method(q, by[q.map_scene], bc.METHODS["wf_default"], seed + qi)
        j = bc.judge(q, by[q.map_scene], res)
        print(q.name, j, flush=True)
        recs.append(
            {
                "query": q.name,
                "qi": qi,
                "H": res["H"],
                "inliers": res["inliers"],
                "accepted": res["accepted"],
                **j,
            }
        )
    Path(out).write_bytes(pickle.dumps(recs))


def map_image(sc) -> object:
    """The map scene as a MapImage in the benchmark's map units (x = col * gsd, y = -row * gsd)."""
    from rasterio.transform import Affine

    from georeg.register.refine import MapImage

    g = sc.map_gsd
    gray = np.where(sc.map_gray > 0, sc.map_gray.astype(np.float32), np.nan)
    return MapImage(gray, Affine(g, 0, -0.5 * g, 0, -g, 0.5 * g))


def truth_h(q, g: float) -> np.ndarray:
    """Affine query px -> map x, y fitted to the truth points (the truth is affine here)."""
    A = np.c_[q.truth, np.ones(len(q.truth))]
    dst = q.truth_map * np.array([g, -g])
    coef = np.linalg.lstsq(A, dst, rcond=None)[0]
    H = np.eye(3)
    H[:2] = coef.T
    return H


def err_at(x: np.ndarray, y: np.ndarray, q, g: float) -> np.ndarray:
    """Error (map px) of per-pixel x, y at the benchmark's truth points (bilinear)."""
    from scipy.ndimage import map_coordinates

    c, r = q.truth[:, 0], q.truth[:, 1]
    ex = map_coordinates(x, [r, c], order=1) / g
    ey = -map_coordinates(y, [r, c], order=1) / g
    return np.hypot(ex - q.truth_map[:, 0], ey - q.truth_map[:, 1])


def st(e: np.ndarray) -> str:
    return f"{np.median(e):5.2f}/{np.percentile(e, 90):5.2f}/{e.max():5.2f}"


def analyse(path: str, variants: list[str], a_only: tuple[str, ...] = (),
            which: str = "protocol") -> None:
    import yaml

    from georeg.register.geolocation import map_xy
    from georeg.register.refine import refine

    recs = pickle.loads(Path(path).read_bytes())
    scenes, queries = build(which)
    by = {s.name: s for s in scenes}
    qby = {q.name: q for q in queries}
    rconf = yaml.safe_load((ROOT / "config" / "config.yaml").read_text())["refine"]
    extra = {
        "homog": {"model": "homography", "iterations": 1},
    }
    for r in recs:
        if r["outcome"] != "success":
            continue
        q = qby[r["query"]]
        sc = by[q.map_scene]
        g = sc.map_gsd
        band = next(iter(q.bands.values()))
        h, w = band.shape
        mi = map_image(sc)
        x, y = map_xy(r["H"], w, h)
        e0 = err_at(x, y, q, g)
        T = truth_h(q, g)
        # the error field's structure: its translation at the footprint centre vs the rest
        xt, yt = map_xy(T, w, h)
        ev = np.stack([(x - xt) / g, -(y - yt) / g], -1)
        valid = band > 0
        ec = ev[h // 2, w // 2]
        lin = np.hypot(*(ev[valid] - ec).T)
        if a_only and not any(k in r["query"] for k in a_only):
            continue
        line = (
            f"{r['query']:26s} {w:4d}px inl {r['inliers']:3d} q/m {q.gsd / g:4.2f} "
            f"glob {st(e0)} ctr {np.hypot(*ec):4.2f} lin-p90 {np.percentile(lin, 90):5.2f}"
        )
        from georeg.register.densefit import dense_fit

        Hd, dinfo = dense_fit(band, r["H"], mi, {}, rconf)
        xd, yd = map_xy(Hd, w, h)
        line += (
            f" | dense {'ok' if dinfo['accepted'] else 'NO'} {st(err_at(xd, yd, q, g))} "
            f"cv {dinfo.get('cv_rms_px', {}).get('refit', 0):.2f}/"
            f"{dinfo.get('cv_rms_px', {}).get('feature', 0):.2f}"
        )
        for model in ("affine", "auto"):
            Ha, ainfo = dense_fit(band, r["H"], mi, {"model": model}, rconf)
            xa, ya = map_xy(Ha, w, h)
            line += (f" | {model} {'ok' if ainfo['accepted'] else 'NO'} "
                     f"{ainfo.get('model', '-')[:3]} {st(err_at(xa, ya, q, g))}")  # fmt: skip
        for v in variants:
            conf = {**rconf, **extra.get(v, {})} if v != "default" else rconf
            xr, yr, info = refine(band, Hd if v == "dense+local" else r["H"], mi, conf)
            e1 = err_at(xr, yr, q, g)
            line += f" | {v} {info['model'][:4]} {st(e1)}"
        print(line, flush=True)


def truth_check() -> None:
    """Dense CFOG fit of each Sentinel-2 scene's 20 m SWIR band (whole scene) against the 10 m
    luminance of the same date and of the other date, started from the geo-referencing: the
    offset (map px, at the scene centre) and p90 / max of the fitted-vs-geo-referencing field."""
    import yaml

    from georeg.register.densefit import dense_fit
    from georeg.register.geolocation import map_xy

    rconf = yaml.safe_load((ROOT / "config" / "config.yaml").read_text())["refine"]
    cities = sorted(p.name for p in (bc.DATES / "oscd_dev").iterdir())
    for city in cities:
        for rev in (False, True):
            sc = bc.s2_scene(city, rev)  # SWIR of the query date vs RGB of the other date
            # same date: the SWIR against its own date's luminance
            same = bc.s2_scene(city, not rev)
            for label, q_sc, m_sc in (("cross-date", sc, sc), ("same-date", sc, same)):
                # same-date: the map of the query's own date = the other scene's map
                band = bc._stretch(q_sc.swir["1.6um"])
                h, w = band.shape
                to_map = q_sc.to_map if label == "cross-date" else _same_date_to_map(city, rev)
                T = bc.georef_affine(to_map, w, h, m_sc.map_gsd)
                Hf, info = dense_fit(band, T, map_image(m_sc), {"min_gain": -10.0}, rconf)
                xf, yf = map_xy(Hf, w, h)
                xt, yt = map_xy(T, w, h)
                e = np.hypot(xf - xt, yf - yt)[band > 0] / m_sc.map_gsd
                c = (
                    (xf - xt)[h // 2, w // 2] / m_sc.map_gsd,
                    -(yf - yt)[h // 2, w // 2] / m_sc.map_gsd,
                )
                print(
                    f"{sc.name:18s} {label:10s} {w}x{h} tp {info.get('tie_points')} "
                    f"centre offset ({c[0]:+.2f}, {c[1]:+.2f}) map px, field median/p90/max "
                    f"{st(e)}",
                    flush=True,
                )


def _same_date_to_map(city: str, rev: bool):
    """SWIR px of the query date -> 10 m px of the SAME date (both geotransforms)."""
    import glob
    import warnings

    import rasterio

    d = bc.DATES / "oscd_dev" / city
    qd = 2 if rev else 1

    def tr(b: str):
        (p,) = glob.glob(str(d / f"imgs_{qd}" / f"*_{b}.tif"))
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            with rasterio.open(p) as s:
                return s.transform

    t1, inv2 = tr("B11"), ~tr("B04")

    def f(p: np.ndarray) -> np.ndarray:
        lon, lat = t1 * ((p[:, 0] + 0.5), (p[:, 1] + 0.5))
        c, r = inv2 * (lon, lat)
        return np.c_[c - 0.5, r - 0.5]

    return f


def refine_variants(paths: list[str], variants: dict[str, dict], which: str = "protocol") -> None:
    """The refinement stage alone on the homographies saved by ``run`` (several pickles, e.g.
    both halves), once per ``variants`` entry (overrides of config.yaml's ``refine``): per
    half, registered queries with p90 <= 2 px against the geo-referenced truth and against the
    Sentinel-2 content truth (``bench_crossspectral.CONTENT_TRUTH``), and how many end more than
    0.25 px worse in p90 than the feature homography (content truth)."""
    scenes, queries = build(which)
    by = {s.name: s for s in scenes}
    qby = {q.name: q for q in queries}
    bc.load_content_truth(scenes, ROOT / "results" / "benchmark" / "content_truth.json")
    stats: dict[tuple[str, str], list] = {}
    for path in paths:
        for r in pickle.loads(Path(path).read_bytes()):
            if r["outcome"] != "success":
                continue
            q = qby[r["query"]]
            sc = by[q.map_scene]
            half = bc.half_of(sc.city) if which == "protocol" else which
            base = bc.judge(q, sc, {"H": r["H"], "accepted": True})
            cells = [f"feature {base['p90_px']:5.2f}/{base['p90_content_px']:5.2f}"]
            for name, over in variants.items():
                out = bc.run_refine(q, sc, r["H"], {"bands": "auto", "refine": over})
                j = bc.judge(q, sc, {**out, "H": r["H"], "accepted": True})
                worse = j["p90_content_px"] > base["p90_content_px"] + 0.25
                stats.setdefault((name, half), []).append((j["p90_px"], j["p90_content_px"], worse))
                cells.append(f"{name} {j['p90_px']:5.2f}/{j['p90_content_px']:5.2f}"
                             f"{' WORSE' if worse else ''} gf {out.get('global_fit')} "
                             f"df {out.get('direct_fit')}")  # fmt: skip
            print(f"{half[:5]} {r['query'][:32]:32s} " + " | ".join(cells), flush=True)
    print("| variant | half | p90 <= 2 px | p90 <= 2 px (content truth) | median p90 (content) "
          "| worse than the feature homography |")  # fmt: skip
    for (name, half), v in stats.items():
        a = np.array(v, float)
        print(f"| {name} | {half} | {int((a[:, 0] <= 2).sum())}/{len(a)} | "
              f"{int((a[:, 1] <= 2).sum())}/{len(a)} | {np.median(a[:, 1]):.2f} | "
              f"{int(a[:, 2].sum())} |")  # fmt: skip


def compare(path: str, base: str = "wf_default") -> None:
    """Per query of a bench_crossspectral.py JSON: p90 / max of every method beside ``base``,
    and per method and half how many registered queries end worse than ``base`` (p90 or max
    more than 0.25 px higher)."""
    import json

    rows = json.loads(Path(path).read_text())["rows"]
    methods = list(rows)
    by = {m: {r["query"]: r for r in rows[m] if r["positive"]} for m in methods}
    for q, r0 in by[base].items():
        if r0["outcome"] != "success":
            continue
        cells = [f"{m}: {by[m][q]['p90_px']:.2f}/{by[m][q]['max_px']:.2f}" for m in methods
                 if by[m][q]["outcome"] == "success"]  # fmt: skip
        print(f"{r0['half'][:5]} {q:28s} " + " | ".join(cells))
    for m in methods:
        for half in ("tuning", "checking"):
            ok = [q for q, r in by[m].items() if r["half"] == half and r["outcome"] == "success"]
            worse = [q for q in ok if by[base][q]["outcome"] == "success" and (
                by[m][q]["p90_px"] > by[base][q]["p90_px"] + 0.25
                or by[m][q]["max_px"] > by[base][q]["max_px"] + 0.25)]  # fmt: skip
            p90 = np.array([by[m][q]["p90_px"] for q in ok])
            mx = np.array([by[m][q]["max_px"] for q in ok])
            print(
                f"{m:32s} {half:8s} registered {len(ok)} p90<=2 {int((p90 <= 2).sum())} "
                f"median p90 {np.median(p90):.2f} median max {np.median(mx):.2f} "
                f"worse than {base} (>0.25 px p90 or max): {len(worse)} {worse}"
            )


if __name__ == "__main__":
    ap = argparse.ArgumentParser()
    ap.add_argument("cmd")
    ap.add_argument("arg", nargs="?")
    ap.add_argument("--half", default="tuning")
    ap.add_argument("--out", default="/tmp/p90/tuning.pkl")
    ap.add_argument("--set", default="protocol", choices=("protocol", "small", "tiny"))
    ap.add_argument("--variants", default="default,direct,primary_band",
                    help="variants: refinement overrides (default, direct, primary_band, gf_sim, no_gf, gf_1se)")
    a = ap.parse_args()
    if a.cmd == "run":
        run(a.half, a.out, which=a.set)
    elif a.cmd == "variants":  # arg: comma-separated pickles
        known = {
            "default": {},
            "direct": {"direct_fit": {"enabled": True}},
            "primary_band": {"pooled_bands": False},
            "gf_sim": {"global_fit": {"model": "similarity"}},
            "no_gf": {"global_fit": {"enabled": False}},
            "gf_1se": {"global_fit": {"auto_rule": "one_se"}},
        }
        refine_variants(a.arg.split(","), {k: known[k] for k in a.variants.split(",")},
                        which=a.set)  # fmt: skip
    elif a.cmd == "analyse":
        analyse(a.arg, [], which=a.set)
    elif a.cmd == "compare":
        compare(a.arg)
    elif a.cmd == "truth":
        truth_check()
