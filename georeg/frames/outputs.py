"""Outputs of frame geo-localisation: poses.json, GeoJSON and KML of cameras and footprints,
overlay images (the map rendered at the found pose, edge-overlaid and blended on the frame)."""

from __future__ import annotations

from pathlib import Path
from typing import Any
from xml.sax.saxutils import escape

import cv2
import numpy as np
import pyproj

from georeg.frames.render import PinholeCamera, Render
from georeg.io.atomic import atomic_path, write_json, write_text


def footprint_xy(cam: PinholeCamera, z_ground: float, n: int = 4) -> np.ndarray:
    """Image border (n points per side, clockwise from the top-left) on the plane z = z_ground.
    Rays above the horizon are cut at 5 x the height above that plane."""
    W, H = cam.width - 1, cam.height - 1
    t = np.linspace(0, 1, n, endpoint=False)
    uv = np.concatenate([np.c_[t * W, 0 * t], np.c_[W + 0 * t, t * H], np.c_[W - t * W, H + 0 * t],
                         np.c_[0 * t, H - t * H]])  # fmt: skip
    d = cam.rays(uv)
    hgt = max(cam.C[2] - z_ground, 1.0)
    s = np.where(d[:, 2] < -1e-6, (z_ground - cam.C[2]) / np.minimum(d[:, 2], -1e-6), 5 * hgt)
    s = np.minimum(s, 5 * hgt / np.maximum(np.hypot(d[:, 0], d[:, 1]), 1e-6))
    return cam.C[None, :2] + s[:, None] * d[:, :2]


def footprint_window(cams: list[PinholeCamera], z_ground: float, margin: float, cap: float,
                     centre: np.ndarray | None = None) -> list[float]:  # fmt: skip
    """Map window (x0, y0, x1, y1) around the cameras' footprints on z = z_ground, grown by
    ``margin``, cut to at most ``cap`` wide around ``centre`` (x, y; default the window's centre)."""
    fp = np.concatenate([footprint_xy(c, z_ground) for c in cams])
    b = [fp[:, 0].min() - margin, fp[:, 1].min() - margin, fp[:, 0].max() + margin,
         fp[:, 1].max() + margin]  # fmt: skip
    cx, cy = ((b[0] + b[2]) / 2, (b[1] + b[3]) / 2) if centre is None else centre[:2]
    half = cap / 2
    return [max(b[0], cx - half), max(b[1], cy - half), min(b[2], cx + half), min(b[3], cy + half)]


def write_poses(path: str | Path, poses: list[dict]) -> None:
    write_json(path, poses)


def crs_urn(crs: pyproj.CRS) -> str | None:
    """GeoJSON 2008 CRS name of an EPSG CRS (None without an EPSG code)."""
    epsg = crs.to_epsg()
    return f"urn:ogc:def:crs:EPSG::{epsg}" if epsg else None


def write_feature_collection(path: str | Path, feats: list[dict], crs: pyproj.CRS) -> None:
    """A GeoJSON FeatureCollection in the map CRS: the GeoJSON 2008 ``crs`` member when the CRS
    has a URN, the WKT in the properties; written atomically."""
    fc: dict[str, Any] = {"type": "FeatureCollection", "features": feats,
                          "properties": {"crs_wkt": crs.to_wkt()}}  # fmt: skip
    urn = crs_urn(crs)
    if urn:
        fc["crs"] = {"type": "name", "properties": {"name": urn}}
    write_json(path, fc, indent=1)


def write_geojson(path: str | Path, poses: list[dict], crs_wkt: str) -> None:
    """Cameras (Point, x y z) and ground footprints (Polygon) in the map CRS (GeoJSON 2008 `crs`
    member, like the products' footprint.geojson; WKT in properties)."""
    crs = pyproj.CRS.from_user_input(crs_wkt)
    feats = []
    for p in poses:
        if p["status"] != "registered":
            continue
        props = {k: p[k] for k in ("image", "status", "inliers", "reprojection_px") if k in p}
        feats.append({"type": "Feature", "properties": {**props, "kind": "camera"},
                      "geometry": {"type": "Point", "coordinates": p["camera_center_xyz"]}})  # fmt: skip
        fp = p.get("footprint_xy")
        if fp:
            ring = [list(map(float, v)) for v in fp] + [list(map(float, fp[0]))]
            feats.append({"type": "Feature", "properties": {**props, "kind": "footprint"},
                          "geometry": {"type": "Polygon", "coordinates": [ring]}})  # fmt: skip
    write_feature_collection(path, feats, crs)


def write_kml(path: str | Path, poses: list[dict], crs_wkt: str) -> None:
    """KML 2.2 (WGS84): a placemark per camera (absolute altitude) and its footprint polygon."""
    tr = pyproj.Transformer.from_crs(
        pyproj.CRS.from_user_input(crs_wkt), "EPSG:4326", always_xy=True
    )
    out = ['<?xml version="1.0" encoding="UTF-8"?>', '<kml xmlns="http://www.opengis.net/kml/2.2">',
           "<Document>", "<name>georeg frames</name>"]  # fmt: skip
    for p in poses:
        if p["status"] != "registered":
            continue
        x, y, z = p["camera_center_xyz"]
        lon, lat = tr.transform(x, y)
        name = escape(Path(p["image"]).name)
        out += [f"<Placemark><name>{name}</name><Point><altitudeMode>absolute</altitudeMode>"
                f"<coordinates>{lon:.8f},{lat:.8f},{z:.2f}</coordinates></Point></Placemark>"]  # fmt: skip
        fp = p.get("footprint_xy")
        if fp:
            a = np.asarray(fp, float)
            lo, la = tr.transform(a[:, 0], a[:, 1])
            ring = " ".join(
                f"{u:.8f},{v:.8f},0" for u, v in zip([*lo, lo[0]], [*la, la[0]], strict=True)
            )
            out += [f"<Placemark><name>{name} footprint</name><Polygon><outerBoundaryIs><LinearRing>"
                    f"<coordinates>{ring}</coordinates></LinearRing></outerBoundaryIs></Polygon></Placemark>"]  # fmt: skip
    out += ["</Document>", "</kml>"]
    write_text(path, "\n".join(out) + "\n")


def overlay(frame_rgb: np.ndarray, rend: Render | None, alpha: float = 0.5) -> np.ndarray:
    """Left: frame blended with the render; right: frame with the render's edges in magenta.
    A not-found frame gets the frame alone with a red border."""
    f = frame_rgb.copy()
    if rend is None:
        cv2.rectangle(f, (0, 0), (f.shape[1] - 1, f.shape[0] - 1), (255, 0, 0), 8)
        return f
    r = rend.image
    m = rend.mask[..., None]
    blend = np.where(m, (alpha * r + (1 - alpha) * f).astype(np.uint8), f)
    e = rend.edges()
    ed = f.copy()
    ed[e] = (255, 0, 255)
    return np.hstack([blend, ed])


def write_png(path: str | Path, rgb: np.ndarray) -> None:
    with atomic_path(path) as tmp:
        if not cv2.imwrite(str(tmp), cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR)):
            raise OSError(f"cannot write {path}")
