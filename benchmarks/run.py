"""Registration benchmark suite (issue 7): a ladder of difficulty and real cases, paper vs index.

    source /work/venv/bin/activate
    python benchmarks/run.py                 # default suite (benchmarks/scenarios.yaml), minutes
    python benchmarks/run.py --full          # + the `full_scenarios`
    python benchmarks/run.py --only demo,inverted --strategies index

Each scenario is a query band + a map with a known truth (true map x, y per query pixel). The
map's features, vocabulary and index are built here with the library (georeg.index.features,
georeg.index.vocabulary, georeg.index.map_index; cached under results/benchmark/cache/), the query is split into
parts searched with georeg.register.search and fused with georeg.register.fuse, exactly as the workflow does, and
the result is judged with georeg.report.evaluation. Output: results/benchmark/summary.csv (one row per
scenario, the strategies side by side) and summary.json (everything), which the report shows.
"""

from __future__ import annotations

import argparse
import csv
import hashlib
import json
import logging
import math
import sys
import time
import warnings
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import yaml

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
SHARED = ROOT.parent / "shared" / "data"

from georeg.report.evaluation import classify, error_field, error_stats, inside_fraction  # noqa: E402

log = logging.getLogger("benchmark")


# ----------------------------------------------------------------------------- data


@dataclass
class MapImage:
    """A map raster: gray uint8 image (0 = nodata), validity, affine transform, CRS WKT."""

    gray: np.ndarray
    valid: np.ndarray
    transform: Any
    crs_wkt: str | None

    @property
    def bounds(self) -> tuple[float, float, float, float]:
        from rasterio.transform import array_bounds

        w, s, e, n = array_bounds(self.gray.shape[0], self.gray.shape[1], self.transform)
        return (w, s, e, n)


@dataclass
class Query:
    """A query band (uint8, 0 = nodata), its GSD (None = unknown) and the truth x, y."""

    band: np.ndarray
    gsd_m: float | None
    tx: np.ndarray
    ty: np.ndarray


def _read(path: Path) -> Any:
    import rasterio

    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        return rasterio.open(path)


def _stretch(a: np.ndarray, valid: np.ndarray) -> np.ndarray:
    from georeg.register.band import stretch_uint8

    return stretch_uint8(a.astype(np.float32), valid)[0]


DEMO_DIR: Path | None = None  # --demo-dir


def demo_dir(cache: Path) -> Path:
    """--demo-dir, else results/demo when the workflow made it, else a scene generated into the
    cache (the demo config of config/config.yaml)."""
    d = DEMO_DIR or ROOT / "results" / "demo"
    if (d / "orthophoto.tif").exists() and (d / "queries" / "demo_truth.tif").exists():
        return d
    d = cache / "demo_scene"
    if not (d / "queries" / "demo_truth.tif").exists():
        from georeg.demo import generate_scene

        conf = yaml.safe_load((ROOT / "config" / "config.yaml").read_text())["demo"]
        log.info("generating the demo scene into %s (about a minute)", d)
        generate_scene(conf, d)
    return d


