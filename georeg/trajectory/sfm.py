"""Structure from motion of video keyframes with pycolmap (the paper's 3-D feature map).

SIFT extraction, sequential matching and incremental mapping with one camera shared by all
keyframes: fixed when ``camera`` ({fx, fy, cx, cy}) is known (frames already undistorted),
self-calibrated (SIMPLE_RADIAL) otherwise. Points seen in fewer than ``min_track_len`` keyframes
are dropped; each kept point carries one SIFT descriptor (its track's medoid).

Conventions (the frames contract): OpenCV camera axes (COLMAP uses the same), ``X_cam = R (X - C)``,
pixel centres at integer coordinates (COLMAP's are at +0.5: converted here both ways).
"""

from __future__ import annotations

import json
import logging
import shutil
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from georeg.io.atomic import atomic_path
from georeg.io.errors import InputError

log = logging.getLogger(__name__)

IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg", ".tif", ".tiff")

DEFAULTS: dict[str, Any] = {
    "max_features": 4000,  # SIFT features per keyframe
    "max_image_size": 1600,  # keyframes larger than this are downscaled for extraction
    "matching": "sequential",  # sequential (ordered keyframes) | exhaustive (unordered photos)
    "overlap": 10,  # sequential matching: each keyframe against the next `overlap`
    "min_num_matches": 15,  # verified matches for a pair to enter the mapper
    "min_track_len": 4,  # keep points seen in >= this many keyframes (as the paper)
    "max_runtime_s": 900.0,  # incremental mapping time box
    "num_threads": 1,  # 1: deterministic; with 2 the model varies run to run (2196/2178/2195 points)
    "seed": 0,
    "colmap_log_level": 1,  # COLMAP's own log to stderr: 0 info, 1 warnings, 2 errors
}


@dataclass
class SfMModel:
    """A keyframe reconstruction in its own (arbitrary similarity) frame."""

    names: list[str]  # registered keyframes, in file-name order
    R: np.ndarray  # (M, 3, 3) world -> camera
    C: np.ndarray  # (M, 3) camera centres
    K: np.ndarray  # (3, 3) shared intrinsics, pixel centres at integers
    dist: np.ndarray  # (k,) OpenCV distortion (k1, k2, p1, p2) of the shared camera
    width: int
    height: int
    xyz: np.ndarray  # (N, 3) points
    track_len: np.ndarray  # (N,) number of keyframes observing each point
    descriptors: np.ndarray  # (N, 128) uint8 SIFT (track medoid)
    rgb: np.ndarray  # (N, 3) uint8
    obs_point: list[np.ndarray] = field(default_factory=list)  # per keyframe: (k,) point indices
    obs_uv: list[np.ndarray] = field(default_factory=list)  # per keyframe: (k, 2) (col, row)
    info: dict[str, Any] = field(default_factory=dict)
    cams: dict[str, tuple] = field(default_factory=dict)  # per image (K, dist, width, height) if mixed

    def camera(self, name: str) -> tuple[np.ndarray, np.ndarray, int, int]:
        """(K, OpenCV distortion, width, height) of image ``name`` (the shared camera unless
        the model has per-image cameras)."""
        return self.cams.get(name, (self.K, self.dist, self.width, self.height))

    def index(self, name: str) -> int:
        """Position of keyframe ``name`` in ``names`` (ValueError if not registered)."""
        try:
            return self.names.index(name)
        except ValueError:
            raise ValueError(f"keyframe {name!r} is not in the SfM model") from None

    def observations(self, name: str) -> tuple[np.ndarray, np.ndarray]:
        """(point indices, (col, row) pixels) of keyframe ``name``."""
        i = self.index(name)
        return self.obs_point[i], self.obs_uv[i]


def keyframe_names(image_dir: str | Path) -> list[str]:
    """Sorted image file names of ``image_dir``."""
    d = Path(image_dir)
    if not d.is_dir():
        raise InputError(d, "keyframe directory does not exist")
    return sorted(p.name for p in d.iterdir() if p.suffix.lower() in IMAGE_SUFFIXES)


