"""Cross-spectral, cross-date matching benchmark: SWIR of one date vs RGB of another.

    . /work/main/.venv/bin/activate
    nice -n 5 python benchmarks/bench_crossspectral.py -v       # the protocol's default methods
    nice -n 5 python benchmarks/bench_crossspectral.py --methods wf_adaptive --half checking
    nice -n 5 python benchmarks/bench_crossspectral.py --set small --methods wf_nosmall,wf_small

``--set small``: the small-query development subset (45-100 px crops of the TUNING scenes only,
own seed, with their unrelated pairs; docs/BENCHMARKS.md "Small queries"); ``--set tiny``: the
same with 40-80 px crops and another seed (5 per scene). The ``wf_*`` methods
pass the workflow's orthophoto window reader on the plain map array (``plain_window_reader``), so
the small-query fallback (``register.small``, on by default) runs as in the workflow.

Protocol (docs/BENCHMARKS.md "Cross-spectral matching"): the scenes of ../shared/data are split
by city into a tuning half (nanjing, abudhabi, saclay) and a checking half (taizhou, hongkong,
norcia, potsdam); a change is kept only if it helps the checking half. Scenes: Landsat Nanjing
and Taizhou in both date directions, the five Sentinel-2 cities in both date directions, EnMAP
Potsdam (SWIR vs its own visible bands). Per scene, seeded: crops of half the scene side and
smaller ones, rotated by any angle, rescaled x0.75-1.3 (Potsdam: 150 px at 12-20 m), a random
SWIR band, stripped of geo-referencing; the map is the RGB luminance of the other date. Truth
from both dates' geo-referencing. Unrelated pairs (each query against the map of another city of
its half) must come out not found.

Methods: single-region matchers on the whole map (``sift_plain``, ``paper``, ``vote_*``), the
workflow's registration stages on plain map arrays (``wf_*``: georeg.register.fuse.register_query
with config/config.yaml's ``register`` section).
Outcome per query: success = accepted with median error <= 5 map pixels; false accept = accepted
with a larger error, or any acceptance of an unrelated pair; missed = not accepted. Per half:
registered, false accepts, unrelated accepted, median error, median p90 and max error over the
footprint (the truth grid), registered queries with p90 <= 2 px, seconds per query. Methods with
``refine`` also run the workflow's refinement stage and are judged on the refined geometry. Output: a table on stdout and
results/benchmark/crossspectral.json (or ``--out``).
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
from georeg.register import acceptance, matching  # noqa: E402

SUCCESS_PX = 5.0
TINY_SIDES = (40, 80)  # --set tiny: query px a side, like the checking half's smallest crops


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
    city: str = ""
    scale_range: tuple[float, float] = (0.75, 1.3)  # query px per source px
    query_px: int | None = None  # fixed query side (px); None = a fraction of the scene side


# The protocol's fixed split by city (never tune on CHECKING): a change is kept only if it helps
# the checking half too. Saclay east and west are one city.
TUNING = ("nanjing", "abudhabi", "saclay")
CHECKING = ("taizhou", "hongkong", "norcia", "potsdam")


def half_of(city: str) -> str:
    return "tuning" if city in TUNING else "checking"


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
    return Scene(f"{city}_d{query_date + 1}", swir, 30.0, gray, 30.0, lambda p: p, city)


def enmap_scene() -> Scene:
    """EnMAP Potsdam: SWIR bands vs the visible luminance of the same acquisition (30 m); the
    queries are warped to 12-20 m and cropped to 150 x 150 px."""
    from georeg.io.query import open_query
    from georeg.register.band import select_band

    cube = open_query(str(SHARED / "enmap_potsdam" / "enmap_potsdam_mosaic_subset.tif"))

    def band(spec: str) -> np.ndarray:
        b, m, _ = select_band(cube, spec)
        return np.where(m, b, np.nan).astype(np.float32)

    r, g, b = band("650nm"), band("560nm"), band("480nm")
    swir = {"1650nm": band("1650nm"), "2200nm": band("2200nm")}
    return Scene("enmap_potsdam", swir, 30.0, _lum(r, g, b), 30.0, lambda p: p, "potsdam",
                 (1.5, 2.5), 150)  # fmt: skip


def s2_scene(city: str, reverse: bool = False) -> Scene:
    import rasterio

    d = DATES / "oscd_dev" / city

    def band(date: int, b: str):
        (p,) = glob.glob(str(d / f"imgs_{date}" / f"*_{b}.tif"))
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            with rasterio.open(p) as s:
                return s.read(1).astype(np.float32), s.transform

    qd, md = (2, 1) if reverse else (1, 2)
    b11, t1 = band(qd, "B11")
    b12, _ = band(qd, "B12")
    r, t2 = band(md, "B04")
    g, _ = band(md, "B03")
    b, _ = band(md, "B02")
    inv2 = ~t2

    def to_map(p: np.ndarray) -> np.ndarray:
        lon, lat = t1 * ((p[:, 0] + 0.5), (p[:, 1] + 0.5))
        c, rr = inv2 * (lon, lat)
        return np.c_[c - 0.5, rr - 0.5]

    name = f"s2_{city}" + ("_rev" if reverse else "")
    swir = {"1.6um": b11, "2.2um": b12}
    return Scene(name, swir, 20.0, _lum(r, g, b), 10.0, to_map, city.split("_")[0])


def all_scenes(enmap: bool = True) -> list[Scene]:
    """Landsat both directions, Sentinel-2 both directions, EnMAP (when present)."""
    out = [landsat_scene(c, k) for c in ("nanjing", "taizhou") for k in (0, 1)]
    for c in sorted(p.name for p in (DATES / "oscd_dev").iterdir()):
        out += [s2_scene(c), s2_scene(c, reverse=True)]
    if enmap and (SHARED / "enmap_potsdam").is_dir():
        out.append(enmap_scene())
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


def make_query(
    sc: Scene, rng: np.random.Generator, i: int, frac: float = 0.5, side_px: int | None = None
) -> Query:
    """Rotate, rescale and crop a SWIR band of ``sc`` (seeded); truth on a grid of query pixels.

    Side: ``frac`` of the scene's smaller side (``side_px`` or ``sc.query_px`` query px when
    set); the centre is drawn again until at least half of the crop is valid."""
    first_band = next(iter(sc.swir.values()))
    h, w = first_band.shape
    s = float(rng.uniform(*sc.scale_range))
    px = side_px or sc.query_px
    side = px / s if px else frac * min(h, w)
    theta = float(rng.uniform(0, 360))
    half = side / math.sqrt(2)
    ok = np.isfinite(first_band) & (first_band > 0)
    for _ in range(100):
        cx, cy = rng.uniform(half, w - half), rng.uniform(half, h - half)
        r0, c0 = int(cy - side / 2), int(cx - side / 2)
        if ok[r0 : r0 + int(side), c0 : c0 + int(side)].mean() >= 0.5:
            break
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
    qp = qp[bands[first][qp[:, 1].astype(int), qp[:, 0].astype(int)] > 0]
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


_FORCE_SPLIT = {"min_part_features": 0, "min_part_side_px": 0, "whole_if_parts_fail": False}

METHODS: dict[str, dict[str, Any]] = {
    # the issue's outside baseline: plain OpenCV SIFT, ratio 0.8, all matches, MAGSAC, > 5 inliers
    "sift_plain": {"ratio": 0.8, "max_matches": 0, "acceptance": {"mode": "paper"}},
    # the workflow (config/config.yaml register section) on plain map arrays: split plan, the
    # search_part jobs (index strategy, register.index.rank: hough -- the Hough vote through
    # exact nearest neighbours over all map features --, top 8 candidates), whole-query
    # fallback, fusion; "pipeline" overrides the config
    # the paper's halves, always, each part's NFA counting its own candidates only (the
    # behaviour before the split plan)
    "wf_halves": {"pipeline": {"split": {**_FORCE_SPLIT, "count_searches": False}}},
    "wf_whole": {"pipeline": {"parts": 1}},  # never split
    # split only large queries; the whole query when every part fails
    "wf_adaptive_only": {"pipeline": {"split": {"parts_if_whole_fails": False}}},
    # the default: as above, and the parts of a small query when the whole query fails
    "wf_adaptive": {"pipeline": {}},
    # both SWIR bands' features pooled, the random band first
    "wf_adaptive_2bands": {"pipeline": {}, "bands": 2},
    # the workflow's query stage exactly: `band: auto` (nearest 1200 nm: the ~1.6 um band here)
    # and `bands: auto` (+ the band nearest 2200 nm) -- the workflow default; and `bands: one`
    "wf_default": {"pipeline": {}, "bands": "auto"},
    "wf_rift": {"pipeline": {"rift": {"enabled": True}}, "bands": "auto"},  # + the opt-in rift source
    # the learned source forced on (an error without the extra, where the default skips it)
    "wf_learned": {"pipeline": {"learned": {"enabled": True}}, "bands": "auto"},
    # rift's map shrunk to the query's GSD when the query is > 1.5x coarser (register.rift.
    # max_upsample before session 53; since then 2.5: session 53's runs of it were named wf_up2)
    "wf_upsample15": {"pipeline": {"rift": {"max_upsample": 1.5}}, "bands": "auto"},
    # small queries (georeg.register.small, register.small): off / on whatever the config says
    "wf_nosmall": {"pipeline": {"small": {"enabled": False}}, "bands": "auto"},
    "wf_small": {"pipeline": {"small": {"enabled": True}}, "bands": "auto"},  # dense Hough windows
    "wf_small_160": {"pipeline": {"small": {"enabled": True, "max_side_px": 160}},
                     "bands": "auto"},  # fmt: skip
    # (--set tiny candidates measured and removed: several CFOG peaks per window,
    # register.small.peaks; a similarity below 8 inliers, register.ransac.similarity_below;
    # figures in docs/BENCHMARKS.md "Small queries")
    # the calibrated CFOG-peak null as a second source of evidence (docs/BENCHMARKS.md "A
    # calibrated null for the CFOG peak")
    "wf_null": {"pipeline": {"small": {"null_test": {"enabled": True}}}, "bands": "auto"},
    "wf_nonull": {"pipeline": {"small": {"null_test": {"enabled": False}}}, "bands": "auto"},
    # a small query's feature fit checked by the same scan, replaced on a conflict (the default
    # since session 8; docs/BENCHMARKS.md "The null scan as a check of small feature fits")
    "wf_nocheck": {"pipeline": {"small": {"null_test": {"check": False}}}, "bands": "auto"},
    # accepted fits checked densely against the orthophoto in the fuse step
    # (georeg.register.ortho_check, register.ortho_check): a fit that does not verify becomes not
    # found (the refit that replaced the fit was measured and removed)
    "wf_ortho_off": {"pipeline": {"ortho_check": {"mode": "off"}}, "bands": "auto"},
    # the candidate measured (docs/BENCHMARKS.md "Dense check of accepted fits") was reject +
    # replace; the default is record (decisions and fits unchanged)
    "wf_ortho": {"pipeline": {"ortho_check": {"mode": "reject"}}, "bands": "auto"},
    # the same with the ranking before the Hough vote on plain arrays (register.index.rank:
    # tiles, which without an index means 1-NN votes of the query descriptors on footprint cells)
    # the workflow default followed by the workflow's refinement stage (rule refine_registration:
    # georeg.register.refine.refine with config/config.yaml's `refine` section, against the map
    # image): since issue 20 ("accuracy over the whole footprint") the global homography is first
    # refitted to dense CFOG tie points (refine.global_fit); `_before` = the refinement without it
    "wf_default_refined": {"pipeline": {}, "bands": "auto", "refine": {}},
    # a location prior (queries.<name>.prior, georeg/io/prior.py): a square of half side
    # `prior` x the query's ground side around the true centre moved by a seeded offset of up to
    # half that; an unrelated pair: the same square at a seeded place of its map
    "wf_prior2": {"pipeline": {}, "bands": "auto", "prior": 2.0},
    "wf_prior8": {"pipeline": {}, "bands": "auto", "prior": 8.0},
    # an accepted fit kept as RANSAC's least squares fitted it (before session 9) instead of
    # refitted with the model chosen by leave-one-out CV (register.ransac.final_model)
    "wf_ransac_final": {"pipeline": {"ransac": {"final_model": "ransac"}}, "bands": "auto"},
    "wf_ransac_final_refined": {"pipeline": {"ransac": {"final_model": "ransac"}},
                                "bands": "auto", "refine": {}},  # fmt: skip
    "wf_default_refined_before": {
        "pipeline": {},
        "bands": "auto",
        "refine": {"global_fit": {"enabled": False}},
    },
    "wf_default_refined_affine": {
        "pipeline": {},
        "bands": "auto",
        "refine": {"global_fit": {"model": "affine"}},
    },
    # the refit's guard at 5 % (the first candidate) and 10 % (the default since issue 20)
    "wf_default_refined_gain05": {
        "pipeline": {},
        "bands": "auto",
        "refine": {"global_fit": {"min_gain": 0.05}},
    },
    "wf_default_refined_gain10": {
        "pipeline": {},
        "bands": "auto",
        "refine": {"global_fit": {"min_gain": 0.1}},
    },
    "wf_default_refined_homography": {
        "pipeline": {},
        "bands": "auto",
        "refine": {"global_fit": {"model": "homography", "min_gain": 0.05}},
    },
    "wf_default_cellvote": {"pipeline": {"index": {"rank": "tiles"}}, "bands": "auto"},
    "wf_default_one": {"pipeline": {}, "bands": "one"},
    # one band chosen by wavelength (the nearest the scene has): which SWIR band alone
    "wf_band_1600nm": {"pipeline": {}, "bands": "1600nm"},
    "wf_band_2200nm": {"pipeline": {}, "bands": "2200nm"},
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


def _deep(a: dict[str, Any], b: dict[str, Any]) -> dict[str, Any]:
    out = dict(a)
    for k, v in b.items():
        out[k] = _deep(out.get(k) or {}, v) if isinstance(v, dict) else v
    return out


def workflow_register_conf() -> dict[str, Any]:
    """The ``register`` section of config/config.yaml (the workflow default)."""
    import yaml

    return yaml.safe_load((ROOT / "config" / "config.yaml").read_text())["register"]


def workflow_band_order(names: list[str], rule: str) -> list[int]:
    """Indexes of the query bands named by wavelength (``1.6um``, ``2200nm``) that the workflow's
    query stage pools (georeg.register.band: ``band: auto``, then ``bands: auto`` or ``one``);
    a wavelength rule (``"2200nm"``): the one band nearest it."""
    from georeg.register.band import auto_index, auto_partner, parse_band_spec

    wl = np.array([float(parse_band_spec(n).value) for n in names])
    if rule not in ("auto", "one"):  # one band by wavelength
        return [int(np.argmin(np.abs(wl - float(parse_band_spec(rule).value))))]
    first = auto_index(wl)
    other = auto_partner(wl, first) if rule == "auto" else None
    return [first] + ([other] if other is not None else [])


def query_stack(q: Query, bands: int | str) -> np.ndarray:
    """The query image(s) a method sees: the first ``bands`` bands (the random band first), the
    workflow's own choice (``"auto"`` / ``"one"``) or the band nearest a wavelength."""
    names = list(q.bands)
    if isinstance(bands, str):
        order = workflow_band_order(names, bands)
    else:
        order = list(range(min(int(bands), len(names))))
    if len(order) == 1:
        return q.bands[names[order[0]]]
    return np.stack([q.bands[names[i]] for i in order])


