"""Single-frame geo-localisation: one frame set -> poses.json, GeoJSON, KML, overlays.

Per frame: read (EXIF orientation applied), reduced to the pyramid level below
``max_frame_mpx`` (intrinsics scaled), undistorted (known ``camera``); direct 2-D/3-D matching
against the map (the whole small map, else around the coarse location of ``frame_coarse``),
verified; render-match-PnP (``frame_pnp``) and the intensity refinement (``frame_refine``) only
when that pose verifies weak (``adaptive``) or there is none; the best verified hypothesis wins;
when none verifies, the intensity pose search around the best coarse vote (``frames.search``,
accepted by its own similarity bound; ``search_attempts`` in the record); outputs
(``frame_outputs``). A frame whose hypotheses do not reach the bounds is ``not_found``
(never an error).
Unknown intrinsics (``camera: null``): the EXIF focal length of the file when it has one
(``frame_exif``: 35 mm equivalent, focal length and focal-plane resolution, or focal length and
the sensor width of a common drone camera; ``intrinsics.source`` = "exif", ``exif_tags``; refitted
on the best pose's guided inliers, ``exif_focal_refine``, kept only if it verifies higher), else
the focal length is searched in the coarse PnP over ``focal_factors`` x the image width (in
turn, until one falls below a strong best) and
refined on the render stage's inliers (``frame_focal``, ``focal_rounds``; ``focal`` in the
record, with the fit's relative standard deviation: a nadir view of flat ground does not
determine it); principal point at the centre, no distortion, in both cases.
"""

from __future__ import annotations

import dataclasses
import logging
import time
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from georeg.frames.coarse import INDEX_DEFAULTS, Coarse, coarse_index, coarse_locate, strong_inliers
from georeg.frames.direct import DEFAULTS as DIRECT_DEFAULTS
from georeg.frames.direct import (
    Matches,
    direct_pose,
    ground_distance,
    guided_matches,
    match_window,
    polish,
    verification_tolerance,
    verify,
)
from georeg.frames.exif import exif_camera
from georeg.frames.focal import estimate_focal, focal_from_matches, refine_focal
from georeg.frames.outputs import (
    footprint_window,
    footprint_xy,
    overlay,
    write_geojson,
    write_kml,
    write_png,
    write_poses,
)
from georeg.frames.pnp import PnPResult, register_by_rendering
from georeg.frames.render import (
    PinholeCamera,
    PointCloud,
    Render,
    read_heightfield,
    read_laz_cloud,
    render,
)
from georeg.frames.search import DEFAULTS as SEARCH_DEFAULTS
from georeg.frames.search import search_pose
from georeg.io.errors import InputError
from georeg.io.video import frame_images, read_frame

log = logging.getLogger(__name__)

MIN_FRAME_PX = 64  # smaller frames are an input error

DEFAULTS: dict[str, Any] = {
    "dense_coarse": True,  # coarse votes on dense features of the index's best windows
    "render_source": "heightfield",  # heightfield (ortho + DSM mosaics, with walls) | points (points.laz)
    "cloud_margin_m": 120.0,  # map window read around the coarse footprint
    "max_cloud_extent_m": 1600.0,
    "focal_factors": [0.6, 0.8, 1.0, 1.3, 1.7],  # unknown camera: fx candidates x image width
    "focal_rounds": 4,  # unknown camera: focal refinement + render-stage rounds (0: search only)
    "focal_from_window": True,  # unknown camera, large map: focal + k1 from the coarse window's matches
    "coarse": {},
    "pnp": {},
    "refine": {"enabled": True},
    "vote_starts": 2,  # nadir-vote poses also tried as render-stage starts (after the coarse PnP)
    "refine_max_extra_px": 1.5,  # refined pose kept if the PnP inliers' RMS grows less than this
    "min_inliers": 15,  # PnP inliers of a hypothesis, and its verification score, to register
    "render_after_direct": True,  # render-match-PnP also from a verified direct pose ...
    # ... and the intensity refinement, only when that pose's verification is weak (adaptive)
    "adaptive": {"enabled": True, "strong_score": 100, "strong_rms_frac": 0.5},
    "direct": {},  # overrides of georeg.frames.direct.DEFAULTS (direct matching, verification)
    "overlay_alpha": 0.5,
    "exif_focal_refine": True,  # an EXIF focal refit on the best pose's guided inliers (kept if better)
    "max_frame_mpx": 2.0,  # a larger frame is localised on its pyramid level (halvings) below this
    "search": {},  # overrides of georeg.frames.search.DEFAULTS (last resort: intensity pose search)
}


def pyramid_level(width: int, height: int, max_px: float) -> int:
    """The number of halvings that bring a ``width`` x ``height`` frame to at most ``max_px``."""
    n = float(width) * float(height)
    return max(0, int(np.ceil(np.log2(n / float(max_px)) / 2))) if n > max_px > 0 else 0


def scale_camera(camera: dict | None, sx: float, sy: float) -> dict | None:
    """A ``camera`` dict for the image resized by (``sx``, ``sy``) (pixel centres kept:
    c' = (c + 0.5) s - 0.5; distortion coefficients are in normalised coordinates, unchanged)."""
    if not camera:
        return camera
    return {**camera, "fx": camera["fx"] * sx, "fy": camera["fy"] * sy,
            "cx": (camera["cx"] + 0.5) * sx - 0.5, "cy": (camera["cy"] + 0.5) * sy - 0.5}  # fmt: skip


def working_level(rgb: np.ndarray, camera: dict | None, max_mpx: float):
    """(rgb, camera, pyramid record): a frame above ``max_mpx`` Mpx reduced by halvings (area
    averaging) with its intrinsics scaled to match; unchanged below."""
    h0, w0 = rgb.shape[:2]
    lvl = pyramid_level(w0, h0, float(max_mpx) * 1e6)
    info = {"level": lvl, "full_size": [w0, h0], "size": [w0, h0], "scale": 1.0}
    if not lvl:
        return rgb, camera, info
    w, h = max(1, round(w0 / 2**lvl)), max(1, round(h0 / 2**lvl))
    rgb = cv2.resize(rgb, (w, h), interpolation=cv2.INTER_AREA)
    info.update(size=[w, h], scale=w / w0)
    log.info("frame %d x %d px: pyramid level %d (%d x %d px)", w0, h0, lvl, w, h)
    return rgb, scale_camera(camera, w / w0, h / h0), info


