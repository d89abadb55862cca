"""Frame geo-localisation tables (docs/BENCHMARKS.md "Frame geo-localisation").

Demo table, from the poses.json of sets with `truth`:

    python benchmarks/bench_frames.py results/frames/demo/poses.json [more poses.json ...]

Real-data table (../shared/data/frames_dev: `ngi` aerial, `odm` drone): the map of each case is
built in a work dir (grid, tiles, DEM elevation, features, vocabulary, index, mosaics), then
every query frame is located twice, by the plain baseline written here (SIFT frame vs map ortho,
z from the elevation raster, PnP in RANSAC + LM) and by this project's ``localize_frame``:

    python benchmarks/bench_frames.py real [--cases ngi odm] [--pan] [--work DIR]

``--pan`` also runs both against a panchromatic (1-band) copy of each map orthophoto.
``--variants [gsd2 gsd4 u16 rgbn nodem half]`` runs only ours against variants of each case's map
or frames a user may hand over (coarser ortho, 16-bit, 4 bands, no elevation, halved frames).
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path
from typing import Any

import cv2
import numpy as np

REPO = Path(__file__).resolve().parents[1]
FRAMES_DEV = REPO.parent / "shared" / "data" / "frames_dev"
#: the index settings of config/config.yaml (features), a small vocabulary for these small maps
FEATURES = {"rootsift": True, "max_features_per_mpx": 8000}
VOCAB = {"k": 200, "sample_size": 50000}


# ----------------------------------------------------------------------------- demo table


def rows(path: str) -> list[dict]:
    out = []
    for p in json.loads(Path(path).read_text()):
        ev = p.get("evaluation") or {}
        out.append({"frame": Path(p["image"]).stem, "status": p["status"], "expected": ev.get("expected"),
                    "pnp": ev.get("pnp"), "final": ev.get("final"), "inliers": p.get("inliers"),
                    "refine_kept": (p.get("refine") or {}).get("accepted"),
                    "seconds": (p.get("timings_s") or {}).get("total_s")})  # fmt: skip
    return out


def fmt(e: dict | None) -> str:
    if not e:
        return "-"
    return f"{e['horizontal_m']:.2f} / {e['vertical_m']:.2f} m, {e['rotation_deg']:.2f} deg"


def demo_table(paths: list[str]) -> None:
    allr = [r for p in paths for r in rows(p)]
    print(
        "| frame | status (expected) | PnP error h / v, rot | refined error h / v, rot | inliers | refine kept | s |"
    )
    print("|---|---|---|---|---|---|---|")
    for r in allr:
        print(f"| {r['frame']} | {r['status']} ({r['expected']}) | {fmt(r['pnp'])} | {fmt(r['final'])} | "
              f"{r['inliers']} | {r['refine_kept']} | {r['seconds']:.1f} |")  # fmt: skip
    reg = [r for r in allr if r["final"]]
    for key in ("pnp", "final"):
        v = [r[key] for r in reg if r[key]]
        if v:
            n = len(v)
            print(f"mean {key}: position {sum(e['position_m'] for e in v) / n:.2f} m, horizontal "
                  f"{sum(e['horizontal_m'] for e in v) / n:.2f} m, vertical {sum(e['vertical_m'] for e in v) / n:.2f} m, "
                  f"rotation {sum(e['rotation_deg'] for e in v) / n:.2f} deg over {n} frames")  # fmt: skip


# ----------------------------------------------------------------------------- real cases


def build_case_map(ortho: str | Path, dem: str | Path | None, out: str | Path) -> dict[str, Any]:
    """The map of one orthophoto + DEM as the workflow builds it (one call per rule):
    returns {"index": dir, "ortho": vrt, "dsm": vrt or None, "gsd": m}."""
    from georeg.index.features import extract_tile_from_grid
    from georeg.index.map_index import MapIndex
    from georeg.index.vocabulary import build_vocabulary
    from georeg.map.elevation import LAYERS, make_elevation_tile
    from georeg.map.grid import make_ortho_tile, tile_ids, write_grid, write_mosaic

    out = Path(out)
    grid = out / "grid.json"
    write_grid(grid, [str(ortho)], 1024, 64)
    tiles = tile_ids(grid)
    fdirs = []
    for t in tiles:
        tdir = out / "tiles" / t
        make_ortho_tile(grid, t, tdir / "ortho.tif")
        outs = {k: str(tdir / f"{k}.tif") for k in LAYERS} | {"points": str(tdir / "points.laz")}
        if dem is not None:
            make_elevation_tile(str(tdir / "ortho.tif"), outs, None, dem=str(dem))
        el = (outs["dsm"], outs["ndsm"]) if dem is not None else (None, None)
        extract_tile_from_grid(grid, t, tdir / "ortho.tif", *el, FEATURES, out / "features" / t)
        fdirs.append(out / "features" / t)
    build_vocabulary(fdirs, out / "vocab", VOCAB, 42)
    crs = json.loads(grid.read_text()).get("crs")
    MapIndex.build(fdirs, tiles, np.load(out / "vocab" / "centroids.npy"), out / "index", crs_wkt=crs)
    layers = ["ortho"] + (["dsm"] if dem is not None else [])
    for layer in layers:
        write_mosaic(grid, layer, [str(out / "tiles" / t / f"{layer}.tif") for t in tiles],
                     out / "mosaic" / f"{layer}.vrt")  # fmt: skip
    return {"index": out / "index", "ortho": out / "mosaic" / "ortho.vrt",
            "dsm": out / "mosaic" / "dsm.vrt" if dem is not None else None}  # fmt: skip


def panchromatic(src: str | Path, dst: str | Path) -> Path:
    """A 1-band copy of an RGB orthophoto (BT.601 luminance, same grid and nodata)."""
    import rasterio

    from georeg.index.features import rgb_to_gray

    with rasterio.open(src) as s:
        prof = s.profile.copy()
        rgb = s.read()
        msk = s.dataset_mask()
    g = rgb_to_gray(rgb[:3])
    g = np.where(msk > 0, np.maximum(g, 1), 0).astype(np.uint8)  # 0 stays nodata
    prof.update(count=1, photometric="minisblack")
    prof.pop("photometric", None)
    with rasterio.open(dst, "w", **prof) as d:
        d.write(g, 1)
    return Path(dst)


def case_frames(case: str) -> list[tuple[Path, dict, dict]]:
    """(frame path, camera dict, truth record) of every query of a case."""
    cdir = FRAMES_DEV / case
    meta = json.loads((cdir / "case.json").read_text())
    out = []
    for qid, q in sorted(meta["queries"].items()):
        it = q["intrinsics"]
        cam = {k: it[k] for k in ("fx", "fy", "cx", "cy")} | {"dist": list(it["dist"])}
        out.append((cdir / q["image"], cam, json.loads((cdir / "truth" / f"{qid}.json").read_text())))
    return out


def pose_errors(R, C, truth: dict) -> tuple[float, float]:
    """(camera centre error m, rotation error deg) against a truth record."""
    if R is None or C is None:
        return float("nan"), float("nan")
    Rt, Ct = np.asarray(truth["R_world_to_cam"]), np.asarray(truth["camera_center_xyz"])
    c = (np.trace(np.asarray(R) @ Rt.T) - 1) / 2
    return float(np.linalg.norm(np.asarray(C) - Ct)), float(np.degrees(np.arccos(np.clip(c, -1, 1))))


def baseline(frame: Path, camera: dict, ortho: str | Path, elevation: str | Path | None,
             ground_z: float = 0.0) -> dict[str, Any]:  # fmt: skip
    """The plain baseline: SIFT on the whole frame and the whole map orthophoto (plain OpenCV
    SIFT, FLANN 2-NN, ratio 0.8), z of every map keypoint from the elevation raster (bilinear;
    ``ground_z`` without one), PnP in RANSAC (4 px, seeded) and LM on the inliers."""
    import rasterio

    from georeg.index.features import map_to_pixel, pixel_to_map, rgb_to_gray, sample_bilinear

    t0 = time.perf_counter()
    cv2.setRNGSeed(0)
    gray = cv2.imread(str(frame), cv2.IMREAD_GRAYSCALE)
    K = np.array([[camera["fx"], 0, camera["cx"]], [0, camera["fy"], camera["cy"]], [0, 0, 1]])
    dist = np.asarray(camera.get("dist") or np.zeros(5), float)
    with rasterio.open(ortho) as s:
        mgray = rgb_to_gray(s.read()[: min(3, s.count)])
        mmask = (s.dataset_mask() > 0).astype(np.uint8) * 255
        tr = s.transform
    if mgray.dtype != np.uint8:
        from georeg.index.features import to_uint8

        mgray = to_uint8(mgray, mmask > 0)
    sift = cv2.SIFT_create()
    kq, dq = sift.detectAndCompute(gray, None)
    km, dm = sift.detectAndCompute(mgray, mmask)
    flann = cv2.FlannBasedMatcher({"algorithm": 1, "trees": 4}, {"checks": 64})
    knn = flann.knnMatch(dq, dm, k=2)
    good = [m[0] for m in knn if len(m) == 2 and m[0].distance < 0.8 * m[1].distance]
    uv = np.array([kq[m.queryIdx].pt for m in good], float).reshape(-1, 2)
    mp = np.array([km[m.trainIdx].pt for m in good], float).reshape(-1, 2)
    x, y = pixel_to_map(tr, mp[:, 0], mp[:, 1])  # OpenCV keypoint (pixel-centre coords) -> x, y
    if elevation is not None:
        with rasterio.open(elevation) as e:
            band, etr, nod = e.read(1), e.transform, e.nodata
        cc, rr = map_to_pixel(etr, x, y)
        z = sample_bilinear(band, cc, rr, nod).astype(float)
    else:
        z = np.full(len(x), float(ground_z))
    xyz = np.c_[x, y, z]
    ok = np.isfinite(xyz).all(axis=1)
    xyz, uv = xyz[ok], uv[ok]
    rec: dict[str, Any] = {"status": "not_found", "R": None, "C": None, "inliers": 0, "matches": len(uv)}
    if len(uv) >= 6:
        o = xyz.mean(axis=0)
        okp, rvec, tvec, inl = cv2.solvePnPRansac(xyz - o, uv, K, dist, iterationsCount=10000,
                                                  reprojectionError=4.0, confidence=0.999)  # fmt: skip
        if okp and inl is not None and len(inl) >= 6:
            inl = inl.ravel()
            rvec, tvec = cv2.solvePnPRefineLM(xyz[inl] - o, uv[inl], K, dist, rvec, tvec)
            R = cv2.Rodrigues(rvec)[0]
            rec.update(status="registered", R=R, C=-R.T @ tvec.ravel() + o, inliers=int(len(inl)))
    rec["seconds"] = time.perf_counter() - t0
    return rec


def ours(frame: Path, camera: dict, maps: dict, conf: dict | None = None,
         ground_z: float = 0.0) -> dict[str, Any]:  # fmt: skip
    """This project's single-frame localisation of one frame; the pose record."""
    from georeg.frames.localize import MapSources, localize_frame

    t0 = time.perf_counter()
    ms = MapSources(maps["index"], maps["ortho"], maps["dsm"], ground_z=ground_z)
    rec, _ = localize_frame(str(frame), camera, ms, conf or {})
    rec["seconds"] = time.perf_counter() - t0
    return rec


