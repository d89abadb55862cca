"""Video trajectory geo-referencing: one registered keyframe geo-references a video.

As in the seed paper (Bodensteiner et al., section 3), for one frame set with a ``video`` (or an
ordered ``images`` list):

1. keyframes by visual overlap and baseline (``georeg.trajectory.keyframes``), undistorted to PNGs;
2. SfM of the keyframes with pycolmap (``georeg.trajectory.sfm``): the 3-D feature map, points with long
   tracks only;
3. a few keyframes ("anchors") registered to the map by the single-frame method
   (``georeg.frames.localize.localize_image``);
4. structure projection: the anchors' SfM points get map points from the depth buffer of the map
   rendered at the anchor poses; Sim(3) SfM -> map by RANSAC + Umeyama, refined on Sim(3)
   (``georeg.trajectory.structure_projection``);
5. ICP of the transformed SfM points against the map surface (``georeg.trajectory.icp``, point-to-plane);
6. every frame located: keyframes from the transformed reconstruction, the frames between them by
   tracking the keyframe's geo-registered points (LK + PnP), relocalisation against the point
   descriptors when tracking is lost (``georeg.trajectory.relocalize``);
7. outputs: poses.json (the frames contract, one entry per frame), CSV / GeoJSON / KML of the
   trajectory, the 3-D feature map (LAZ + descriptors), overlays.
"""

from __future__ import annotations

import json
import logging
import shutil
import time
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from georeg.frames.localize import (
    MapSources,
    camera_matrix,
    display_render,
    evaluate,
    localize_image,
)
from georeg.frames.outputs import footprint_window, footprint_xy, overlay, write_png, write_poses
from georeg.frames.render import PinholeCamera
from georeg.io.atomic import write_json
from georeg.trajectory.relocalize import FramePose, PointMapLocalizer, Tracker
from georeg.trajectory.sim3 import Sim3, transform_pose

log = logging.getLogger(__name__)

DEFAULTS: dict[str, Any] = {
    "step": 1,  # every n-th video frame
    "max_frames": None,
    "fps": 10.0,  # image lists: frames per second (time_s)
    "keyframes": {},  # georeg.trajectory.keyframes defaults
    "sfm": {},  # georeg.trajectory.sfm defaults
    "anchors": 2,  # keyframes registered to the map by the single-frame method
    "anchor_tries": 6,  # keyframes tried at most to find them
    "structure": {},  # georeg.trajectory.structure_projection defaults (RANSAC threshold ...)
    "icp": {"enabled": True},  # georeg.trajectory.icp defaults
    "track": {},  # georeg.trajectory.relocalize defaults
    "corridor_margin_m": 80.0,  # map read around the trajectory's footprints (ICP, overlays)
    "overlays": 6,  # overlay images, evenly spread over the registered frames
    "look_every": 10,  # GeoJSON / KML look directions every n frames (and every keyframe)
    "seed": 0,
}


def _undistorter(camera: dict | None, size: tuple[int, int]):
    """(K of the undistorted frames or None, function rgb -> undistorted rgb)."""
    if not camera:
        return None, lambda im: im
    w, h = size
    K, dist = camera_matrix(camera, w, h)
    if not np.any(dist):
        return K, lambda im: im
    m1, m2 = cv2.initUndistortRectifyMap(K, dist, None, K, (w, h), cv2.CV_16SC2)
    return K, lambda im: cv2.remap(im, m1, m2, cv2.INTER_LINEAR)


def _gray(rgb: np.ndarray) -> np.ndarray:
    return cv2.cvtColor(rgb, cv2.COLOR_RGB2GRAY)


def _kf_name(index: int) -> str:
    return f"kf_{index:06d}.png"


def _pose_error(R, C, truth: dict) -> dict:
    return evaluate({"camera_center_xyz": list(map(float, C)), "R_world_to_cam": np.asarray(R).tolist()},
                    truth)["final"]  # fmt: skip


def _stats(errs: list[dict]) -> dict:
    if not errs:
        return {"n": 0}
    out: dict[str, Any] = {"n": len(errs)}
    for k in ("position_m", "horizontal_m", "vertical_m", "rotation_deg"):
        v = np.array([e[k] for e in errs], float)
        out[k] = {"mean": float(v.mean()), "median": float(np.median(v)),
                  "p90": float(np.percentile(v, 90)), "max": float(v.max())}  # fmt: skip
    return out