def load_map(spec: dict[str, Any], cache: Path) -> MapImage:
    """The map image of a `maps:` entry (optionally cropped to a fraction of its width)."""
    from georeg.index.features import rgb_to_gray

    src = spec["source"]
    if src == "demo":
        with _read(demo_dir(cache) / "orthophoto.tif") as ds:
            rgb, tr, crs = ds.read(), ds.transform, ds.crs
        gray = rgb_to_gray(rgb[:3])
        valid = np.ones(gray.shape, bool)
        gray = np.clip(gray, 1, 255).astype(np.uint8)
    elif src == "enmap_visible":
        with _read(SHARED / "enmap_potsdam" / "enmap_potsdam_mosaic_subset.tif") as ds:
            wl = [float(d.split()[0]) for d in ds.descriptions]
            idx = [int(np.argmin(np.abs(np.array(wl) - w))) + 1 for w in (640, 550, 460)]
            rgb, tr, crs = ds.read(idx), ds.transform, ds.crs
        valid = np.isfinite(rgb).all(axis=0)
        gray = _stretch(np.nan_to_num(rgb_to_gray(np.nan_to_num(rgb))), valid)
    elif src in ("nanjing_rgb_date2", "taizhou_rgb_date2"):
        path = _landsat(src.split("_")[0], 2)
        with _read(path) as ds:
            rgb, tr, crs = ds.read([3, 2, 1]), ds.transform, ds.crs
        valid = (rgb > 0).any(axis=0)
        gray = _stretch(rgb_to_gray(rgb.astype(np.float32)), valid)
    else:
        raise ValueError(f"unknown map source {src!r}")
    if "crop_x" in spec:
        a, b = spec["crop_x"]
        w = gray.shape[1]
        c0, c1 = int(a * w), int(b * w)
        gray, valid = gray[:, c0:c1], valid[:, c0:c1]
        from rasterio.transform import Affine

        tr = tr * Affine.translation(c0, 0)
    return MapImage(np.ascontiguousarray(gray), valid, tr, crs.to_wkt() if crs else None)


def _landsat(city: str, date: int) -> Path:
    d = SHARED / "swir_dates" / f"landsat_{city}"
    names = {
        "nanjing": ["LT51200382000124BJC00_Nanjing", "LT51200382002193BJC00_Nanjing"],
        "taizhou": ["2000TM", "2003TM"],
    }
    return d / names[city][date - 1]


def load_base(name: str, cache: Path, rng: np.random.Generator) -> Query:
    """The base query of a scenario (before the warp)."""
    from georeg.io.query import open_query
    from georeg.register.band import select_band, stretch_uint8
    from georeg.report.evaluation import read_truth

    if name in ("demo", "outside"):
        d = demo_dir(cache) / "queries"
        band, mask, _ = select_band(open_query(d / f"{name}.hdr"), "1200nm")
        u8 = stretch_uint8(band, mask)[0]
        tx, ty = read_truth(d / f"{name}_truth.tif")
        return Query(u8, 0.8, tx, ty)
    if name == "enmap_swir":
        with _read(SHARED / "enmap_potsdam" / "enmap_potsdam_mosaic_subset.tif") as ds:
            wl = np.array([float(x.split()[0]) for x in ds.descriptions])
            b = ds.read(int(np.argmin(np.abs(wl - 1650))) + 1)
            tr = ds.transform
        valid = np.isfinite(b)
        return _georef_query(_stretch(np.nan_to_num(b), valid), tr, 30.0, None)
    if name in ("nanjing_swir_date1", "taizhou_swir_date1"):
        with _read(_landsat(name.split("_")[0], 1)) as ds:
            b = ds.read(5)
            tr = ds.transform
        h, w = b.shape
        win = (int(0.2 * h), int(0.2 * w), int(0.6 * h), int(0.55 * w))  # r0, c0, height, width
        return _georef_query(_stretch(b, b > 0), tr, 30.0, win)
    raise ValueError(f"unknown base query {name!r}")


def _georef_query(
    u8: np.ndarray, tr: Any, gsd: float, win: tuple[int, int, int, int] | None
) -> Query:
    """A band of a geo-referenced raster as a query: the truth is its own geotransform."""
    if win is not None:
        r0, c0, h, w = win
        u8 = u8[r0 : r0 + h, c0 : c0 + w]
        from rasterio.transform import Affine

        tr = tr * Affine.translation(c0, r0)
    h, w = u8.shape
    cols, rows = np.meshgrid(np.arange(w) + 0.5, np.arange(h) + 0.5)
    tx = tr.a * cols + tr.b * rows + tr.c
    ty = tr.d * cols + tr.e * rows + tr.f
    return Query(np.ascontiguousarray(u8), gsd, tx, ty)


# ----------------------------------------------------------------------------- warps