def _seed_options(opts: Any, seed: int, threads: int) -> None:
    for name, value in (("random_seed", seed), ("num_threads", threads)):
        if hasattr(opts, name):
            setattr(opts, name, value)


def _reader(camera: dict | None) -> Any:
    """Image reader options: ``camera`` {fx, fy, cx, cy[, dist]} (our pixel centres) held fixed;
    None: one SIMPLE_RADIAL camera, self-calibrated."""
    import pycolmap

    reader = pycolmap.ImageReaderOptions()
    if not camera:
        reader.camera_model = "SIMPLE_RADIAL"
        return reader
    fx, fy = float(camera["fx"]), float(camera["fy"])
    cx, cy = float(camera["cx"]) + 0.5, float(camera["cy"]) + 0.5  # COLMAP pixel centres
    dist = [float(v) for v in (camera.get("dist") or [])]
    if any(dist):  # OpenCV k1, k2, p1, p2, k3[, k4, k5, k6]
        reader.camera_model = "FULL_OPENCV"
        reader.camera_params = ",".join(repr(v) for v in [fx, fy, cx, cy, *(dist + [0.0] * 8)[:8]])
    else:
        reader.camera_model = "PINHOLE"
        reader.camera_params = f"{fx!r},{fy!r},{cx!r},{cy!r}"
    return reader


def _extract(db: Path, image_dir: Path, groups: list[tuple[list[str], dict | None]], conf: dict) -> None:
    """SIFT features; one COLMAP camera per group of image names (``_reader``)."""
    import pycolmap

    ext = pycolmap.FeatureExtractionOptions()
    ext.num_threads = int(conf["num_threads"])
    ext.use_gpu = False
    ext.max_image_size = int(conf["max_image_size"])
    ext.sift.max_num_features = int(conf["max_features"])
    for names, camera in groups:
        pycolmap.extract_features(
            db, image_dir, image_names=names, camera_mode=pycolmap.CameraMode.SINGLE,
            reader_options=_reader(camera), extraction_options=ext, device=pycolmap.Device.cpu,
        )  # fmt: skip


def _match(db: Path, conf: dict) -> None:
    import pycolmap

    mopt = pycolmap.FeatureMatchingOptions()
    mopt.num_threads = int(conf["num_threads"])
    mopt.use_gpu = False
    if conf["matching"] == "exhaustive":  # every pair (unordered photo collections)
        ver = pycolmap.TwoViewGeometryOptions()
        ver.ransac.random_seed = int(conf["seed"])
        pycolmap.match_exhaustive(db, matching_options=mopt, verification_options=ver,
                                  device=pycolmap.Device.cpu)  # fmt: skip
        return
    if conf["matching"] != "sequential":
        raise ValueError(f"SfM: matching {conf['matching']!r} is not sequential or exhaustive")
    pair = pycolmap.SequentialPairingOptions()
    pair.overlap = int(conf["overlap"])
    pair.quadratic_overlap = False
    pair.loop_detection = False
    pair.num_threads = int(conf["num_threads"])
    ver = pycolmap.TwoViewGeometryOptions()
    ver.ransac.random_seed = int(conf["seed"])
    pycolmap.match_sequential(db, matching_options=mopt, pairing_options=pair,
                              verification_options=ver, device=pycolmap.Device.cpu)  # fmt: skip