def georeference_video(frame_set: dict, maps: MapSources, frame_loc: dict, conf: dict,
                       out_dir: str | Path, work_dir: str | Path | None = None,
                       truth_path: str | None = None) -> list[dict]:  # fmt: skip
    """Rule ``trajectory``: one frame set with a video -> results/frames/{set}/ (see module).

    ``work_dir`` (keyframe PNGs, the COLMAP database): kept when given, else ``out_dir/.work``,
    removed at the end."""
    keep = work_dir is not None
    work = Path(work_dir) if keep else Path(out_dir) / ".work"
    try:
        return _georeference(frame_set, maps, frame_loc, conf, Path(out_dir), work, truth_path)
    finally:
        if not keep:
            shutil.rmtree(work, ignore_errors=True)


def _georeference(frame_set: dict, maps: MapSources, frame_loc: dict, conf: dict, out: Path,
                  work: Path, truth_path: str | None) -> list[dict]:  # fmt: skip
    from georeg.io.video import FrameSource, video_name
    from georeg.trajectory.icp import icp_refine
    from georeg.trajectory.keyframes import iter_keyframes
    from georeg.trajectory.sfm import run_sfm
    from georeg.trajectory.structure_projection import estimate_sfm_to_map

    c = {**DEFAULTS, **(conf or {})}
    t_all = time.perf_counter()
    timings: dict[str, float] = {}
    src = FrameSource(frame_set.get("video") or frame_set.get("images"), int(c["step"]),
                      c["max_frames"], frame_set.get("fps") or c["fps"])  # fmt: skip
    fps = float(src.fps or c["fps"])
    camera = frame_set.get("camera")
    w, h = src.width, src.height
    K, undistort = _undistorter(camera, (w, h))
    log.info("%s: %d frames of %d x %d at %.3g fps", src.video or "image list", len(src), w, h, fps)

    # 1. keyframes (streamed: one decode; each written undistorted for the SfM when decided)
    t0 = time.perf_counter()
    kf_dir = work / "keyframes"
    if kf_dir.exists():
        shutil.rmtree(kf_dir)
    kf_dir.mkdir(parents=True)
    names: dict[int, str] = {}
    current: dict[str, np.ndarray] = {}

    def gray_frames():
        for i, name, rgb in src:
            names[i] = name
            current["rgb"] = undistort(rgb)
            yield i, _gray(current["rgb"])

    key_idx = []
    for k in iter_keyframes(gray_frames(), c["keyframes"]):  # current = keyframe k's frame
        key_idx.append(k.index)
        cv2.imwrite(str(kf_dir / _kf_name(k.index)), cv2.cvtColor(current["rgb"], cv2.COLOR_RGB2BGR))
    timings["keyframes_s"] = time.perf_counter() - t0
    if src.unreadable:  # corrupt video frames: left out, listed in the outputs
        info_bad = [{"frame": i, "image": video_name(src.video, i), "time_s": round(i / fps, 4)}
                    for i in src.unreadable]  # fmt: skip
    else:
        info_bad = []
    log.info("%d keyframes of %d frames (%.1f s)", len(key_idx), len(names), timings["keyframes_s"])

    # 2. SfM
    t0 = time.perf_counter()
    cam_sfm = ({k: float(camera[k]) for k in ("fx", "fy", "cx", "cy")} if camera else None)
    info: dict[str, Any] = {"frames": len(names), "keyframes": len(key_idx)}
    if info_bad:
        info["unreadable_frames"] = info_bad
    try:
        model = run_sfm(kf_dir, work / "sfm", cam_sfm, {"seed": int(c["seed"]), **c["sfm"]})
    except ValueError as exc:  # no usable reconstruction: an honest not_found, not a crash
        log.warning("SfM failed: %s", exc)
        info["reason"] = f"SfM: {exc}"
        return _write_not_found(out, names, fps, maps.crs_wkt, info, timings, t_all)
    timings["sfm_s"] = time.perf_counter() - t0
    K = np.asarray(model.K, float) if K is None else K

    def cam_at(R: np.ndarray, C: np.ndarray) -> PinholeCamera:
        return PinholeCamera(K[0, 0], K[1, 1], K[0, 2], K[1, 2], w, h, R, C)

    kf_dist = np.zeros(5) if camera else np.r_[np.asarray(model.dist, float), np.zeros(5)][:5]
    cam_known = {"fx": K[0, 0], "fy": K[1, 1], "cx": K[0, 2], "cy": K[1, 2], "dist": kf_dist.tolist()}
    log.info("SfM: %d of %d keyframes, %d points (%.1f s)", len(model.names), len(key_idx),
             len(model.xyz), timings["sfm_s"])  # fmt: skip

    # 3. anchors: keyframes registered to the map by the single-frame method
    t0 = time.perf_counter()
    n_obs = np.array([len(p) for p in model.obs_point])
    order = _anchor_order(n_obs, int(c["anchor_tries"]))
    anchors, anchor_recs = [], []
    single: dict[str, dict] = {}  # keyframe name -> its single-frame record
    # no intensity pose search for anchors (15-45 s a try, a looser pose): the next keyframe instead
    a_loc = {**frame_loc, "search": {**(frame_loc.get("search") or {}), "enabled": False}}
    for j in order:
        if len(anchors) >= int(c["anchors"]):
            break
        nm = model.names[j]
        rgb = cv2.cvtColor(cv2.imread(str(kf_dir / nm)), cv2.COLOR_BGR2RGB)
        rec, _ = localize_image(rgb, nm, cam_known, maps, a_loc)
        anchor_recs.append({k: rec.get(k) for k in ("image", "status", "inliers", "reprojection_px",
                                                     "camera_center_xyz", "reason", "timings_s")})  # fmt: skip
        single[nm] = rec
        if rec["status"] == "registered":
            anchors.append((nm, np.asarray(rec["R_world_to_cam"]), np.asarray(rec["camera_center_xyz"])))
    timings["anchors_s"] = time.perf_counter() - t0
    info.update(sfm={**model.info, "registered": len(model.names), "points": int(len(model.xyz))},
                anchors=anchor_recs)  # fmt: skip
    if not anchors:
        log.warning("no keyframe registered to the map: every frame not_found")
        info["reason"] = "no anchor keyframe registered to the map"
        return _write_not_found(out, names, fps, maps.crs_wkt, info, timings, t_all)

    # 4. structure projection -> Sim(3)
    t0 = time.perf_counter()
    zg = maps.ground_z(anchors[0][2])
    bounds = footprint_window([cam_at(R, C) for _, R, C in anchors], zg,
                              float(frame_loc.get("cloud_margin_m", 120.0)),
                              float(frame_loc.get("max_cloud_extent_m", 1600.0)))  # fmt: skip
    source = frame_loc.get("render_source", "heightfield")
    cloud_a = maps.cloud(bounds, source)
    try:
        sim, sinfo = estimate_sfm_to_map(model, [(*a, K) for a in anchors], cloud_a,
                                         c["structure"], int(c["seed"]))  # fmt: skip
    except ValueError as exc:
        log.warning("Sim(3) SfM -> map failed: %s", exc)
        info["reason"] = f"structure projection: {exc}"
        return _write_not_found(out, names, fps, maps.crs_wkt, info, timings, t_all)
    timings["sim3_s"] = time.perf_counter() - t0
    info["sim3"] = {**sinfo, "scale": float(sim.s)}

    # 5. ICP against the map surface along the whole trajectory
    t0 = time.perf_counter()
    kcams = [cam_at(*transform_pose(sim, R, C)) for R, C in zip(model.R, model.C, strict=True)]
    corridor = footprint_window(kcams, zg, float(c["corridor_margin_m"]), 4000.0)
    cloud = maps.cloud(corridor, source)
    final = sim
    if (c.get("icp") or {}).get("enabled", True):
        T, iinfo = icp_refine(sim.apply(model.xyz), cloud, c["icp"], guard_xyz=sim.apply(model.C))
        final = Sim3.from_matrix(np.asarray(T) @ sim.matrix())
        info["icp"] = iinfo
    timings["icp_s"] = time.perf_counter() - t0
    xyz_map = final.apply(model.xyz)
    pre_icp = sim.compose(final.inverse())  # map (after ICP) -> map (before ICP)

    # 6. every frame
    t0 = time.perf_counter()
    kf_frame = {_kf_name(i): i for i in key_idx}  # keyframe PNG name -> frame index
    kf_pose = {kf_frame[nm]: transform_pose(final, R, C)
               for nm, R, C in zip(model.names, model.R, model.C, strict=True)}  # fmt: skip
    n_ov = int(c["overlays"])
    ov_frames = set(np.asarray(src.indices())[np.linspace(0, len(src) - 1, n_ov).round().astype(int)]
                    .tolist()) if n_ov else set()  # fmt: skip
    ov_dir = out / "overlays"
    if ov_dir.exists():
        shutil.rmtree(ov_dir)
    ov_dir.mkdir(parents=True)
    tracker = Tracker(K, c["track"])
    reloc = PointMapLocalizer(xyz_map, model.descriptors, K, (w, h), c["track"])
    truth = _read_truth(truth_path)
    poses: list[dict] = []
    last: tuple[np.ndarray, np.ndarray] | None = None
    per_frame_s = []
    for i, name, rgb in src:
        tf = time.perf_counter()
        gray = _gray(undistort(rgb))
        rec: dict[str, Any] = {"image": name, "frame": i, "time_s": round(i / fps, 4),
                               "keyframe": i in kf_pose, "status": "not_found"}  # fmt: skip
        if i in kf_pose:
            R, C = kf_pose[i]
            pt, uv = model.observations(_kf_name(i))
            tracker.reset(gray, uv, xyz_map[pt])
            proj, _ = cam_at(R, C).project(xyz_map[pt])
            rms = float(np.sqrt(np.mean(np.sum((proj - uv) ** 2, axis=1)))) if len(pt) else float("nan")
            fp = FramePose(True, R, C, int(len(pt)), rms, "sfm")
        else:
            fp = tracker.step(gray)
            if not fp.ok:
                fp, uv, xyz = reloc.locate(gray, last)
                if fp.ok:
                    tracker.reset(gray, uv, xyz)
        if fp.ok:
            last = (fp.R, fp.C)
            cam = cam_at(fp.R, fp.C)
            rec.update(status="registered", source=fp.source,
                       camera_center_xyz=[float(v) for v in fp.C],
                       R_world_to_cam=np.asarray(fp.R).tolist(), inliers=int(fp.inliers),
                       reprojection_px=float(fp.reprojection_px),
                       footprint_xy=footprint_xy(cam, zg).tolist())  # fmt: skip
        else:
            rec.update(source=fp.source, camera_center_xyz=None, R_world_to_cam=None,
                       inliers=int(fp.inliers), reprojection_px=None)  # fmt: skip
        if _kf_name(i) in single:  # this keyframe was also tried alone (as an anchor)
            rec["single_frame"] = single_frame_record(single[_kf_name(i)], rec)
        rec["intrinsics"] = {"fx": float(K[0, 0]), "fy": float(K[1, 1]), "cx": float(K[0, 2]),
                             "cy": float(K[1, 2]), "dist": list(map(float, (camera or {}).get("dist") or
                                                                     kf_dist)), "width": w, "height": h,
                             "source": "given" if camera else "sfm self-calibration"}  # fmt: skip
        per_frame_s.append(time.perf_counter() - tf)
        rec["timings_s"] = {"total_s": round(per_frame_s[-1], 4)}
        if name in truth:
            ev = evaluate(rec, truth[name])
            if fp.ok:
                Rb, Cb = transform_pose(pre_icp, fp.R, fp.C)
                ev["before_icp"] = _pose_error(Rb, Cb, truth[name])
            rec["evaluation"] = ev
        poses.append(rec)
        if i in ov_frames:  # the map rendered at the found pose, over the frame
            rend = display_render(cloud, cam_at(fp.R, fp.C), maps.gsd) if fp.ok else None
            write_png(ov_dir / f"frame_{i:06d}.png", overlay(undistort(rgb), rend))
    timings["frames_s"] = time.perf_counter() - t0
    info["frames_per_second"] = len(per_frame_s) / max(sum(per_frame_s), 1e-9)
    info["evaluation"] = _evaluate_set(poses, truth, model, kf_frame)
    info["single_frame"] = single_frame_summary(poses)
    points = (xyz_map, model.rgb, model.track_len, model.descriptors)
    return _write_outputs(out, poses, maps.crs_wkt, zg, points, info, int(c["look_every"]), timings,
                          t_all)  # fmt: skip