def workflow_refine_conf() -> dict[str, Any]:
    """The ``refine`` section of config/config.yaml (the workflow's refinement stage)."""
    import yaml

    return yaml.safe_load((ROOT / "config" / "config.yaml").read_text())["refine"]


def map_image(sc: Scene) -> Any:
    """The map scene as a georeg MapImage in this benchmark's map units (x = col * gsd,
    y = -row * gsd, pixel centres), NaN = nodata."""
    from rasterio.transform import Affine

    from georeg.register.refine import MapImage

    g = sc.map_gsd
    gray = np.where(sc.map_gray > 0, sc.map_gray.astype(np.float32), np.nan)
    return MapImage(gray, Affine(g, 0, -0.5 * g, 0, -g, 0.5 * g))


def run_refine(q: Query, sc_map: Scene, H: np.ndarray, spec: dict[str, Any]) -> dict[str, Any]:
    """The workflow's refinement stage on the primary query band: refined map x, y per pixel."""
    from georeg.register.refine import refine

    band = query_stack(q, spec.get("bands", 1))
    conf = _deep(workflow_refine_conf(), spec["refine"])
    if band.ndim == 3 and not conf.get("pooled_bands", True):  # the primary band only
        band = band[0]
    x, y, info = refine(band, H, map_image(sc_map), conf)
    gf = info.get("global_fit") or {}
    return {"xy": (x, y), "refine_model": info["model"],
            "global_fit": gf.get("accepted"), "global_fit_reason": gf.get("reason")}  # fmt: skip


