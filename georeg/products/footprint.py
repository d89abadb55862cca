"""Footprint of a registered query from its geolocation: GeoJSON (map CRS) and KML (WGS84).

The outline follows the centres of the outermost valid query pixels (OpenCV contour of the valid
mask, simplified by Douglas-Peucker at a quarter of the ground pixel spacing in map units), so a
pushbroom's wavy edges are kept. The polygon therefore lies half a pixel inside the imaged area.

* ``footprint.geojson``: coordinates in the **map CRS** (not RFC 7946 WGS84): a GeoJSON 2008
  ``crs`` member names it (``urn:ogc:def:crs:EPSG::<code>`` when it has one) and the full WKT is in
  ``properties.crs_wkt``. Also ``bbox`` and the four corner pixel centres.
* ``footprint.kml``: KML 2.2 in WGS84 lon/lat (Google Earth), the polygon plus one Placemark per
  corner pixel centre (``line0/sample0``, ``line0/last sample``, ...).
"""

from __future__ import annotations

import os
from typing import Any
from xml.sax.saxutils import escape

import numpy as np
import pyproj

from georeg.io.atomic import write_json, write_text

CORNER_NAMES = ("line0/sample0", "line0/last sample", "last line/last sample", "last line/sample0")


def outline_pixels(valid: np.ndarray) -> np.ndarray:
    """(n, 2) (col, row) of the outer contour of the largest valid region, counter-clockwise."""
    import cv2

    m = np.ascontiguousarray(valid.astype(np.uint8))
    contours, _ = cv2.findContours(m, cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_NONE)
    if not contours:
        return np.empty((0, 2), np.int64)
    c = max(contours, key=cv2.contourArea)[:, 0, :]
    return c.astype(np.int64)


def outline_xy(x: np.ndarray, y: np.ndarray, tol: float | None = None) -> np.ndarray:
    """(n, 2) map x, y ring (closed) of the footprint, simplified to ``tol`` map units."""
    import cv2

    from georeg.products.cube_resample import pixel_spacing

    valid = np.isfinite(x) & np.isfinite(y)
    pix = outline_pixels(valid)
    if len(pix) < 3:
        return np.empty((0, 2))
    xy = np.column_stack([x[pix[:, 1], pix[:, 0]], y[pix[:, 1], pix[:, 0]]])
    tol = 0.25 * pixel_spacing(x, y) if tol is None else tol
    o = xy.mean(axis=0)
    simp = cv2.approxPolyDP((xy - o).astype(np.float32)[:, None, :], float(tol), True)[:, 0, :]
    # approxPolyDP works in float32 relative coordinates: take the exact vertices back
    d = np.linalg.norm((xy - o)[:, None, :] - simp[None, :, :].astype(np.float64), axis=2)
    ring = xy[np.sort(np.argmin(d, axis=0))]
    if _signed_area(ring) < 0:  # exterior ring counter-clockwise (right-hand rule)
        ring = ring[::-1]
    return np.vstack([ring, ring[:1]])


def _signed_area(r: np.ndarray) -> float:
    x, y = r[:, 0], r[:, 1]
    return 0.5 * float(np.sum(x * np.roll(y, -1) - np.roll(x, -1) * y))


