"""Sentinel-2 cities as a user hands them over, through the real ``snakemake`` command.

The unseen case of issue 34 (19 OSCD cities: a date's 20 m SWIR under an unknown rotation, the
other date's 10 m RGB as the map) in the form it comes in, on the five cities of
``../shared/data/swir_dates/oscd_dev``: the map is the map date's B04/B03/B02 stacked into one
GeoTIFF in EPSG:4326 as delivered (the release's geotransform: the city's bounding box spread
over the pixels, square in degrees), ``map.crs`` the city's UTM zone (what the input check asks
for); the query is the other date's B11 + B12 whole, rotated onto a canvas (a 2-band GeoTIFF
without CRS, wavelengths in the band descriptions, ``gsd_m: 20``); the truth is every query
pixel's map x, y through the two dates' geotransforms. Each city in both date directions; each
map also gets another city's query of its half (``--others all``: every other city's), which
must end ``not_found``. Success: registered with a
median error <= 5 map px. Halves by city as the cross-spectral protocol: tuning Abu Dhabi,
Saclay; checking Hong Kong, Norcia.

Beside it, plain OpenCV SIFT on the same files as the workflow's map grid holds them (the
query's first band against the map's luminance in the map CRS, ratio 0.8, MAGSAC homography,
> 5 inliers).

    nice python benchmarks/bench_s2_cities.py --work /tmp/s2cities --out benchmarks/out/s2.json

Three queries of each city direction run against its map in one ``snakemake`` run (the map made
once): both bands (``query.tif``), and B11 and B12 each alone as a one-band file without
wavelengths.

Seconds: wall time of the whole ``snakemake`` run (map, index, registration, products, report).
"""

from __future__ import annotations

import argparse
import glob
import json
import os
import subprocess
import sys
import time
import warnings
from pathlib import Path
from typing import Any

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from bench_crossspectral import rotation_canvas  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
OSCD = ROOT.parent / "shared" / "data" / "swir_dates" / "oscd_dev"
TUNING = ("abudhabi", "saclay_e", "saclay_w")
SUCCESS_PX = 5.0
MIN_CROP_PX = 96  # ``--crop``: a query side at least this many px (1.9 km at 20 m)


def utm_of(lon: float, lat: float) -> str:
    return f"EPSG:{(32600 if lat >= 0 else 32700) + int((lon + 180) // 6) + 1}"


def _band(city: str, date: int, band: str) -> tuple[np.ndarray, dict[str, Any]]:
    import rasterio

    (p,) = glob.glob(str(OSCD / city / f"imgs_{date}" / f"*_{band}.tif"))
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        with rasterio.open(p) as s:
            return s.read(1), s.profile


