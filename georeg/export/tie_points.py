"""Rule export_tie_points: the tie points of a SWIR registration's refinement (registration.json
``refine.points``) as a GeoPackage point table beside the footprint GeoJSON / KML.

Per tie point: the query pixel (col, row), where the final registration puts it (map x, y from
geolocation.tif, bilinear; z from the DSM as there), the measured residual shift against the final
mapping and against the global one (query px and map units), the correlation score and whether it
was accepted. A query without refinement tie points gets an empty table (and says why)."""

from __future__ import annotations

import json
from pathlib import Path

import cv2
import numpy as np

from georeg.export.gpkg import write_points
from georeg.io.errors import InputError

TABLE = "tie_points"


def _sample(a: np.ndarray, col: np.ndarray, row: np.ndarray) -> np.ndarray:
    """Bilinear sample of a float raster at pixel centres (col, row); NaN outside or next to NaN."""
    m = cv2.remap(a.astype(np.float32), col.astype(np.float32)[None], row.astype(np.float32)[None],
                  cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT, borderValue=np.nan)  # fmt: skip
    return m[0].astype(float)


def export_tie_points(registration_json: str | Path, geolocation_tif: str | Path,
                      out_gpkg: str | Path, crs_wkt: str | None = None) -> dict:  # fmt: skip
    """Write the table; returns {"tie_points": n, "reason": ...}."""
    import rasterio

    try:
        reg = json.loads(Path(registration_json).read_text())
    except (OSError, ValueError) as exc:
        raise InputError(registration_json, f"cannot read the registration: {exc}") from exc
    crs = crs_wkt or reg.get("crs")
    if not crs:
        raise InputError(registration_json, "the registration has no CRS")
    pts = (reg.get("refine") or {}).get("points")
    if not pts or not pts.get("col"):
        why = (reg.get("refine") or {}).get("reason") or "no refinement tie points"
        write_points(out_gpkg, TABLE, np.zeros((0, 3)), _columns(0), crs, f"none: {why}")
        return {"tie_points": 0, "reason": why}
    col, row = np.asarray(pts["col"], float), np.asarray(pts["row"], float)
    try:
        with rasterio.open(geolocation_tif) as ds:
            x, y, z = (ds.read(i) for i in (1, 2, 3))
    except rasterio.errors.RasterioIOError as exc:
        raise InputError(geolocation_tif, f"cannot read the geolocation raster: {exc}") from exc
    xyz = np.c_[_sample(x, col, row), _sample(y, col, row), _sample(z, col, row)]
    after = np.asarray(pts["after"], float).reshape(-1, 2)
    before = np.asarray(pts["before"], float).reshape(-1, 2)
    qpx = float((reg.get("refine") or {}).get("query_px_m") or np.nan)
    cols = _columns(len(col))
    cols.update(query_col=col, query_row=row, map_x=xyz[:, 0], map_y=xyz[:, 1], map_z=xyz[:, 2],
                residual_px=np.hypot(*after.T), residual_before_px=np.hypot(*before.T),
                residual_m=np.hypot(*after.T) * qpx, shift_col_px=after[:, 0], shift_row_px=after[:, 1],
                score=np.array([np.nan if s is None else s for s in pts["score"]], float),
                accepted=np.asarray(pts["accepted"], bool),
                accepted_after=np.asarray(pts["accepted_after"], bool))  # fmt: skip
    desc = (f"refinement tie points of {reg.get('query') or Path(registration_json).parent.name}: "
            f"model {reg['refine'].get('model')}; residual = measured shift against the final mapping")  # fmt: skip
    write_points(out_gpkg, TABLE, xyz, cols, crs, desc)
    return {"tie_points": int(len(col))}


def _columns(n: int) -> dict[str, np.ndarray]:
    f = lambda: np.full(n, np.nan)  # noqa: E731
    return {"query_col": f(), "query_row": f(), "map_x": f(), "map_y": f(), "map_z": f(),
            "residual_px": f(), "residual_before_px": f(), "residual_m": f(), "shift_col_px": f(),
            "shift_row_px": f(), "score": f(), "accepted": np.zeros(n, bool),
            "accepted_after": np.zeros(n, bool)}  # fmt: skip