def corners_xy(x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """Map x, y of the four corner pixel centres (order of ``CORNER_NAMES``); NaN if invalid."""
    h, w = x.shape
    rc = [(0, 0), (0, w - 1), (h - 1, w - 1), (h - 1, 0)]
    return np.array([[x[r, c], y[r, c]] for r, c in rc], dtype=np.float64)


def _crs_member(crs: pyproj.CRS) -> dict[str, Any]:
    epsg = crs.to_epsg()
    name = f"urn:ogc:def:crs:EPSG::{epsg}" if epsg else crs.name
    return {"type": "name", "properties": {"name": name}}


def footprint_geojson(
    x: np.ndarray, y: np.ndarray, crs_wkt: str, properties: dict[str, Any] | None = None
) -> dict[str, Any]:
    """A FeatureCollection: the footprint polygon (map CRS) with its corners and area."""
    crs = pyproj.CRS.from_wkt(crs_wkt)
    ring = outline_xy(x, y)
    corners = corners_xy(x, y)
    area = abs(_signed_area(ring[:-1])) if len(ring) else 0.0
    props = {
        "crs_wkt": crs_wkt,
        "coordinates": "map CRS (see crs / crs_wkt), not WGS84: this is not RFC 7946 GeoJSON",
        "outline": "centres of the outermost valid query pixels",
        "area_map_units2": round(area, 3),
        "corners": {n: [float(v) for v in c] for n, c in zip(CORNER_NAMES, corners, strict=True)},
        **(properties or {}),
    }
    feat = {
        "type": "Feature",
        "geometry": {"type": "Polygon", "coordinates": [ring.round(4).tolist()]},
        "properties": props,
    }
    bbox = (
        [
            float(ring[:, 0].min()),
            float(ring[:, 1].min()),
            float(ring[:, 0].max()),
            float(ring[:, 1].max()),
        ]
        if len(ring)
        else []
    )
    return {"type": "FeatureCollection", "crs": _crs_member(crs), "bbox": bbox, "features": [feat]}


def footprint_kml(x: np.ndarray, y: np.ndarray, crs_wkt: str, name: str) -> str:
    """KML 2.2 document: footprint polygon and corner placemarks in WGS84 lon/lat."""
    tr = pyproj.Transformer.from_crs(pyproj.CRS.from_wkt(crs_wkt), "EPSG:4326", always_xy=True)
    ring = outline_xy(x, y)
    lon, lat = tr.transform(ring[:, 0], ring[:, 1]) if len(ring) else ([], [])
    coords = " ".join(f"{a:.9f},{b:.9f},0" for a, b in zip(lon, lat, strict=True))
    corners = corners_xy(x, y)
    clon, clat = tr.transform(corners[:, 0], corners[:, 1])
    marks = "".join(
        f"    <Placemark><name>{escape(n)}</name><styleUrl>#corner</styleUrl>"
        f"<Point><coordinates>{a:.9f},{b:.9f},0</coordinates></Point></Placemark>\n"
        for n, a, b in zip(CORNER_NAMES, clon, clat, strict=True)
        if np.isfinite(a) and np.isfinite(b)
    )
    return (
        '<?xml version="1.0" encoding="UTF-8"?>\n'
        '<kml xmlns="http://www.opengis.net/kml/2.2">\n'
        "  <Document>\n"
        f"    <name>{escape(name)} footprint</name>\n"
        '    <Style id="footprint"><LineStyle><color>ff0000ff</color><width>2</width></LineStyle>'
        "<PolyStyle><color>400000ff</color></PolyStyle></Style>\n"
        '    <Style id="corner"><IconStyle><scale>0.6</scale></IconStyle></Style>\n'
        f"    <Placemark><name>{escape(name)}</name><styleUrl>#footprint</styleUrl>\n"
        "      <Polygon><tessellate>1</tessellate><altitudeMode>clampToGround</altitudeMode>"
        f"<outerBoundaryIs><LinearRing><coordinates>{coords}</coordinates></LinearRing>"
        "</outerBoundaryIs></Polygon>\n"
        "    </Placemark>\n"
        f"{marks}"
        "  </Document>\n"
        "</kml>\n"
    )


def write_footprint(
    x: np.ndarray,
    y: np.ndarray,
    crs_wkt: str,
    name: str,
    out_geojson: str | os.PathLike,
    out_kml: str | os.PathLike,
    properties: dict[str, Any] | None = None,
) -> dict[str, Any]:
    """Write both files atomically; returns the GeoJSON feature's properties."""
    gj = footprint_geojson(x, y, crs_wkt, properties)
    write_json(out_geojson, gj, indent=1)
    write_text(out_kml, footprint_kml(x, y, crs_wkt, name))
    return gj["features"][0]["properties"]