def map_identity(sc: Scene) -> str:
    """The map's identity for the sources' in-memory caches (register_query's ``map_id``): its
    name and a hash of its pixels (kept on the scene)."""
    if getattr(sc, "_identity", None) is None:
        import hashlib

        h = hashlib.sha256(np.ascontiguousarray(sc.map_gray).tobytes()).hexdigest()[:16]
        sc._identity = f"{sc.name}:{sc.map_gray.shape}:{h}"  # type: ignore[attr-defined]
    return sc._identity  # type: ignore[attr-defined]


def plain_window_reader(sc: Scene) -> Any:
    """The workflow's orthophoto window reader (fuse.ortho_window_reader) on a plain map array:
    bounds (map x, y; x = col g, y = -row g) -> (float window, NaN = nodata; 3 x 3 window pixel
    centre -> map x, y) or None: ``plain_level_reader`` at the map's own pixel size."""
    from georeg.register.level import window_reader

    return window_reader(plain_level_reader(sc), sc.map_gsd)


def plain_level_reader(sc: Scene) -> Any:
    """The map array as a ``georeg.register.level.LevelReader``: bounds (x = col g, y = -row g)
    -> (gray averaged to ``gsd``, 0 = nodata; level pixel centre -> map x, y)."""
    g = sc.map_gsd
    h, w = sc.map_gray.shape

    def read(b: tuple[float, ...], gsd: float) -> tuple[np.ndarray, np.ndarray] | None:
        c0, c1 = max(0, int(math.floor(b[0] / g))), min(w, int(math.ceil(b[2] / g)) + 1)
        r0, r1 = max(0, int(math.floor(-b[3] / g))), min(h, int(math.ceil(-b[1] / g)) + 1)
        f = g / gsd
        ow, oh = max(1, round((c1 - c0) * f)), max(1, round((r1 - r0) * f))
        if ow < 8 or oh < 8:
            return None
        win = sc.map_gray[r0:r1, c0:c1]
        valid = cv2.resize((win > 0).astype(np.float32), (ow, oh), interpolation=cv2.INTER_AREA)
        img = cv2.resize(win.astype(np.float32), (ow, oh), interpolation=cv2.INTER_AREA)
        gray = np.where(valid > 0.99, np.clip(img / np.maximum(valid, 1e-6), 1, 255), 0)
        sx, sy = (c1 - c0) * g / ow, (r1 - r0) * g / oh
        A = np.array([[sx, 0, (c0 - 0.5) * g + 0.5 * sx], [0, -sy, -(r0 - 0.5) * g - 0.5 * sy],
                      [0, 0, 1.0]])  # fmt: skip
        return gray.round().astype(np.uint8), A

    return read


