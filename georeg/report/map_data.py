"""What the map view (``results/report/map.html``) shows, in full-resolution map pixel coordinates.

Every layer is placed on the map grid (``results/map/grid.json``): a point (x, y) of the map CRS
is drawn at (col, row) = the inverse grid transform of (x, y), pixel corners at integers, rows
down. The browser draws them in ``L.CRS.Simple`` as (lat, lng) = (-row, col) and converts the
mouse position back to the map CRS with the grid transform.

* ``MapFrame``: the grid (transform, size, CRS).
* ``render_ortho``: the orthophoto, decimated to at most ``max_px`` per side (JPEG).
* ``warp_query``: a registered query's band warped into the map frame (RGBA PNG over the query's
  bounding box) through its delivered geolocation (``geolocation.tif``): the homography inverts
  it approximately and a fixed-point iteration on the residual field (geolocation - H) corrects
  the local refinement's displacements.
* ``query_features`` / ``frame_set_features``: GeoJSON features (footprints, truth outlines,
  cameras, look directions, trajectories) whose ``info`` property is the table a click shows.
"""

from __future__ import annotations

import json
import logging
import math
import warnings
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from georeg.io.atomic import atomic_path
from georeg.io.errors import InputError
from georeg.report.frames_html import _truth_centres, frame_name
from georeg.report.plotting import crop_rgb, read_crop, truth_outline

log = logging.getLogger(__name__)

#: background of the page where the orthophoto has no data (RGB)
NODATA_RGB = (32, 37, 43)


@dataclass(frozen=True)
class MapFrame:
    """The map grid: affine (a, b, c, d, e, f) of pixel corners, size and CRS."""

    transform: tuple[float, float, float, float, float, float]
    width: int
    height: int
    crs_wkt: str | None = None

    @classmethod
    def from_grid(cls, path: str | Path) -> MapFrame:
        try:
            g = json.loads(Path(path).read_text())
            g["transform"], g["width"], g["height"]  # noqa: B018 - the keys the view needs
        except (OSError, ValueError, KeyError, TypeError) as exc:
            raise InputError(path, f"not a map grid (grid.json): {exc}") from exc
        return cls(tuple(float(v) for v in g["transform"][:6]), int(g["width"]),  # type: ignore[arg-type]
                   int(g["height"]), g.get("crs"))  # fmt: skip

    def px_matrix(self) -> np.ndarray:
        """3x3 matrix map (x, y, 1) -> map pixel (col, row, 1)."""
        a, b, c, d, e, f = self.transform
        return np.linalg.inv(np.array([[a, b, c], [d, e, f], [0, 0, 1.0]]))

    def to_px(self, xy: Any) -> np.ndarray:
        """(n, 2) map x, y -> (n, 2) map pixel (col, row)."""
        p = np.asarray(xy, np.float64).reshape(-1, 2)
        return p @ self.px_matrix()[:2, :2].T + self.px_matrix()[:2, 2]

    @property
    def pixel_m(self) -> float:
        """Side of a map pixel in map units."""
        a, b, _, d, e, _ = self.transform
        return float(math.sqrt(abs(a * e - b * d)))

    def crs_name(self) -> str:
        if not self.crs_wkt:
            return "map CRS"
        try:
            import pyproj

            crs = pyproj.CRS.from_user_input(self.crs_wkt)
            epsg = crs.to_epsg()
            return f"EPSG:{epsg}" if epsg else crs.name
        except Exception:  # noqa: BLE001 - a name for display only
            return "map CRS"


def _coords(px: np.ndarray, nd: int = 2) -> list[list[float]]:
    return [[round(float(c), nd), round(float(r), nd)] for c, r in px]


def _bbox(px: np.ndarray) -> list[float]:
    return [float(px[:, 0].min()), float(px[:, 1].min()), float(px[:, 0].max()),
            float(px[:, 1].max())]  # fmt: skip


