"""Earlier sets' geo-registered 3-D feature maps as a map layer (issue 33).

A feature map is what rule ``trajectory`` writes: ``sfm_points.laz`` (map CRS) and
``sfm_points_descriptors.npy`` beside it (COLMAP SIFT, row i = point_id i). A frame is matched
against it first: its COLMAP SIFT (the descriptors the map stores) against the map points'
descriptors (2-NN ratio), PnP in MAGSAC++ then LM. The pose is only a hypothesis: the caller
verifies it against the orthophoto / DSM by the same score as every other path
(``georeg.frames.localize``). Bad input is an InputError naming the file: a missing descriptor
file, a descriptor count that is not the point count, a feature map in another CRS or without
one, a feature map with no point on the orthophoto."""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import pyproj

from georeg.frames.pnp import PnPResult, solve_pnp
from georeg.io.atomic import atomic_path
from georeg.io.errors import InputError

log = logging.getLogger(__name__)

DEFAULTS: dict[str, Any] = {
    "ratio": 0.8,  # 2-NN ratio of frame -> map descriptor matches
    "reproj_px": 4.0,  # PnP inlier threshold (working-level px)
    "min_inliers": 15,  # fewer PnP inliers: the feature map does not cover the frame
    "max_features": 8000,  # COLMAP SIFT features of the frame
    "polish_gain": 1.5,  # the pose polished on the map window replaces it when it verifies this x higher
    "seed": 0,
}


def descriptor_path(laz_path: str | Path) -> Path:
    """``<stem>_descriptors.npy`` beside a feature map's LAZ."""
    p = Path(laz_path)
    return p.with_name(p.stem + "_descriptors.npy")