def location_prior(q: Query, sc_map: Scene, factor: float, seed: int) -> dict[str, Any]:
    """A prior ``{"centre", "radius_m"}`` in this benchmark's map units (x = col g, y = -row g):
    radius = ``factor`` x the query's ground side, centred on the true centre moved by a seeded
    offset of up to half the radius (an unrelated pair: at a seeded place of its map)."""
    rng = np.random.default_rng(seed + 7)
    g = sc_map.map_gsd
    r = factor * next(iter(q.bands.values())).shape[0] * q.gsd
    if q.truth_map is not None:
        c = np.mean(q.truth_map, axis=0) * np.array([g, -g])
    else:
        h, w = sc_map.map_gray.shape
        c = np.array([rng.uniform(0, w) * g, -rng.uniform(0, h) * g])
    c = c + rng.uniform(-0.5, 0.5, 2) * r
    return {"centre": [float(c[0]), float(c[1])], "radius_m": float(r)}


def run_pipeline(q: Query, sc_map: Scene, spec: dict[str, Any], seed: int, read_elevation: Any = None,
                 elevation_id: str | None = None) -> dict[str, Any]:  # fmt: skip
    """The workflow's registration stages (georeg.register.fuse.register_query) on plain arrays;
    with ``spec["refine"]`` also the refinement stage. ``read_elevation`` / ``elevation_id``: the
    map's DSM (register_query's; benchmarks/bench_elevation.py)."""
    from georeg.register.fuse import register_query
    from georeg.register.search import MapSource

    t0 = time.perf_counter()
    conf = _deep(workflow_register_conf(), spec["pipeline"])
    fgsd = sc_map.map_gsd
    mxy, mdesc, mang, msize = map_features(sc_map, fgsd, merged_conf(FEATURES))
    # ``extent``: the map's extent, as an index's tile bounds give it in the workflow, not its
    # features' (a map window half water has features in the other half only: Hong Kong in
    # bench_scale_gap --map-inside). Off by default: the other sets' figures were measured on the
    # features' extent, and it moves their feature search (Pucallpa's visible control, session 56)
    h, w = sc_map.map_gray.shape
    g = sc_map.map_gsd
    ext = (-0.5 * g, -(h - 0.5) * g, (w - 0.5) * g, 0.5 * g) if spec.get("extent") else None
    src = MapSource(mxy, mdesc, fgsd, angle=mang, scale=msize * fgsd, extent=ext)
    u8 = query_stack(q, spec.get("bands", 1))
    prior = None if not spec.get("prior") else location_prior(q, sc_map, float(spec["prior"]), seed)
    # ``no_gsd``: the query's GSD withheld, as a user who does not know it (the guesses searched)
    gsd, factors = (None, conf["unknown_gsd_factors"]) if spec.get("no_gsd") else (q.gsd, [q.gsd / fgsd])
    res = register_query(u8, src, conf, gsd, factors, seed, plain_window_reader(sc_map),
                         prior, plain_level_reader(sc_map), map_identity(sc_map),
                         read_elevation=read_elevation, elevation_id=elevation_id)  # fmt: skip
    split = res.get("split") or {}
    wins = (split.get("small") or {}).get("windows") or []
    sw = [w.get("log10_nfa") for w in wins if w.get("log10_nfa") is not None]
    acc = [w.get("peak") for w in wins if w.get("accepted")]
    cn = (split.get("small") or {}).get("cfog_null") or {}
    extra: dict[str, Any] = {"small_nfa": min(sw) if sw else None,
                             "small_peak": acc[0] if acc else None,
                             "null_nfa": cn.get("log10_nfa"), "null_accepted": cn.get("accepted")}
    nk = res.get("null_check") or {}
    extra["null_check"] = nk.get("outcome")
    oc = res.get("ortho_check") or {}
    extra["ortho"] = oc.get("outcome")
    extra["ortho_gain"] = oc.get("gain")  # the tie points at H vs moved hypotheses (fits <= max_inliers)
    extra["context_refit"] = res.get("context_refit")  # the learned extra's LightGlue re-fit
    if spec.get("refine") is not None and res["status"] == "registered":
        extra.update(run_refine(q, sc_map, np.array(res["homography"]), spec))
    return {
        **extra,
        "matches": res.get("matches") or 0,
        "inliers": res.get("inliers") or 0,
        "accepted": res["status"] == "registered",
        "log10_nfa": res.get("log10_nfa"),
        "H": None if res.get("homography") is None else np.array(res["homography"]),
        "parts": split.get("parts"),
        "level": res.get("level"),
        "sources": res.get("sources"),
        "second_pass": res.get("second_pass"),
        "rift": split.get("rift"),
        "learned": split.get("learned"),
        "elevation": split.get("elevation"),
        "cfog_peaks": split.get("cfog_peaks"),
        "pose_source": res.get("pose_source"),
        "whole": split.get("whole_query_searched"),
        "features": split.get("query_features"),
        "part_side": split.get("part_side_map_px"),
        "seconds": time.perf_counter() - t0,
    }