def real_rows(case: str, work: Path, pan: bool = False, conf: dict | None = None,
              camera_null: bool = False) -> list[dict]:  # fmt: skip
    """Baseline and ours on every frame of one case (map built under ``work``)."""
    cdir = FRAMES_DEV / case
    ortho = cdir / "map_ortho.tif"
    label = case
    if pan:
        work.mkdir(parents=True, exist_ok=True)
        ortho = panchromatic(ortho, work / "map_pan.tif")
        label = f"{case} (1-band map)"
    maps = build_case_map(ortho, cdir / "elevation.tif", work / "map")
    gsd = json.loads((cdir / "case.json").read_text())["map_resolution_m"]
    out = []
    for frame, cam, truth in case_frames(case):
        b = baseline(frame, cam, ortho, cdir / "elevation.tif")
        o = ours(frame, None if camera_null else cam, maps, conf)  # baseline: always the true camera
        ob = (o.get("camera_center_xyz"), o.get("R_world_to_cam"))
        out.append({"case": label, "frame": frame.stem, "map_gsd": gsd,
                    "baseline": {"status": b["status"], "inliers": b["inliers"], "seconds": b["seconds"],
                                 "errors": pose_errors(b["R"], b["C"], truth)},
                    "ours": {"status": o["status"], "inliers": o.get("inliers"), "seconds": o["seconds"],
                             "errors": pose_errors(ob[1], ob[0], truth), "path": o.get("path"),
                             "score": (o.get("verification") or {}).get("score"),
                             "timings_s": o.get("timings_s"), "adaptive": o.get("adaptive"),
                             "rms_px": (o.get("verification") or {}).get("rms_px"),
                             "tolerance_px": (o.get("verification") or {}).get("tolerance_px")}})  # fmt: skip
    return out