def write_image(path: str | Path, img: np.ndarray, ext: str, quality: int = 88) -> None:
    """RGB(A) uint8 image to PNG / JPEG, atomically."""
    bgr = cv2.cvtColor(img, cv2.COLOR_RGBA2BGRA if img.shape[2] == 4 else cv2.COLOR_RGB2BGR)
    params = [cv2.IMWRITE_JPEG_QUALITY, quality] if ext == ".jpg" else [cv2.IMWRITE_PNG_COMPRESSION, 6]
    ok, buf = cv2.imencode(ext, bgr, params)
    if not ok:
        raise OSError(f"cannot encode {path}")
    with atomic_path(path) as tmp:
        tmp.write_bytes(buf.tobytes())


def render_ortho(ortho: str | Path, frame: MapFrame, out: str | Path, max_px: int = 2048) -> dict:
    """The orthophoto decimated to ``max_px`` per side as JPEG; returns its map pixel bounds."""
    try:
        crop = read_crop(ortho, None, max_px)
    except Exception as exc:  # noqa: BLE001 - rasterio / GDAL errors of a bad file
        raise InputError(ortho, f"cannot read the orthophoto: {exc}") from exc
    if crop is None:
        raise InputError(ortho, "the orthophoto is absent")
    rgba = crop_rgb(crop)
    rgb = np.where(rgba[..., 3:] > 0, rgba[..., :3], np.array(NODATA_RGB, np.uint8))
    write_image(out, np.ascontiguousarray(rgb), ".jpg")
    w, s, e, n = crop.bounds
    px = frame.to_px([[w, n], [e, s]])
    return {"bounds": _bbox(px), "size": [int(rgb.shape[1]), int(rgb.shape[0])]}


def read_raster(path: str | Path | None) -> np.ndarray | None:
    if not path or not Path(path).exists():
        return None
    import rasterio

    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        with rasterio.open(path) as ds:
            return ds.read()


def _stretch(band: np.ndarray, valid: np.ndarray) -> np.ndarray:
    """uint8 display of a query band: 1-99 % of its valid pixels."""
    v = band[valid].astype(np.float64)
    lo, hi = np.percentile(v, [1, 99]) if v.size else (0.0, 1.0)
    return np.clip((band - lo) / max(hi - lo, 1e-9) * 255, 0, 255).astype(np.uint8)