def query_seed(seed: int, name: str) -> int:
    """The seed of one query's run: the run's ``--seed`` and the query's name, not its position
    in the run (which ``--half``, ``--limit`` or the sets chosen change: SRIF pair oo 161 was a
    false accept at position 91 and missed at 41, its feature RANSAC seeded differently)."""
    import zlib

    return int(seed) + zlib.crc32(name.encode()) % 100_000


def run_method(q: Query, sc_map: Scene, spec: dict[str, Any], seed: int) -> dict[str, Any]:
    if "pipeline" in spec:
        return run_pipeline(q, sc_map, spec, seed)
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
            xy, d, r = matching.add_polarity(xy, d, r)
            ang, size = np.r_[ang, (ang + 180.0) % 360.0], np.r_[size, size]
        xs.append(xy), ds.append(d), rs.append(r), angs.append(ang), sizes.append(size)
    qxy, qd, qr = np.concatenate(xs), np.concatenate(ds), np.concatenate(rs)
    qang, qsize = np.concatenate(angs), np.concatenate(sizes)
    knn = matching.knn2(mdesc)
    if spec.get("vote"):
        hyps = matching.rotation_hypotheses(
            qxy, qd, qang, qsize, mxy, mang, msize, knn, spec["vote"]
        )
    else:
        nt = spec.get("max_matches", REG["max_matches"])
        ratio = spec.get("ratio", REG["ratio"])
        hyps = [(matching.ratio_matches(qxy, qd, qr, mxy, knn, ratio, nt), 1)]
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
            fit.H, fit.residual_px, fit.n_inliers, area, n, n, q.gsd,
            {**REG["acceptance"], **spec.get("acceptance", {})},
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
        gm = matching.guided_matches(qxy, qd, fit0.H, mxy, mdesc, radius, 0.8, knn)
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


# Sentinel-2 dates disagree in their geo-referencing by up to ~1.5 map px (docs/BENCHMARKS.md
# "Accuracy over the whole footprint", (c)). The content truth: the whole scene's SWIR band fitted
# to the other date's luminance by the dense CFOG refit started from the geo-referencing
# (thousands of tie points; against the same date it agrees with the geo-referencing to
# 0.13-0.32 px), as a map -> map correction per scene direction. Landsat and EnMAP share one
# grid: their truth is exact and stays.
CONTENT_TRUTH: dict[str, np.ndarray] = {}


def georef_affine(to_map: Any, w: int, h: int, gsd: float) -> np.ndarray:
    """The affine src px -> map (x = col gsd, y = -row gsd) of a scene's ``to_map`` (affine)."""
    src = np.array([[0.0, 0.0], [w - 1.0, 0.0], [0.0, h - 1.0]])
    dst = to_map(src) * np.array([gsd, -gsd])
    A = np.linalg.lstsq(np.c_[src, np.ones(3)], dst, rcond=None)[0]
    T = np.eye(3)
    T[:2] = A.T
    return T


def content_correction(sc: Scene) -> tuple[np.ndarray, dict[str, Any]]:
    """Map (x, y) -> map (x, y) that moves the geo-referenced truth onto the image content."""
    import yaml

    from georeg.register.densefit import dense_fit

    rconf = yaml.safe_load((ROOT / "config" / "config.yaml").read_text())["refine"]
    band = _stretch(sc.swir["1.6um"])
    T = georef_affine(sc.to_map, *band.shape[::-1], sc.map_gsd)
    Hf, info = dense_fit(band, T, map_image(sc), {"min_gain": -10.0}, rconf)
    return Hf @ np.linalg.inv(T), {k: info.get(k) for k in ("tie_points", "inliers", "cover")}


