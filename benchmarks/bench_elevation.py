"""The map's DSM as an image to match (issue 34 item 3: ``register.elevation``), on real data.

    . /work/main/.venv/bin/activate
    nice python benchmarks/bench_elevation.py --methods sift_plain,wf_ortho,wf_elevation \\
        --out benchmarks/out/elevation.json -v

A map whose orthophoto misses the query's place (blanked to nodata over the query's footprint,
dilated by 10 px: an area the orthophoto does not cover, or covers at another season) while
its DSM holds there; the query is an optical crop of the orthophoto, rotated by any angle and
rescaled (``bench_crossspectral.make_query``). Scenes (../shared/data, made by nobody here):

- ``brighton``: ODM's orthophoto and DSM of one DJI flight (0.15 m, 715 x 653 px; the DSM from
  the photogrammetric cloud, so co-registered with the orthophoto exactly).
- ``autzen``: the 1 ft orthophoto (NAD83(HARN) / Oregon Lambert, ft) and a DSM of 1.25 ft cells
  rasterised here from ``autzen_trim.laz`` (airborne LiDAR, 110,000 points, about 1.8 a m2,
  another date than the orthophoto; highest point per cell, holes up to 3 cells filled: the
  neighbours' highest), the map at 1.25 ft over the LiDAR's 360 x 170 m. (At 2.5 ft, queries of
  0.45-0.6 of the map's 226 px height were 90-116 px, fewer than rift's 16 cells of 36 px:
  0/6 by every method.)

Split: queries alternate tuning / checking (one scene each way is too few to split by scene).
Negatives (``outside``): the same queries with the DSM blanked over the footprint too: nothing
of the map shows the place, so every one must end ``not_found``.
Methods: ``sift_plain`` (OpenCV SIFT of the query against the DSM as an 8-bit image, ratio 0.8,
MAGSAC, > 5 inliers: the plain way to match an image to a DSM); ``wf_ortho`` (the workflow's
register stage with the orthophoto only: what the map offered before); ``wf_elevation`` (the
same with the DSM: ``register.elevation``). Success: median error <= 5 map px.
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
import bench_crossspectral as bx  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
DATA = ROOT.parent / "shared" / "data"


def _u8(v: np.ndarray) -> np.ndarray:
    """Heights (NaN = nodata) as uint8 1..255 (0 = nodata), 1-99 % stretch: the plain baseline's
    image (the workflow reads the heights themselves)."""
    ok = np.isfinite(v)
    lo, hi = np.percentile(v[ok], [1, 99])
    out = np.clip((v - lo) / max(hi - lo, 1e-6) * 254 + 1, 1, 255)
    return np.where(ok, out, 0).astype(np.uint8)


def brighton() -> tuple[np.ndarray, np.ndarray, float]:
    import rasterio

    with rasterio.open(DATA / "brighton" / "map_ortho.tif") as ds:
        rgb = ds.read().astype(np.float32)
        ok = ds.read_masks(1) > 0
    with rasterio.open(DATA / "brighton" / "elevation.tif") as ds:
        z = ds.read(1).astype(np.float32)
    gray = 0.299 * rgb[0] + 0.587 * rgb[1] + 0.114 * rgb[2]
    return np.where(ok, gray, np.nan), np.where(np.isfinite(z), z, np.nan), 0.15


def autzen(cell_ft: float = 1.25, fill: int = 3) -> tuple[np.ndarray, np.ndarray, float]:
    """The orthophoto averaged to ``cell_ft`` and the LiDAR's DSM on that grid, cropped to the
    LiDAR's extent (units: ft)."""
    import laspy
    import rasterio
    from rasterio.enums import Resampling
    from rasterio.windows import from_bounds

    las = laspy.read(DATA / "autzen" / "autzen_trim.laz")
    x, y, z = np.asarray(las.x), np.asarray(las.y), np.asarray(las.z)
    x0, y1 = math.floor(x.min()), math.ceil(y.max())
    W, H = int((x.max() - x0) // cell_ft) + 1, int((y1 - y.min()) // cell_ft) + 1
    c, r = ((x - x0) // cell_ft).astype(int), ((y1 - y) // cell_ft).astype(int)
    dsm = np.full(H * W, -np.inf, np.float32)
    np.maximum.at(dsm, r * W + c, z.astype(np.float32))
    dsm = dsm.reshape(H, W)
    for _ in range(fill):  # holes up to ``fill`` cells: the neighbours' highest
        hole = ~np.isfinite(dsm)
        dsm = np.where(hole, cv2.dilate(np.where(hole, -1e9, dsm).astype(np.float32), np.ones((3, 3))), dsm)
        dsm[dsm < -1e8] = -np.inf
    dsm[~np.isfinite(dsm)] = np.nan
    with rasterio.open(DATA / "autzen" / "autzen.jpg") as ds:
        win = from_bounds(x0, y1 - H * cell_ft, x0 + W * cell_ft, y1, ds.transform)
        rgb = ds.read(window=win, out_shape=(3, H, W), resampling=Resampling.average,
                      boundless=True, fill_value=0).astype(np.float32)  # fmt: skip
    gray = 0.299 * rgb[0] + 0.587 * rgb[1] + 0.114 * rgb[2]
    return np.where(rgb.sum(0) > 0, gray, np.nan), dsm, cell_ft


#: scene -> (loader, crop side as a fraction of the scene's smaller side, query px per map px)
SCENES = {"brighton": (brighton, (0.35, 0.5), (0.55, 0.85)), "autzen": (autzen, (0.55, 0.7), (0.7, 0.9))}


def queries(name: str, n: int, seed: int) -> tuple[np.ndarray, np.ndarray, float, list[bx.Query]]:
    """Scene ``name``'s orthophoto gray, DSM, pixel size and its first ``n`` queries (seeded:
    the same queries for any ``n``)."""
    load, frac, scale = SCENES[name]
    gray, z, g = load()
    src = bx.Scene(name, {"gray": gray}, g, np.zeros(gray.shape, np.uint8), g, lambda p: p, scale_range=scale)
    rng = np.random.default_rng(seed)
    return gray, z, g, [bx.make_query(src, rng, i, frac=float(rng.uniform(*frac))) for i in range(n)]


def _blank(img: np.ndarray, q: bx.Query, pad: int = 10) -> np.ndarray:
    """``img`` with the query's footprint (its truth points' hull, dilated by ``pad`` px) set to
    nodata."""
    m = np.zeros(img.shape, np.uint8)
    cv2.fillConvexPoly(m, cv2.convexHull(np.round(q.truth_map).astype(np.int32)), 1)
    m = cv2.dilate(m, np.ones((2 * pad + 1, 2 * pad + 1), np.uint8)) > 0
    return np.where(m, 0 if img.dtype == np.uint8 else np.nan, img)


def height_reader(z: np.ndarray, g: float) -> Any:
    """The workflow's DSM window reader (fuse.ortho_window_reader on dsm.vrt) on a plain array:
    bounds (x = col g, y = -row g) -> (heights, NaN = nodata; 3 x 3 pixel centre -> map x, y)."""
    h, w = z.shape

    def read(b: tuple[float, ...]) -> tuple[np.ndarray, np.ndarray] | None:
        c0, c1 = max(0, int(math.floor(b[0] / g))), min(w, int(math.ceil(b[2] / g)) + 1)
        r0, r1 = max(0, int(math.floor(-b[3] / g))), min(h, int(math.ceil(-b[1] / g)) + 1)
        if c1 - c0 < 8 or r1 - r0 < 8:
            return None
        A = np.array([[g, 0, (c0 + 0.5) * g], [0, -g, -(r0 + 0.5) * g], [0, 0, 1.0]])
        return z[r0:r1, c0:c1].astype(np.float32), A

    return read


def srif_depth_as_map(per_half: int, seed: int, verbose: bool) -> list[dict[str, Any]]:
    """SRIF optical-depth pairs reversed (the public stand-in, ../shared/data/srif_dev): the
    optical reference (north-up) is the query, the depth image (rotated 0-90 deg, black fill =
    nodata) the map at 1 m; truth = the GT (bench_devset.srif_images), success within 8 map px
    (the data README's scoring, in depth-image px). The elevation source's search alone
    (``rift.register``, as ``bench_devset``'s ``src_rift``: no polish, structure check or turn)
    and plain SIFT; the first ``per_half`` pairs of each half (1-99 tuning, 101-199 checking)."""
    import bench_devset as bd

    from georeg.register import rift

    rows = []
    for half in ("tuning", "checking"):
        pairs = [i for i in bd.srif_pairs("od") if bd.srif_half(i) == half][:per_half]
        for i in pairs:
            ref, dep, A0 = bd.srif_images("od", i)
            s = math.sqrt(abs(np.linalg.det(A0[:2, :2])))  # map (depth) px per query px
            qp = bd.truth_grid(ref)
            q = bx.Query(f"od_{i}_reversed", "srif", "srif", {"gray": np.maximum(ref, 1)}, s, qp,
                         bx.matching.apply_h(A0, qp))  # fmt: skip
            sc = bx.Scene(f"srif_od_depth_{i}", {}, 1.0, dep, 1.0, lambda p: p)
            for m in ("sift_plain", "src_elevation"):
                if m == "sift_plain":
                    res = bx.run_method(q, sc, bx.METHODS["sift_plain"], seed)
                else:
                    t0 = time.perf_counter()
                    r = rift.register(q.bands["gray"], dep, s, {"log_nfa_max": 0.0}, {})
                    H = None if r["H"] is None else np.diag([1.0, -1.0, 1.0]) @ r["H"]  # map px -> x, -y
                    res = {"accepted": r["accepted"], "H": H, "seconds": time.perf_counter() - t0}
                j = bx.judge(q, sc, res)
                ok = j["outcome"] == "success" or (j["outcome"] == "false_accept" and j["error_px"] <= 8.0)
                j["outcome"] = "success" if ok else j["outcome"]
                rows.append({"scene": "srif_od", "query": q.name, "kind": "in_map", "half": half, "method": m,
                             "side_px": int(ref.shape[0]), "gsd": s, "pose_source": None,
                             "seconds": res.get("seconds"), **j})  # fmt: skip
                if verbose:
                    e = "-" if j["error_px"] is None else f"{j['error_px']:.2f}"
                    print(f"{half[:5]} {q.name:28s} {m:13s} {j['outcome']:13s} err {e:>7s}", flush=True)
    return rows


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scenes", default="brighton,autzen")
    ap.add_argument("--methods", default="sift_plain,wf_ortho,wf_elevation")
    ap.add_argument("--per-scene", type=int, default=8)
    ap.add_argument("--seed", type=int, default=11)
    ap.add_argument("--no-outside", action="store_true")
    ap.add_argument("--srif-od", type=int, default=0,
                    help="also SRIF optical-depth reversed (the depth image as the map), this many pairs a half")
    ap.add_argument("--out", default=str(ROOT / "benchmarks" / "out" / "elevation.json"))
    ap.add_argument("-v", action="store_true")
    a = ap.parse_args()
    rows = []
    for name in [n for n in a.scenes.split(",") if n]:
        gray, z, g, qs = queries(name, a.per_scene, a.seed)
        for i, q in enumerate(qs):
            half = "tuning" if i % 2 == 0 else "checking"
            ortho = _blank(bx._stretch(gray), q)
            cases = [("in_map", q, z)]
            if not a.no_outside:
                out_q = bx.Query(q.name + "_outside", q.scene, q.map_scene, q.bands, q.gsd, None, None)
                cases.append(("outside", out_q, _blank(z, q)))
            for kind, qq, zz in cases:
                for m in a.methods.split(","):
                    if m == "sift_plain":
                        # (bench_crossspectral.map_features keeps features by the scene's name)
                        sc = bx.Scene(f"{name}_dsm_{kind}_{i}", {}, g, _u8(zz), g, lambda p: p)
                        res = bx.run_method(qq, sc, bx.METHODS["sift_plain"], a.seed)
                    else:
                        sc = bx.Scene(f"{name}_ortho_{i}", {}, g, ortho, g, lambda p: p)
                        spec = {"pipeline": {"elevation": {"enabled": m == "wf_elevation"}}, "bands": 1}
                        res = bx.run_pipeline(qq, sc, spec, a.seed, read_elevation=height_reader(zz, g),
                                              elevation_id=f"{name}:{kind}:{i}")  # fmt: skip
                    j = bx.judge(qq, sc, res)
                    row = {"scene": name, "query": qq.name, "kind": kind, "half": half, "method": m,
                           "side_px": int(q.bands["gray"].shape[0]), "gsd": q.gsd,
                           "pose_source": res.get("pose_source"), "seconds": res.get("seconds"), **j}
                    rows.append(row)
                    if a.v:
                        e = "-" if j["error_px"] is None else f"{j['error_px']:.2f}"
                        print(f"{half[:5]} {qq.name:28s} {m:13s} {j['outcome']:13s} err {e:>7s} "
                              f"{row['pose_source'] or '-':10s} {row['seconds'] or 0:6.1f}s", flush=True)  # fmt: skip
    if a.srif_od:
        rows += srif_depth_as_map(a.srif_od, a.seed, a.v)
    Path(a.out).parent.mkdir(parents=True, exist_ok=True)
    Path(a.out).write_text(json.dumps(rows, indent=1, default=float))
    print("| method | half | registered | false accepts | outside accepted | median err px | s/query |")
    print("|---|---|---:|---:|---:|---:|---:|")
    for m in dict.fromkeys(x["method"] for x in rows):
        for half in ("tuning", "checking"):
            r = [x for x in rows if x["method"] == m and x["half"] == half]
            ins = [x for x in r if x["kind"] == "in_map"]
            ok = [x for x in ins if x["outcome"] == "success"]
            fa = sum(x["outcome"] == "false_accept" for x in ins)
            outs = [x for x in r if x["kind"] == "outside"]
            oa = sum(x["outcome"] != "rejected" for x in outs)
            med = float(np.median([x["error_px"] for x in ok])) if ok else float("nan")
            sec = float(np.median([x["seconds"] or 0 for x in r])) if r else float("nan")
            print(f"| {m} | {half} | {len(ok)}/{len(ins)} | {fa} | {oa}/{len(outs)} | {med:.2f} | {sec:.1f} |")


if __name__ == "__main__":
    main()