def single_frame_record(single: dict, seq: dict) -> dict[str, Any]:
    """What the single-frame method found for a keyframe beside the sequence's pose ``seq``:
    its status and reason, and (both registered) how far apart the two camera centres are."""
    out: dict[str, Any] = {"status": single.get("status"), "reason": single.get("reason"),
                           "inliers": single.get("inliers")}  # fmt: skip
    a, b = single.get("camera_center_xyz"), seq.get("camera_center_xyz")
    if single.get("status") == "registered" and a is not None and b is not None:
        out["centre_diff_m"] = round(float(np.linalg.norm(np.subtract(a, b))), 3)
    out["located_by_sequence_only"] = single.get("status") != "registered" and seq["status"] == "registered"
    return out


def single_frame_summary(poses: list[dict]) -> dict[str, Any]:
    """Keyframes tried alone: how many the single-frame method registered, how many only the
    sequence located, and the median distance between both poses where both exist."""
    recs = [p["single_frame"] for p in poses if "single_frame" in p]
    diffs = [r["centre_diff_m"] for r in recs if "centre_diff_m" in r]
    return {"tried": len(recs), "registered": sum(r["status"] == "registered" for r in recs),
            "located_by_sequence_only": sum(bool(r["located_by_sequence_only"]) for r in recs),
            "median_centre_diff_m": float(np.median(diffs)) if diffs else None}  # fmt: skip


