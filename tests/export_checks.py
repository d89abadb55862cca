"""Independent checks of the exports (used by test_export*.py): ODM's parsing rules, pycolmap
loading and reprojection, GCP reprojection through poses.json."""

from __future__ import annotations

import json
import re
from pathlib import Path

import cv2
import numpy as np
import pyproj


def parse_odm_crs(line: str) -> pyproj.CRS:
    """ODM's first line (opendm.location.parse_srs_header): ``EPSG:<code>``, ``WGS84 UTM <zone><N|S>``
    or a PROJ string."""
    h = line.strip()
    m = re.match(r"^WGS84 UTM (\d{1,2})([NS])$", h, re.I)
    if m:
        south = m.group(2).upper() == "S"
        return pyproj.CRS.from_proj4(f"+proj=utm +zone={m.group(1)} {'+south ' if south else ''}"
                                     "+datum=WGS84 +units=m +no_defs")  # fmt: skip
    if h.lower().startswith("epsg:"):
        return pyproj.CRS.from_epsg(int(h.split(":")[1]))
    if h.startswith("+"):
        return pyproj.CRS.from_proj4(h)
    raise ValueError(f"not a CRS line ODM reads: {h!r}")


def parse_gcp_list(path: Path) -> tuple[pyproj.CRS, list[dict]]:
    """ODM's gcp_list.txt rules: BOM stripped, first line the CRS, then per non-empty,
    non-comment line at least 6 whitespace-separated fields geo_x geo_y geo_z im_x im_y image
    [gcp_name [extras]]; a shorter line is malformed (an error here)."""
    lines = [s.strip() for s in path.read_text().replace("\ufeff", "").strip().split("\n")]
    crs = parse_odm_crs(lines[0])
    rows = []
    for s in lines[1:]:
        if not s or s.startswith("#"):
            continue
        f = s.split()
        assert len(f) >= 6, f"malformed GCP line: {s!r}"
        rows.append({"xyz": [float(v) for v in f[:3]], "uv": [float(f[3]), float(f[4])],
                     "image": f[5], "name": f[6] if len(f) > 6 else None})  # fmt: skip
    return crs, rows


def parse_geo_txt(path: Path) -> tuple[pyproj.CRS, dict[str, list[float]]]:
    """ODM's geo.txt: CRS line, then ``image x y [z] [yaw pitch roll] [acc_h acc_v] [extras]``."""
    lines = [s.strip() for s in path.read_text().replace("\ufeff", "").strip().split("\n")]
    crs = parse_odm_crs(lines[0])
    out = {}
    for s in lines[1:]:
        if not s or s.startswith("#"):
            continue
        f = s.split()
        assert len(f) >= 3, f"malformed geo line: {s!r}"
        out[f[0]] = [float(v) for v in f[1:7]]
    return crs, out


def check_gcp_list(export_dir: Path, poses: list[dict], min_points: int = 5, min_views: int = 3,
                   tol_px: float = 2.0) -> dict:  # fmt: skip
    """gcp_list.txt parses as ODM's, has >= min_points points each in >= min_views images, and
    every row reprojects within tol_px through its image's pose in poses.json (OpenCV, the raw
    full-size image: an implementation independent of the exporter's)."""
    from georeg.export.views import export_name

    _, rows = parse_gcp_list(export_dir / "gcp_list.txt")
    by_name = {export_name(p["image"]): p for p in poses if p.get("status") == "registered"}
    per_point: dict[str, set] = {}
    errs = []
    for r in rows:
        p = by_name[r["image"]]
        k, s = p["intrinsics"], float((p.get("pyramid") or {}).get("scale") or 1.0)
        K = np.array([[k["fx"] / s, 0, (k["cx"] + 0.5) / s - 0.5], [0, k["fy"] / s, (k["cy"] + 0.5) / s - 0.5],
                      [0, 0, 1]])  # fmt: skip
        R, C = np.asarray(p["R_world_to_cam"]), np.asarray(p["camera_center_xyz"])
        uv, _ = cv2.projectPoints(np.array([r["xyz"]]), cv2.Rodrigues(R)[0], -R @ C, K,
                                  np.asarray(k.get("dist") or [0] * 5, float))  # fmt: skip
        errs.append(float(np.hypot(*(uv.ravel() - r["uv"]))))
        per_point.setdefault(r["name"], set()).add(r["image"])
    good = [n for n, ims in per_point.items() if len(ims) >= min_views]
    assert len(good) >= min_points, f"{len(good)} GCPs in >= {min_views} images"
    assert all(len(ims) >= min_views for ims in per_point.values())
    # the geo coordinates are written to the mm: their rounding is part of the error
    assert max(errs) < tol_px, f"a GCP row reprojects {max(errs):.3f} px off"
    return {"rows": len(rows), "points": len(per_point), "max_err_px": max(errs)}


def check_colmap(model_dir: Path, tol_rms_px: float = 2.0) -> dict:
    """pycolmap loads the model; its points reproject into its images with RMS < tol."""
    import pycolmap

    rec = pycolmap.Reconstruction(str(model_dir))
    assert rec.num_reg_images() > 0
    res = []
    for img in rec.images.values():
        for p2 in img.points2D:
            if p2.has_point3D():
                uv = img.project_point(rec.points3D[p2.point3D_id].xyz)
                res.append(np.asarray(uv) - np.asarray(p2.xy))
    rms = float(np.sqrt(np.mean(np.sum(np.square(res), axis=1)))) if res else 0.0
    assert rms < tol_rms_px, f"COLMAP reprojection RMS {rms:.3f} px"
    geo = json.loads((model_dir / "georef.json").read_text())
    assert len(geo["offset_xyz"]) == 3
    return {"images": rec.num_reg_images(), "points": rec.num_points3D(), "rms_px": rms,
            "observations": len(res)}  # fmt: skip