def camera_matrix(camera: dict | None, width: int, height: int, fx: float | None = None):
    """(K, dist) of the configured camera; for ``camera: null`` a centred K with ``fx``."""
    if camera:
        K = np.array(
            [[camera["fx"], 0, camera["cx"]], [0, camera["fy"], camera["cy"]], [0, 0, 1]], float
        )
        dist = np.asarray(camera.get("dist") or [0, 0, 0, 0, 0], float)
        return K, dist
    f = float(fx if fx is not None else width)
    return np.array(
        [[f, 0, (width - 1) / 2], [0, f, (height - 1) / 2], [0, 0, 1]], float
    ), np.zeros(5)


#: recorded in poses.json (``ground.warning``) and logged when the map has no elevation
FLAT_GROUND_WARNING = (
    "the pose assumes a flat ground: over relief or buildings the camera position can be off "
    "by far more than the map GSD (measured on real frames over 540 m of relief: 0.5-1 km) "
    "while the frame still verifies; give the map a DEM or LiDAR for reliable poses"
)


class MapSources:
    """What a frame is registered to: the index, the mosaics, the LiDAR tiles, the CRS.
    ``dsm_vrt`` None: no elevation, the ground is the plane z = ``ground_z``."""

    def __init__(self, index_dir, ortho_vrt, dsm_vrt, laz_paths=(), crs_wkt: str | None = None,
                 dense_coarse: bool = True, ground_z: float = 0.0):  # fmt: skip
        from georeg.index.map_index import MapIndex

        self.index = MapIndex.load(index_dir)
        self.ortho, self.laz = str(ortho_vrt), [str(p) for p in laz_paths]
        self.dsm = str(dsm_vrt) if dsm_vrt else None
        self.flat_z = float(ground_z)
        self.crs_wkt = crs_wkt or self.index.crs_wkt
        self.gsd = float(self.index.gsd_m or 1.0)
        self.dense = (self.ortho, self.dsm, self.flat_z) if dense_coarse else None
        self.coarse_index = self.index if self.dsm else FlatIndex(self.index, self.flat_z)
        if not self.dsm:
            log.warning("the map has no elevation: frames are localised on a flat ground at z = %g; "
                        "%s", self.flat_z, FLAT_GROUND_WARNING)  # fmt: skip
        self.window_cache: dict = {}  # the whole (small) map's dense features, for every frame
        self.feature_map = None  # earlier sets' feature maps (georeg.frames.feature_map), tried first
        self.prior_box: tuple | None = None  # the set's location prior (map CRS box), if any

    def ground_z(self, C: np.ndarray, radius: float = 150.0) -> float:
        """Median elevation of the map features within ``radius`` of C (x, y), the radius grown
        x4 up to 3 times where the map has no features (a nadir off the map's texture); the
        flat ground's height without a DSM."""
        if not self.dsm:
            return self.flat_z
        for k in range(4):
            r = radius * 4**k
            ids = self.index.features_in((C[0] - r, C[1] - r, C[0] + r, C[1] + r))
            z = np.asarray(self.index.features(ids)["z"], float) if len(ids) else np.zeros(0)
            z = z[np.isfinite(z)]
            if z.size:
                return float(np.median(z))
        return float(C[2] - 100.0)

    def bounds(self) -> tuple[float, float, float, float]:
        import rasterio

        with rasterio.open(self.ortho) as so:
            return tuple(so.bounds)

    def whole_map_px(self) -> int:
        import rasterio

        with rasterio.open(self.ortho) as so:
            return int(so.width) * int(so.height)

    def ground_distance(self, cam: PinholeCamera) -> float:
        return ground_distance(cam, self.ground_z(cam.C))

    def cloud(self, bounds, source: str, max_px: int = 4_000_000) -> PointCloud:
        """The map cloud of a window (x0, y0, x1, y1): ``points`` (the LiDAR tiles) or the
        height field of the mosaics (decimated above ``max_px`` map pixels)."""
        if source == "points" and self.laz:
            return read_laz_cloud(self.laz, bounds)
        return read_heightfield(self.ortho, self.dsm, bounds, max_px=max_px, flat_z=self.flat_z)

    def cloud_around(self, cam: PinholeCamera, c: dict, max_px: int = 4_000_000) -> PointCloud:
        """The map around the footprint of ``cam``: ``cloud_margin_m`` around it, at most
        ``max_cloud_extent_m`` or 1.5 x the footprint wide (a 6 km aerial footprint stays whole)."""
        zg = self.ground_z(cam.C)
        fp = footprint_xy(cam, zg)
        cap = max(float(c["max_cloud_extent_m"]), 1.5 * float(np.ptp(fp, axis=0).max()))
        b = footprint_window([cam], zg, float(c["cloud_margin_m"]), cap, centre=cam.C)
        return self.cloud(b, c["render_source"], max_px)


class FlatIndex:
    """A map index seen with every feature at the height ``z`` (a map without a DSM)."""

    def __init__(self, index, z: float) -> None:
        self._index, self._z = index, float(z)

    def __getattr__(self, name: str):
        return getattr(self._index, name)

    def features(self, ids) -> dict[str, np.ndarray]:
        f = dict(self._index.features(ids))
        f["z"] = np.full(len(f["xy"]), self._z)
        return f