def load_content_truth(scenes: list[Scene], cache: Path) -> None:
    """Fill ``CONTENT_TRUTH`` for every Sentinel-2 scene (cached in ``cache``)."""
    got = json.loads(cache.read_text()) if cache.is_file() else {}
    for sc in scenes:
        if not sc.name.startswith("s2_"):
            continue
        if sc.name not in got:
            C, info = content_correction(sc)
            got[sc.name] = {"C": C.tolist(), **info}
            print(f"content truth {sc.name}: {info}", flush=True)
        CONTENT_TRUTH[sc.name] = np.array(got[sc.name]["C"])
    cache.parent.mkdir(parents=True, exist_ok=True)
    cache.write_text(json.dumps(got, indent=1))


def judge(q: Query, sc_map: Scene, res: dict[str, Any]) -> dict[str, Any]:
    """Outcome and error (map px) at the truth grid: median, p90, max; of the refined geometry
    (``res["xy"]``, bilinear at the grid points) when the method refines, else of ``H``."""
    err = p90 = emax = p90c = None
    if res["H"] is not None and q.truth is not None:
        if res.get("xy") is not None:
            from scipy.ndimage import map_coordinates

            rc = [q.truth[:, 1], q.truth[:, 0]]
            est = np.c_[map_coordinates(res["xy"][0], rc, order=1),
                        map_coordinates(res["xy"][1], rc, order=1)]  # fmt: skip
        else:
            est = matching.apply_h(res["H"], q.truth)
        est = est / np.array([sc_map.map_gsd, -sc_map.map_gsd])
        e = np.linalg.norm(est - q.truth_map, axis=1)
        e = np.where(np.isfinite(e), e, np.inf)
        err, p90, emax = float(np.median(e)), float(np.percentile(e, 90)), float(e.max())
        p90c = p90
        C = CONTENT_TRUTH.get(sc_map.name) if q.scene == q.map_scene else None
        if C is not None:
            g = np.array([sc_map.map_gsd, -sc_map.map_gsd])
            tc = matching.apply_h(C, q.truth_map * g) / g
            ec = np.linalg.norm(est - tc, axis=1)
            p90c = float(np.percentile(np.where(np.isfinite(ec), ec, np.inf), 90))
    if not res["accepted"]:
        outcome = "missed" if q.truth is not None else "rejected"
    elif q.truth is None or err is None or err > SUCCESS_PX:
        outcome = "false_accept"
    else:
        outcome = "success"
    return {"outcome": outcome, "error_px": err, "p90_px": p90, "max_px": emax,
            "p90_content_px": p90c}


# ----------------------------------------------------------------------------- main


def rotation_canvas(w: int, h: int, theta: float) -> tuple[int, int, np.ndarray]:
    """A ``w`` x ``h`` image rotated by ``theta`` degrees onto a canvas that holds it whole: the
    canvas width and height and the 2 x 3 canvas px -> image px (about the centres; for
    ``cv2.warpAffine(..., WARP_INVERSE_MAP)``)."""
    c, si = math.cos(math.radians(theta)), math.sin(math.radians(theta))
    cw = int(math.ceil(abs(w * c) + abs(h * si)))
    ch = int(math.ceil(abs(w * si) + abs(h * c)))
    A = np.array([[c, -si], [si, c]])
    t = np.array([(w - 1) / 2, (h - 1) / 2]) - A @ np.array([(cw - 1) / 2, (ch - 1) / 2])
    return cw, ch, np.c_[A, t]


def make_whole_query(sc: Scene, band: str, theta: float, i: int) -> Query:
    """One SWIR band of ``sc`` whole, at its own GSD, rotated by ``theta`` degrees onto a canvas
    that holds it (0 = nodata outside): the form of a delivered scene, not a crop."""
    src = sc.swir[band]
    cw, ch, M = rotation_canvas(src.shape[1], src.shape[0], theta)
    A, t = M[:, :2], M[:, 2]
    warped = cv2.warpAffine(src, M, (cw, ch), flags=cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP,
                            borderValue=np.nan)  # fmt: skip
    u8 = _stretch(warped)
    uu, vv = np.meshgrid(np.linspace(2, cw - 3, 16), np.linspace(2, ch - 3, 16))
    qp = np.c_[uu.ravel(), vv.ravel()]
    qp = qp[u8[qp[:, 1].astype(int), qp[:, 0].astype(int)] > 0]
    return Query(f"whole_{sc.name}_{i}_{band}", sc.name, sc.name, {band: u8}, sc.swir_gsd, qp,
                 sc.to_map(qp @ A.T + t))  # fmt: skip


def build_whole_set(seed: int) -> tuple[list[Scene], list[Query]]:
    """The delivered-scene form (the unseen Sentinel-2 case of issue 34): every Sentinel-2 scene
    direction, each SWIR band whole at 20 m as its own query under a seeded rotation, against the
    other date's 10 m luminance; and each scene's first band against another city's map of the
    same half (it must end ``not_found``)."""
    scenes = [sc for sc in all_scenes(enmap=False) if sc.name.startswith("s2_")]
    rng = np.random.default_rng(seed + 700)
    qs = [make_whole_query(sc, b, float(rng.uniform(0, 360)), 0) for sc in scenes for b in sc.swir]
    neg = []
    for k, sc in enumerate(scenes):
        others = [o for o in scenes[k + 1 :] + scenes[:k]
                  if o.city != sc.city and half_of(o.city) == half_of(sc.city)]  # fmt: skip
        if not others:
            others = [o for o in scenes if o.city != sc.city]
        other = others[1 % len(others)]
        q = next(x for x in qs if x.scene == sc.name)
        neg.append(Query(q.name + "_vs_" + other.name, sc.name, other.name, q.bands, q.gsd,
                         None, None))  # fmt: skip
    return scenes, qs + neg


