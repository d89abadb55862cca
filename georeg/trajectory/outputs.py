"""Outputs of video trajectory geo-referencing.

* ``trajectory.csv``: one row per frame (frame, time, status, source, x y z, heading / pitch /
  roll of the optical axis, lon / lat).
* ``trajectory.geojson``: the camera path (LineString, x y z in the map CRS) and, every
  ``look_every`` frames, the look direction (a LineString from the camera to where its optical
  axis meets the ground).
* ``trajectory.kml``: the same in WGS84 for Google Earth: the path at absolute altitude and
  look-direction placemarks carrying a ``<Camera>`` view (heading, tilt, roll), so a double click
  flies to what the camera saw.
* ``sfm_points.laz`` (map CRS, RGB, extra dimensions ``track_len`` and ``point_id``) and
  ``sfm_points_descriptors.npy`` (uint8, row i = point_id i): the geo-registered 3-D feature map,
  for later relocalisation.
"""

from __future__ import annotations

import csv
import io
import math
from pathlib import Path
from typing import Any
from xml.sax.saxutils import escape

import numpy as np
import pyproj

from georeg.frames.feature_map import descriptor_path, write_feature_map
from georeg.frames.outputs import write_feature_collection
from georeg.io.atomic import write_text


def view_angles(R: np.ndarray) -> tuple[float, float, float]:
    """(heading, pitch, roll) in degrees of a world -> camera rotation (map grid frame).

    heading: azimuth of the optical axis clockwise from grid north; pitch: angle of the axis below
    the horizon (90 = nadir); roll: rotation of the image x axis out of the horizontal plane."""
    R = np.asarray(R, float)
    z = R[2]  # optical axis in the world
    x = R[0]  # image right in the world
    heading = math.degrees(math.atan2(z[0], z[1])) % 360.0
    pitch = math.degrees(math.asin(float(np.clip(-z[2], -1, 1))))
    roll = math.degrees(math.asin(float(np.clip(-x[2], -1, 1))))
    return heading, pitch, roll


def look_point(C: np.ndarray, R: np.ndarray, z_ground: float, max_range: float) -> np.ndarray:
    """Where the optical axis meets the plane z = z_ground (at most ``max_range`` away)."""
    d = np.asarray(R, float)[2]
    s = (z_ground - C[2]) / d[2] if d[2] < -1e-6 else max_range
    return np.asarray(C, float) + min(max(s, 0.0), max_range) * d


def _registered(poses: list[dict]) -> list[dict]:
    return [p for p in poses if p.get("status") == "registered"]


def write_csv(path: str | Path, poses: list[dict], crs_wkt: str) -> None:
    tr = pyproj.Transformer.from_crs(pyproj.CRS.from_user_input(crs_wkt), "EPSG:4326",
                                     always_xy=True)  # fmt: skip
    buf = io.StringIO()
    w = csv.writer(buf, lineterminator="\n")
    w.writerow(["frame", "time_s", "image", "status", "source", "keyframe", "x", "y", "z",
                "heading_deg", "pitch_deg", "roll_deg", "lon", "lat", "inliers"])  # fmt: skip
    for p in poses:
        row: list[Any] = [p.get("frame"), p.get("time_s"), p.get("image"), p["status"],
                          p.get("source", ""), int(bool(p.get("keyframe")))]  # fmt: skip
        if p["status"] == "registered":
            C = p["camera_center_xyz"]
            h, pt, rl = view_angles(np.asarray(p["R_world_to_cam"]))
            lon, lat = tr.transform(C[0], C[1])
            row += [f"{C[0]:.3f}", f"{C[1]:.3f}", f"{C[2]:.3f}", f"{h:.3f}", f"{pt:.3f}",
                    f"{rl:.3f}", f"{lon:.8f}", f"{lat:.8f}", p.get("inliers")]  # fmt: skip
        else:
            row += [""] * 8 + [p.get("inliers", 0)]
        w.writerow(row)
    write_text(path, buf.getvalue())