def make_case(city: str, reverse: bool, theta: float, out: Path,
              crop: tuple[int, int, int, int] | None = None) -> dict[str, Any]:
    """Write the user's inputs of one city direction under ``out``: ``map.tif`` (EPSG:4326 RGB),
    ``query.tif`` (B11 + B12, only the window ``crop`` = (row, col, height, width) of them when
    given, rotated by ``theta`` deg), ``b11.tif`` and ``b12.tif`` (each band
    alone, without its wavelength), ``truth.tif`` (2 bands: map x, y of each query pixel centre
    in the map CRS); returns the ``map`` entry and the ``query`` (both bands), ``b11`` and ``b12``
    query entries."""
    import cv2
    import rasterio
    from pyproj import Transformer

    warnings.simplefilter("ignore", rasterio.errors.NotGeoreferencedWarning)
    qd, md = (2, 1) if reverse else (1, 2)
    out.mkdir(parents=True, exist_ok=True)
    rgb = [_band(city, md, b) for b in ("B04", "B03", "B02")]
    prof = rgb[0][1] | {"count": 3, "driver": "GTiff"}
    t = prof["transform"]
    lon, lat = t.c + t.a * prof["width"] / 2, t.f + t.e * prof["height"] / 2
    crs = utm_of(lon, lat)
    with rasterio.open(out / "map.tif", "w", **prof) as ds:
        ds.write(np.stack([a for a, _ in rgb]))
        for i, w in enumerate((665, 560, 490), 1):
            ds.set_band_description(i, f"{w} nm")
    (b11, p11), (b12, _) = _band(city, qd, "B11"), _band(city, qd, "B12")
    r0, c0 = (crop[0], crop[1]) if crop else (0, 0)
    if crop:
        b11, b12 = (b[r0 : r0 + crop[2], c0 : c0 + crop[3]] for b in (b11, b12))
    cw, ch, M = rotation_canvas(b11.shape[1], b11.shape[0], theta)  # query px -> source px
    A, off = M[:, :2], M[:, 2]

    def warp(a: np.ndarray) -> np.ndarray:
        return cv2.warpAffine(a.astype(np.float32), M, (cw, ch),
                              flags=cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP, borderValue=0)  # fmt: skip

    with rasterio.open(out / "query.tif", "w", driver="GTiff", width=cw, height=ch, count=2,
                       dtype="uint16", nodata=0) as ds:  # fmt: skip
        ds.write(np.stack([warp(b11), warp(b12)]).astype(np.uint16))
        ds.set_band_description(1, "1610 nm")
        ds.set_band_description(2, "2190 nm")
    for name, band in (("b11", b11), ("b12", b12)):  # one band, no wavelength: band 0 alone
        with rasterio.open(out / f"{name}.tif", "w", driver="GTiff", width=cw, height=ch, count=1,
                           dtype="uint16", nodata=0) as ds:  # fmt: skip
            ds.write(warp(band).astype(np.uint16)[None])
    uu, vv = np.meshgrid(np.arange(cw, dtype=float), np.arange(ch, dtype=float))
    sx, sy = A[0, 0] * uu + A[0, 1] * vv + off[0] + c0, A[1, 0] * uu + A[1, 1] * vv + off[1] + r0
    T = p11["transform"]
    lo, la = T.c + (sx + 0.5) * T.a + (sy + 0.5) * T.b, T.f + (sx + 0.5) * T.d + (sy + 0.5) * T.e
    X, Y = Transformer.from_crs("EPSG:4326", crs, always_xy=True).transform(lo, la)
    with rasterio.open(out / "truth.tif", "w", driver="GTiff", width=cw, height=ch, count=2,
                       dtype="float64") as ds:  # fmt: skip
        ds.write(np.stack([X, Y]))
    truth = str(out / "truth.tif")
    return {"map": {"orthophoto": str(out / "map.tif"), "crs": crs, "lidar": []},
            "query": {"image": str(out / "query.tif"), "gsd_m": 20.0, "truth": truth},
            **{k: {"image": str(out / f"{k}.tif"), "gsd_m": 20.0, "truth": truth} for k in ("b11", "b12")}}  # fmt: skip


def run_workflow(work: Path, map_entry: dict[str, Any], queries: dict[str, Any],
                 extra: dict[str, Any] | None = None) -> dict[str, Any]:
    """``snakemake --cores 2`` in ``work`` with the map and ``queries`` (and ``extra`` keys, e.g.
    ``register``): each one's outcome."""
    import yaml

    work.mkdir(parents=True, exist_ok=True)
    cfg = work / "config.yaml"
    cfg.write_text(yaml.safe_dump({**(extra or {}), "map": map_entry, "queries": queries, "frames": {}}))
    t0 = time.perf_counter()
    cmd = [sys.executable, "-m", "snakemake", "-s", str(ROOT / "Snakefile"), "-d", str(work),
           *[f"results/queries/{q}/registration.json" for q in queries],
           "--cores", "2", "--configfile", str(cfg)]  # fmt: skip
    proc = subprocess.run(cmd, capture_output=True, text=True, cwd=work)
    secs = time.perf_counter() - t0
    if proc.returncode != 0:
        return {q: {"status": "error", "seconds": secs, "stderr": proc.stderr[-2000:]} for q in queries}
    out = {}
    for q in queries:
        reg = json.loads((work / f"results/queries/{q}/registration.json").read_text())
        ev = reg.get("evaluation") or {}
        rift = (reg.get("split") or {}).get("rift") or {}
        out[q] = {"status": reg["status"], "median_px": (ev.get("px") or {}).get("median"),
                  "seconds": secs, "aspects": rift.get("aspects"), "reason": reg.get("reason"),
                  "sources": [s["name"] for s in reg.get("sources") or [] if s.get("accepted")]}  # fmt: skip
    return out