def build_set(per_scene: int, seed: int, small: int = 1) -> tuple[list[Scene], list[Query]]:
    """Per scene: ``per_scene`` crops of half the scene side and ``small`` crops of 0.3-0.45 of
    it (seeded; Potsdam: 150 px crops throughout). Unrelated pairs: every query against the map
    of another city of the same half."""
    scenes = all_scenes()
    rng = np.random.default_rng(seed)
    qs = [make_query(sc, rng, i) for sc in scenes for i in range(per_scene)]
    rng2 = np.random.default_rng(seed + 1)
    qs += [
        make_query(sc, rng2, per_scene + i, float(rng2.uniform(0.3, 0.45)))
        for sc in scenes
        for i in range(small)
    ]
    neg = []
    for k, sc in enumerate(scenes):
        others = [o for o in scenes[k + 1 :] + scenes[:k]
                  if o.city != sc.city and half_of(o.city) == half_of(sc.city)]  # fmt: skip
        other = others[1 % len(others)]
        for q in (x for x in qs if x.scene == sc.name):
            name = q.name + "_vs_" + other.name
            neg.append(Query(name, sc.name, other.name, q.bands, q.gsd, None, None))
    return scenes, qs + neg


def build_small_set(per_scene: int, seed: int, sides: tuple[int, int] = (45, 100),
                    prefix: str = "small_", seed_offset: int = 500
                    ) -> tuple[list[Scene], list[Query]]:
    """The small-query development subset: ``per_scene`` crops of ``sides`` query px a side
    (same rotations, rescales and random band as the protocol) of the TUNING scenes only, drawn
    with their own seed (``seed`` + ``seed_offset``), and each against the map of another tuning
    city. ``--set tiny`` = 40-80 px, prefix ``tiny_``, ``seed`` + 600."""
    scenes = [sc for sc in all_scenes(enmap=False) if half_of(sc.city) == "tuning"]
    rng = np.random.default_rng(seed + seed_offset)
    qs = []
    for sc in scenes:
        for i in range(per_scene):
            n = int(rng.integers(sides[0], sides[1] + 1))
            q = make_query(sc, rng, 100 + i, side_px=n)
            qs.append(Query(prefix + q.name, *[getattr(q, f) for f in
                                                 ("scene", "map_scene", "bands", "gsd", "truth",
                                                  "truth_map")]))  # fmt: skip
    neg = []
    for k, sc in enumerate(scenes):
        others = [o for o in scenes[k + 1 :] + scenes[:k] if o.city != sc.city]
        other = others[1 % len(others)]
        for q in (x for x in qs if x.scene == sc.name):
            neg.append(Query(q.name + "_vs_" + other.name, sc.name, other.name, q.bands, q.gsd,
                             None, None))  # fmt: skip
    return scenes, qs + neg