def apply_warp(q: Query, warp: dict[str, Any] | None, rng: np.random.Generator) -> Query:
    """Rotate / scale the band and its truth together, then degrade the band's radiometry."""
    if not warp:
        return q
    band, tx, ty, gsd = q.band, q.tx, q.ty, q.gsd_m
    ang = float(warp.get("rotate_deg", 0.0))
    s = float(warp.get("scale", 1.0))
    if ang or s != 1.0:
        h, w = band.shape
        M = cv2.getRotationMatrix2D(((w - 1) / 2, (h - 1) / 2), ang, s)
        c, si = abs(M[0, 0]), abs(M[0, 1])
        nw, nh = int(math.ceil(w * c + h * si)), int(math.ceil(w * si + h * c))
        M[0, 2] += (nw - 1) / 2 - (w - 1) / 2
        M[1, 2] += (nh - 1) / 2 - (h - 1) / 2
        band = cv2.warpAffine(
            band, M, (nw, nh), flags=cv2.INTER_AREA if s < 1 else cv2.INTER_LINEAR
        )
        valid = cv2.warpAffine((q.band > 0).astype(np.uint8), M, (nw, nh), flags=cv2.INTER_NEAREST)
        band = np.where(valid > 0, np.maximum(band, 1), 0).astype(np.uint8)
        tx, ty = _warp_truth64(q.tx, q.ty, M, (nh, nw))
        tx[valid == 0] = np.nan
        ty[valid == 0] = np.nan
        gsd = None if gsd is None else gsd / s
    valid = band > 0
    f = band.astype(np.float32)
    h, w = f.shape
    if warp.get("shadows"):
        f *= np.where(_blobs(h, w, float(warp["shadows"]), rng, 40), 0.35, 1.0)
    if warp.get("change"):
        m = _blobs(h, w, float(warp["change"]), rng, 25, rect=True)
        f = np.where(m, _patches(h, w, rng), f)
    if warp.get("noise_sigma"):
        f += rng.normal(0, float(warp["noise_sigma"]), f.shape).astype(np.float32)
    if warp.get("invert"):
        f = 256.0 - f
    out = np.where(valid, np.clip(np.round(f), 1, 255), 0).astype(np.uint8)
    return Query(out, gsd if warp.get("gsd_known", True) else None, tx, ty)


def _warp_truth64(tx: np.ndarray, ty: np.ndarray, M: np.ndarray, shape: tuple[int, int]):
    """Truth of the warped query in float64: bilinear in the source truth at M^-1 positions."""
    from georeg.index.features import sample_bilinear

    Mi = cv2.invertAffineTransform(M)
    nh, nw = shape
    u, v = np.meshgrid(np.arange(nw, dtype=np.float64), np.arange(nh, dtype=np.float64))
    su = Mi[0, 0] * u + Mi[0, 1] * v + Mi[0, 2]
    sv = Mi[1, 0] * u + Mi[1, 1] * v + Mi[1, 2]
    # sample offsets from the first valid value in float32 (exact enough) and add it back
    x0 = float(np.nanmin(tx))
    y0 = float(np.nanmin(ty))
    ox = sample_bilinear((tx - x0).astype(np.float32), su.ravel(), sv.ravel()).reshape(nh, nw)
    oy = sample_bilinear((ty - y0).astype(np.float32), su.ravel(), sv.ravel()).reshape(nh, nw)
    return ox.astype(np.float64) + x0, oy.astype(np.float64) + y0