def sift_plain(work: Path, q: str, truth: str | None) -> dict[str, Any]:
    """Plain SIFT: the query's first band against the map grid's orthophoto (luminance)."""
    import cv2
    import rasterio

    t0 = time.perf_counter()
    with rasterio.open(work / "results/map/mosaic/ortho.vrt") as ds:
        rgb = ds.read().astype(np.float32)
        G = ds.transform
    with rasterio.open(work / f"results/queries/{q}/band.tif") as ds:
        q = ds.read(1)
    lum = (0.299 * rgb[0] + 0.587 * rgb[1] + 0.114 * rgb[2]).astype(np.uint8)
    sift = cv2.SIFT_create()
    kq, dq = sift.detectAndCompute(q, (q > 0).astype(np.uint8))
    km, dm = sift.detectAndCompute(lum, (lum > 0).astype(np.uint8))
    out: dict[str, Any] = {"accepted": False, "median_px": None}
    if dq is not None and dm is not None and len(kq) >= 4 and len(km) >= 4:
        fl = cv2.FlannBasedMatcher({"algorithm": 1, "trees": 4}, {"checks": 64})
        good = [m for m, n in (p for p in fl.knnMatch(dq, dm, k=2) if len(p) == 2)
                if m.distance < 0.8 * n.distance]  # fmt: skip
        if len(good) >= 4:
            a = np.float32([kq[m.queryIdx].pt for m in good])
            b = np.float32([km[m.trainIdx].pt for m in good])
            H, inl = cv2.findHomography(a, b, cv2.USAC_MAGSAC, 3.0)
            if H is not None and int(inl.sum()) > 5:
                out["accepted"] = True
                if truth:
                    with rasterio.open(truth) as ds:
                        X, Y = ds.read()
                    vv, uu = np.nonzero(q > 0)
                    p = cv2.perspectiveTransform(np.float32(np.c_[uu, vv])[None], H)[0]
                    col, row = ~G * (X[vv, uu], Y[vv, uu])
                    out["median_px"] = float(np.median(np.hypot(p[:, 0] + 0.5 - col, p[:, 1] + 0.5 - row)))
    out["seconds"] = time.perf_counter() - t0
    return out