def real_table(rs: list[dict]) -> None:
    def e(r: dict) -> str:
        p, a = r["errors"]
        return "-" if np.isnan(p) else f"{p:.2f} m, {a:.2f} deg"

    print("| case | frame | map GSD | baseline: status, error, inliers, s | ours: status, error | "
          "ours: winning path (score) | ours: s |")  # fmt: skip
    print("|---|---|---|---|---|---|---|")
    for r in rs:
        b, o = r["baseline"], r["ours"]
        print(f"| {r['case']} | {r['frame']} | {r['map_gsd']} m | {b['status']}, {e(b)}, {b['inliers']}, "
              f"{b['seconds']:.1f} | {o['status']}, {e(o)} | {o['path'] or '-'} ({o['score']}) | "
              f"{o['seconds']:.1f} |")  # fmt: skip


def stage_table(rs: list[dict]) -> None:
    """Seconds per stage of ours (``timings_s`` of each pose record)."""
    keys = ["direct_s", "coarse_s", "cloud_s", "pnp_s", "verify_s", "refine_s", "overlay_render_s",
            "total_s"]  # fmt: skip
    print("\n| case | frame | " + " | ".join(k[:-2] for k in keys) + " |")
    print("|---|---|" + "---|" * len(keys))
    for r in rs:
        t = r["ours"].get("timings_s") or {}
        print(f"| {r['case']} | {r['frame']} | " + " | ".join(f"{t[k]:.1f}" if k in t else "-" for k in keys)
              + " |")  # fmt: skip