def display_render(cloud: PointCloud, cam: PinholeCamera, map_gsd: float,
                   dist: float | None = None) -> Render:  # fmt: skip
    """The map at ``cam`` for overlays: rendered at about the map's GSD (no splat blocks), then
    upsampled to the frame (linear colour, nearest depth). ``dist``: the scene distance along
    the axis when known (else the median depth of a small render)."""
    if dist is None:
        r0 = render(cloud, cam.scaled(min(1.0, 160 / cam.width)))
        d = r0.depth[np.isfinite(r0.depth)]
        dist = float(np.median(d)) if d.size else 100.0
    s = float(np.clip(dist / cam.fx / map_gsd, 0.1, 1.0))
    r = render(cloud, cam.scaled(s))
    size = (cam.width, cam.height)
    img = cv2.resize(r.image, size, interpolation=cv2.INTER_LINEAR)
    dep = cv2.resize(r.depth, size, interpolation=cv2.INTER_NEAREST)
    return Render(img, dep, cam)


def _rot_err(Ra, Rb) -> float:
    c = (np.trace(np.asarray(Ra) @ np.asarray(Rb).T) - 1) / 2
    return float(np.degrees(np.arccos(np.clip(c, -1, 1))))


def check_frame(path: str | Path) -> np.ndarray:
    """The frame as RGB; ``InputError`` naming the file when it is not a readable image (empty,
    truncated, not an image) or smaller than ``MIN_FRAME_PX`` on a side."""
    if Path(path).is_file() and Path(path).stat().st_size == 0:
        raise InputError(path, "empty frame file", "a PNG/JPEG/TIFF image")
    rgb = read_frame(path)
    if min(rgb.shape[:2]) < MIN_FRAME_PX:
        raise InputError(path, f"frame of {rgb.shape[1]} x {rgb.shape[0]} px is too small to localise",
                         f"at least {MIN_FRAME_PX} px per side")  # fmt: skip
    return rgb


def localize_frame(
    path: str, camera: dict | None, maps: MapSources, conf: dict
) -> tuple[dict, Any]:
    """Pose of one frame file; returns (pose record, (undistorted rgb, final Render or None)).
    ``camera`` None: the EXIF focal length when the file has one (``frame_exif``)."""
    rgb = check_frame(path)
    if not camera:
        camera = exif_camera(path, rgb.shape[1], rgb.shape[0])
    return localize_image(rgb, str(path), camera, maps, conf)


def _refine_exif_focal(scored: list, window_of, rec: dict, max_sigma: float = 0.02) -> None:
    """An EXIF focal length (nominal: lens rounding, a crop) fitted on the guided inliers of the
    best pose (least squares over pose and focal, ``frame_focal.refine_focal``); the fit joins the
    candidates when its relative sigma is below ``max_sigma`` and it verifies higher (same score)."""
    p, cam, res, v0 = scored[0]
    mt, tol = window_of(cam)
    q, m = guided_matches(mt, cam, tol)
    if len(q) < 12:
        return
    f, R, C, rms, sig = refine_focal(mt.map_xyz[m], mt.ff.xy[q], cam, loss_px=tol / 2)
    cam_f = dataclasses.replace(cam, fx=f, fy=f * cam.fy / cam.fx, R=R, C=np.asarray(C, float))
    v = verify(mt, cam_f, tol)
    ok = bool(sig < max_sigma and v["score"] > v0["score"])
    rec["focal"] = {"start_fx": float(cam.fx), "fx": float(f), "fx_rel_sigma": float(sig),
                    "lsq_rms_px": float(rms), "score": v["score"], "start_score": v0["score"],
                    "accepted": ok}  # fmt: skip
    if ok:
        scored.append((f"{p} + focal refinement", cam_f, res, v))
        scored.sort(key=lambda t: -t[3]["score"])


def verifies_strong(v: dict, ad: dict) -> bool:
    """A verification strong by the adaptive bounds ``ad`` (``frame_loc.adaptive``): at least
    ``strong_score`` matches within the tolerance, RMS at most ``strong_rms_frac`` of it; such a
    pose ends the search."""
    return bool(ad["enabled"] and v["score"] >= int(ad["strong_score"])
                and (v["rms_px"] or np.inf) <= float(ad["strong_rms_frac"]) * float(v["tolerance_px"]))  # fmt: skip


def feature_map_hypothesis(gray: np.ndarray, K: np.ndarray, w: int, h: int, maps: MapSources,
                           vconf: dict, feat_conf: dict, min_inl: int, rec: dict, windows: list,
                           ad: dict, small_map: bool = False) -> tuple | None:  # fmt: skip
    """The pose of the frame against the feature maps (``maps.feature_map``), verified against
    the orthophoto / DSM by the same score as every path: (path, camera, PnPResult, verification)
    when it reaches ``min_inl``, else a recorded fallback (``feature_map`` in the record) and
    None; a covered frame whose pose does not verify gets ``feature_map.start`` (the caller's
    direct matching starts from ``feature_map.pose`` instead of the coarse search).
    ``feature_map.served``: the pose ends the search (no map-only stage runs) when it verifies
    strong by the adaptive bounds ``ad`` (the bar a direct pose must pass to end the search), or
    verifies as the feature map gives it on a map larger than ``direct.whole_map_first_px`` (where
    the map-only search is the coarse search, not the cheap whole-map matching); else it joins
    the map-only hypotheses (the best score wins).
    The pose is taken as the feature map gives it unless its polish on the map window scores at
    least ``polish_gain`` x higher, or higher and strong (``feature_map.polished``): with the few
    window matches of a small frame the polish moves a 0.5 m feature-map pose by 1-6 m at about
    the same score (demo video: x 1.0-1.14), while a feature map a metre or two off the map
    verifies far higher once polished (brighton: x 5.7-9.8); docs/experiments/
    2026-11-26-feature-maps.md "session 12"."""
    t = time.perf_counter()
    r = maps.feature_map.locate(gray, K)
    rec["feature_map"] = {"sources": [Path(s).name for s in maps.feature_map.sources], **r.info}
    if not r.ok:
        rec["feature_map"].update(used=False, fallback=f"map-only path: {r.info.get('reason')}")
        return None
    cam = PinholeCamera(K[0, 0], K[1, 1], K[0, 2], K[1, 2], w, h, r.pnp.R, r.pnp.C)
    rec["feature_map"]["pose"] = _cam_record(cam)
    zg = maps.ground_z(cam.C)
    mt = match_window(gray, cam, maps.ortho, maps.dsm, feat_conf, maps.gsd, zg, vconf, maps.flat_z)
    tol = verification_tolerance(cam, maps.gsd, zg, float(vconf["verify_px"]))
    v = {**verify(mt, cam, tol), "polish_moved_m": 0.0}
    cam_p = polish(mt, cam, tol, int(vconf["polish_rounds"]), bool(vconf["polish_distinct"]))
    vp = {**verify(mt, cam_p, tol), "polish_moved_m": float(np.linalg.norm(cam_p.C - cam.C))}
    # polished when clearly higher, or higher and strong (then well determined by many matches)
    polished = vp["score"] >= float(maps.feature_map.c["polish_gain"]) * max(v["score"], 1) or (
        verifies_strong(vp, ad) and vp["score"] > v["score"])  # fmt: skip
    rec["feature_map"].update(raw_score=v["score"], polished_score=vp["score"], polished=bool(polished),
                              polish_moved_m=round(vp["polish_moved_m"], 3))  # fmt: skip
    cam, v = (cam_p, vp) if polished else (cam, v)
    strong = verifies_strong(v, ad)
    served = strong or not (polished or small_map)
    rec["feature_map"].update(score=v["score"], rms_px=v["rms_px"], strong=strong, served=served,
                              seconds=round(time.perf_counter() - t, 3))  # fmt: skip
    if v["score"] < min_inl:  # covered, but off the map by more than the tolerance: a start only
        rec["feature_map"].update(used=False, start=True, fallback=f"map-only path from the feature-map "
                                  f"pose as its start (it verifies {v['score']} < {min_inl} against the map)")  # fmt: skip
        return None
    if rec["feature_map"]["served"]:  # a weak one must not change the window map-only poses are scored on
        windows.append(mt)
    rec["feature_map"]["used"] = True
    return ("feature map 2D-3D", cam, r.pnp, v)