def outcome(positive: bool, accepted: bool, median_px: float | None) -> str:
    if not positive:
        return "accepted" if accepted else "rejected"
    if not accepted:
        return "missed"
    return "success" if median_px is not None and median_px <= SUCCESS_PX else "false_accept"


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawTextHelpFormatter)
    ap.add_argument("--work", default="/tmp/bench_s2_cities")
    ap.add_argument("--out", default=str(ROOT / "results" / "benchmark" / "s2_cities.json"))
    ap.add_argument("--seed", type=int, default=11)
    ap.add_argument("--cities", default="", help="comma-separated subset (default: all five)")
    ap.add_argument("--others", choices=("half", "all"), default="half",
                    help="negatives per map: one other city's query of its half, or every other city's")
    ap.add_argument("--crop", type=float, default=0.0,
                    help="a part of the city: each query cut to this fraction of each side (at least "
                         "MIN_CROP_PX), at a random place (0: the whole scene)")
    ap.add_argument("--config", default="",
                    help="a YAML file of extra configuration keys for every run (e.g. register: ...)")
    a = ap.parse_args(argv)
    extra = None
    if a.config:
        import yaml

        try:
            extra = yaml.safe_load(Path(a.config).read_text()) or {}
        except (OSError, yaml.YAMLError) as e:
            print(f"--config {a.config}: cannot be read as YAML ({e})", file=sys.stderr)
            return 1
        if not isinstance(extra, dict):
            print(f"--config {a.config}: not a mapping of configuration keys", file=sys.stderr)
            return 1
    if not OSCD.is_dir():
        print(f"no development data at {OSCD}", file=sys.stderr)
        return 1
    cities = a.cities.split(",") if a.cities else sorted(p.name for p in OSCD.iterdir())
    rng = np.random.default_rng(a.seed)
    cases = [(c, rev, float(rng.uniform(0, 360))) for c in cities for rev in (False, True)]
    work = Path(a.work)
    rows = []
    made = {}
    for city, rev, theta in cases:  # the crops drawn after the rotations: a seed's rotations kept
        name = f"{city}{'_rev' if rev else ''}"
        crop = None
        if a.crop > 0:
            H, W = _band(city, 2 if rev else 1, "B11")[0].shape
            h, w = (min(n, max(MIN_CROP_PX, round(n * a.crop))) for n in (H, W))
            crop = (int(rng.integers(0, H - h + 1)), int(rng.integers(0, W - w + 1)), h, w)
        made[name] = make_case(city, rev, theta, work / "inputs" / name, crop)
    names = list(made)
    for k, name in enumerate(names):
        city = name.removesuffix("_rev")
        half = "tuning" if city in TUNING else "checking"
        base = city.split("_")[0]
        others = [n for n in names[k + 1:] + names[:k] if n.removesuffix("_rev").split("_")[0] != base]
        if a.others == "all":  # every other city's query (one date direction each)
            others = [n for n in others if not n.endswith("_rev")]
            others = [n for i, n in enumerate(others) if n.split("_")[0] not in {m.split("_")[0] for m in others[:i]}]
        else:  # one, of the same half
            others = [next(n for n in others if (n.removesuffix("_rev") in TUNING) == (half == "tuning"))]
        queries = {"q": made[name]["query"], "b11": made[name]["b11"], "b12": made[name]["b12"],
                   **{f"other_{o}": {k: v for k, v in made[o]["query"].items() if k != "truth"}
                      for o in others}}  # fmt: skip
        res = run_workflow(work / "runs" / name, made[name]["map"], queries, extra)
        for key, r in res.items():
            positive = not key.startswith("other")
            s = (sift_plain(work / "runs" / name, key, queries[key].get("truth"))
                 if r["status"] != "error" else {"accepted": False})  # fmt: skip
            row = {"map": name, "query": key.removeprefix("other_") if not positive else name,
                   "kind": key if positive else "other", "half": half,
                   "positive": positive, **r,
                   "outcome": outcome(positive, r.get("status") == "registered", r.get("median_px")),
                   "sift_plain": {**s, "outcome": outcome(positive, s["accepted"], s.get("median_px"))}}  # fmt: skip
            rows.append(row)
            mp = "-" if r.get("median_px") is None else f"{r['median_px']:.2f}"
            print(f"{half[:5]} {row['query'] + ' ' + key:20s} on {name:14s} {row['outcome']:12s} {mp:>6s} px "
                  f"{r['seconds']:5.1f} s by {r.get('sources')}  plain SIFT {row['sift_plain']['outcome']}",
                  flush=True)  # fmt: skip
    print("| method | half | both bands pooled | B11 alone | B12 alone | false accepts | other city's map accepted |")
    print("|---|---|---:|---:|---:|---:|---:|")
    summary: dict[str, Any] = {}
    for method in ("workflow", "sift_plain"):
        for half in ("tuning", "checking"):
            rs = [r if method == "workflow" else {**r["sift_plain"], "kind": r["kind"]}
                  for r in rows if r["half"] == half]  # fmt: skip
            sm: dict[str, Any] = {}
            for kind in ("q", "b11", "b12"):
                pos = [x for x in rs if x["kind"] == kind]
                sm[kind] = f"{sum(x['outcome'] == 'success' for x in pos)}/{len(pos)}"
            sm["false_accept"] = sum(x["outcome"] == "false_accept" for x in rs)
            neg = [x for x in rs if x["kind"] == "other"]
            sm["negatives"] = f"{sum(x['outcome'] == 'accepted' for x in neg)}/{len(neg)}"
            summary[f"{method}/{half}"] = sm
            print(f"| {method} | {half} | {sm['q']} | {sm['b11']} | {sm['b12']} | {sm['false_accept']} "
                  f"| {sm['negatives']} |")  # fmt: skip
    Path(a.out).parent.mkdir(parents=True, exist_ok=True)
    tmp = Path(a.out).with_suffix(".tmp")
    tmp.write_text(json.dumps({"summary": summary, "rows": rows}, indent=1, default=float))
    os.replace(tmp, a.out)
    return 0


if __name__ == "__main__":
    sys.exit(main())
