"""Unordered photo collections (issue 33 item 3): one place, mixed cameras, any file order.

For a frame set with ``collection: true``:

1. photos in file-name order (the result does not depend on the order they are listed in);
   one camera per (image size, EXIF focal) group: the set's ``camera`` held fixed, else the
   EXIF focal length (``georeg.frames.exif``) held fixed (as a prior refined by the SfM it bent
   the brighton model: docs/experiments/2026-11-26-collection.md), else self-calibrated;
2. SfM of all photos with exhaustive pair matching (``georeg.trajectory.sfm``, the video path's
   reconstruction; cost grows with the square of the number of photos);
3. photos localised alone by the single-frame method (``localize_frame``, feature maps first when
   the set has them): every photo (``anchors: null``) or the best-observed ones until ``anchors``
   registered; the registered ones in the SfM model are the anchors of the Sim(3) SfM -> map
   (structure projection, RANSAC), then ICP against the map surface (the video path's stages);
4. every photo in the SfM model is posed by the transformed reconstruction (``posed_by:
   sfm+sim3``); a photo outside the model keeps its single-frame pose (``single``) or is
   ``not_found``. Outputs as rule localize_frames (poses.json, cameras GeoJSON / KML), plus the
   geo-registered SfM points (a feature map) and collection.json.
"""

from __future__ import annotations

import logging
import shutil
import time
from pathlib import Path
from typing import Any

import numpy as np

from georeg.frames.localize import MapSources, check_frame, evaluate, localize_frame
from georeg.frames.outputs import (
    footprint_window,
    footprint_xy,
    write_geojson,
    write_kml,
    write_poses,
)
from georeg.frames.render import PinholeCamera
from georeg.io.atomic import write_json
from georeg.io.errors import InputError
from georeg.trajectory.pipeline import single_frame_record
from georeg.trajectory.sim3 import Sim3, transform_pose

log = logging.getLogger(__name__)

DEFAULTS: dict[str, Any] = {
    "anchors": None,  # photos localised alone before the Sim(3): None = every photo
    "sfm": {"matching": "exhaustive"},  # georeg.trajectory.sfm DEFAULTS overrides
    "structure": {},  # georeg.trajectory.structure_projection DEFAULTS overrides
    "icp": {"enabled": True},  # georeg.trajectory.icp DEFAULTS overrides
    "corridor_margin_m": 80.0,  # map read around the photos' footprints (ICP)
    "seed": 0,
}


def collection_photos(paths: list[str]) -> list[Path]:
    """The photos sorted by file name; InputError when two share a name (SfM names images by it)."""
    out = sorted((Path(p) for p in paths), key=lambda p: (p.name, str(p)))
    names = [p.name for p in out]
    dup = sorted({n for n in names if names.count(n) > 1})
    if dup:
        raise InputError(out[names.index(dup[0])], f"photo names {dup[:3]} occur twice in the collection",
                         "unique file names")  # fmt: skip
    return out


def camera_groups(
    photos: list[Path], camera: dict | None
) -> tuple[list[tuple[list[str], dict | None]], dict]:
    """SfM camera groups (names, camera) and each photo's single-frame camera. The set's
    ``camera``: one fixed camera; else per (size, EXIF focal): that focal fixed, or (no EXIF
    focal) self-calibrated."""
    from PIL import Image

    from georeg.frames.exif import exif_camera

    groups: dict[tuple, tuple[list[str], dict | None]] = {}
    single: dict[str, dict | None] = {}
    for p in photos:
        with Image.open(p) as im:
            w, h = im.size
        if camera:
            key, cam, single[p.name] = ("given",), dict(camera), camera
        else:
            ex = exif_camera(p, w, h)
            single[p.name] = ex
            key = (w, h, None if ex is None else round(float(ex["fx"]), 1))
            cam = None if ex is None else dict(ex)
        groups.setdefault(key, ([], cam))[0].append(p.name)
    return list(groups.values()), single


def _intrinsics(K: np.ndarray, dist: np.ndarray, w: int, h: int, source: str) -> dict:
    return {"fx": float(K[0, 0]), "fy": float(K[1, 1]), "cx": float(K[0, 2]), "cy": float(K[1, 2]),
            "dist": [float(v) for v in dist], "width": int(w), "height": int(h), "source": source}  # fmt: skip


def _anchor_order(model, names: list[str]) -> list[str]:
    """Photos in the model first, best observed first (ties by name), then the rest by name."""
    n_obs = {n: len(model.obs_point[i]) for i, n in enumerate(model.names)} if model else {}
    return sorted(names, key=lambda n: (n not in n_obs, -n_obs.get(n, 0), n))


