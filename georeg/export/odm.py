"""OpenDroneMap inputs: ``gcp_list.txt`` (ground control points with their image positions) and
``geo.txt`` (image positions and angles), both headed by the CRS line ODM parses: ``EPSG:<code>``
when the CRS has one, else its PROJ string. Image positions use ODM's pixel convention (x right,
y down, (0, 0) = centre of the top-left pixel, the raw image with its distortion)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pyproj

from georeg.export.points import Points
from georeg.export.views import View
from georeg.io.atomic import write_text
from georeg.trajectory.outputs import view_angles


def crs_line(crs_wkt: str) -> str:
    """``EPSG:<code>`` or the PROJ string of the map CRS (ODM's first line)."""
    crs = pyproj.CRS.from_user_input(crs_wkt)
    epsg = crs.to_epsg()
    if epsg:
        return f"EPSG:{epsg}"
    return crs.to_proj4().replace("+type=crs", "").strip()


def write_gcp_list(path: str | Path, views: list[View], gcps: Points, crs_wkt: str) -> int:
    """One line per observation ``geo_x geo_y geo_z im_x im_y image_name gcp_name``; returns
    the number of lines."""
    lines = [crs_line(crs_wkt)]
    for i, (X, ob) in enumerate(zip(gcps.xyz, gcps.obs, strict=True), start=1):
        for j, u, v in ob:
            lines.append(f"{X[0]:.3f} {X[1]:.3f} {X[2]:.3f} {u:.2f} {v:.2f} {views[j].name} gcp{i:03d}")
    write_text(path, "\n".join(lines) + "\n")
    return len(lines) - 1


def write_geo_txt(path: str | Path, views: list[View], crs_wkt: str) -> None:
    """``image_name x y z yaw pitch roll`` per view: yaw = heading of the optical axis clockwise
    from grid north, pitch = its angle to the horizon (-90 = nadir, as DJI's gimbal pitch), roll =
    the image x axis out of the horizontal (degrees; ODM uses the angles for radiometry only)."""
    lines = [crs_line(crs_wkt)]
    for v in views:
        yaw, pitch, roll = view_angles(np.asarray(v.R))
        lines.append(f"{v.name} {v.C[0]:.3f} {v.C[1]:.3f} {v.C[2]:.3f} {yaw:.3f} {-pitch:.3f} {roll:.3f}")
    write_text(path, "\n".join(lines) + "\n")