def _cam_record(cam: PinholeCamera) -> dict:
    return {"camera_center_xyz": [float(v) for v in cam.C], "R_world_to_cam": np.asarray(cam.R).tolist()}


def whole_map_camera(rgb: np.ndarray, w: int, h: int, maps: MapSources, feat_conf: dict,
                     vconf: dict, c: dict, rec: dict) -> dict | None:  # fmt: skip
    """``camera: null`` on a small map: the frame matched once to the whole map's features (the
    matches do not depend on the focal), then ``camera_from_matches``."""
    t = time.perf_counter()
    gray = cv2.cvtColor(rgb, cv2.COLOR_RGB2GRAY)
    cam0 = PinholeCamera(float(w), float(w), (w - 1) / 2, (h - 1) / 2, w, h, np.eye(3), np.zeros(3))
    _, mt = direct_pose(gray, cam0, maps.ortho, maps.dsm, feat_conf, maps.gsd, 0.0, vconf,
                        maps.flat_z, maps.bounds(), min(1.0, float(np.sqrt(3e6 / (h * w)))),
                        maps.window_cache)  # fmt: skip
    return camera_from_matches(mt, w, h, vconf, c, rec, "whole-map", time.perf_counter() - t)


def camera_from_matches(mt: Matches, w: int, h: int, vconf: dict, c: dict, rec: dict, where: str,
                        seconds: float = 0.0) -> dict | None:  # fmt: skip
    """The camera of a frame from its 2-D/3-D matches ``mt`` (``focal.focal_from_matches``: PnP
    over ``focal_factors``, then pose + focal + k1 fitted); recorded in
    ``rec["focal_from_matches"]``. None when no focal gives a pose."""
    t = time.perf_counter()
    est = focal_from_matches(mt.xyz, mt.uv, w, h, list(c["focal_factors"]),
                             float(vconf["reproj_px"]), int(vconf["seed"]))  # fmt: skip
    rec["focal_from_matches"] = {**(est or {"fitted": False, "reason": "no PnP at any focal"}),
                                 "matches": int(len(mt.uv)), "where": where,
                                 "seconds": seconds + time.perf_counter() - t}  # fmt: skip
    if est is None:
        return None
    log.info("camera: null -> fx %.0f px, k1 %.3f from %d %s 2D-3D inliers (%s, sigma %.1f %%)",
             est["fx"], est.get("k1", 0.0), est["inliers"], where,
             "fitted" if est["fitted"] else "searched", 100 * est["fx_rel_sigma"])  # fmt: skip
    how = "pose + focal fit" if est["fitted"] else "best of focal_factors"
    return {"fx": est["fx"], "fy": est["fx"], "cx": (w - 1) / 2, "cy": (h - 1) / 2,
            "dist": [float(est.get("k1", 0.0)), 0.0, 0.0, 0.0, 0.0],
            "source": f"estimated ({where} 2D-3D matches, {how})"}


def run_coarse(gray: np.ndarray, K: np.ndarray, maps: MapSources, conf: dict | None) -> Coarse:
    """The coarse search of ``frame_loc.coarse.mode``: ``index`` (``coarse_index``: region votes
    of the map index at the frame's footprint, bounded budget, within the set's ``prior`` box when
    given; on maps of at least ``index_min_px`` pixels, the plain search below that) or ``plain`` (``coarse_locate``: 400 m windows re-extracted densely, then the rest
    of the map)."""
    c = conf or {}
    mode = str(c.get("mode", INDEX_DEFAULTS["mode"]))
    if mode == "index" and maps.whole_map_px() < int(c.get("index_min_px", INDEX_DEFAULTS["index_min_px"])):
        mode = "plain"  # a map small enough for the plain search, which is the surer there
    if mode == "plain":
        co = coarse_locate(gray, K, maps.coarse_index, c, maps.dense)
        co.budget = {"mode": "plain", **co.budget}
        return co
    if mode != "index":
        raise ValueError(f"unknown frame_loc.coarse.mode {mode!r} (index | plain)")
    return coarse_index(gray, K, maps.coarse_index, maps.gsd, c, maps.prior_box)