def georeference_collection(frame_set: dict, maps: MapSources, frame_loc: dict, conf: dict,
                            out_dir: str | Path, work_dir: str | Path | None = None,
                            truth_path: str | None = None) -> list[dict]:  # fmt: skip
    """Rule ``collection``: one unordered photo set -> results/frames/{set}/ (see module).
    ``work_dir`` (photo links, the COLMAP database): kept when given, else removed."""
    from georeg.io.video import frame_images

    keep = work_dir is not None
    out = Path(out_dir)
    work = Path(work_dir) if keep else out / ".work"
    photos = collection_photos(frame_images(frame_set.get("images")))
    if not photos:
        raise InputError(None, f"the photo list {frame_set.get('images')!r} matches no file",
                         "check frames.<set>.images")  # fmt: skip
    for p in photos:
        check_frame(p)
    try:
        return _georeference(
            photos, frame_set.get("camera"), maps, frame_loc, conf, out, work, truth_path
        )
    finally:
        if not keep:
            shutil.rmtree(work, ignore_errors=True)


def _sfm(photos: list[Path], groups: list, work: Path, c: dict) -> tuple[Any, str | None]:
    """The SfM model of the photos (links in ``work/photos``), or (None, why) when it fails."""
    from georeg.trajectory.sfm import run_sfm

    d = work / "photos"
    if d.exists():
        shutil.rmtree(d)
    d.mkdir(parents=True)
    for p in photos:
        (d / p.name).symlink_to(p.resolve())
    if len(photos) < 3:
        return None, f"{len(photos)} photos; SfM needs at least 3"
    try:
        return run_sfm(
            d, work / "sfm", None, {"seed": int(c["seed"]), **(c["sfm"] or {})}, groups
        ), None
    except ValueError as exc:
        log.warning("SfM failed: %s", exc)
        return None, f"SfM: {exc}"


def _single(
    photos: list[Path], cams: dict, model, maps: MapSources, frame_loc: dict, c: dict
) -> dict[str, dict]:
    """Single-frame records: photos outside the model always; photos in it until ``anchors``
    registered (None: all), best observed first. No intensity search here (see _fallback)."""
    loc = {**frame_loc, "search": {**(frame_loc.get("search") or {}), "enabled": False}}
    by_name = {p.name: p for p in photos}
    in_model = set(model.names) if model else set()
    need = None if c["anchors"] is None else int(c["anchors"])
    recs: dict[str, dict] = {}
    n_anchor = 0
    for n in _anchor_order(model, list(by_name)):
        if n in in_model and need is not None and n_anchor >= need:
            continue
        recs[n], _ = localize_frame(str(by_name[n]), cams[n], maps, loc)
        n_anchor += int(n in in_model and recs[n]["status"] == "registered")
    return recs


def _sim3(model, single: dict[str, dict], maps: MapSources, frame_loc: dict, c: dict):
    """(Sim(3) SfM -> map after ICP, info) from the registered photos in the model, or (None, info)."""
    from georeg.trajectory.icp import icp_refine
    from georeg.trajectory.structure_projection import estimate_sfm_to_map

    anchors = [(n, np.asarray(r["R_world_to_cam"]), np.asarray(r["camera_center_xyz"]))
               for n, r in sorted(single.items()) if r["status"] == "registered" and n in model.names]  # fmt: skip
    info: dict[str, Any] = {"anchors": [a[0] for a in anchors]}
    if not anchors:
        info["reason"] = "no photo of the SfM model registered alone"
        return None, info
    zg = maps.ground_z(anchors[0][2])

    def cams(R_C) -> list[PinholeCamera]:
        out = []
        for n, R, C in R_C:
            K, _, w, h = model.camera(n)
            out.append(PinholeCamera(K[0, 0], K[1, 1], K[0, 2], K[1, 2], w, h, R, C))
        return out

    source = frame_loc.get("render_source", "heightfield")
    bounds = footprint_window(cams(anchors), zg, float(frame_loc.get("cloud_margin_m", 120.0)),
                              float(frame_loc.get("max_cloud_extent_m", 1600.0)))  # fmt: skip
    try:
        sim, sinfo = estimate_sfm_to_map(model, anchors, maps.cloud(bounds, source), c["structure"],
                                         int(c["seed"]))  # fmt: skip
    except ValueError as exc:
        log.warning("Sim(3) SfM -> map failed: %s", exc)
        info["reason"] = f"structure projection: {exc}"
        return None, info
    info["sim3"] = {**sinfo, "scale": float(sim.s)}
    final = sim
    if (c.get("icp") or {}).get("enabled", True):
        posed = [
            (n, *transform_pose(sim, R, C))
            for n, R, C in zip(model.names, model.R, model.C, strict=True)
        ]
        corridor = footprint_window(cams(posed), zg, float(c["corridor_margin_m"]), 4000.0)
        T, info["icp"] = icp_refine(sim.apply(model.xyz), maps.cloud(corridor, source), c["icp"],
                                    guard_xyz=sim.apply(model.C))  # fmt: skip
        final = Sim3.from_matrix(np.asarray(T) @ sim.matrix())
    return final, info