def _map(db: Path, image_dir: Path, out: Path, known: bool, n_images: int, conf: dict) -> list:
    import pycolmap

    opt = pycolmap.IncrementalPipelineOptions()
    seed, threads = int(conf["seed"]), int(conf["num_threads"])
    _seed_options(opt, seed, threads)
    _seed_options(opt.mapper, seed, threads)
    _seed_options(opt.triangulation, seed, threads)
    opt.min_num_matches = int(conf["min_num_matches"])
    opt.min_model_size = min(3, n_images)
    opt.multiple_models = True
    opt.max_runtime_seconds = int(conf["max_runtime_s"])
    opt.extract_colors = True
    if known:
        opt.ba_refine_focal_length = False
        opt.ba_refine_principal_point = False
        opt.ba_refine_extra_params = False
        opt.mapper.abs_pose_refine_focal_length = False
        opt.mapper.abs_pose_refine_extra_params = False
    out.mkdir(parents=True, exist_ok=True)
    recs = pycolmap.incremental_mapping(db, image_dir, out, options=opt)
    return sorted(recs.values(), key=lambda r: r.num_reg_images(), reverse=True)


def _camera_arrays(cam: Any) -> tuple[np.ndarray, np.ndarray]:
    """(K with integer pixel centres, OpenCV distortion) of a COLMAP pinhole-family camera."""
    p = np.asarray(cam.params, float)
    name = cam.model_name
    if name in ("SIMPLE_PINHOLE", "SIMPLE_RADIAL", "RADIAL"):
        fx = fy = p[0]
        cx, cy = p[1], p[2]
        k = p[3:]
        dist = np.array([k[0] if k.size > 0 else 0.0, k[1] if k.size > 1 else 0.0, 0.0, 0.0])
    elif name in ("PINHOLE", "OPENCV", "FULL_OPENCV"):
        fx, fy, cx, cy = p[:4]
        dist = np.r_[p[4:], np.zeros(max(0, 4 - p[4:].size))]
    else:
        raise ValueError(f"SfM: unsupported COLMAP camera model {name}")
    K = np.array([[fx, 0, cx - 0.5], [0, fy, cy - 0.5], [0, 0, 1]], float)
    return K, dist


def _medoid_descriptors(desc: np.ndarray, group: np.ndarray, n: int) -> np.ndarray:
    """Per group: the member descriptor closest (L2) to the group mean. ``group`` in [0, n)."""
    d = desc.astype(np.float64)
    cnt = np.bincount(group, minlength=n).astype(float)
    mean = np.zeros((n, d.shape[1]))
    np.add.at(mean, group, d)
    mean /= np.maximum(cnt, 1)[:, None]
    dist = np.einsum("ij,ij->i", d - mean[group], d - mean[group])
    order = np.lexsort((dist, group))
    first = np.ones(order.size, bool)
    first[1:] = group[order[1:]] != group[order[:-1]]
    out = np.zeros((n, d.shape[1]), np.uint8)
    out[group[order[first]]] = desc[order[first]]
    return out


