"""Rule export_frames: a registered frame set (poses.json, and the SfM point map of a video or
sequence) -> ``results/frames/{set}/export/``: ODM ``gcp_list.txt`` and ``geo.txt``, a COLMAP
text model in ``colmap/`` (+ ``georef.json``), and ``export.json`` (counts, what ODM needs)."""

from __future__ import annotations

import json
import logging
from pathlib import Path
from typing import Any

import numpy as np

from georeg.export.colmap import write_model
from georeg.export.odm import write_gcp_list, write_geo_txt
from georeg.export.points import (
    map_corners,
    observe,
    read_map_window,
    read_sfm_points,
    spread,
    unoccluded,
)
from georeg.export.views import views_from_poses
from georeg.io.atomic import write_json
from georeg.io.errors import InputError

log = logging.getLogger(__name__)

DEFAULTS: dict[str, Any] = {
    "gcp_points": 20,  # ground control points written to gcp_list.txt (spread over the area)
    "gcp_min_views": 3,  # ODM: each GCP seen in at least 3 images
    "odm_min_gcps": 5,  # ODM: at least 5 GCPs
    "model_points": 5000,  # 3-D points of the COLMAP model (seen in >= 2 images)
    "map_corners": 6000,  # single frames: orthophoto corners tried as points
    "occlusion_clearance_m": 1.0,  # a map point is hidden when the DSM rises this far over its ray
    "max_map_px": 2000,  # map window read at most this many pixels a side
}


def _footprint_bounds(poses: list[dict], views) -> tuple[float, float, float, float]:
    xy = [np.asarray(p["footprint_xy"], float) for p in poses if p.get("status") == "registered"
          and p.get("footprint_xy")]  # fmt: skip
    xy = np.concatenate(xy) if xy else np.array([v.C[:2] for v in views], float)
    return float(xy[:, 0].min()), float(xy[:, 1].min()), float(xy[:, 0].max()), float(xy[:, 1].max())


def export_frame_set(poses_json: str | Path, out_dir: str | Path, crs_wkt: str,
                     ortho: str | Path | None = None, dsm: str | Path | None = None,
                     sfm_laz: str | Path | None = None, ground_z: float = 0.0,
                     conf: dict | None = None) -> dict:  # fmt: skip
    """Write the exports of one frame set; returns the summary written to ``export.json``.

    Points: the set's SfM point map when given (``sfm_laz``), else orthophoto corners with DSM
    heights under the footprints (``ortho`` needed), hidden ones removed."""
    c = {**DEFAULTS, **(conf or {})}
    out = Path(out_dir)
    try:
        poses = json.loads(Path(poses_json).read_text())
    except (OSError, ValueError) as exc:
        raise InputError(poses_json, f"cannot read the poses: {exc}") from exc
    views = views_from_poses(poses, poses_json)
    info: dict[str, Any] = {"frames": len(poses), "registered": len(views)}
    if sfm_laz is not None and Path(sfm_laz).exists():
        xyz, rgb, tl = read_sfm_points(sfm_laz)
        pts = observe(views, xyz, rgb)
        score = pts.n_views() + 1e-3 * tl
        info["points_source"] = f"SfM point map ({Path(sfm_laz).name}, {len(xyz)} points)"
    elif views and ortho is not None:
        win = read_map_window(ortho, dsm, _footprint_bounds(poses, views), ground_z, int(c["max_map_px"]))
        xyz, rgb = map_corners(win, int(c["map_corners"]))
        unit = abs(float(win.transform.a))  # clearance at least one map cell
        pts = observe(views, xyz, rgb, unoccluded(win, max(float(c["occlusion_clearance_m"]), unit)))
        score = pts.n_views() - np.arange(len(xyz)) / max(len(xyz), 1)  # corner strength order
        info["points_source"] = (f"orthophoto corners, z from {'the DSM' if dsm else f'the flat ground {ground_z}'}"
                                 f" ({len(xyz)} corners)")  # fmt: skip
    else:
        pts = observe(views, np.zeros((0, 3)), np.zeros((0, 3)))
        score = np.zeros(0)
        info["points_source"] = "none (no registered frame)" if not views else "none (no map given)"
    nv = pts.n_views()
    g_ok = np.flatnonzero(nv >= int(c["gcp_min_views"]))
    gcps = pts.subset(g_ok[spread(pts.xyz[g_ok], score[g_ok], int(c["gcp_points"]))])
    m_ok = np.flatnonzero(nv >= 2)
    model = pts.subset(m_ok[spread(pts.xyz[m_ok], score[m_ok], int(c["model_points"]))])
    n_lines = write_gcp_list(out / "gcp_list.txt", views, gcps, crs_wkt)
    write_geo_txt(out / "geo.txt", views, crs_wkt)
    geo = write_model(out / "colmap", views, model, crs_wkt)
    odm_ready = len(gcps.xyz) >= int(c["odm_min_gcps"])
    info.update(gcps=len(gcps.xyz), gcp_observations=n_lines, gcp_min_views=int(c["gcp_min_views"]),
                model_points=len(model.xyz), model_observations=int(model.n_views().sum()),
                colmap_offset_xyz=geo["offset_xyz"], odm_ready=bool(odm_ready))  # fmt: skip
    if not odm_ready:
        info["reason"] = (f"only {len(gcps.xyz)} points are seen in >= {c['gcp_min_views']} registered "
                          f"images ({len(views)} registered); ODM needs {c['odm_min_gcps']}")  # fmt: skip
        log.warning("export %s: %s", out, info["reason"])
    write_json(out / "export.json", info)
    log.info("export %s: %d views, %d GCPs (%d lines), %d model points", out, len(views),
             len(gcps.xyz), n_lines, len(model.xyz))  # fmt: skip
    return info