def direct_conf(vconf: dict, start: str, co: Coarse, coarse_conf: dict | None) -> dict:
    """Direct matching settings for one start: around the PnP pose of the index coarse search
    (within metres of the truth) the window margin is ``coarse.direct_margin_m``, not the
    ``direct.margin_m`` that covers a vote's error; the same map resolution either way."""
    if start != "coarse PnP" or co.budget.get("mode") != "index":
        return vconf
    m = {**INDEX_DEFAULTS, **(coarse_conf or {})}["direct_margin_m"]
    return {**vconf, "margin_m": float(m)}


def localize_image(
    rgb: np.ndarray, path: str, camera: dict | None, maps: MapSources, conf: dict
) -> tuple[dict, Any]:
    """Pose of one RGB frame named ``path`` (a file name, or ``video#index``); see
    ``localize_frame``.

    Pose hypotheses, every one verified by the same score (``direct.verify``): the direct 2-D/3-D
    match in the map window around the coarse location (always tried), render-match-PnP from
    the best pose so far, and the intensity refinement of the best; the last two are skipped
    after a direct pose verified strong (``adaptive``: score and residual bounds; recorded). The
    highest score wins (``path``, ``verification`` in the record); a frame is ``not_found`` only
    when no hypothesis reaches ``min_inliers``."""
    c = {**DEFAULTS, **(conf or {})}
    t0 = time.perf_counter()
    timings: dict[str, float] = {}
    rgb, camera, pyr = working_level(rgb, camera, float(c["max_frame_mpx"]))
    h, w = rgb.shape[:2]
    rec: dict[str, Any] = {"image": str(path), "status": "not_found"}
    feat_conf = maps.index.meta.get("features_conf") or {}
    min_inl = int(c["min_inliers"])
    # hypotheses: (path, camera, PnPResult); the map windows their scores are taken on
    hyps: list[tuple[str, PinholeCamera, Any]] = []
    windows: list[Matches] = []
    vconf = {**DIRECT_DEFAULTS, **(c.get("direct") or {})}
    map_px = maps.whole_map_px()
    fm_served = None  # a feature-map pose that ends the search: (path, camera, PnPResult, verification)
    fm_weak = None  # a feature-map pose that verified but does not end the search: one more hypothesis
    fm_start = False  # a feature-map pose that did not verify: the direct matching's start

    def whole_map() -> None:
        """Direct matching on the whole (small) map, the frame at full size (at most 3 Mpx)."""
        t = time.perf_counter()
        cam0 = PinholeCamera(K[0, 0], K[1, 1], K[0, 2], K[1, 2], w, h, np.eye(3), np.zeros(3))
        dr, mt = direct_pose(gray, cam0, maps.ortho, maps.dsm, feat_conf, maps.gsd, 0.0, vconf,
                             maps.flat_z, maps.bounds(), min(1.0, float(np.sqrt(3e6 / (h * w)))),
                             maps.window_cache)  # fmt: skip
        windows.append(mt)
        rec.setdefault("direct_attempts", []).append({"start": "whole map", **dr.info})
        if dr.pnp.ok and dr.pnp.inliers >= min_inl:
            hyps.append(("direct 2D-3D (whole map)", cam0.with_pose(dr.pnp.R, dr.pnp.C), dr.pnp))
        timings["direct_s"] = timings.get("direct_s", 0.0) + time.perf_counter() - t

    if not camera and map_px <= int(vconf["whole_map_first_px"]):
        camera = whole_map_camera(rgb, w, h, maps, feat_conf, vconf, c, rec)
    if camera:
        K, dist = camera_matrix(camera, w, h)
        und = cv2.undistort(rgb, K, dist) if np.any(dist) else rgb
        gray = cv2.cvtColor(und, cv2.COLOR_RGB2GRAY)
        if maps.feature_map is not None:  # earlier sets' feature maps first
            t = time.perf_counter()
            fm = feature_map_hypothesis(gray, K, w, h, maps, vconf, feat_conf, min_inl, rec, windows,
                                        {**DEFAULTS["adaptive"], **(c.get("adaptive") or {})},
                                        map_px <= int(vconf["whole_map_first_px"]))  # fmt: skip
            fm_served = fm if fm and rec["feature_map"]["served"] else None
            fm_weak = fm[:3] if fm and not fm_served else None
            hyps += [fm_served[:3]] if fm_served else []  # it ends the search: no map-only stage
            fm_start = bool(rec["feature_map"].get("start"))  # covered, not verified: a start
            timings["feature_map_s"] = time.perf_counter() - t
        if not hyps and map_px <= int(vconf["whole_map_first_px"]):
            whole_map()  # a small map: cheaper than the coarse search
        t0c = time.perf_counter()
        co = (run_coarse(gray, K, maps, c["coarse"]) if not hyps and not fm_start else
              Coarse(False, reason="not run: the " + ("feature map gave a pose" if fm_served
                                                      else "whole-map direct matching gave a pose" if hyps
                                                      else "feature map gave a start")))  # fmt: skip
        timings["coarse_s"] = time.perf_counter() - t0c
        focal_note = camera.get("source", "given")  # "exif": from frame_exif
    else:
        und = rgb
        gray = cv2.cvtColor(und, cv2.COLOR_RGB2GRAY)
        co, K = None, None
        strong = strong_inliers(c["coarse"])
        for fac in c["focal_factors"]:
            Kf, _ = camera_matrix(None, w, h, fac * w)
            r = run_coarse(gray, Kf, maps, c["coarse"])
            log.info("focal search: fx = %.0f px -> %s, %d inliers", fac * w, r.ok, r.inliers)
            if co is None or (r.ok and r.inliers > co.inliers):
                co, K = r, Kf
            elif co.ok and co.inliers >= strong:  # past the peak of a strong place (the coarse
                break  # search's own stop): farther focals only fall
        dist = np.zeros(5)
        focal_note = "estimated (focal search in PnP)"
        timings["coarse_s"] = time.perf_counter() - t0
        if co.ok and c.get("focal_from_window", True):  # the matches under the coarse pose
            t = time.perf_counter()
            cam_c = PinholeCamera(K[0, 0], K[1, 1], K[0, 2], K[1, 2], w, h, co.R, co.C)
            mt = match_window(gray, cam_c, maps.ortho, maps.dsm, feat_conf, maps.gsd,
                              maps.ground_z(co.C), vconf, maps.flat_z)  # fmt: skip
            est = camera_from_matches(mt, w, h, vconf, c, rec, "coarse-window", time.perf_counter() - t)
            if est and est["source"].endswith("pose + focal fit)"):  # a determined focal only
                camera = est
                K, dist = camera_matrix(camera, w, h)
                und = cv2.undistort(rgb, K, dist) if np.any(dist) else rgb
                gray = cv2.cvtColor(und, cv2.COLOR_RGB2GRAY)
                focal_note = camera["source"]
    rec["intrinsics"] = {"fx": float(K[0, 0]), "fy": float(K[1, 1]), "cx": float(K[0, 2]),
                         "cy": float(K[1, 2]), "dist": [float(v) for v in dist], "width": w,
                         "height": h, "source": focal_note}  # fmt: skip
    rec["pyramid"] = pyr  # the level the frame was localised on (intrinsics above: that level's)
    if camera and camera.get("exif_tags"):
        rec["intrinsics"]["exif_tags"] = camera["exif_tags"]  # which tags gave the focal
    rec["ground"] = ({"source": "dsm"} if maps.dsm else
                     {"source": "flat (no DSM given)", "z": maps.flat_z, "warning": FLAT_GROUND_WARNING})  # fmt: skip
    rec["coarse"] = {"ok": co.ok, "inliers": co.inliers, "reason": co.reason,
                     "budget": co.budget, "candidates": co.candidates}  # fmt: skip
    starts = [(co.R, co.C, "coarse PnP")] if co.ok else []
    if fm_start:  # the feature-map pose: the first start of the direct matching
        fp = rec["feature_map"]["pose"]
        starts.insert(0, (np.asarray(fp["R_world_to_cam"]), np.asarray(fp["camera_center_xyz"]), "feature map"))
    starts += [
        (R, C, f"nadir vote ({v} votes)") for R, C, v in co.hypotheses[: int(c["vote_starts"])]
    ]
    cam_of = lambda R, C: PinholeCamera(K[0, 0], K[1, 1], K[0, 2], K[1, 2], w, h, R, C)  # noqa: E731

    # 1. direct 2-D/3-D matching around each start, until one gives a verified pose
    t1 = time.perf_counter()
    for R0, C0, how in starts if not hyps else []:
        cam0 = cam_of(R0, C0)
        dr, mt = direct_pose(gray, cam0, maps.ortho, maps.dsm, feat_conf, maps.gsd,
                             maps.ground_z(C0), direct_conf(vconf, how, co, c["coarse"]), maps.flat_z)  # fmt: skip
        windows.append(mt)
        rec.setdefault("direct_attempts", []).append({"start": how, **dr.info})
        if dr.pnp.ok and dr.pnp.inliers >= min_inl:
            hyps.append(("direct 2D-3D", cam0.with_pose(dr.pnp.R, dr.pnp.C), dr.pnp))
            break
    timings["direct_s"] = timings.get("direct_s", 0.0) + time.perf_counter() - t1
    tried_whole = any(a["start"] == "whole map" for a in rec.get("direct_attempts", []))
    if not hyps and not tried_whole and map_px <= int(vconf["whole_map_px"]):
        whole_map()
    if fm_weak:  # a feature-map pose that does not end the search competes with the map-only ones
        hyps.append(fm_weak)

    # every hypothesis is polished by LM on its guided matches over the whole frame, then scored
    # (guided inliers, the same map window); the intensity refinement of the best must beat it
    def window_of(cam: PinholeCamera) -> tuple[Matches, float]:
        zg = maps.ground_z(cam.C)
        mt = next((m for m in windows if m.contains(footprint_xy(cam, zg).mean(axis=0))), None)
        if mt is None:
            mt = match_window(gray, cam, maps.ortho, maps.dsm, feat_conf, maps.gsd, zg, vconf,
                              maps.flat_z)  # fmt: skip
            windows.append(mt)
        return mt, verification_tolerance(cam, maps.gsd, zg, float(vconf["verify_px"]))

    scored: list[tuple[str, PinholeCamera, Any, dict]] = []

    def score_new() -> None:
        t = time.perf_counter()
        for p, cam, res in hyps[len(scored) :]:
            mt, tol = window_of(cam)
            rounds, distinct = int(vconf["polish_rounds"]), bool(vconf["polish_distinct"])
            cam_p = polish(mt, cam, tol, rounds, distinct)
            v = verify(mt, cam_p, tol)
            v["polish_moved_m"] = float(np.linalg.norm(cam_p.C - cam.C))
            scored.append((p, cam_p, res, v))
        timings["verify_s"] = timings.get("verify_s", 0.0) + time.perf_counter() - t

    # adaptive: a direct pose verified strong (many guided inliers, small residuals) is final;
    # render-match-PnP and the intensity refinement run only after a weak one (or none). Not
    # with a searched focal: the render stage refines it
    ad = {**DEFAULTS["adaptive"], **(c.get("adaptive") or {})}
    strong = False
    if fm_served:  # the feature-map pose ends the search: final, no render stage nor refinement
        scored.append(fm_served)
        strong = True
        rec["adaptive"] = {"feature_map_served": True, "skipped": ["coarse search", "direct 2D-3D",
                           "render-match-PnP", "intensity refinement", "focal refinement"]}  # fmt: skip
    elif hyps and ad["enabled"] and camera:
        score_new()
        v = scored[0][3]
        strong = verifies_strong(v, ad)
        rec["adaptive"] = {"direct_score": v["score"], "direct_rms_px": v["rms_px"],
                           "strong": bool(strong), "skipped": ["render-match-PnP",
                           "intensity refinement"] if strong else []}  # fmt: skip

    # 2. render-match-PnP from the direct pose (else from the coarse starts, as before)
    rstarts = [(hyps[0][1].R, hyps[0][1].C, "direct 2D-3D")] if hyps else starts
    if hyps and (not c["render_after_direct"] or strong):
        rstarts = []
    cloud, cloud_at, fcam = None, None, None
    for R0, C0, how in rstarts:
        t1 = time.perf_counter()
        cam0 = cam_of(R0, C0)
        cloud, cloud_at = maps.cloud_around(cam0, c), C0
        timings["cloud_s"] = timings.get("cloud_s", 0.0) + time.perf_counter() - t1
        t2 = time.perf_counter()
        res = register_by_rendering(gray, cam0, cloud, maps.gsd, feat_conf, c["pnp"])
        if not camera and res.ok and int(c["focal_rounds"]) > 0:  # searched focal: refine it
            res, cam_f, rec["focal"] = estimate_focal(gray, res, cam0.with_pose(res.R, res.C), cloud,
                                                      maps.gsd, feat_conf, c["pnp"], int(c["focal_rounds"]))  # fmt: skip
            cam0 = dataclasses.replace(cam0, fx=cam_f.fx, fy=cam_f.fy)
            fcam = cam0
        timings["pnp_s"] = timings.get("pnp_s", 0.0) + time.perf_counter() - t2
        rec.setdefault("pnp_attempts", []).append({"start": how, "start_center_xyz": [float(v) for v in C0],
                                                   "inliers": res.inliers, "history": res.history})  # fmt: skip
        if res.ok and res.inliers >= min_inl:
            hyps.append(("render-match-PnP", cam0.with_pose(res.R, res.C), res))
            break

    if fcam is not None:  # the focal refined on the render stage's inliers holds for every pose
        hyps = [(p, dataclasses.replace(cm, fx=fcam.fx, fy=fcam.fy), r) for p, cm, r in hyps]
        scored.clear()  # scored again at that focal

    # 3. every hypothesis scored; the intensity refinement of the best must beat it
    score_new()
    scored.sort(key=lambda t: -t[3]["score"])
    if scored and camera and camera.get("source") == "exif" and c["exif_focal_refine"] and not fm_served:
        _refine_exif_focal(scored, window_of, rec)
    if scored and (c.get("refine") or {}).get("enabled", True) and not strong:
        from georeg.frames.refine import refine_pose

        p, cam, res, v0 = scored[0]
        t4 = time.perf_counter()
        if cloud is None or np.linalg.norm(np.asarray(cloud_at) - cam.C) > 0.05 * maps.ground_distance(cam):
            cloud, cloud_at = maps.cloud_around(cam, c), cam.C
        ref = refine_pose(gray, cam, cloud, c.get("refine") or {})
        cam_r = cam.with_pose(ref.R, ref.C)
        timings["refine_s"] = time.perf_counter() - t4
        mt, tol = window_of(cam_r)
        v = verify(mt, cam_r, tol)
        ref.info.update(start=p, score=v["score"], accepted=v["score"] > v0["score"])
        scored.append((f"{p} + intensity refinement", cam_r, res, v))
        scored.sort(key=lambda t: -t[3]["score"])  # stable: a tie keeps the unrefined pose
        rec["refine"] = ref.info
    # 4. nothing verified: the intensity pose search around the coarse votes (known camera)
    sconf = {**SEARCH_DEFAULTS, **(c.get("search") or {})}
    if camera and sconf["enabled"] and not (scored and scored[0][3]["score"] >= min_inl):
        t6 = time.perf_counter()
        cconf = {**c, "cloud_margin_m": float(sconf["cloud_margin_m"])}
        for R0, C0, how in starts[: int(sconf["votes"])]:
            cam0 = cam_of(R0, C0)
            scloud = maps.cloud_around(cam0, cconf)
            sr = search_pose(gray, cam0, scloud, sconf, lambda cm: maps.cloud_around(cm, cconf))  # + decoys' maps
            rec.setdefault("search_attempts", []).append({"start": how, **sr.info})
            if sr.cam is not None:
                mt, tol = window_of(sr.cam)  # the feature score, recorded (not what accepts it)
                v = {**verify(mt, sr.cam, tol), "accepted_by": "intensity search",
                     "similarity": sr.info["similarity"],
                     "similarity_bound": max(float(sconf["accept_similarity"]), float(sconf["decoy_ratio"])
                                             * max(sr.info["decoy_similarity"]))}  # fmt: skip
                scored.insert(0, (f"intensity search ({how})", sr.cam, PnPResult(True, sr.cam.R, sr.cam.C), v))
                cloud, cloud_at = scloud, C0
                break
        timings["search_s"] = time.perf_counter() - t6
    rec["verification"] = {"candidates": [{"path": p, **v} for p, _, _, v in scored]}
    final_render = None
    if scored and (scored[0][3]["score"] >= min_inl or scored[0][3].get("accepted_by")):
        p, cam, res, v = scored[0]
        rec["path"] = p
        rec["verification"].update(v)
        base = next(cm for pp, cm, _, _ in scored if pp == p.split(" + ")[0])
        rec["pnp"] = {**_cam_record(base), "inliers": res.inliers,
                      "reprojection_px": res.reprojection_px if res.inliers else None}  # fmt: skip
        if cam.fx != K[0, 0]:
            how = ("exif, refined on the PnP inliers" if focal_note == "exif" else
                   "estimated (focal search, then refined in PnP)")  # fmt: skip
            rec["intrinsics"].update(fx=float(cam.fx), fy=float(cam.fy), source=how)
        z_med = float(np.median(res.inlier_xyz[:, 2])) if res.inlier_xyz is not None else maps.ground_z(cam.C)
        rec.update(status="registered", **_cam_record(cam), inliers=int(res.inliers),
                   reprojection_px=float(res.reprojection_px) if res.inliers else None,
                   footprint_xy=footprint_xy(cam, z_med).tolist())  # fmt: skip
        rec.pop("reason", None)
        t5 = time.perf_counter()
        dist = maps.ground_distance(cam)
        if cloud is None or np.linalg.norm(np.asarray(cloud_at) - cam.C) > 0.05 * dist:
            cloud = maps.cloud_around(cam, c, max_px=max(250_000, 2 * w * h))  # for display only
        final_render = display_render(cloud, cam, maps.gsd, dist)
        timings["overlay_render_s"] = time.perf_counter() - t5
    else:
        best = max([v["score"] for _, _, _, v in scored], default=0)
        tried = [a["start"] for a in rec.get("direct_attempts", [])]
        rec["reason"] = (f"no pose hypothesis verified: best score {best} (< {min_inl}); coarse: "
                         f"{co.reason or 'ok'}; direct 2D-3D from {tried or 'no start'}, "
                         f"render-match-PnP from {len(rstarts)} start(s)")  # fmt: skip
    if rec["status"] != "registered":
        best_inl = max([a["inliers"] for a in rec.get("pnp_attempts", []) + rec.get("direct_attempts", [])],
                       default=0)  # fmt: skip
        rec.update(camera_center_xyz=None, R_world_to_cam=None, inliers=int(best_inl),
                   reprojection_px=None)  # fmt: skip
    timings["total_s"] = time.perf_counter() - t0
    rec["timings_s"] = {k: round(v, 3) for k, v in timings.items()}
    log.info("frame %s: %s by %s (%.1f s)", path, rec["status"], rec.get("path"), timings["total_s"])
    return rec, (und, final_render)