def _to_model(rec: Any, db_path: Path, names_order: list[str], min_track_len: int) -> SfMModel:
    """Arrays of a pycolmap Reconstruction + descriptors from the database."""
    import pycolmap

    imgs = {im.name: im for im in rec.images.values() if im.has_pose}
    names = [n for n in names_order if n in imgs]
    Rs, Cs = [], []
    for n in names:
        cfw = imgs[n].cam_from_world()
        Rs.append(np.asarray(cfw.rotation.matrix(), float))
        Cs.append(np.asarray(imgs[n].projection_center(), float))
    cam = imgs[names[0]].camera
    K, dist = _camera_arrays(cam)
    cams = {}
    if len({imgs[n].camera_id for n in names}) > 1:  # mixed cameras (a photo collection)
        cams = {n: (*_camera_arrays(imgs[n].camera), int(imgs[n].camera.width), int(imgs[n].camera.height))
                for n in names}  # fmt: skip
    pids = np.array(sorted(rec.points3D.keys()), np.int64)
    tl = np.array([rec.points3D[p].track.length() for p in pids], int)
    keep = pids[tl >= min_track_len]
    pos = {int(p): i for i, p in enumerate(keep)}
    xyz = np.array([rec.points3D[p].xyz for p in keep], float).reshape(-1, 3)
    rgb = np.array([rec.points3D[p].color for p in keep], np.uint8).reshape(-1, 3)
    obs_point, obs_uv, d_all, g_all = [], [], [], []
    db = pycolmap.Database.open(db_path)
    try:
        for n in names:
            im = imgs[n]
            idx = np.asarray(im.get_observation_point2D_idxs(), np.int64)
            pts = im.points2D
            p3 = np.array([pos.get(int(pts[i].point3D_id), -1) for i in idx], np.int64)
            ok = p3 >= 0
            idx, p3 = idx[ok], p3[ok]
            uv = np.array([pts[i].xy for i in idx], float).reshape(-1, 2) - 0.5
            obs_point.append(p3)
            obs_uv.append(uv)
            desc = np.asarray(db.read_descriptors(im.image_id).data)
            d_all.append(desc[idx])
            g_all.append(p3)
    finally:
        db.close()
    track = np.bincount(np.concatenate(g_all), minlength=len(keep)) if keep.size else np.zeros(0)
    descriptors = (
        _medoid_descriptors(np.concatenate(d_all), np.concatenate(g_all), len(keep))
        if keep.size
        else np.zeros((0, 128), np.uint8)
    )
    return SfMModel(
        names=names, R=np.array(Rs), C=np.array(Cs), K=K, dist=dist, width=int(cam.width),
        height=int(cam.height), xyz=xyz, track_len=track.astype(int), descriptors=descriptors,
        rgb=rgb, obs_point=obs_point, obs_uv=obs_uv, cams=cams,
    )  # fmt: skip


def run_sfm(
    image_dir: str | Path, work_dir: str | Path, camera: dict | None = None,
    conf: dict | None = None, groups: list[tuple[list[str], dict | None]] | None = None,
) -> SfMModel:  # fmt: skip
    """Reconstruct the keyframes of ``image_dir`` (work files under ``work_dir``, overwritten).

    ``camera``: {fx, fy, cx, cy} in pixels of the (undistorted) keyframes, held fixed; None
    self-calibrates one shared SIMPLE_RADIAL camera. ``groups`` (photo collections, mixed
    cameras): (image names, camera) pairs, one COLMAP camera each (``_reader``: fixed, or None
    self-calibrated); then ``camera`` is ignored. Returns the largest model.
    """
    import pycolmap

    conf = {**DEFAULTS, **(conf or {})}
    image_dir, work = Path(image_dir), Path(work_dir)
    names = keyframe_names(image_dir)
    if len(names) < 3:
        raise InputError(image_dir, f"{len(names)} keyframe images; SfM needs at least 3")
    if work.exists():
        shutil.rmtree(work)
    work.mkdir(parents=True)
    level = pycolmap.logging.minloglevel
    pycolmap.logging.minloglevel = int(conf["colmap_log_level"])
    try:
        if groups is None:
            groups = [(names, camera)]
        else:
            missing = sorted(set(names) - {n for g, _ in groups for n in g})
            if missing:
                raise ValueError(f"SfM: images {missing[:3]} of {image_dir} are in no camera group")
        return _reconstruct(image_dir, work, names, groups, conf)
    finally:
        pycolmap.logging.minloglevel = level