def write_geojson(path: str | Path, poses: list[dict], crs_wkt: str, z_ground: float,
                  look_every: int = 10) -> None:  # fmt: skip
    """The camera path and look directions in the map CRS."""
    crs = pyproj.CRS.from_user_input(crs_wkt)
    reg = _registered(poses)
    feats: list[dict] = []
    if len(reg) >= 2:
        feats.append({"type": "Feature", "properties": {"kind": "path", "frames": len(reg)},
                      "geometry": {"type": "LineString",
                                   "coordinates": [p["camera_center_xyz"] for p in reg]}})  # fmt: skip
    for i, p in enumerate(reg):
        if i % max(1, look_every) and not p.get("keyframe"):
            continue
        C, R = np.asarray(p["camera_center_xyz"]), np.asarray(p["R_world_to_cam"])
        g = look_point(C, R, z_ground, 5 * max(C[2] - z_ground, 1.0))
        h, pt, rl = view_angles(R)
        props = {"kind": "look", "image": p.get("image"), "frame": p.get("frame"),
                 "keyframe": bool(p.get("keyframe")), "source": p.get("source"),
                 "heading_deg": round(h, 3), "pitch_deg": round(pt, 3), "roll_deg": round(rl, 3)}  # fmt: skip
        feats.append({"type": "Feature", "properties": props,
                      "geometry": {"type": "LineString", "coordinates": [C.tolist(), g.tolist()]}})  # fmt: skip
    write_feature_collection(path, feats, crs)


def write_kml(path: str | Path, poses: list[dict], crs_wkt: str, z_ground: float,
              look_every: int = 10) -> None:  # fmt: skip
    """KML 2.2 in WGS84: the path (absolute altitude) and look directions with camera views."""
    tr = pyproj.Transformer.from_crs(pyproj.CRS.from_user_input(crs_wkt), "EPSG:4326",
                                     always_xy=True)  # fmt: skip
    geod = pyproj.Geod(ellps="WGS84")
    reg = _registered(poses)
    out = ['<?xml version="1.0" encoding="UTF-8"?>', '<kml xmlns="http://www.opengis.net/kml/2.2">',
           "<Document>", "<name>georeg trajectory</name>",
           '<Style id="path"><LineStyle><color>ff00ffff</color><width>3</width></LineStyle></Style>',
           '<Style id="look"><LineStyle><color>ffff00ff</color><width>1</width></LineStyle></Style>']  # fmt: skip
    if len(reg) >= 2:
        xyz = np.array([p["camera_center_xyz"] for p in reg], float)
        lon, lat = tr.transform(xyz[:, 0], xyz[:, 1])
        coords = " ".join(f"{a:.8f},{b:.8f},{c:.2f}" for a, b, c in zip(lon, lat, xyz[:, 2], strict=True))
        out += ["<Placemark><name>camera path</name><styleUrl>#path</styleUrl><LineString>"
                f"<altitudeMode>absolute</altitudeMode><coordinates>{coords}</coordinates>"
                "</LineString></Placemark>"]  # fmt: skip
    for i, p in enumerate(reg):
        if i % max(1, look_every) and not p.get("keyframe"):
            continue
        C, R = np.asarray(p["camera_center_xyz"]), np.asarray(p["R_world_to_cam"])
        g = look_point(C, R, z_ground, 5 * max(C[2] - z_ground, 1.0))
        (lo0, lo1), (la0, la1) = tr.transform([C[0], g[0]], [C[1], g[1]])
        az = geod.inv(lo0, la0, lo1, la1)[0] % 360.0 if np.hypot(*(g - C)[:2]) > 1e-3 else 0.0
        _, pitch, roll = view_angles(R)
        name = escape(str(p.get("image")))
        out += [f"<Placemark><name>{name}</name><styleUrl>#look</styleUrl>"
                f"<Camera><longitude>{lo0:.8f}</longitude><latitude>{la0:.8f}</latitude>"
                f"<altitude>{C[2]:.2f}</altitude><heading>{az:.3f}</heading>"
                f"<tilt>{90.0 - pitch:.3f}</tilt><roll>{-roll:.3f}</roll>"
                "<altitudeMode>absolute</altitudeMode></Camera>"
                "<LineString><altitudeMode>absolute</altitudeMode><coordinates>"
                f"{lo0:.8f},{la0:.8f},{C[2]:.2f} {lo1:.8f},{la1:.8f},{g[2]:.2f}"
                "</coordinates></LineString></Placemark>"]  # fmt: skip
    out += ["</Document>", "</kml>"]
    write_text(path, "\n".join(out) + "\n")


def write_point_map(laz_path: str | Path, xyz: np.ndarray, rgb: np.ndarray, track_len: np.ndarray,
                    descriptors: np.ndarray, crs_wkt: str) -> Path:  # fmt: skip
    """The geo-registered 3-D feature map: LAZ (map CRS) + descriptors beside it (.npy), in the
    format the frames stage reads back (``georeg.frames.feature_map``)."""
    write_feature_map(laz_path, xyz, rgb, descriptors, crs_wkt, track_len)
    return descriptor_path(laz_path)