def evaluate(rec: dict, truth: dict) -> dict:
    """Position (horizontal, vertical, 3-D, m) and rotation (deg) errors against a truth record."""
    out: dict[str, Any] = {"expected": truth.get("status")}
    Ct, Rt = np.asarray(truth["camera_center_xyz"]), np.asarray(truth["R_world_to_cam"])
    out["truth_center_xyz"] = [float(v) for v in Ct]  # the report's camera path plot
    for key, src in (("final", rec), ("pnp", rec.get("pnp"))):
        if not src or src.get("camera_center_xyz") is None:
            continue
        d = np.asarray(src["camera_center_xyz"]) - Ct
        out[key] = {"horizontal_m": float(np.hypot(d[0], d[1])), "vertical_m": float(abs(d[2])),
                    "position_m": float(np.linalg.norm(d)),
                    "rotation_deg": _rot_err(src["R_world_to_cam"], Rt)}  # fmt: skip
    return out


def open_map_sources(index_dir, ortho_vrt, dsm_vrt, laz_paths, conf: dict, ground_z: float = 0.0,
                     feature_maps: list | None = None) -> MapSources:  # fmt: skip
    """The map of a frame set, video or collection (``conf`` = ``frame_loc``), with earlier sets'
    feature maps (sfm_points.laz, tried first: ``georeg.frames.feature_map``) when given."""
    maps = MapSources(index_dir, ortho_vrt, dsm_vrt, laz_paths,
                      dense_coarse=bool(conf.get("dense_coarse", DEFAULTS["dense_coarse"])),
                      ground_z=ground_z)  # fmt: skip
    if feature_maps:
        from georeg.frames.feature_map import load_feature_maps

        maps.feature_map = load_feature_maps(list(feature_maps), maps.crs_wkt, maps.bounds(),
                                             conf.get("feature_map"))  # fmt: skip
    return maps