def _reconstruct(
    image_dir: Path, work: Path, names: list[str], groups: list[tuple[list[str], dict | None]],
    conf: dict,
) -> SfMModel:
    import pycolmap

    db = work / "database.db"
    pycolmap.set_random_seed(int(conf["seed"]))
    t0 = time.perf_counter()
    _extract(db, image_dir, groups, conf)
    t1 = time.perf_counter()
    _match(db, conf)
    t2 = time.perf_counter()
    d = pycolmap.Database.open(db)
    try:
        n_kp = d.num_keypoints()
        n_match = [int(g.inlier_matches.shape[0]) for g in d.read_two_view_geometries()[1]]
        n_pairs = sum(k >= int(conf["min_num_matches"]) for k in n_match)
        n_inl = sum(n_match)
    finally:
        d.close()
    log.info("SfM: %d keyframes, %d features (%.1f s), %d verified pairs, %d inlier matches "
             "(%.1f s)", len(names), n_kp, t1 - t0, n_pairs, n_inl, t2 - t1)  # fmt: skip
    fixed = all(bool(cam) for _, cam in groups)
    recs = _map(db, image_dir, work / "sparse", fixed, len(names), conf)
    t3 = time.perf_counter()
    if not recs:
        raise ValueError(f"SfM of {image_dir}: the mapper produced no model (too little overlap "
                         "or texture between keyframes)")  # fmt: skip
    for k, r in enumerate(recs[1:], 1):
        log.info("SfM: model %d dropped (%d images, %d points)", k, r.num_reg_images(),
                 r.num_points3D())  # fmt: skip
    rec = recs[0]
    if rec.num_reg_images() < 3:
        raise ValueError(f"SfM of {image_dir}: only {rec.num_reg_images()} of {len(names)} "
                         "keyframes registered (need >= 3)")  # fmt: skip
    model = _to_model(rec, db, names, int(conf["min_track_len"]))
    model.info = {
        "n_keyframes": len(names), "n_registered": len(model.names), "n_features": n_kp,
        "n_verified_pairs": n_pairs, "n_inlier_matches": n_inl, "n_models": len(recs),
        "n_points_all": rec.num_points3D(), "n_points": len(model.xyz),
        "mean_reproj_px": float(rec.compute_mean_reprojection_error()),
        "seconds": {"extract": t1 - t0, "match": t2 - t1, "map": t3 - t2},
        "camera_model": rec.cameras[rec.images[rec.reg_image_ids()[0]].camera_id].model_name,
        "camera_fixed": fixed, "cameras": len(groups), "matching": conf["matching"],
    }  # fmt: skip
    log.info("SfM: %d/%d keyframes registered, %d points (%d with track >= %d), mean reprojection "
             "%.2f px, focal %.1f px (%.1f s mapping)", len(model.names), len(names),
             rec.num_points3D(), len(model.xyz), conf["min_track_len"],
             model.info["mean_reproj_px"], model.K[0, 0], t3 - t2)  # fmt: skip
    return model


def write_model(path: str | Path, model: SfMModel) -> None:
    """Save ``model`` as one .npz (atomically); observations flattened with per-keyframe counts."""
    counts = np.array([len(p) for p in model.obs_point], np.int64)
    arrays = {
        "names": np.array(model.names), "R": model.R, "C": model.C, "K": model.K,
        "dist": model.dist, "size": np.array([model.width, model.height]), "xyz": model.xyz,
        "track_len": model.track_len, "descriptors": model.descriptors, "rgb": model.rgb,
        "obs_count": counts,
        "obs_point": np.concatenate(model.obs_point) if counts.sum() else np.zeros(0, np.int64),
        "obs_uv": np.concatenate(model.obs_uv) if counts.sum() else np.zeros((0, 2)),
        "info": np.array(json.dumps(model.info, default=float)),
    }  # fmt: skip
    with atomic_path(path) as tmp, open(tmp, "wb") as f:
        np.savez_compressed(f, **arrays)


def read_model(path: str | Path) -> SfMModel:
    """Load a model saved by ``write_model``."""
    try:
        z = np.load(path, allow_pickle=False)
    except (OSError, ValueError) as e:
        raise InputError(path, f"cannot read the SfM model ({e})") from None
    cuts = np.cumsum(z["obs_count"])[:-1]
    w, h = (int(v) for v in z["size"])
    return SfMModel(
        names=[str(n) for n in z["names"]], R=z["R"], C=z["C"], K=z["K"], dist=z["dist"],
        width=w, height=h, xyz=z["xyz"], track_len=z["track_len"], descriptors=z["descriptors"],
        rgb=z["rgb"], obs_point=np.split(z["obs_point"], cuts), obs_uv=np.split(z["obs_uv"], cuts),
        info=json.loads(str(z["info"])),
    )  # fmt: skip