def _anchor_order(n_obs: np.ndarray, tries: int) -> list[int]:
    """Keyframes to try as anchors: the best-observed one of each of ``tries`` equal segments of
    the sequence, best first (spread along the path, so two anchors constrain the scale)."""
    n = len(n_obs)
    segs = np.array_split(np.arange(n), max(1, min(tries, n)))
    best = [int(s[np.argmax(n_obs[s])]) for s in segs if len(s)]
    return sorted(best, key=lambda j: -n_obs[j])


def _read_truth(path: str | None) -> dict[str, dict]:
    if not path:
        return {}
    return {t["image"]: t for t in json.loads(Path(path).read_text())}


def _evaluate_set(poses: list[dict], truth: dict, model, kf_frame: dict[str, int]) -> dict:
    """Mean / p90 errors over all frames (after and before ICP), keyframes only, and the Sim(3)
    scale against the truth (SfM keyframe centres aligned to the true centres by Umeyama)."""
    if not truth:
        return {}
    from georeg.trajectory.sim3 import umeyama

    ev = [p["evaluation"] for p in poses if "evaluation" in p]
    out: dict[str, Any] = {
        "frames": len(ev),
        "registered": sum(1 for p in poses if p["status"] == "registered"),
        "after_icp": _stats([e["final"] for e in ev if "final" in e]),
        "before_icp": _stats([e["before_icp"] for e in ev if "before_icp" in e]),
        "keyframes_after_icp": _stats([p["evaluation"]["final"] for p in poses
                                       if p.get("keyframe") and "final" in p.get("evaluation", {})]),  # fmt: skip
    }
    by_frame = {p["frame"]: p for p in poses}
    src, dst = [], []
    for nm, C in zip(model.names, model.C, strict=True):
        p = by_frame.get(kf_frame[nm])
        if p is not None and p["image"] in truth:
            src.append(C)
            dst.append(truth[p["image"]]["camera_center_xyz"])
    if len(src) >= 3:
        out["true_scale"] = float(umeyama(np.asarray(src), np.asarray(dst)).s)
    return out