def _sfm_record(model, i: int, sim: Sim3, xyz_map: np.ndarray, zg: float, cam_src: str) -> dict:
    """The pose record of the model's photo ``i`` in the map (reprojection of its points)."""
    import cv2

    n = model.names[i]
    R, C = transform_pose(sim, model.R[i], model.C[i])
    K, dist, w, h = model.camera(n)
    cam = PinholeCamera(K[0, 0], K[1, 1], K[0, 2], K[1, 2], w, h, R, C)
    pt, uv = model.observations(n)
    if len(uv) and np.any(dist != 0):
        uv = cv2.undistortPoints(np.asarray(uv, float).reshape(-1, 1, 2), K, dist, P=K).reshape(
            -1, 2
        )
    proj, _ = cam.project(xyz_map[pt])
    rms = float(np.sqrt(np.mean(np.sum((proj - uv) ** 2, axis=1)))) if len(pt) else None
    return {"status": "registered", "path": "sfm+sim3", "camera_center_xyz": [float(v) for v in C],
            "R_world_to_cam": np.asarray(R).tolist(), "inliers": int(len(pt)), "reprojection_px": rms,
            "footprint_xy": footprint_xy(cam, zg).tolist(), "intrinsics": _intrinsics(K, dist, w, h, cam_src)}  # fmt: skip


def verify_pose(
    path: Path,
    K: np.ndarray,
    dist: np.ndarray,
    R: np.ndarray,
    C: np.ndarray,
    maps: MapSources,
    frame_loc: dict,
) -> dict:
    """The single-frame path's verification score of the pose (R, C) of photo ``path`` (K and
    distortion of the full-size photo): guided matches against the orthophoto / DSM window under
    the pose that reproject within the tolerance (``georeg.frames.direct.verify``)."""
    import cv2

    from georeg.frames.direct import DEFAULTS as DIRECT_DEFAULTS
    from georeg.frames.direct import match_window, verification_tolerance, verify
    from georeg.frames.localize import DEFAULTS as LOC_DEFAULTS
    from georeg.frames.localize import working_level

    rgb = check_frame(path)
    if np.any(dist):
        rgb = cv2.undistort(rgb, K, np.asarray(dist, float))
    cam0 = {"fx": K[0, 0], "fy": K[1, 1], "cx": K[0, 2], "cy": K[1, 2]}
    mpx = float(frame_loc.get("max_frame_mpx", LOC_DEFAULTS["max_frame_mpx"]))
    rgb, k, _ = working_level(rgb, cam0, mpx)
    gray = cv2.cvtColor(rgb, cv2.COLOR_RGB2GRAY)
    cam = PinholeCamera(k["fx"], k["fy"], k["cx"], k["cy"], gray.shape[1], gray.shape[0], R, C)
    vconf = {**DIRECT_DEFAULTS, **(frame_loc.get("direct") or {})}
    feat = maps.index.meta.get("features_conf") or {}
    zg = maps.ground_z(C)
    mt = match_window(gray, cam, maps.ortho, maps.dsm, feat, maps.gsd, zg, vconf, maps.flat_z)
    return verify(mt, cam, verification_tolerance(cam, maps.gsd, zg, float(vconf["verify_px"])))


