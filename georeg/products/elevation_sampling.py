"""Per-pixel elevation in the query's own geometry (no spectrum is resampled).

For every query pixel, DSM, DTM and nDSM are sampled bilinearly from the map mosaics (VRTs) at the
pixel's map x, y from ``geolocation.tif``, in row blocks (each block reads only the mosaic window
it covers), plus WGS84 longitude / latitude. Query-geometry rasters carry a grid of GCPs
(query pixel -> map x, y, z) so GIS software can place them on the fly.
"""

from __future__ import annotations

import logging
import os
import warnings
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np
import pyproj
import rasterio
from rasterio.control import GroundControlPoint
from rasterio.crs import CRS

from georeg.io.atomic import atomic_path
from georeg.io.raster import tiled_profile
from georeg.register.geolocation import sample_raster

log = logging.getLogger(__name__)

ELEVATION_BANDS = ("dsm", "dtm", "ndsm", "lon", "lat")
ELEVATION_DESCRIPTIONS = (
    "dsm (m, map vertical datum)",
    "dtm (m, map vertical datum)",
    "ndsm (m, height above ground)",
    "lon (deg, WGS84)",
    "lat (deg, WGS84)",
)


def gcps_from_geolocation(
    x: np.ndarray, y: np.ndarray, z: np.ndarray | None = None, n: int = 8
) -> list[GroundControlPoint]:
    """An ``n`` x ``n`` grid of GCPs (pixel centre -> map x, y, z) over the valid pixels."""
    h, w = x.shape
    out = []
    for r in np.unique(np.linspace(0, h - 1, n).round().astype(int)):
        for c in np.unique(np.linspace(0, w - 1, n).round().astype(int)):
            if np.isfinite(x[r, c]) and np.isfinite(y[r, c]):
                zz = float(z[r, c]) if z is not None and np.isfinite(z[r, c]) else 0.0
                out.append(
                    GroundControlPoint(
                        row=r + 0.5,
                        col=c + 0.5,
                        x=float(x[r, c]),
                        y=float(y[r, c]),
                        z=zz,
                        id=f"r{r}c{c}",
                    )  # fmt: skip
                )
    return out


def open_query_raster(
    path: str | os.PathLike,
    width: int,
    height: int,
    count: int,
    dtype: str,
    nodata: float | None,
    descriptions: Sequence[str],
    gcps: list[GroundControlPoint] | None,
    crs_wkt: str | None,
):
    """Open a query-geometry GeoTIFF for writing (caller writes windows, then closes)."""
    ds = rasterio.open(path, "w", **tiled_profile(width, height, count, dtype, nodata))
    for i, d in enumerate(descriptions, start=1):
        ds.set_band_description(i, d)
    if gcps and crs_wkt:
        ds.gcps = (gcps, CRS.from_wkt(crs_wkt))
    return ds


def sample_elevation(
    geolocation: str | os.PathLike,
    mosaics: dict[str, str | os.PathLike],
    crs_wkt: str,
    out_path: str | os.PathLike,
    block_rows: int = 256,
) -> dict[str, Any]:
    """Write ``elevation.tif`` (5 bands float64: dsm, dtm, ndsm, lon, lat) in query geometry.

    ``mosaics`` maps ``dsm``, ``dtm`` and (optionally) ``ndsm`` to rasters in the map CRS; without
    an nDSM mosaic nDSM = DSM - DTM. NaN where the geolocation or the mosaics have no value.
    """
    from georeg.products.cube_resample import read_geolocation

    x, y, z = read_geolocation(geolocation)
    h, w = x.shape
    to_ll = pyproj.Transformer.from_crs(
        pyproj.CRS.from_wkt(crs_wkt), pyproj.CRS.from_epsg(4326), always_xy=True
    )
    stats = {k: [0, 0.0, np.inf, -np.inf] for k in ("dsm", "dtm", "ndsm")}
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", rasterio.errors.NotGeoreferencedWarning)
        with atomic_path(out_path) as tmp:
            with open_query_raster(
                tmp, w, h, 5, "float64", float("nan"), ELEVATION_DESCRIPTIONS,
                gcps_from_geolocation(x, y, z), crs_wkt,
            ) as dst:  # fmt: skip
                for r0 in range(0, h, block_rows):
                    r1 = min(h, r0 + block_rows)
                    bx, by = x[r0:r1], y[r0:r1]
                    layers = {}
                    for k in ("dsm", "dtm"):
                        layers[k] = sample_raster(mosaics[k], bx, by).astype(np.float64)
                    if mosaics.get("ndsm") and Path(mosaics["ndsm"]).exists():
                        layers["ndsm"] = sample_raster(mosaics["ndsm"], bx, by).astype(np.float64)
                    else:
                        layers["ndsm"] = layers["dsm"] - layers["dtm"]
                    ok = np.isfinite(bx) & np.isfinite(by)
                    lon = np.full(bx.shape, np.nan)
                    lat = np.full(bx.shape, np.nan)
                    lon[ok], lat[ok] = to_ll.transform(bx[ok], by[ok])
                    block = np.stack([layers["dsm"], layers["dtm"], layers["ndsm"], lon, lat])
                    dst.write(block, window=((r0, r1), (0, w)))
                    for k in stats:
                        v = layers[k][np.isfinite(layers[k])]
                        if v.size:
                            s = stats[k]
                            s[0] += v.size
                            s[1] += float(v.sum())
                            s[2] = min(s[2], float(v.min()))
                            s[3] = max(s[3], float(v.max()))
                dst.update_tags(
                    CONTENT="elevation per query pixel (query geometry), sampled bilinearly from "
                    "the map mosaics through geolocation.tif",
                    BANDS=",".join(ELEVATION_BANDS),
                    MAP_CRS_WKT=crs_wkt,
                )
    n = h * w
    return {
        k: {
            "valid_fraction": s[0] / n if n else 0.0,
            "mean": s[1] / s[0] if s[0] else None,
            "min": s[2] if s[0] else None,
            "max": s[3] if s[0] else None,
        }
        for k, s in stats.items()
    }


def read_elevation_band(path: str | os.PathLike, name: str) -> np.ndarray:
    """One band of ``elevation.tif`` by name (``dsm``, ``dtm``, ``ndsm``, ``lon``, ``lat``)."""
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", rasterio.errors.NotGeoreferencedWarning)
        with rasterio.open(path) as ds:
            return ds.read(ELEVATION_BANDS.index(name) + 1)