def _write_outputs(out: Path, poses: list[dict], crs: str, zg: float, points: tuple, info: dict,
                   look_every: int, timings: dict, t_all: float) -> list[dict]:  # fmt: skip
    """Trajectory CSV / GeoJSON / KML, the point map, trajectory.json, then poses.json; the
    frames in ``info["unreadable_frames"]`` join the poses as ``unreadable``. Returns the poses."""
    from georeg.trajectory.outputs import write_csv, write_geojson, write_kml, write_point_map

    have = {p["frame"] for p in poses}
    bad = [{**b, "status": "unreadable", "reason": "the video frame could not be decoded (corrupt "
            "data, or a frame predicted from one)", "camera_center_xyz": None,
            "R_world_to_cam": None, "inliers": 0, "reprojection_px": None}
           for b in info.get("unreadable_frames") or [] if b["frame"] not in have]  # fmt: skip
    poses = sorted([*poses, *bad], key=lambda p: p["frame"])
    write_csv(out / "trajectory.csv", poses, crs)
    write_geojson(out / "trajectory.geojson", poses, crs, zg, look_every)
    write_kml(out / "trajectory.kml", poses, crs, zg, look_every)
    write_point_map(out / "sfm_points.laz", *points, crs)
    timings["total_s"] = time.perf_counter() - t_all
    info["timings_s"] = {k: round(v, 3) for k, v in timings.items()}
    write_json(out / "trajectory.json", info)
    write_poses(out / "poses.json", poses)
    return poses


def _write_not_found(out: Path, names: dict, fps: float, crs: str, info: dict, timings: dict,
                     t_all: float) -> list[dict]:  # fmt: skip
    """Every frame ``not_found`` (no reconstruction, no anchor, no Sim(3)): the same outputs."""
    poses = [{"image": n, "frame": i, "time_s": round(i / fps, 4), "status": "not_found",
              "camera_center_xyz": None, "R_world_to_cam": None, "inliers": 0,
              "reprojection_px": None} for i, n in names.items()]  # fmt: skip
    (out / "overlays").mkdir(parents=True, exist_ok=True)
    empty = (np.zeros((0, 3)), np.zeros((0, 3)), np.zeros(0), np.zeros((0, 128)))
    return _write_outputs(out, poses, crs, 0.0, empty, info, 1, timings, t_all)