def _blobs(h: int, w: int, frac: float, rng: np.random.Generator, size: int, rect: bool = False):
    """A random mask of ellipses (shadows) or rectangles (changes) covering about ``frac``."""
    m = np.zeros((h, w), np.uint8)
    while m.mean() < frac:
        cx, cy = int(rng.integers(0, w)), int(rng.integers(0, h))
        a, b = (int(v) for v in rng.integers(size // 3, size * 2, 2))
        if rect:
            cv2.rectangle(m, (cx, cy), (cx + a, cy + b), 1, -1)
        else:
            cv2.ellipse(m, (cx, cy), (a, b), float(rng.uniform(0, 180)), 0, 360, 1, -1)
    return m > 0


def _patches(h: int, w: int, rng: np.random.Generator) -> np.ndarray:
    """Random new surfaces: blocks of random brightness with a little texture."""
    small = rng.uniform(20, 235, (max(1, h // 25), max(1, w // 25))).astype(np.float32)
    big = cv2.resize(small, (w, h), interpolation=cv2.INTER_NEAREST)
    return big + rng.normal(0, 6, (h, w)).astype(np.float32)


# ----------------------------------------------------------------------------- the map index


def build_source(
    name: str, m: MapImage, spec: dict[str, Any], features_conf: dict, cache: Path, seed: int
) -> Any:
    """Tile the map, extract features, train the vocabulary, build the index (cached)."""
    from georeg.index.features import save_tile_features, tile_features
    from georeg.index.map_index import MapIndex
    from georeg.index.vocabulary import sample_descriptors, train_kmeans
    from georeg.register.search import MapSource

    key = hashlib.sha1(
        json.dumps(
            [name, spec, features_conf, seed, m.gray.shape], sort_keys=True, default=str
        ).encode()
    ).hexdigest()[:10]
    d = cache / "maps" / f"{name}-{key}"
    index_dir = d / "index"
    if not (index_dir / "meta.json").exists():
        t0 = time.perf_counter()
        tp = int(spec.get("tile_px", 512))
        h, w = m.gray.shape
        dirs, ids = [], []
        for r in range(0, h, tp):
            for c in range(0, w, tp):
                # a margin so keypoints near the core edges are detected as in one image
                mg = 32
                r0, c0 = max(0, r - mg), max(0, c - mg)
                r1, c1 = min(h, r + tp + mg), min(w, c + tp + mg)
                g = m.gray[r0:r1, c0:c1]
                v = m.valid[r0:r1, c0:c1]
                if not v.any():
                    continue
                from rasterio.transform import Affine

                tr = m.transform * Affine.translation(c0, r0)
                core = (c - c0, r - r0, min(tp, w - c), min(tp, h - r))
                tf = tile_features(g, None if v.all() else v, tr, features_conf, core)
                tid = f"r{r // tp:03d}_c{c // tp:03d}"
                meta = {
                    "n": len(tf),
                    "crs_wkt": m.crs_wkt,
                    "features_conf": features_conf,
                    "features_conf_hash": "bench",
                    "gsd_m": abs(m.transform.a),
                }
                save_tile_features(d / "features" / tid, tf, meta)
                dirs.append(d / "features" / tid)
                ids.append(tid)
        x = sample_descriptors(dirs, 200_000, seed)
        k = min(int(spec.get("k", 500)), max(2, len(x) // 8))
        cent, _ = train_kmeans(x, k, seed, "faiss", 15, threads=2)
        MapIndex.build(
            dirs,
            ids,
            cent,
            index_dir,
            crs_wkt=m.crs_wkt,
            extra_meta={"features_conf": features_conf, "gsd_m": abs(m.transform.a)},
        )
        log.info(
            "map %s: %d tiles, %d words, built in %.1f s",
            name,
            len(ids),
            k,
            time.perf_counter() - t0,
        )
    src = MapSource.from_index(index_dir)
    src.gsd_m = abs(float(m.transform.a))
    return src


# ----------------------------------------------------------------------------- one run


def register(q: Query, source: Any, conf: dict[str, Any], seed: int) -> dict[str, Any]:
    """Parts searched one after the other (as the workflow's jobs would), then fused."""
    from georeg.register.band import feature_scales
    from georeg.register.fuse import fuse
    from georeg.register.search import part_rows, query_features, search_part

    t0 = time.perf_counter()
    factors = feature_scales(q.gsd_m, source.gsd_m, conf.get("unknown_gsd_factors", [1.0]))
    h = q.band.shape[0]
    n = int(conf.get("parts", 2))
    parts = []
    for i in range(n):
        qf = query_features(q.band, part_rows(h, n, i), factors, source.features_conf)
        parts.append({"part": i, **search_part(qf, source, conf, q.gsd_m, seed + 1000 * i)})
    t_search = time.perf_counter() - t0
    if any(p["accepted"] for p in parts):
        full = query_features(q.band, (0, h), factors, source.features_conf)
        fused = fuse(full, source, parts, conf, q.gsd_m, seed)
    else:
        fused = {"status": "not_found", "homography": None}
    fused["seconds"] = time.perf_counter() - t0
    fused["search_seconds"] = t_search
    fused["candidates_tried"] = int(sum(p["candidates_tried"] for p in parts))
    return fused


def evaluate(q: Query, fused: dict[str, Any], map_bounds, map_px: float, rconf) -> dict[str, Any]:
    """Outcome and error of one registration against the query's truth."""
    from georeg.register.geolocation import map_xy

    ok = fused.get("status") == "registered" and fused.get("homography") is not None
    inside = inside_fraction(q.tx, q.ty, map_bounds)
    stats = None
    if ok:
        x, y = map_xy(np.asarray(fused["homography"]), q.band.shape[1], q.band.shape[0])
        stats = error_stats(error_field(x, y, q.tx, q.ty), map_px)
    return {
        "outcome": classify(ok, stats, inside, rconf),
        "status": fused.get("status"),
        "inliers": fused.get("inliers", 0),
        "candidates": fused.get("candidates_tried"),
        "error_median_px": (stats or {}).get("px", {}).get("median"),
        "error_p90_px": (stats or {}).get("px", {}).get("p90"),
        "time_s": round(float(fused["seconds"]), 2),
        "inside_fraction": inside,
    }


def merged(base: dict[str, Any], over: dict[str, Any]) -> dict[str, Any]:
    out = dict(base)
    for k, v in (over or {}).items():
        out[k] = merged(out.get(k) or {}, v) if isinstance(v, dict) else v
    return out


def workflow_defaults() -> dict[str, Any]:
    """The workflow's register / features config with the schema defaults filled in."""
    from snakemake.utils import validate

    cfg = yaml.safe_load((ROOT / "config" / "config.yaml").read_text())
    validate(cfg, str(ROOT / "workflow" / "schemas" / "config.schema.yaml"))
    return cfg


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawTextHelpFormatter)
    ap.add_argument("--scenarios", default=str(ROOT / "benchmarks" / "scenarios.yaml"))
    ap.add_argument("--full", action="store_true", help="also run the full_scenarios")
    ap.add_argument("--only", default="", help="comma-separated scenario names")
    ap.add_argument("--strategies", default="", help="comma-separated (default: from the YAML)")
    ap.add_argument("--out", default=str(ROOT / "results" / "benchmark"))
    ap.add_argument("--demo-dir", default="", help="a demo scene (default results/demo)")
    args = ap.parse_args(argv)
    global DEMO_DIR
    DEMO_DIR = Path(args.demo_dir) if args.demo_dir else None
    logging.basicConfig(
        level=logging.INFO, format="%(asctime)s %(levelname)s %(name)s: %(message)s"
    )
    for noisy in (
        "georeg.register.search",
        "georeg.register.fuse",
        "georeg.register.matching",
        "georeg.index.map_index",
        "georeg.index.vocabulary",
        "georeg.index.features",
    ):
        logging.getLogger(noisy).setLevel(logging.WARNING)
    spec = yaml.safe_load(Path(args.scenarios).read_text())
    cfg = workflow_defaults()
    conf = merged(cfg["register"], spec.get("register") or {})
    from georeg.index.features import merged_conf

    features_conf = merged_conf(cfg["features"])
    rconf = merged(cfg.get("report") or {}, spec.get("report") or {})
    strategies = [s for s in (args.strategies or ",".join(spec["strategies"])).split(",") if s]
    seed = int(spec.get("seed", 42))
    scen = list(spec["scenarios"]) + (list(spec.get("full_scenarios") or []) if args.full else [])
    if args.only:
        keep = set(args.only.split(","))
        scen = [s for s in scen if s["name"] in keep]
    out = Path(args.out)
    cache = out / "cache"
    sources: dict[str, Any] = {}
    maps: dict[str, MapImage] = {}
    rows, detail = [], []
    t_all = time.perf_counter()
    for s in scen:
        row: dict[str, Any] = {
            "scenario": s["name"],
            "group": s.get("group", ""),
            "map": s["map"],
            "note": s.get("note", ""),
        }
        try:
            mspec = spec["maps"][s["map"]]
            if s["map"] not in sources:
                maps[s["map"]] = load_map(mspec, cache)
                sources[s["map"]] = build_source(
                    s["map"], maps[s["map"]], mspec, features_conf, cache, seed
                )
            m, src = maps[s["map"]], sources[s["map"]]
            rng = np.random.default_rng(seed)
            warp = dict(s.get("warp") or {})
            if s.get("gsd_known") is False:
                warp["gsd_known"] = False
            q = apply_warp(load_base(s["base"], cache, rng), warp, rng)
            if s.get("gsd_known") is False:
                q.gsd_m = None
        except (FileNotFoundError, OSError) as exc:
            log.warning("scenario %s skipped: %s", s["name"], exc)
            row["note"] = f"skipped: {exc}"
            rows.append(row)
            continue
        row["inside_fraction"] = round(inside_fraction(q.tx, q.ty, m.bounds) or 0.0, 3)
        for st in strategies:
            c = merged(conf, {"strategy": st})
            fused = register(q, src, c, seed)
            ev = evaluate(q, fused, m.bounds, abs(m.transform.a), rconf)
            detail.append({"scenario": s["name"], "strategy": st, **ev})
            for k in (
                "outcome",
                "inliers",
                "error_median_px",
                "error_p90_px",
                "time_s",
                "candidates",
            ):
                v = ev[k]
                row[f"{st}_{k}"] = round(v, 2) if isinstance(v, float) else v
            log.info(
                "%-28s %-6s %-18s inliers %4s  median %s px  %.1f s",
                s["name"],
                st,
                ev["outcome"],
                ev["inliers"],
                "-" if ev["error_median_px"] is None else f"{ev['error_median_px']:.2f}",
                ev["time_s"],
            )
        rows.append(row)
    cols = ["scenario", "group", "map", "inside_fraction"]
    for st in strategies:
        cols += [
            f"{st}_{k}"
            for k in (
                "outcome",
                "error_median_px",
                "error_p90_px",
                "inliers",
                "candidates",
                "time_s",
            )
        ]
    cols.append("note")
    out.mkdir(parents=True, exist_ok=True)
    from georeg.io.atomic import atomic_path, write_json

    with atomic_path(out / "summary.csv") as tmp, tmp.open("w", newline="") as f:
        w = csv.DictWriter(f, cols, extrasaction="ignore", lineterminator="\n")
        w.writeheader()
        for r in rows:
            w.writerow({k: ("" if r.get(k) is None else r.get(k)) for k in cols})
    write_json(
        out / "summary.json",
        {
            "scenarios": rows,
            "runs": detail,
            "seconds": time.perf_counter() - t_all,
            "register": conf,
            "report": rconf,
        },
    )
    tally = {st: {} for st in strategies}
    for d in detail:
        tally[d["strategy"]][d["outcome"]] = tally[d["strategy"]].get(d["outcome"], 0) + 1
    log.info("done in %.0f s: %s -> %s", time.perf_counter() - t_all, tally, out / "summary.csv")
    return 0


if __name__ == "__main__":
    sys.exit(main())