def summarise(r: list[dict[str, Any]]) -> dict[str, Any]:
    """Counts and error figures of one method's records (one half or all)."""
    pos = [x for x in r if x["positive"]]
    ok = [x for x in pos if x["outcome"] == "success"]
    p90 = [x["p90_px"] for x in ok]
    return {
        "success": len(ok),
        "positives": len(pos),
        "false_accept": sum(x["outcome"] == "false_accept" for x in pos),
        "unrelated_accepted": sum(x["outcome"] == "false_accept" for x in r if not x["positive"]),
        "negatives": len(r) - len(pos),
        "median_error_px": float(np.median([x["error_px"] for x in ok])) if ok else float("nan"),
        "median_p90_px": float(np.median(p90)) if ok else float("nan"),
        "median_max_px": float(np.median([x["max_px"] for x in ok])) if ok else float("nan"),
        "p90_within_2px": sum(v <= 2.0 for v in p90),
        "p90_within_2px_content": sum(
            (x.get("p90_content_px") if x.get("p90_content_px") is not None else x["p90_px"]) <= 2.0
            for x in ok
        ),
        "seconds_per_query": float(np.mean([x["seconds"] for x in r])) if r else float("nan"),
    }


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawTextHelpFormatter)
    ap.add_argument(
        "--methods",
        default="sift_plain,vote_pol_refine,wf_halves,wf_whole,wf_adaptive_only,wf_adaptive",
    )
    ap.add_argument("--per-scene", type=int, default=3, help="crops of half the scene side")
    ap.add_argument("--small", type=int, default=1, help="smaller crops (0.3-0.45 of the side)")
    ap.add_argument("--half", choices=("tuning", "checking", "both"), default="both")
    ap.add_argument("--set", choices=("protocol", "small", "tiny", "whole"), default="protocol",
                    help="small: the small-query development subset of the tuning cities "
                    "(45-100 px a side, own seed; its rows are the half 'small'); tiny: the "
                    "same with 40-80 px, another seed (rows 'tiny'); whole: each Sentinel-2 SWIR "
                    "band whole at 20 m, rotated, by the protocol's halves")  # fmt: skip
    ap.add_argument("--small-per-scene", type=int, default=None,
                    help="--set small / tiny: crops per scene (default 6 / 5)")
    ap.add_argument("--seed", type=int, default=11)
    ap.add_argument("--out", default=str(ROOT / "results" / "benchmark" / "crossspectral.json"))
    ap.add_argument("-v", action="store_true", help="one line per query and method")
    ap.add_argument("--shard", default="0/1",
                    help="k/n: only every n-th query from the k-th (seeds as in the whole run), "
                    "to spread one run over processes")  # fmt: skip
    ap.add_argument("--from", dest="first", type=int, default=0,
                    help="skip the queries before this index")
    ap.add_argument("--only", default="",
                    help="only these queries (comma-separated whole names; a rerun of a subset)")
    ap.add_argument("--positives-only", action="store_true",
                    help="skip the unrelated pairs (for changes that cannot alter a decision)")
    ap.add_argument("--content-truth", action="store_true",
                    help="also judge p90 against the Sentinel-2 content truth (CONTENT_TRUTH; "
                    "cached in results/benchmark/content_truth.json)")  # fmt: skip
    a = ap.parse_args(argv)
    if not DATES.is_dir():
        print(f"no development data at {DATES}", file=sys.stderr)
        return 1
    cv2.setNumThreads(1)
    if a.set == "small":
        scenes, queries = build_small_set(a.small_per_scene or 6, a.seed)
    elif a.set == "tiny":
        scenes, queries = build_small_set(a.small_per_scene or 5, a.seed, TINY_SIDES, "tiny_", 600)
    elif a.set == "whole":
        scenes, queries = build_whole_set(a.seed)
    else:
        scenes, queries = build_set(a.per_scene, a.seed, a.small)
    by = {s.name: s for s in scenes}
    if a.content_truth:
        load_content_truth(scenes, ROOT / "results" / "benchmark" / "content_truth.json")
    if a.positives_only:
        queries = [q for q in queries if q.truth is not None]
    if a.only:
        keep = set(a.only.split(","))
        queries = [q for q in queries if q.name in keep]
    if a.half != "both" and a.set in ("protocol", "whole"):
        queries = [q for q in queries if half_of(by[q.scene].city) == a.half]
    methods = a.methods.split(",")
    rows: dict[str, list[dict[str, Any]]] = {m: [] for m in methods}
    k_shard, n_shard = (int(v) for v in a.shard.split("/"))
    for qi, q in enumerate(queries):
        if qi % n_shard != k_shard or qi < a.first:
            continue
        half = a.set if a.set in ("small", "tiny") else half_of(by[q.scene].city)
        for name in methods:
            res = run_method(q, by[q.map_scene], METHODS[name], query_seed(a.seed, q.name))
            j = judge(q, by[q.map_scene], res)
            rec = {"query": q.name, "half": half, "positive": q.truth is not None, **j,
                   "inliers": res["inliers"], "matches": res["matches"],
                   "parts": res.get("parts"), "whole": res.get("whole"),
                   "features": res.get("features"), "part_side": res.get("part_side"),
                   "size_px": next(iter(q.bands.values())).shape[0],
                   "log10_nfa": res.get("log10_nfa"), "seconds": res["seconds"],
                   "refine_model": res.get("refine_model"),
                   "global_fit": res.get("global_fit"), "small_nfa": res.get("small_nfa"),
                   "null_nfa": res.get("null_nfa"), "null_accepted": res.get("null_accepted"),
                   "global_fit_reason": res.get("global_fit_reason"),
                   "ortho": res.get("ortho"), "ortho_gain": res.get("ortho_gain"), "rift": res.get("rift"),
                   "null_check": res.get("null_check"), "pose_source": res.get("pose_source"),
                   "learned": res.get("learned"), "cfog_peaks": res.get("cfog_peaks"),
                   "context_refit": res.get("context_refit")}  # fmt: skip
            rows[name].append(rec)
            if a.v:
                e = ("-" if j["error_px"] is None
                     else f"{j['error_px']:.2f}/{j['p90_px']:.2f}/{j['max_px']:.2f}")  # fmt: skip
                print(f"{half[:5]} {q.name:40s} {name:16s} {j['outcome']:12s} err {e:>12s} "
                      f"inl {res['inliers']:3d}/{res['matches']:3d} parts {res.get('parts')} "
                      f"{res['seconds']:.2f}s"
                      + ("" if res.get("small_nfa") is None
                         else f" small log10 NFA {res['small_nfa']:.1f}")
                      + ("" if res.get("small_peak") is None
                         else f" peak {res['small_peak']}")
                      + ("" if res.get("null_nfa") is None
                         else f" null log10 p {res['null_nfa']:.1f}"
                         + (" ACCEPTED" if res.get("null_accepted") else ""))
                      + ("" if res.get("null_check") is None
                         else f" null check {res['null_check']}")
                      + ("" if res.get("ortho") is None
                         else f" ortho {res['ortho']}")
                      + ("" if not res.get("pose_source") else f" by {res['pose_source']}"),
                      flush=True)  # fmt: skip
    print(f"\n{len(queries)} queries and unrelated pairs, seed {a.seed}; halves by city: "
          f"tuning {', '.join(TUNING)}; checking {', '.join(CHECKING)}")  # fmt: skip
    print("| method | half | registered | false accepts | unrelated accepted | median err px "
          "| median p90 px | median max px | p90 <= 2 px | p90 <= 2 px (content truth) | s/query |")  # fmt: skip
    print("|---|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|")
    summary: dict[str, Any] = {}
    for name in methods:
        summary[name] = {}
        for half in ("small", "tiny", "tuning", "checking"):
            sm = summarise([x for x in rows[name] if x["half"] == half])
            summary[name][half] = sm
            if not sm["positives"]:
                continue
            print(f"| {name} | {half} | {sm['success']}/{sm['positives']} | {sm['false_accept']} "
                  f"| {sm['unrelated_accepted']}/{sm['negatives']} | {sm['median_error_px']:.2f} "
                  f"| {sm['median_p90_px']:.2f} | {sm['median_max_px']:.2f} "
                  f"| {sm['p90_within_2px']}/{sm['success']} "
                  f"| {sm['p90_within_2px_content']}/{sm['success']} "
                  f"| {sm['seconds_per_query']:.2f} |")  # fmt: skip
    Path(a.out).parent.mkdir(parents=True, exist_ok=True)
    Path(a.out).write_text(json.dumps({"summary": summary, "rows": rows}, indent=1, default=float))
    return 0


if __name__ == "__main__":
    sys.exit(main())