def _apply(A: np.ndarray, c: np.ndarray, r: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """A 3x3 homography applied to coordinate arrays."""
    den = A[2, 0] * c + A[2, 1] * r + A[2, 2]
    return (A[0, 0] * c + A[0, 1] * r + A[0, 2]) / den, (A[1, 0] * c + A[1, 1] * r + A[1, 2]) / den


@dataclass
class QueryLookup:
    """Where each pixel of a query's drawn image comes from: the (decimated) query pixel
    ``qc``, ``qr`` under each overlay pixel centre, the overlay's map pixel ``bounds`` [c0, r0,
    c1, r1], the decimation ``k`` and the geolocation in map pixels ``gc``, ``gr`` (decimated)."""

    qc: np.ndarray
    qr: np.ndarray
    bounds: list[float]
    k: int
    gc: np.ndarray
    gr: np.ndarray

    def centres(self) -> tuple[np.ndarray, np.ndarray]:
        """Map pixel coordinates of the overlay pixel centres."""
        c0, r0, c1, r1 = self.bounds
        h, w = self.qc.shape
        return np.meshgrid(c0 + (np.arange(w) + 0.5) * (c1 - c0) / w,
                           r0 + (np.arange(h) + 0.5) * (r1 - r0) / h)  # fmt: skip


def query_lookup(shape: tuple[int, int], geo_xy: tuple[np.ndarray, np.ndarray] | None, H: Any,
                 frame: MapFrame, max_px: int = 1024, iterations: int = 4) -> QueryLookup | None:  # fmt: skip
    """Inverse of a query's geolocation on the overlay grid; None when nothing is registered.

    The overlay covers the footprint's bounding box at about the query's own resolution (at most
    ``max_px`` per side; a query larger than 2 ``max_px`` is decimated to every k-th pixel). Each
    overlay pixel centre m looks up the query pixel whose geolocation lands on it:
    q = A^-1(m - d(q)), iterated ``iterations`` times from q = A^-1(m), where A is H in map
    pixels and d the residual of the geolocation from A (0 iterations: H alone)."""
    k = max(1, math.ceil(max(shape) / (2 * max_px)))
    if k > 1:
        geo_xy = None if geo_xy is None else (geo_xy[0][::k, ::k], geo_xy[1][::k, ::k])
        H = None if H is None else np.asarray(H, np.float64) @ np.diag([k, k, 1.0])
    h, w = len(range(0, shape[0], k)), len(range(0, shape[1], k))
    A = None if H is None else frame.px_matrix() @ np.asarray(H, np.float64)
    cols, rows = np.meshgrid(np.arange(w, dtype=np.float64), np.arange(h, dtype=np.float64))
    if geo_xy is not None and np.isfinite(geo_xy[0]).any():
        g = frame.to_px(np.c_[geo_xy[0].ravel(), geo_xy[1].ravel()])
        gc, gr = g[:, 0].reshape(h, w), g[:, 1].reshape(h, w)
    elif A is not None:
        gc, gr = _apply(A, cols, rows)
    else:
        return None
    ok = np.isfinite(gc) & np.isfinite(gr)
    if ok.sum() < 4:
        return None
    if A is None:  # no homography: fit one to the geolocation
        every = max(1, int(ok.sum()) // 5000)
        src = np.c_[cols[ok], rows[ok]][::every]
        A, _ = cv2.findHomography(src, np.c_[gc[ok], gr[ok]][::every], 0)
        if A is None:
            return None
    # query pixel side in map pixels (median neighbour spacing) sets the overlay's resolution
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        step = float(np.nanmedian(np.hypot(np.diff(gc, axis=1), np.diff(gr, axis=1)))) if w > 1 else 1.0
    step = step if np.isfinite(step) and step > 0 else 1.0
    c0, r0 = float(gc[ok].min()) - step / 2, float(gr[ok].min()) - step / 2
    c1, r1 = float(gc[ok].max()) + step / 2, float(gr[ok].max()) + step / 2
    res = max(step, max(c1 - c0, r1 - r0) / max_px)
    ow, oh = max(1, math.ceil((c1 - c0) / res)), max(1, math.ceil((r1 - r0) / res))
    c1, r1 = c0 + ow * res, r0 + oh * res
    tc, tr = np.meshgrid(c0 + (np.arange(ow) + 0.5) * res, r0 + (np.arange(oh) + 0.5) * res)
    ac, ar = _apply(A, cols, rows)
    d = np.dstack([np.where(ok, gc - ac, 0), np.where(ok, gr - ar, 0)]).astype(np.float32)
    Ainv = np.linalg.inv(A)
    qc, qr = _apply(Ainv, tc, tr)
    for _ in range(max(0, iterations)):
        dd = cv2.remap(d, qc.astype(np.float32), qr.astype(np.float32), cv2.INTER_LINEAR,
                       borderMode=cv2.BORDER_REPLICATE)  # fmt: skip
        qc, qr = _apply(Ainv, tc - dd[..., 0], tr - dd[..., 1])
    return QueryLookup(qc, qr, [c0, r0, c1, r1], k, gc, gr)


def lookup_residual(lk: QueryLookup) -> np.ndarray:
    """Drawing error (map px) of each overlay pixel inside the footprint: the distance between its
    centre m and the geolocation G(q) of the query position q it shows (G bilinear)."""
    ok = (np.isfinite(lk.gc) & np.isfinite(lk.gr)).astype(np.float32)
    mx, my = lk.qc.astype(np.float32), lk.qr.astype(np.float32)
    g = np.dstack([np.nan_to_num(lk.gc), np.nan_to_num(lk.gr)]).astype(np.float64)
    at = cv2.remap(g, mx, my, cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT, borderValue=0)
    inside = cv2.remap(ok, mx, my, cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT, borderValue=0)
    mc, mr = lk.centres()
    sel = inside > 0.999
    return np.hypot(at[..., 0] - mc, at[..., 1] - mr)[sel]


def warp_query(band: np.ndarray, geo_xy: tuple[np.ndarray, np.ndarray] | None, H: Any,
               frame: MapFrame, max_px: int = 1024, iterations: int = 4) -> tuple[np.ndarray, list[float]] | None:  # fmt: skip
    """The query band (2-D, 0 = nodata) drawn in the map frame through ``query_lookup``: (RGBA
    image, map pixel bounds [c0, r0, c1, r1]); None when there is nothing registered to draw."""
    lk = query_lookup(band.shape, geo_xy, H, frame, max_px, iterations)
    if lk is None:
        return None
    band = band[:: lk.k, :: lk.k]
    valid = (band > 0) & np.isfinite(lk.gc) & np.isfinite(lk.gr)
    mapx, mapy = lk.qc.astype(np.float32), lk.qr.astype(np.float32)
    img = cv2.remap(_stretch(band, valid), mapx, mapy, cv2.INTER_LINEAR, borderValue=0)
    inside = cv2.remap(valid.astype(np.uint8) * 255, mapx, mapy, cv2.INTER_NEAREST, borderValue=0)
    alpha = np.where(inside > 0, 255, 0).astype(np.uint8)
    g = img.astype(np.float32)  # a cool tint tells the query from the orthophoto
    rgba = np.dstack([g * 0.75 + 10, g * 0.88 + 25, g * 0.8 + 60, alpha]).clip(0, 255).astype(np.uint8)
    return rgba, lk.bounds


# ----------------------------------------------------------------------------- features


def _fmt(v: Any, nd: int = 2) -> str:
    if v is None:
        return "-"
    if isinstance(v, bool):
        return "yes" if v else "no"
    if isinstance(v, float):
        return f"{v:.{nd}f}"
    return str(v)


def _feature(geom_type: str, coords: Any, **props: Any) -> dict:
    return {"type": "Feature", "properties": props,
            "geometry": {"type": geom_type, "coordinates": coords}}  # fmt: skip


def _ring(px: np.ndarray) -> list[list[float]]:
    c = _coords(px)
    return c if c[0] == c[-1] else [*c, c[0]]


def query_info(name: str, reg: Mapping[str, Any], ev: Mapping[str, Any]) -> list[list[str]]:
    """The rows a click on a query shows: status, outcome, reason, fit and errors."""
    err = (ev or {}).get("error") or {}
    px, m = err.get("px") or {}, err.get("m") or {}
    rows = [["query", name], ["status", _fmt(reg.get("status"))],
            ["outcome", _fmt((ev or {}).get("outcome", "no truth"))]]  # fmt: skip
    if reg.get("reason"):
        rows.append(["reason", str(reg["reason"])])
    rows += [["inliers / matches", f"{_fmt(reg.get('inliers'))} / {_fmt(reg.get('matches'))}"],
             ["candidates tried", _fmt(reg.get("candidates_tried"))],
             ["LiDAR check", _fmt((reg.get("lidar_check") or {}).get("outcome"))]]  # fmt: skip
    ref = reg.get("refine") or {}
    if ref.get("model"):
        rows.append(["refinement", _fmt(ref.get("model"))])
    for k in ("median", "p90", "max"):
        if px.get(k) is not None:
            rows.append([f"error {k}", f"{_fmt(px.get(k))} px = {_fmt(m.get(k))} m"])
    return rows


def query_features(name: str, reg: Mapping[str, Any], ev: Mapping[str, Any],
                   geo_xy: tuple[np.ndarray, np.ndarray] | None,
                   truth_xy: tuple[np.ndarray, np.ndarray] | None, frame: MapFrame) -> list[dict]:  # fmt: skip
    """A query's delivered footprint (border of its geolocation) and its truth outline."""
    status = str(reg.get("status"))
    outcome = str((ev or {}).get("outcome", "no_truth"))
    info = query_info(name, reg, ev)
    common = {"id": f"query:{name}", "name": name, "status": status, "outcome": outcome,
              "info": info}  # fmt: skip
    feats = []
    fp = truth_outline(*geo_xy) if geo_xy is not None else None
    if fp is None and status == "registered" and reg.get("homography") is not None:
        from georeg.report.plotting import footprint

        fp = footprint(reg["homography"], int(reg["width"]), int(reg["height"]))
    if fp is not None:
        feats.append(_feature("Polygon", [_ring(frame.to_px(fp))], layer="footprints",
                              kind="query_footprint", **common))  # fmt: skip
    tr = truth_outline(*truth_xy) if truth_xy is not None else None
    if tr is not None:
        feats.append(_feature("Polygon", [_ring(frame.to_px(tr))], layer="truth",
                              kind="query_truth", **common))  # fmt: skip
    return feats


def _frame_info(set_name: str, p: Mapping[str, Any]) -> list[list[str]]:
    rows = [["frame set", set_name], ["frame", frame_name(p)], ["status", _fmt(p.get("status"))]]
    ev = p.get("evaluation") or {}
    if ev.get("expected") is not None:
        rows.append(["expected", _fmt(ev.get("expected"))])
    if p.get("reason"):
        rows.append(["reason", str(p["reason"])])
    for k in ("source", "path"):
        if p.get(k):
            rows.append([k, str(p[k])])
    if p.get("keyframe"):
        rows.append(["keyframe", "yes"])
    rows += [["inliers", _fmt(p.get("inliers"))],
             ["reprojection (px)", _fmt(p.get("reprojection_px"))]]  # fmt: skip
    fin = ev.get("final") or {}
    if fin.get("horizontal_m") is not None:
        rows.append(["error horizontal / vertical",
                     f"{_fmt(fin.get('horizontal_m'))} m / {_fmt(fin.get('vertical_m'))} m"])  # fmt: skip
        rows.append(["error rotation", f"{_fmt(fin.get('rotation_deg'))} deg"])
    if (p.get("ground") or {}).get("warning"):
        rows.append(["warning", str(p["ground"]["warning"])])
    c = p.get("camera_center_xyz")
    if c:
        rows.append(["camera x, y, z", ", ".join(f"{float(v):.2f}" for v in c)])
    return rows


def look_end(p: Mapping[str, Any]) -> np.ndarray | None:
    """Ground end (x, y) of a camera's look direction: along its optical axis's horizontal
    direction, as far as the centre of its ground footprint (or 1.5 x its height without one)."""
    C, R = p.get("camera_center_xyz"), p.get("R_world_to_cam")
    if not C or not R:
        return None
    C = np.asarray(C, float)
    axis = np.asarray(R, float)[2]
    fp = p.get("footprint_xy")
    if fp:
        dist = float(np.hypot(*(np.asarray(fp, float)[:, :2].mean(axis=0) - C[:2])))
    else:
        dist = 1.5 * abs(float(C[2]))
    hz = float(np.hypot(axis[0], axis[1]))
    if hz < 0.02:  # nadir: a short tick along the image "up" direction instead
        up = -np.asarray(R, float)[1]
        hz_up = float(np.hypot(up[0], up[1])) or 1.0
        return C[:2] + up[:2] / hz_up * max(dist, 1.0) * 0.3
    return C[:2] + axis[:2] / hz * max(dist, 1.0)


def frame_set_features(set_name: str, poses: Sequence[Mapping[str, Any]],
                       truth: Sequence[Mapping[str, Any]], frame: MapFrame,
                       trajectory: Mapping[str, Any] | None = None, look_every: int = 10,
                       max_markers: int = 400) -> list[dict]:  # fmt: skip
    """Cameras, footprints and look directions of a frame set; a video (entries with ``frame``)
    also gets its path (registered centres in frame order) and the truth path."""
    video = any(p.get("frame") is not None for p in poses) and len(poses) > 1
    order = sorted(range(len(poses)), key=lambda i: (poses[i].get("frame") is None,
                                                     poses[i].get("frame") or 0, i))  # fmt: skip
    ps = [poses[i] for i in order]
    tc = _truth_centres(ps, list(truth))
    feats: list[dict] = []
    if video:
        reg = [p for p in ps if p.get("status") == "registered" and p.get("camera_center_xyz")]
        info = _trajectory_info(set_name, ps, trajectory)
        if len(reg) >= 2:
            xy = frame.to_px([p["camera_center_xyz"][:2] for p in reg])
            feats.append(_feature("LineString", _coords(xy), layer="trajectories", kind="path",
                                  id=f"set:{set_name}", name=set_name, status="registered",
                                  info=info))  # fmt: skip
        t = np.array([c[:2] for c in tc if c is not None], float)
        if len(t) >= 2:
            feats.append(_feature("LineString", _coords(frame.to_px(t)), layer="truth",
                                  kind="truth_path", id=f"set:{set_name}", name=set_name,
                                  status="truth", info=info))  # fmt: skip
    n_reg = 0
    step = max(1, math.ceil(len(ps) / max_markers)) if video else 1
    for i, (p, t) in enumerate(zip(ps, tc, strict=True)):
        regd = p.get("status") == "registered" and p.get("camera_center_xyz")
        shown = not video or i % max(step, look_every) == 0 or bool(p.get("keyframe"))
        common = {"id": f"frame:{set_name}:{frame_name(p)}", "name": frame_name(p),
                  "set": set_name, "status": str(p.get("status")),
                  "info": _frame_info(set_name, p)}  # fmt: skip
        if regd:
            n_reg += 1
            C = np.asarray(p["camera_center_xyz"], float)
            cpx = frame.to_px(C[:2])
            if shown:
                feats.append(_feature("Point", _coords(cpx)[0], layer="cameras", kind="camera",
                                      keyframe=bool(p.get("keyframe")), video=video, **common))  # fmt: skip
                end = look_end(p)
                if end is not None and (not video or i % max(step, look_every) == 0):
                    feats.append(_feature("LineString", _coords(frame.to_px([C[:2], end])),
                                          layer="looks", kind="look", video=video, **common))  # fmt: skip
            fp = p.get("footprint_xy")
            if fp and not video:
                feats.append(_feature("Polygon", [_ring(frame.to_px(np.asarray(fp, float)[:, :2]))],
                                      layer="cameras", kind="frame_footprint", **common))  # fmt: skip
        if t is not None and (not video or (not regd and shown)):
            feats.append(_feature("Point", _coords(frame.to_px(np.asarray(t, float)[:2]))[0],
                                  layer="truth", kind="truth_camera", **common))  # fmt: skip
    log.info("frame set %s: %d entries, %d registered, %d features", set_name, len(ps), n_reg,
             len(feats))  # fmt: skip
    return feats


def _trajectory_info(set_name: str, poses: Sequence[Mapping[str, Any]],
                     trajectory: Mapping[str, Any] | None) -> list[list[str]]:  # fmt: skip
    """The rows a click on a video's path shows: counts and the error statistics."""
    n = len(poses)
    n_reg = sum(p.get("status") == "registered" for p in poses)
    rows = [["video set", set_name], ["frames registered", f"{n_reg} of {n}"]]
    kf = sum(bool(p.get("keyframe")) for p in poses)
    if kf:
        rows.append(["keyframes", str(kf)])
    tj = trajectory or {}
    if tj.get("reason"):
        rows.append(["reason", str(tj["reason"])])
    icp = tj.get("icp") or {}
    if icp:
        rows.append(["ICP", "accepted" if icp.get("accepted") else f"refused: {icp.get('reason')}"])
    ev = tj.get("evaluation") or {}
    fin = ev.get("after_icp") or {}  # georeg.trajectory.pipeline: statistics over all frames
    for k, label in (("horizontal_m", "horizontal error (m)"), ("vertical_m", "vertical error (m)"),
                     ("rotation_deg", "rotation error (deg)")):  # fmt: skip
        s = fin.get(k) if isinstance(fin, Mapping) else None
        if isinstance(s, Mapping) and s.get("median") is not None:
            rows.append([f"{label} median / p90 / max",
                         " / ".join(_fmt(s.get(q)) for q in ("median", "p90", "max"))])  # fmt: skip
    if not any(r[0].startswith("horizontal") for r in rows):
        errs = [((p.get("evaluation") or {}).get("final") or {}).get("horizontal_m") for p in poses]
        errs = [float(e) for e in errs if e is not None]
        if errs:
            rows.append(["horizontal error (m) median / p90 / max",
                         " / ".join(_fmt(float(v)) for v in (np.median(errs),
                                                             np.percentile(errs, 90),
                                                             max(errs)))])  # fmt: skip
    return rows