# ----------------------------------------------------------------------------- map variants

VARIANTS = ("gsd2", "gsd4", "u16", "rgbn", "nodem", "half")


def _rewrite(src: Path, dst: Path, fn, **prof_update) -> Path:
    """``dst`` = ``fn``(bands of ``src``) with the same grid (profile updated)."""
    import rasterio

    with rasterio.open(src) as s:
        prof, a = s.profile.copy(), s.read()
    a = fn(a)
    prof.update(count=a.shape[0], dtype=str(a.dtype), **prof_update)
    with rasterio.open(dst, "w", **prof) as d:
        d.write(a)
    return dst


def coarser(src: Path, dst: Path, f: int) -> Path:
    """The orthophoto averaged over f x f pixels (a map f times coarser)."""
    import rasterio
    from rasterio.enums import Resampling

    with rasterio.open(src) as s:
        prof, h, w = s.profile.copy(), s.height // f, s.width // f
        a = s.read(out_shape=(s.count, h, w), resampling=Resampling.average)
        prof.update(width=w, height=h, transform=s.transform * s.transform.scale(s.width / w, s.height / h))
    with rasterio.open(dst, "w", **prof) as d:
        d.write(a)
    return dst


def variant_rows(case: str, variant: str, work: Path) -> list[dict]:
    """Ours on every frame of ``case`` against a variant of its map or frames a user may hand
    over: ``gsd2`` / ``gsd4`` (ortho 2 / 4 x coarser), ``u16`` (12-bit values in uint16), ``rgbn``
    (a 4th band), ``nodem`` (no elevation: flat ground at the DEM's median), ``half`` (frames
    halved, intrinsics scaled). Errors against the surveyed truth."""
    import rasterio

    cdir = FRAMES_DEV / case
    work.mkdir(parents=True, exist_ok=True)
    ortho, dem, gz = cdir / "map_ortho.tif", cdir / "elevation.tif", 0.0
    if variant.startswith("gsd"):
        ortho = coarser(ortho, work / "ortho.tif", int(variant[3:]))
    elif variant == "u16":
        ortho = _rewrite(ortho, work / "ortho.tif", lambda a: np.where(a > 0, a.astype(np.uint16) * 16 + 3, 0).astype(np.uint16))
    elif variant == "rgbn":
        ortho = _rewrite(ortho, work / "ortho.tif", lambda a: np.concatenate([a, np.clip(a[1:2] * 1.3, 0, 255).astype(a.dtype)]))
    elif variant == "nodem":
        with rasterio.open(dem) as e:
            gz = float(np.nanmedian(e.read(1, masked=True).filled(np.nan)))
        dem = None
    maps = build_case_map(ortho, dem, work / "map")
    out = []
    for frame, cam, truth in case_frames(case):
        if variant == "half":
            img = cv2.imread(str(frame), cv2.IMREAD_COLOR)
            frame = work / f"{frame.stem}.png"
            cv2.imwrite(str(frame), cv2.resize(img, (img.shape[1] // 2, img.shape[0] // 2), interpolation=cv2.INTER_AREA))
            cam = {**cam, "fx": cam["fx"] / 2, "fy": cam["fy"] / 2, "cx": (cam["cx"] + 0.5) / 2 - 0.5,
                   "cy": (cam["cy"] + 0.5) / 2 - 0.5}  # fmt: skip
        o = ours(frame, cam, maps, None, ground_z=gz)
        p, a = pose_errors(o.get("R_world_to_cam"), o.get("camera_center_xyz"), truth)
        out.append({"case": case, "variant": variant, "frame": frame.stem, "status": o["status"],
                    "position_m": p, "rotation_deg": a, "path": o.get("path"),
                    "score": (o.get("verification") or {}).get("score"), "seconds": o["seconds"]})  # fmt: skip
        print(f"| {case} | {variant} | {frame.stem} | {o['status']} | {p:.2f} m, {a:.2f} deg | "
              f"{o.get('path') or '-'} ({out[-1]['score']}) | {o['seconds']:.1f} |", flush=True)  # fmt: skip
    return out


def main(argv: list[str]) -> None:
    if not argv or argv[0] != "real":
        demo_table(argv)
        return
    ap = argparse.ArgumentParser(prog="bench_frames.py real")
    ap.add_argument("--cases", nargs="+", default=["ngi", "odm"])
    ap.add_argument("--pan", action="store_true", help="also against a 1-band copy of each map")
    ap.add_argument("--work", type=Path, default=Path("/tmp/bench_frames_real"))
    ap.add_argument("--conf", type=json.loads, default=None, help="frame_loc overrides (JSON)")
    ap.add_argument("--json", type=Path, default=None, help="rows written here")
    ap.add_argument("--camera-null", action="store_true", help="ours without the camera (unknown)")
    ap.add_argument("--variants", nargs="*", default=None, choices=VARIANTS,
                    help="only ours against these variants of each case's map / frames")  # fmt: skip
    a = ap.parse_args(argv[1:])
    if not FRAMES_DEV.is_dir():
        sys.exit(f"{FRAMES_DEV} is absent")
    if a.variants is not None:
        print("| case | variant | frame | status | error | path (score) | s |\n|---|---|---|---|---|---|---|")
        vr = [r for case in a.cases for v in (a.variants or VARIANTS)
              for r in variant_rows(case, v, a.work / f"{case}_{v}")]  # fmt: skip
        if a.json:
            a.json.write_text(json.dumps(vr, indent=1, default=float))
        return
    rs = []
    for case in a.cases:
        rs += real_rows(case, a.work / case, conf=a.conf, camera_null=a.camera_null)
        if a.pan:
            rs += real_rows(case, a.work / f"{case}_pan", pan=True, conf=a.conf)
    real_table(rs)
    stage_table(rs)
    tot = [r["ours"]["seconds"] for r in rs]
    print(f"\nours: median {np.median(tot):.1f} s, max {np.max(tot):.1f} s over {len(tot)} frames")
    if a.json:
        a.json.write_text(json.dumps(rs, indent=1, default=float))


if __name__ == "__main__":
    main(sys.argv[1:])
