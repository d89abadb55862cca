"""Unordered photo collections (issue 33 item 3) on a real flight, beside single photos.

../shared/data/brighton: 18 DJI photos (GPS removed; gps.json = rough truth). Fixed split by file
name: part A = photos 1-9 (DJI_0018-0026), part B = photos 10-18 (DJI_0027-0035). One part, as an
ordered sequence (rule trajectory's pipeline), builds the feature map; the other part is localised
(a) as single photos (rule localize_frames' path, the plain baseline) and (b) as an unordered
collection (georeg.trajectory.collection; the photos listed in a shuffled order, seed fixed), each
map-only and with the feature map. Tuning half: A builds, B localised; checking half: the roles
swapped (``--swap``). Errors: camera centre vs EXIF GPS, horizontal.

    nice -n 10 python benchmarks/bench_collection.py [--swap] [--work /tmp/bench_coll] [--reuse]

Seconds: CPU seconds of this process (user + sys) per photo; the machine was shared.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path[:0] = [str(REPO / "benchmarks"), str(REPO / "tests")]
BRIGHTON = REPO.parent / "shared" / "data" / "brighton"


def parts() -> tuple[list[Path], list[Path]]:
    """Part A (photos 1-9) and part B (10-18) by file name."""
    photos = sorted((BRIGHTON / "frames").glob("DJI_*.JPG"))
    return photos[:9], photos[9:]


def shuffled(paths: list[Path], seed: int = 7) -> list[str]:
    return [str(paths[i]) for i in np.random.default_rng(seed).permutation(len(paths))]


def run_collection(paths: list[str], ms, fl: dict, out: Path, fmap=None) -> tuple[list[dict], dict]:
    """The collection path on ``paths``; records carry per-photo CPU seconds (total / n)."""
    from georeg.trajectory.collection import georeference_collection

    ms.feature_map = fmap
    t0, c0 = time.perf_counter(), time.process_time()
    poses = georeference_collection({"images": paths, "camera": None}, ms, fl, {}, out)
    ms.feature_map = None
    s = {"wall_s": (time.perf_counter() - t0) / len(poses), "cpu_s": (time.process_time() - c0) / len(poses)}
    for r in poses:
        r["bench"] = s
    return poses, json.loads((out / "collection.json").read_text())


def main(argv: list[str]) -> None:
    import logging

    from bench_feature_maps import check_exports, gps_error, locate_all, repo_conf, summary, table
    from bench_frames import build_case_map

    from georeg.export.frame_set import export_frame_set
    from georeg.frames.feature_map import load_feature_maps
    from georeg.frames.localize import MapSources
    from georeg.trajectory.pipeline import georeference_video

    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--swap", action="store_true", help="checking half: B builds the map, A is localised")
    ap.add_argument("--work", default="/tmp/bench_coll")
    ap.add_argument("--reuse", action="store_true", help="reuse the map and sequence of an earlier run")
    ap.add_argument("--out", default=None, help="summary JSON")
    a = ap.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(levelname)s %(name)s: %(message)s")
    fl, tr = repo_conf()
    work = Path(a.work)
    gps = json.loads((BRIGHTON / "gps.json").read_text())
    A, B = parts()
    seq, loc = (B, A) if a.swap else (A, B)
    tag = "B_builds" if a.swap else "A_builds"
    m = work / "map"
    if a.reuse and (m / "index").is_dir():
        maps = {"index": m / "index", "ortho": m / "mosaic" / "ortho.vrt", "dsm": m / "mosaic" / "dsm.vrt"}
    else:
        maps = build_case_map(BRIGHTON / "map_ortho.tif", BRIGHTON / "elevation.tif", m)
    ms = MapSources(maps["index"], maps["ortho"], maps["dsm"])
    seq_dir = work / tag / "sequence"
    if not (a.reuse and (seq_dir / "sfm_points.laz").exists()):
        georeference_video({"images": [str(p) for p in seq], "trajectory": True, "camera": None, "fps": 1.0},
                           ms, fl, tr, seq_dir)  # fmt: skip
    seq_poses = json.loads((seq_dir / "poses.json").read_text())
    fmap = load_feature_maps([seq_dir / "sfm_points.laz"], ms.crs_wkt, ms.bounds(), fl.get("feature_map"))
    err = lambda r: gps_error(r, gps)  # noqa: E731
    ssum = summary([{**r, "bench": {"cpu_s": 0, "wall_s": 0}} for r in seq_poses], err)
    print(f"## {tag}: sequence {seq[0].stem}..{seq[-1].stem} builds the feature map ({len(fmap)} points): "
          f"{ssum['registered']}/{ssum['frames']} registered, median / max {ssum['median_h_m']:.2f} / "
          f"{ssum['max_h_m']:.2f} m\n")  # fmt: skip
    order = shuffled(loc)
    print(f"localised: {loc[0].stem}..{loc[-1].stem}; collection order: {[Path(p).stem for p in order]}\n")
    single_map = locate_all(loc, None, ms, fl)
    single_fm = locate_all(loc, None, ms, fl, fmap)
    coll_map, info_map = run_collection(order, ms, fl, work / tag / "collection_map")
    coll_fm, info_fm = run_collection(order, ms, fl, work / tag / "collection_fm", fmap)
    by = lambda recs: {Path(r["image"]).name: r for r in recs}  # noqa: E731
    names = [p.name for p in loc]
    for recs in (coll_map, coll_fm):
        for r in recs:
            r["path"] = f"{r['posed_by']}: {r.get('path', '-')}" if r["posed_by"] == "single" else r["posed_by"]
    rows = [("single, map only", single_map), ("single, feature map", single_fm),
            ("collection, map only", [by(coll_map)[n] for n in names]),
            ("collection, feature map", [by(coll_fm)[n] for n in names])]  # fmt: skip
    table(rows, err)
    for nm, info in (("map only", info_map), ("feature map", info_fm)):
        print(f"- collection {nm}: SfM {info['sfm'].get('registered')}/{info['photos']} photos, "
              f"{info['sfm'].get('points')} points, {info.get('cameras')} camera(s); anchors {len(info.get('anchors', []))}; "
              f"Sim(3) {(info.get('sim3') or {}).get('n_inliers')} inliers, RMS {(info.get('sim3') or {}).get('inlier_rms_m')}; "
              f"posed by {info['posed_by']}; {info.get('reason', '')}")  # fmt: skip
    exp = work / tag / "collection_fm" / "export"
    export_frame_set(work / tag / "collection_fm" / "poses.json", exp, ms.crs_wkt,
                     sfm_laz=work / tag / "collection_fm" / "sfm_points.laz")  # fmt: skip
    ex = check_exports("collection, feature map", exp, coll_fm)
    print(f"\n- exports: {ex}")
    out = {"split": tag, "sequence": ssum, "single_map": summary(single_map, err),
           "single_fm": summary(single_fm, err), "collection_map": summary(coll_map, err),
           "collection_fm": summary(coll_fm, err), "posed_by_map": info_map["posed_by"],
           "posed_by_fm": info_fm["posed_by"], "exports": ex}  # fmt: skip
    print(json.dumps(out, default=str))
    if a.out:
        Path(a.out).write_text(json.dumps(out, indent=1, default=str))


if __name__ == "__main__":
    main(sys.argv[1:])
