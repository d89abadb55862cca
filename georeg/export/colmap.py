"""A COLMAP text model (cameras.txt, images.txt, points3D.txt) of registered views.

COLMAP's conventions: the pose is world-to-camera (quaternion QW QX QY QZ, Hamilton, and
translation); pixel (0.5, 0.5) is the centre of the top-left pixel (OpenCV's (0, 0)), so principal
points and observations are shifted by half a pixel. The world is a local metric frame: the map
CRS minus ``offset`` (rounded near the cameras), times ``unit_m`` for a CRS in feet, written to
``georef.json`` beside the model (map = local / unit_m + offset)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pyproj

from georeg.export.points import Points
from georeg.export.views import View
from georeg.io.atomic import write_json, write_text


def quaternion(R: np.ndarray) -> np.ndarray:
    """(qw, qx, qy, qz), qw >= 0, of a rotation matrix (Shepperd's method)."""
    R = np.asarray(R, float)
    tr = np.trace(R)
    if tr > 0:
        s = 2.0 * np.sqrt(tr + 1.0)
        q = [0.25 * s, (R[2, 1] - R[1, 2]) / s, (R[0, 2] - R[2, 0]) / s, (R[1, 0] - R[0, 1]) / s]
    else:
        i = int(np.argmax(np.diag(R)))
        j, k = (i + 1) % 3, (i + 2) % 3
        s = 2.0 * np.sqrt(max(1.0 + R[i, i] - R[j, j] - R[k, k], 1e-300))
        q = [0.0] * 4
        q[0] = (R[k, j] - R[j, k]) / s
        q[1 + i] = 0.25 * s
        q[1 + j] = (R[j, i] + R[i, j]) / s
        q[1 + k] = (R[k, i] + R[i, k]) / s
    q = np.asarray(q, float)
    q /= np.linalg.norm(q)
    return q if q[0] >= 0 else -q


def camera_model(v: View) -> tuple[str, list[float]]:
    """COLMAP model and parameters of a view (PINHOLE, OPENCV or FULL_OPENCV by its distortion)."""
    d = np.r_[np.asarray(v.dist, float).ravel(), np.zeros(8)][:8]
    base = [v.fx, v.fy, v.cx + 0.5, v.cy + 0.5]
    if not np.any(d):
        return "PINHOLE", base
    if not np.any(d[4:]):
        return "OPENCV", base + d[:4].tolist()
    return "FULL_OPENCV", base + d.tolist()


def local_frame(views: list[View], crs_wkt: str) -> dict:
    """Offset (map CRS, rounded to 100 units near the cameras' mean) and metres per CRS unit."""
    C = np.array([v.C for v in views], float).reshape(-1, 3)
    off = np.round(C.mean(axis=0) / 100.0) * 100.0 if len(C) else np.zeros(3)
    off[2] = 0.0
    crs = pyproj.CRS.from_user_input(crs_wkt)
    unit = crs.axis_info[0].unit_conversion_factor if crs.axis_info else 1.0
    return {"offset_xyz": [float(o) for o in off], "unit_m": float(unit), "crs_wkt": crs.to_wkt(),
            "epsg": crs.to_epsg(),
            "map_from_local": "map_xyz = local_xyz / unit_m + offset_xyz (z: the map's vertical unit x unit_m)",
            "conventions": "COLMAP: world-to-camera quaternion (w, x, y, z) and translation; pixel "
                           "(0.5, 0.5) = centre of the top-left pixel"}  # fmt: skip


def write_model(out_dir: str | Path, views: list[View], pts: Points, crs_wkt: str) -> dict:
    """cameras.txt, images.txt, points3D.txt and georef.json in ``out_dir``; returns georef."""
    out = Path(out_dir)
    geo = local_frame(views, crs_wkt)
    off, unit = np.asarray(geo["offset_xyz"]), geo["unit_m"]
    to_local = lambda X: (np.asarray(X, float) - off) * unit  # noqa: E731
    cams: dict[tuple, int] = {}
    cam_lines, view_cam = [], []
    for v in views:
        model, params = camera_model(v)
        key = (model, v.width, v.height, *np.round(params, 6))
        if key not in cams:
            cams[key] = len(cams) + 1
            cam_lines.append(f"{cams[key]} {model} {v.width} {v.height} " + " ".join(f"{p:.10g}" for p in params))
        view_cam.append(cams[key])
    # observations per image, and per point its (image id, point2D index) track
    per_image: list[list[tuple[float, float, int]]] = [[] for _ in views]
    tracks: list[list[tuple[int, int]]] = []
    for pid, ob in enumerate(pts.obs, start=1):
        tr = []
        for j, u, vv in ob:
            tr.append((j + 1, len(per_image[j])))
            per_image[j].append((u + 0.5, vv + 0.5, pid))
        tracks.append(tr)
    img_lines = []
    for j, v in enumerate(views):
        q = quaternion(v.R)
        t = -v.R @ to_local(v.C)
        img_lines.append(f"{j + 1} " + " ".join(f"{a:.12g}" for a in (*q, *t)) + f" {view_cam[j]} {v.name}")
        img_lines.append(" ".join(f"{u:.4f} {w:.4f} {pid}" for u, w, pid in per_image[j]))
    X = to_local(pts.xyz) if len(pts.xyz) else np.zeros((0, 3))
    pt_lines = []
    for pid, (x, c, tr) in enumerate(zip(X, pts.rgb, tracks, strict=True), start=1):
        err = 0.0  # the observations are the projections through the poses
        pt_lines.append(f"{pid} {x[0]:.6f} {x[1]:.6f} {x[2]:.6f} {int(c[0])} {int(c[1])} {int(c[2])} {err} "
                        + " ".join(f"{i} {k}" for i, k in tr))  # fmt: skip
    n_obs = sum(len(t) for t in tracks)
    write_text(out / "cameras.txt", "# Camera list with one line of data per camera:\n"
               "#   CAMERA_ID, MODEL, WIDTH, HEIGHT, PARAMS[]\n"
               f"# Number of cameras: {len(cam_lines)}\n" + "".join(f"{s}\n" for s in cam_lines))  # fmt: skip
    write_text(out / "images.txt", "# Image list with two lines of data per image:\n"
               "#   IMAGE_ID, QW, QX, QY, QZ, TX, TY, TZ, CAMERA_ID, NAME\n"
               "#   POINTS2D[] as (X, Y, POINT3D_ID)\n"
               f"# Number of images: {len(views)}, mean observations per image: "
               f"{n_obs / max(len(views), 1):.3f}\n" + "".join(f"{s}\n" for s in img_lines))  # fmt: skip
    write_text(out / "points3D.txt", "# 3D point list with one line of data per point:\n"
               "#   POINT3D_ID, X, Y, Z, R, G, B, ERROR, TRACK[] as (IMAGE_ID, POINT2D_IDX)\n"
               f"# Number of points: {len(pt_lines)}, mean track length: "
               f"{n_obs / max(len(pt_lines), 1):.4f}\n" + "".join(f"{s}\n" for s in pt_lines))  # fmt: skip
    write_json(out / "georef.json", geo, indent=1)
    return geo