def colmap_sift(max_features: int = 4000):
    """COLMAP's CPU SIFT (L1-root normalised uint8 descriptors, as in the SfM database):
    ``extract(gray) -> (xy (OpenCV pixel centres), float32 descriptors)``."""
    import pycolmap

    o = pycolmap.FeatureExtractionOptions()
    o.sift.max_num_features = int(max_features)
    o.num_threads = 1
    o.use_gpu = False
    ex = pycolmap.FeatureExtractor.create(o)

    def extract(gray: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        kp, d = ex.extract_from_uint8_array(np.ascontiguousarray(gray, np.uint8))
        xy = np.array([[k.x, k.y] for k in kp], float).reshape(-1, 2) - 0.5  # COLMAP: centre 0.5
        return xy, np.asarray(d.data, np.float32).reshape(len(xy), -1)

    return extract


@dataclass
class FeatureMapPose:
    ok: bool
    pnp: PnPResult
    info: dict[str, Any] = field(default_factory=dict)


class FeatureMap:
    """Points (map CRS) with descriptors from one or more feature-map files."""

    def __init__(self, xyz: np.ndarray, desc: np.ndarray, rgb: np.ndarray, sources: list[str],
                 conf: dict | None = None) -> None:  # fmt: skip
        self.xyz = np.asarray(xyz, float).reshape(-1, 3)
        self.desc = np.ascontiguousarray(desc, np.float32)
        self.rgb = np.asarray(rgb, np.uint8).reshape(-1, 3)
        self.sources = sources
        self.c = {**DEFAULTS, **(conf or {})}
        self._extract = None
        self._index = None

    def __len__(self) -> int:
        return len(self.xyz)

    def bounds(self) -> tuple[float, float, float, float]:
        return (*self.xyz[:, :2].min(0).tolist(), *self.xyz[:, :2].max(0).tolist())

    def locate(self, gray: np.ndarray, K: np.ndarray) -> FeatureMapPose:
        """Pose of an undistorted frame ``gray`` with intrinsics ``K`` against the feature map."""
        import faiss

        t0 = time.perf_counter()
        if self._extract is None:
            self._extract = colmap_sift(int(self.c["max_features"]))
            self._index = faiss.IndexFlatL2(self.desc.shape[1])
            self._index.add(self.desc)
        xy, d = self._extract(gray)
        info: dict[str, Any] = {"features": int(len(xy)), "map_points": len(self)}
        if len(xy) < 2:
            return FeatureMapPose(False, PnPResult(False), {**info, "reason": "no frame features"})
        dist, nn = self._index.search(d, 2)
        ok = np.sqrt(np.maximum(dist[:, 0], 0)) < float(self.c["ratio"]) * np.sqrt(np.maximum(dist[:, 1], 0))
        q = np.flatnonzero(ok)
        info["matches"] = int(len(q))
        r = solve_pnp(self.xyz[nn[q, 0]], xy[q], K, float(self.c["reproj_px"]), seed=int(self.c["seed"]))
        good = bool(r.ok and r.inliers >= int(self.c["min_inliers"]))
        info.update(inliers=int(r.inliers), reprojection_px=float(r.reprojection_px) if r.ok else None,
                    seconds=round(time.perf_counter() - t0, 3))  # fmt: skip
        if not good:
            info["reason"] = (f"{r.inliers} PnP inliers of {len(q)} matches < {self.c['min_inliers']}: "
                              "the feature map does not cover the frame")  # fmt: skip
        return FeatureMapPose(good, r, info)


def _crs_of(las, path) -> pyproj.CRS:
    try:
        crs = las.header.parse_crs()
    except Exception as exc:  # laspy raises several types for a bad VLR
        raise InputError(path, f"cannot read the feature map's CRS: {exc}") from exc
    if crs is None:
        raise InputError(path, "the feature map has no CRS", "write it with rule trajectory")
    return pyproj.CRS.from_user_input(crs)


def load_feature_maps(paths: list[str | Path], map_crs_wkt: str, map_bounds=None,
                      conf: dict | None = None) -> FeatureMap | None:  # fmt: skip
    """The feature maps at ``paths`` (LAZ, descriptors beside) as one FeatureMap; None for no
    path. Every file checked first (see module)."""
    import laspy

    from georeg.map.lidar import split_crs

    if not paths:
        return None
    map_crs = pyproj.CRS.from_user_input(map_crs_wkt)
    xyz, desc, rgb = [], [], []
    for p in paths:
        p = Path(p)
        if not p.exists():
            raise InputError(p, "the feature map does not exist", "list a set that wrote sfm_points.laz")
        dp = descriptor_path(p)
        if not dp.exists():
            raise InputError(dp, "the feature map's descriptor file is missing",
                             f"it is written beside {p.name} by rule trajectory")  # fmt: skip
        try:
            las = laspy.read(str(p))
        except Exception as exc:  # laspy raises several types for a bad file
            raise InputError(p, f"cannot read the feature map: {exc}") from exc
        crs = split_crs(_crs_of(las, p))[0]
        if not crs.equals(split_crs(map_crs)[0], ignore_axis_order=True):
            raise InputError(p, f"the feature map is in {crs.name}, the map in {map_crs.name}",
                             "a feature map is only used in the CRS it was registered in")  # fmt: skip
        try:
            d = np.load(dp, mmap_mode="r")
        except (OSError, ValueError) as exc:
            raise InputError(dp, f"cannot read the descriptors: {exc}") from exc
        ids = np.asarray(las.point_id, int) if "point_id" in set(las.point_format.extra_dimension_names) \
            else np.arange(len(las.x))  # fmt: skip
        if d.ndim != 2 or d.shape[1] != 128 or (len(ids) and ids.max() >= len(d)):
            raise InputError(dp, f"descriptors {d.shape} do not fit the {len(ids)} points of {p.name}")
        xyz.append(np.c_[las.x, las.y, las.z].astype(float))
        desc.append(np.asarray(d[ids], np.float32))
        rgb.append((np.c_[las.red, las.green, las.blue] // 257).astype(np.uint8))
    fm = FeatureMap(np.concatenate(xyz), np.concatenate(desc), np.concatenate(rgb), [str(p) for p in paths], conf)
    if map_bounds is not None:
        x0, y0, x1, y1 = map_bounds
        inside = (fm.xyz[:, 0] >= x0) & (fm.xyz[:, 0] <= x1) & (fm.xyz[:, 1] >= y0) & (fm.xyz[:, 1] <= y1)
        if not inside.any():
            raise InputError(paths[0], f"none of the feature maps' {len(fm)} points lies on the orthophoto",
                             "a feature map of another place cannot be verified against this map")  # fmt: skip
    log.info("feature maps %s: %d points", [Path(p).name for p in paths], len(fm))
    return fm


def write_feature_map(laz_path: str | Path, xyz: np.ndarray, rgb: np.ndarray, desc: np.ndarray,
                      crs_wkt: str, track_len: np.ndarray | None = None) -> None:  # fmt: skip
    """A feature map (LAZ in the map CRS, ``point_id`` = descriptor row; descriptors beside)."""
    import laspy

    from georeg.map.lidar import output_crs

    xyz = np.asarray(xyz, float).reshape(-1, 3)
    header = laspy.LasHeader(point_format=7, version="1.4")
    header.scales = np.array([0.001, 0.001, 0.001])
    if len(xyz):
        header.offsets = np.floor(xyz.min(axis=0))
    header.add_crs(output_crs(pyproj.CRS.from_user_input(crs_wkt)))
    header.add_extra_dims([laspy.ExtraBytesParams("track_len", np.uint16, "SfM track length"),
                           laspy.ExtraBytesParams("point_id", np.uint32, "row in the descriptors")])  # fmt: skip
    las = laspy.LasData(header)
    las.x, las.y, las.z = xyz[:, 0], xyz[:, 1], xyz[:, 2]
    rgb16 = np.asarray(rgb, np.uint16).reshape(-1, 3) * 257
    las.red, las.green, las.blue = rgb16[:, 0], rgb16[:, 1], rgb16[:, 2]
    tl = np.full(len(xyz), 1) if track_len is None else np.asarray(track_len)
    las.track_len = np.clip(tl, 0, 65535).astype(np.uint16)
    las.point_id = np.arange(len(xyz), dtype=np.uint32)
    with atomic_path(descriptor_path(laz_path)) as tmp:
        with open(tmp, "wb") as fh:
            np.save(fh, np.clip(np.round(np.asarray(desc, float)), 0, 255).astype(np.uint8))
    with atomic_path(laz_path) as tmp:
        las.write(str(tmp))