def set_prior(maps: MapSources, prior: Any, set_name: str = "<set>") -> dict | None:
    """The set's location prior as a box in the map CRS on ``maps`` (the index coarse search keeps
    to it); what poses.json records of it (None without a prior). A bad prior: ``InputError``."""
    from georeg.io.prior import prior_bounds, prior_record

    key = f"frames.{set_name}.prior"
    maps.prior_box = prior_bounds(prior, maps.crs_wkt, where=key, key=key)
    return prior_record(prior, maps.prior_box)


def localize_set(images: Any, camera: dict | None, index_dir, ortho_vrt, dsm_vrt, laz_paths,
                 conf: dict, out_dir, truth_path: str | None = None, ground_z: float = 0.0,
                 feature_maps: list | None = None, prior: Any = None,
                 set_name: str = "<set>") -> list[dict]:  # fmt: skip
    """Rule ``localize_frames``: every frame of a set -> results/frames/{set}/. ``dsm_vrt`` None:
    the ground is the plane z = ``ground_z`` (recorded as ``ground`` in every pose).
    ``feature_maps``: earlier sets' sfm_points.laz, tried first (``georeg.frames.feature_map``).
    ``prior`` (``frames.<set>.prior``, ``georeg.io.prior``): the coarse search keeps to its box."""
    out = Path(out_dir)
    paths = frame_images(images)
    if not paths:
        raise InputError(None, f"the frame list {images!r} matches no file", "check frames.<set>.images")
    for p in paths:  # every frame readable and large enough before anything is written
        check_frame(p)
    maps = open_map_sources(index_dir, ortho_vrt, dsm_vrt, laz_paths, conf, ground_z, feature_maps)
    prior_rec = set_prior(maps, prior, set_name)
    truth = {}
    if truth_path:
        import json

        truth = {Path(t["image"]).name: t for t in json.loads(Path(truth_path).read_text())}
    poses = []
    for p in paths:
        rec, (und, rend) = localize_frame(p, camera, maps, conf)
        if prior_rec is not None:
            rec["prior"] = prior_rec
        if Path(p).name in truth:
            rec["evaluation"] = evaluate(rec, truth[Path(p).name])
        a = float(conf.get("overlay_alpha", DEFAULTS["overlay_alpha"]))
        write_png(out / "overlays" / f"{Path(p).stem}.png", overlay(und, rend, a))
        poses.append(rec)
    write_geojson(out / "cameras.geojson", poses, maps.crs_wkt)
    write_kml(out / "cameras.kml", poses, maps.crs_wkt)
    if maps.feature_map is not None:
        served = sum(1 for p in poses if (p.get("feature_map") or {}).get("used")
                     and str(p.get("path", "")).startswith("feature map"))  # fmt: skip
        log.info("feature maps served %d of %d frames", served, len(poses))
        if not served:
            log.warning("the feature maps %s served none of the frames: every frame took the "
                        "map-only path (recorded per frame as feature_map.fallback)", feature_maps)  # fmt: skip
    write_poses(out / "poses.json", poses)
    return poses
