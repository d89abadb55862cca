"""Feature maps as a map layer (issue 33): frames localised against an earlier set's feature map
vs against the map alone (the plain baseline: this project's map-only single-frame path), and the
exports of the registered sets checked as ODM and COLMAP read them.

Real flight (../shared/data/brighton: 18 DJI photos in 3 strips, GPS kept apart as rough truth):
the first ``--split`` photos, as an ordered sequence (rule trajectory's pipeline), build the
feature map; every other photo is localised alone, map-only and with the feature map:

    nice python benchmarks/bench_feature_maps.py brighton [--split 9] [--swap] [--work /tmp/bench_fm]

(``--swap``: the photos after the split build the feature map, the first ones are localised.)

Demo (a finished default run in <results dir>): every ``--every``-th frame of the second half of
the demo video, alone, against the feature map of a trajectory built from the first half only,
and the demo frames against the whole video's feature map (the workflow's), each also map-only;
errors against the demo truth:

    nice python benchmarks/bench_feature_maps.py demo results [--every 20] [--work /tmp/bench_fm_demo]

Seconds are per-frame CPU seconds of this process (user + sys; the machine was shared) and
wall seconds; the configuration is config/config.yaml's ``frame_loc`` and ``trajectory``.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np
import yaml

REPO = Path(__file__).resolve().parents[1]
sys.path[:0] = [str(REPO), str(REPO / "benchmarks"), str(REPO / "tests")]  # this checkout's georeg
BRIGHTON = REPO.parent / "shared" / "data" / "brighton"


def repo_conf() -> tuple[dict, dict]:
    cfg = yaml.safe_load((REPO / "config" / "config.yaml").read_text())
    fl = {k: v for k, v in cfg["frame_loc"].items() if k != "demo_frames"}
    tr = {k: v for k, v in cfg["trajectory"].items() if k != "demo_video"}
    return fl, tr


def cpu() -> float:
    t = time.process_time()
    return t


def locate_all(frames: list, camera: dict | None, ms, fl: dict, fmap=None) -> list[dict]:
    """Each frame alone (localize_frame), with ``ms.feature_map`` = ``fmap``; per-frame seconds."""
    from georeg.frames.localize import localize_frame, localize_image

    ms.feature_map = fmap
    out = []
    for f in frames:
        t0, c0 = time.perf_counter(), cpu()
        if isinstance(f, tuple):  # (name, rgb) of a video frame
            rec, _ = localize_image(f[1], f[0], camera, ms, fl)
        else:
            rec, _ = localize_frame(str(f), camera, ms, fl)
        rec["bench"] = {"wall_s": time.perf_counter() - t0, "cpu_s": cpu() - c0}
        out.append(rec)
    ms.feature_map = None
    return out


def gps_error(rec: dict, gps: dict) -> dict | None:
    if rec["status"] != "registered":
        return None
    g = gps["frames"][Path(rec["image"]).stem]
    C = np.asarray(rec["camera_center_xyz"])
    return {"horizontal_m": float(np.hypot(*(C[:2] - g["gps_xy"]))), "vertical_m": float(C[2] - g["gps_altitude"])}


def summary(recs: list[dict], err) -> dict[str, Any]:
    e = [err(r) for r in recs]
    h = [x["horizontal_m"] for x in e if x]
    return {"frames": len(recs), "registered": sum(r["status"] == "registered" for r in recs),
            "by_feature_map": sum(str(r.get("path", "")).startswith("feature map") for r in recs),
            "median_h_m": float(np.median(h)) if h else None, "max_h_m": float(np.max(h)) if h else None,
            "median_cpu_s": float(np.median([r["bench"]["cpu_s"] for r in recs])),
            "median_wall_s": float(np.median([r["bench"]["wall_s"] for r in recs]))}  # fmt: skip


def table(rows: list[tuple[str, list[dict]]], err) -> None:
    print("| frame | " + " | ".join(f"{n}: status, path, error, CPU s" for n, _ in rows) + " |")
    print("|---|" + "---|" * len(rows))
    for i in range(len(rows[0][1])):
        cells = []
        for _, recs in rows:
            r = recs[i]
            e = err(r)
            es = f"{e['horizontal_m']:.2f} m h / {e.get('vertical_m', float('nan')):+.2f} m v" if e else "-"
            fm = r.get("feature_map") or {}
            fs = (f" [fm {fm.get('inliers')} inl, score {fm.get('score')}{', start' if fm.get('start') else ''}]"
                  if fm else "")  # fmt: skip
            cells.append(f"{r['status']}, {r.get('path', '-')}{fs}, {es}, {r['bench']['cpu_s']:.1f}")
        print(f"| {Path(rows[0][1][i]['image']).name} | " + " | ".join(cells) + " |")
    print()
    print("| variant | registered | by feature map | median / max horizontal error (m) | median CPU s | median wall s |")
    print("|---|---|---|---|---|---|")
    for n, recs in rows:
        s = summary(recs, err)
        f = lambda v: "-" if v is None else f"{v:.2f}"  # noqa: E731
        print(f"| {n} | {s['registered']}/{s['frames']} | {s['by_feature_map']} | {f(s['median_h_m'])} / "
              f"{f(s['max_h_m'])} | {s['median_cpu_s']:.2f} | {s['median_wall_s']:.2f} |")
    print()


def check_exports(name: str, export_dir: Path, poses: list[dict]) -> dict:
    from export_checks import check_colmap, check_gcp_list

    info = json.loads((export_dir / "export.json").read_text())
    out = {"set": name, **{k: info[k] for k in ("registered", "gcps", "gcp_observations", "model_points", "odm_ready")}}
    try:
        out["gcp_check"] = check_gcp_list(export_dir, poses)
    except AssertionError as exc:
        out["gcp_check"] = f"FAILED: {exc}"
    out["colmap_check"] = check_colmap(export_dir / "colmap")
    return out


def brighton(a) -> dict:
    from bench_frames import build_case_map

    from georeg.export.frame_set import export_frame_set
    from georeg.frames.feature_map import load_feature_maps
    from georeg.frames.localize import MapSources
    from georeg.trajectory.pipeline import georeference_video

    fl, tr = repo_conf()
    work = Path(a.work)
    gps = json.loads((BRIGHTON / "gps.json").read_text())
    photos = sorted((BRIGHTON / "frames").glob("DJI_*.JPG"))
    seq, single = photos[: a.split], photos[a.split :]
    if a.swap:  # the checking half: the last photos build the feature map, the first are localised
        seq, single = photos[a.split :], photos[: a.split]
    t0 = time.perf_counter()
    if a.reuse and (work / "map" / "index").is_dir():  # the map of an earlier run of this command
        m = work / "map"
        maps = {"index": m / "index", "ortho": m / "mosaic" / "ortho.vrt", "dsm": m / "mosaic" / "dsm.vrt"}
    else:
        maps = build_case_map(BRIGHTON / "map_ortho.tif", BRIGHTON / "elevation.tif", work / "map")
    print(f"map built ({time.perf_counter() - t0:.0f} s)", file=sys.stderr)
    ms = MapSources(maps["index"], maps["ortho"], maps["dsm"])
    # 1. the sequence builds the feature map
    t0, c0 = time.perf_counter(), cpu()
    seq_dir = work / "sequence"
    if a.reuse and (seq_dir / "sfm_points.laz").exists():  # its sequence too (seconds: that run's)
        seq_poses = json.loads((seq_dir / "poses.json").read_text())
    else:
        seq_poses = georeference_video({"images": [str(p) for p in seq], "trajectory": True, "camera": None,
                                        "fps": 1.0}, ms, fl, tr, seq_dir)  # fmt: skip
    seq_s = {"wall_s": time.perf_counter() - t0, "cpu_s": cpu() - c0}
    for r in seq_poses:
        r["bench"] = {"wall_s": seq_s["wall_s"] / len(seq_poses), "cpu_s": seq_s["cpu_s"] / len(seq_poses)}
    print(f"## Sequence {seq[0].stem}..{seq[-1].stem} (feature map): {seq_s['cpu_s']:.0f} CPU s\n")
    table([("sequence", seq_poses)], lambda r: gps_error(r, gps))
    laz = seq_dir / "sfm_points.laz"
    fmap = load_feature_maps([laz], ms.crs_wkt, ms.bounds(), fl.get("feature_map"))
    # 2. the other photos alone: map-only (baseline) and with the feature map, interleaved order
    print(f"## Single photos {single[0].stem}..{single[-1].stem} ({len(fmap)} feature-map points)\n")
    base = locate_all(single, None, ms, fl)
    withfm = locate_all(single, None, ms, fl, fmap)
    table([("map only", base), ("feature map", withfm)], lambda r: gps_error(r, gps))
    (work / "records.json").write_text(json.dumps({"map_only": base, "feature_map": withfm}, default=str))
    # 3. exports of the flight: the sequence (SfM points) and the single photos (map corners)
    from georeg.io.atomic import write_json

    single_dir = work / "single"
    write_json(single_dir / "poses.json", withfm)
    exports = []
    export_frame_set(seq_dir / "poses.json", seq_dir / "export", ms.crs_wkt, sfm_laz=laz)
    exports.append(check_exports("sequence", seq_dir / "export", seq_poses))
    export_frame_set(single_dir / "poses.json", single_dir / "export", ms.crs_wkt, ortho=maps["ortho"], dsm=maps["dsm"])
    exports.append(check_exports("single photos", single_dir / "export", withfm))
    print("## Exports\n")
    for e in exports:
        print(f"- {e['set']}: {e['registered']} images, {e['gcps']} GCPs ({e['gcp_observations']} rows, "
              f"odm_ready {e['odm_ready']}), gcp check {e['gcp_check']}, COLMAP {e['colmap_check']}")
    return {"sequence": summary(seq_poses, lambda r: gps_error(r, gps)), "sequence_seconds": seq_s,
            "map_only": summary(base, lambda r: gps_error(r, gps)),
            "feature_map": summary(withfm, lambda r: gps_error(r, gps)), "exports": exports}  # fmt: skip


def demo(a) -> dict:
    """The demo video's first half builds a feature map; the demo frames and frames of the
    second half are localised alone against it and map-only (truth: the demo's)."""
    import cv2

    from georeg.frames.feature_map import load_feature_maps
    from georeg.frames.localize import MapSources, evaluate
    from georeg.trajectory.pipeline import georeference_video

    fl, tr = repo_conf()
    cfg = yaml.safe_load((REPO / "config" / "config.yaml").read_text())
    res = Path(a.results)
    work = Path(a.work)
    ms = MapSources(res / "index" / "map", res / "map" / "mosaic" / "ortho.vrt", res / "map" / "mosaic" / "dsm.vrt")
    vcam = cfg["frames"]["demo_video"]["camera"]
    video = res / "demo" / "video" / "flight.mp4"
    vtruth = {t["image"]: t for t in json.loads((res / "demo" / "video" / "truth.json").read_text())}
    cap = cv2.VideoCapture(str(video))
    n = int(cap.get(cv2.CAP_PROP_FRAME_COUNT))
    half = n // 2
    t0, c0 = time.perf_counter(), cpu()
    if not (a.reuse and (work / "first_half" / "sfm_points.laz").exists()):
        georeference_video({"video": str(video), "camera": vcam}, ms, fl, {**tr, "max_frames": half}, work / "first_half")
    print(f"first half ({half} frames) geo-referenced: {cpu() - c0:.0f} CPU s, {time.perf_counter() - t0:.0f} s wall",
          file=sys.stderr)  # fmt: skip
    from georeg.io.video import video_name

    frames = []
    for i in range(half, n, int(a.every)):
        cap.set(cv2.CAP_PROP_POS_FRAMES, i)
        ok, bgr = cap.read()
        if ok:
            frames.append((video_name(video, i), cv2.cvtColor(bgr, cv2.COLOR_BGR2RGB)))
    fmap = load_feature_maps([work / "first_half" / "sfm_points.laz"], ms.crs_wkt, ms.bounds(), fl.get("feature_map"))

    def err(r):
        t = vtruth.get(r["image"])
        if t is None or r["status"] != "registered":
            return None
        e = evaluate(r, t)["final"]
        return {"horizontal_m": e["horizontal_m"], "vertical_m": e["vertical_m"], "position_m": e["position_m"]}

    base = locate_all(frames, vcam, ms, fl)
    withfm = locate_all(frames, vcam, ms, fl, fmap)
    print(f"## Demo video, frames {half}..{n - 1} every {a.every} alone ({len(fmap)} feature-map points)\n")
    table([("map only", base), ("feature map", withfm)], err)
    (work / "records.json").write_text(json.dumps({"map_only": base, "feature_map": withfm}, default=str))
    out = {"video": {"map_only": summary(base, err), "feature_map": summary(withfm, err)}}
    if a.skip_frames:
        return out
    # the demo frames (other places and heights)
    dcam = cfg["frames"]["demo"]["camera"]
    dtruth = {Path(t["image"]).name: t for t in json.loads((res / "demo" / "frames" / "truth.json").read_text())}
    dframes = [res / "demo" / "frames" / f"{nm}.png" for nm in ("nadir_120", "oblique35_100", "oblique45_300")]

    def derr(r):
        t = dtruth.get(Path(r["image"]).name)
        if t is None or r["status"] != "registered":
            return None
        e = evaluate(r, t)["final"]
        return {"horizontal_m": e["horizontal_m"], "vertical_m": e["vertical_m"]}

    full = res / "frames" / "demo_video" / "sfm_points.laz"  # the workflow's whole-video feature map
    fmap_full = load_feature_maps([full], ms.crs_wkt, ms.bounds(), fl.get("feature_map")) if full.exists() else fmap
    # map-only: the workflow's own records of these frames (same code and configuration; wall
    # seconds of that run: 3-4 min a frame with the intensity search, not rerun here)
    wf = {Path(p["image"]).name: p for p in json.loads((res / "frames" / "demo" / "poses.json").read_text())}
    dbase = [{**wf[f.name], "bench": {"wall_s": wf[f.name]["timings_s"]["total_s"], "cpu_s": float("nan")}}
             for f in dframes]  # fmt: skip
    dfm = locate_all(dframes, dcam, ms, fl, fmap_full)
    print(f"## Demo frames (against {'the whole video' if full.exists() else 'the first half'}'s feature map, "
          f"{len(fmap_full)} points)\n")
    table([("map only", dbase), ("feature map", dfm)], derr)
    out["frames"] = {"map_only": summary(dbase, derr), "feature_map": summary(dfm, derr)}
    return out


def main(argv: list[str]) -> None:
    import logging

    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    sub = ap.add_subparsers(dest="cmd", required=True)
    b = sub.add_parser("brighton")
    b.add_argument("--split", type=int, default=9)
    b.add_argument("--swap", action="store_true", help="photos after --split build the map, the others are localised")
    b.add_argument("--work", default="/tmp/bench_fm")
    d = sub.add_parser("demo")
    d.add_argument("results")
    d.add_argument("--every", type=int, default=20)
    d.add_argument("--skip-frames", action="store_true", help="only the video frames")
    d.add_argument("--work", default="/tmp/bench_fm_demo")
    for p in (b, d):
        p.add_argument("--out", default=None, help="summary JSON")
        p.add_argument("--reuse", action="store_true", help="reuse the map / first sequence of an earlier run in --work")
    a = ap.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(levelname)s %(name)s: %(message)s")
    out = brighton(a) if a.cmd == "brighton" else demo(a)
    if a.out:
        Path(a.out).parent.mkdir(parents=True, exist_ok=True)
        Path(a.out).write_text(json.dumps(out, indent=1, default=str))


if __name__ == "__main__":
    main(sys.argv[1:])