def _georeference(photos: list[Path], camera: dict | None, maps: MapSources, frame_loc: dict,
                  conf: dict, out: Path, work: Path, truth_path: str | None) -> list[dict]:  # fmt: skip
    from georeg.trajectory.outputs import write_point_map

    c = {**DEFAULTS, **(conf or {})}
    c["sfm"] = {**DEFAULTS["sfm"], **(c.get("sfm") or {})}
    t_all = time.perf_counter()
    timings: dict[str, float] = {}
    groups, cams = camera_groups(photos, camera)
    t0 = time.perf_counter()
    model, why = _sfm(photos, groups, work, c)
    timings["sfm_s"] = time.perf_counter() - t0
    info: dict[str, Any] = {"photos": len(photos), "cameras": len(groups)}
    info["sfm"] = {**model.info, "registered": len(model.names), "points": int(len(model.xyz))} if model else {"reason": why}  # fmt: skip
    t0 = time.perf_counter()
    single = _single(photos, cams, model, maps, frame_loc, c)
    timings["single_s"] = time.perf_counter() - t0
    t0 = time.perf_counter()
    sim, sinfo = _sim3(model, single, maps, frame_loc, c) if model else (None, {"reason": why})
    info.update(sinfo)
    timings["sim3_icp_s"] = time.perf_counter() - t0
    cam_src = "given" if camera else "EXIF focal, or sfm self-calibration without one"
    xyz_map, zg = np.zeros((0, 3)), 0.0
    if sim is not None:  # the ground under the footprints: the SfM points' median height
        xyz_map = sim.apply(model.xyz)
        zg = (
            float(np.median(xyz_map[:, 2]))
            if len(xyz_map)
            else maps.ground_z(sim.apply(model.C)[0])
        )
    t0 = time.perf_counter()
    single = _fallback(
        photos, cams, single, set(model.names) if (model and sim) else set(), maps, frame_loc
    )
    timings["fallback_s"] = time.perf_counter() - t0
    truth = _truth(truth_path)
    poses = []
    for p in photos:
        n = p.name
        if sim is not None and n in model.names:
            rec = {
                "image": str(p),
                **_sfm_record(model, model.index(n), sim, xyz_map, zg, cam_src),
                "posed_by": "sfm+sim3",
            }
            K, dist, _, _ = model.camera(n)
            R, C = np.asarray(rec["R_world_to_cam"]), np.asarray(rec["camera_center_xyz"])
            rec["verification"] = verify_pose(p, K, dist, R, C, maps, frame_loc)
            if n in single:
                sf = single[n]
                rec["single_frame"] = {
                    **single_frame_record(sf, rec),
                    "camera_center_xyz": sf.get("camera_center_xyz"),
                }
        else:
            rec = {
                **single[n],
                "posed_by": "single" if single[n]["status"] == "registered" else "not_found",
            }
        if n in truth:
            rec["evaluation"] = evaluate(rec, truth[n])
        poses.append(rec)
    info["posed_by"] = {
        k: sum(r["posed_by"] == k for r in poses) for k in ("sfm+sim3", "single", "not_found")
    }
    log.info("collection: %d photos, posed by %s", len(poses), info["posed_by"])
    write_geojson(out / "cameras.geojson", poses, maps.crs_wkt)
    write_kml(out / "cameras.kml", poses, maps.crs_wkt)
    if sim is not None:
        write_point_map(
            out / "sfm_points.laz",
            xyz_map,
            model.rgb,
            model.track_len,
            model.descriptors,
            maps.crs_wkt,
        )
    else:
        write_point_map(out / "sfm_points.laz", np.zeros((0, 3)), np.zeros((0, 3)), np.zeros(0),
                        np.zeros((0, 128)), maps.crs_wkt)  # fmt: skip
    timings["total_s"] = time.perf_counter() - t_all
    info["timings_s"] = {k: round(v, 3) for k, v in timings.items()}
    write_json(out / "collection.json", info)
    write_poses(out / "poses.json", poses)
    return poses


def _fallback(photos: list[Path], cams: dict, single: dict[str, dict], posed: set[str], maps: MapSources,
              frame_loc: dict) -> dict[str, dict]:  # fmt: skip
    """Photos not posed by the SfM: tried alone when not yet (the model's photos beyond
    ``anchors`` when the Sim(3) failed), and once more with the whole single-frame configuration
    (its intensity pose search) when enabled and they did not register."""
    search = bool((frame_loc.get("search") or {}).get("enabled", False))
    out = dict(single)
    for p in photos:
        rec = out.get(p.name)
        if p.name not in posed and (rec is None or (search and rec["status"] != "registered")):
            out[p.name], _ = localize_frame(str(p), cams[p.name], maps, frame_loc)
    return out


def _truth(path: str | None) -> dict[str, dict]:
    if not path:
        return {}
    import json

    return {Path(t["image"]).name: t for t in json.loads(Path(path).read_text())}
