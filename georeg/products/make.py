"""Spectral-elevation products of a registered query: the rule bodies.

Two steps, so that changing the segmentation never recomputes the (heavy) geo-referenced cube:

* :func:`make_cube` -> ``cube.tif`` (COG) + ``cube.hdr``/``cube.bsq`` (ENVI) on the product grid,
  manifest ``cube.json``.
* :func:`make_products` -> ``elevation.tif``, ``fused.tif``, ``segmentation.tif`` (query
  geometry), ``segmentation_geo.tif`` (product grid), ``segmentation_legend.png``,
  ``class_areas.csv``, ``footprint.geojson``, ``footprint.kml``, ``points_spectra.laz``,
  manifest ``products.json``.

Both are driven by ``geolocation.tif`` only (never the homography). A ``not_found`` query gets a
manifest with ``status: not_found`` and no other file: the manifests are the only declared
outputs (Snakemake targets); each product is written atomically before its manifest, and the
manifest lists every file it vouches for.
"""

from __future__ import annotations

import functools
import json
import logging
import os
import time
import warnings
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import rasterio

from georeg.io.atomic import atomic_path, write_json
from georeg.io.errors import InputError
from georeg.io.query import Cube, open_query
from georeg.products import segmentation as seg
from georeg.products.cube_resample import (
    GDAL_CACHE_MB,
    InverseGeolocation,
    ProductGrid,
    band_labels,
    band_tags,
    inverse_maps,
    nearest_index,
    product_grid,
    read_geolocation,
    resample_cube,
)
from georeg.products.elevation_sampling import (
    gcps_from_geolocation,
    open_query_raster,
    read_elevation_band,
    sample_elevation,
)
from georeg.products.footprint import write_footprint
from georeg.products.pointcloud_fusion import fuse_points

log = logging.getLogger(__name__)

DEFAULTS: dict[str, Any] = {
    "grid": "query_gsd",
    "gsd_m": None,
    "resampling": "nearest",
    "chunk_bands": 16,
    "inverse_step_px": 8,
    "envi_copy": True,
    "fused": True,
    "reflectance_scale": None,
    "points": {"enabled": True, "bands": "all", "chunk_points": 100000},
    "segmentation": dict(seg.DEFAULTS),
}


def _in_gdal_env(fn: Callable) -> Callable:
    """Run ``fn`` inside a rasterio.Env with the products' GDAL cache bound."""

    @functools.wraps(fn)
    def wrapped(*args: Any, **kwargs: Any) -> Any:
        with rasterio.Env(**({} if GDAL_CACHE_MB is None else {"GDAL_CACHEMAX": GDAL_CACHE_MB})):
            return fn(*args, **kwargs)

    return wrapped


def merged_conf(conf: dict[str, Any] | None) -> dict[str, Any]:
    """``products`` config over the defaults (one level deep for points / segmentation)."""
    c = {**DEFAULTS, **(conf or {})}
    c["points"] = {**DEFAULTS["points"], **((conf or {}).get("points") or {})}
    c["segmentation"] = {**DEFAULTS["segmentation"], **((conf or {}).get("segmentation") or {})}
    return c


def read_registration(path: str | os.PathLike) -> dict[str, Any]:
    try:
        return json.loads(Path(path).read_text())
    except (OSError, json.JSONDecodeError) as exc:
        raise InputError(path, f"cannot read the registration: {exc}") from exc


def _not_found(reg: dict[str, Any], name: str, out_manifest: str | os.PathLike, what: str) -> dict:
    m = {
        "query": name,
        "status": reg.get("status", "not_found"),
        "reason": reg.get("reason", "the query was not registered"),
        "note": f"no {what}: products exist only for registered queries",
        "files": {},
    }
    write_json(out_manifest, m)
    log.info("query %s not registered: %s written without products", name, out_manifest)
    return m


def _rel(path: str | os.PathLike, base: Path) -> str:
    return os.path.relpath(Path(path), base)


def _inverse(x: np.ndarray, y: np.ndarray, c: dict[str, Any]) -> InverseGeolocation:
    return InverseGeolocation.build(x, y, step=int(c["inverse_step_px"]))


@_in_gdal_env
def make_cube(
    registration: str | os.PathLike,
    geolocation: str | os.PathLike,
    image: str | os.PathLike,
    out_manifest: str | os.PathLike,
    conf: dict[str, Any] | None = None,
    map_raster: str | os.PathLike | None = None,
    name: str = "query",
    threads: int = 1,
) -> dict[str, Any]:
    """Geo-referenced cube (COG + ENVI) on the product grid, and its manifest ``cube.json``."""
    c = merged_conf(conf)
    reg = read_registration(registration)
    if reg.get("status") != "registered":
        return _not_found(reg, name, out_manifest, "geo-referenced cube")
    out_dir = Path(out_manifest).parent
    t0 = time.perf_counter()
    x, y, _ = read_geolocation(geolocation)
    if not (np.isfinite(x) & np.isfinite(y)).any():
        return _not_found({"reason": "geolocation is all NaN"}, name, out_manifest, "cube")
    crs = reg["crs"]
    grid = product_grid(x, y, crs, c["grid"], c["gsd_m"], map_raster)
    inv = _inverse(x, y, c)
    col, row = inverse_maps(inv, grid)
    t_inv = time.perf_counter() - t0
    cube = open_query(image)
    files = {"cube_cog": out_dir / "cube.tif"}
    if c["envi_copy"]:
        files["cube_envi_header"] = out_dir / "cube.hdr"
        files["cube_envi_data"] = out_dir / "cube.bsq"
    info = resample_cube(
        cube,
        col,
        row,
        grid,
        files["cube_cog"],
        files.get("cube_envi_header"),
        c["resampling"],
        int(c["chunk_bands"]),
        threads,
    )
    m = {
        "query": name,
        "status": "registered",
        "crs": crs,
        "grid": {"mode": c["grid"], **grid.to_json()},
        "cube": {**info, "bands": cube.count, "source": str(image)},
        "inverse": {"step_px": int(c["inverse_step_px"]), "query_gsd": inv.gsd},
        "files": {k: _rel(v, out_dir) for k, v in files.items()},
        "timings_s": {
            "inverse": round(t_inv, 2),
            "resample": info["seconds_total"],
            "total": round(time.perf_counter() - t0, 2),
        },
    }
    write_json(out_manifest, m)
    return m


def write_fused(
    path: str | os.PathLike,
    cube: Cube,
    elevation: str | os.PathLike,
    gcps: list,
    crs_wkt: str,
    chunk_bands: int = 16,
) -> None:
    """``fused.tif``: the cube's bands (float32, NaN = nodata) + dsm, dtm, ndsm, query geometry."""
    from georeg.products.cube_resample import read_band_chunk

    n = cube.count
    descs = band_labels(cube) + ["dsm (m)", "dtm (m)", "ndsm (m, height above ground)"]
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", rasterio.errors.NotGeoreferencedWarning)
        with atomic_path(path) as tmp:
            with open_query_raster(
                tmp, cube.width, cube.height, n + 3, "float32", float("nan"), descs, gcps, crs_wkt
            ) as dst:
                for b0 in range(0, n, chunk_bands):
                    b1 = min(n, b0 + chunk_bands)
                    a = read_band_chunk(cube, b0, b1).astype(np.float32)
                    if cube.nodata is not None:
                        a[a == cube.nodata] = np.nan
                    dst.write(a, indexes=list(range(b0 + 1, b1 + 1)))
                    del a
                for j, k in enumerate(("dsm", "dtm", "ndsm")):
                    dst.write(read_elevation_band(elevation, k).astype(np.float32), n + 1 + j)
                for i in range(n):
                    t = band_tags(cube, i)
                    if t:
                        dst.update_tags(i + 1, **t)
                for j in range(3):
                    dst.update_tags(n + 1 + j, units="m")
                dst.update_tags(
                    CONTENT="spectra (bands 1..N, cube units) + elevation (last 3 bands, m) per "
                    "query pixel; query geometry with GCPs to the map CRS",
                    SPECTRAL_BANDS=str(n),
                )


SEGMENTATION_FILES = ("segmentation", "segmentation_geo", "segmentation_legend", "class_areas")


def _segmentation(
    cube: Cube,
    c: dict[str, Any],
    x: np.ndarray,
    y: np.ndarray,
    f: dict[str, Path],
    gcps: list,
    crs: str,
    grid: ProductGrid,
    inv: InverseGeolocation,
    labels: str | os.PathLike | None,
) -> dict[str, Any]:
    """SWIR indices + nDSM classes in query geometry and on the product grid; legend and areas."""
    sc = c["segmentation"]
    ind = seg.spectral_indices(cube, c["reflectance_scale"], int(sc.get("smooth_px", 1)))
    ndsm = read_elevation_band(f["elevation"], "ndsm")
    ind["valid"] &= np.isfinite(x) & np.isfinite(y)
    classes = seg.classify(ind, ndsm, sc)
    del ind
    seg.write_classes_query(f["segmentation"], classes, gcps, crs)
    col, row = inverse_maps(inv, grid)
    idx = nearest_index(col, row, cube.width)
    del col, row
    geo = np.zeros((grid.height, grid.width), np.uint8)
    geo[idx >= 0] = classes.ravel()[idx[idx >= 0]]
    del idx
    seg.write_classes_geo(f["segmentation_geo"], geo, crs, grid.transform)
    del geo
    import pyproj

    unit = pyproj.CRS.from_wkt(crs).axis_info[0].unit_conversion_factor
    rows = seg.class_areas(classes, seg.pixel_areas(x, y, unit))
    seg.write_class_areas(f["class_areas"], rows)
    seg.write_legend(f["segmentation_legend"], rows)
    out = {
        "thresholds": sc,
        "windows_nm": seg.WINDOWS_NM,
        "classes": {k: v["label"] for k, v in seg.CLASSES.items()},
        "class_areas": rows,
    }
    if labels and Path(labels).exists():
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", rasterio.errors.NotGeoreferencedWarning)
            with rasterio.open(labels) as ds:
                lab = ds.read(1)
        lut = np.zeros(256, np.uint8)
        for k, v in seg.DEMO_TO_SEG.items():
            lut[k] = v
        out["accuracy"] = seg.accuracy(classes, lut[lab])
    return out


@_in_gdal_env
def make_products(
    registration: str | os.PathLike,
    geolocation: str | os.PathLike,
    image: str | os.PathLike,
    map_raster: str | os.PathLike | None,
    mosaics: dict[str, str | os.PathLike],
    point_tiles: list[str | os.PathLike],
    out_manifest: str | os.PathLike,
    conf: dict[str, Any] | None = None,
    grid_json: str | os.PathLike | None = None,
    name: str = "query",
    labels: str | os.PathLike | None = None,
    map_heights: bool = True,
) -> dict[str, Any]:
    """Elevation, fused product, segmentation, footprint and point cloud; manifest products.json.

    ``map_raster``: the map mosaic whose lattice the product grid follows with ``grid: map``; the
    grid is the cube's (``product_grid`` of the same geolocation and keys), so this runs beside
    ``make_cube`` rather than after it.
    ``labels``: optional truth class raster in query geometry (demo class codes, see
    ``segmentation.DEMO_TO_SEG``) to score the segmentation; the scores go into the manifest.
    ``map_heights``: False for an orthophoto-only map. Without heights under the footprint the
    height bands of ``elevation.tif`` and ``fused.tif`` are nodata, ``points_spectra.laz`` and the
    segmentation are skipped; a product the cube cannot make (e.g. no band near a segmentation
    window) is skipped too. ``skipped`` in the manifest says which and why.
    """
    c = merged_conf(conf)
    reg = read_registration(registration)
    if reg.get("status") != "registered":
        return _not_found(reg, name, out_manifest, "products")
    out_dir = Path(out_manifest).parent
    timings: dict[str, float] = {}
    t = time.perf_counter()
    crs = reg["crs"]
    x, y, z = read_geolocation(geolocation)
    gcps = gcps_from_geolocation(x, y, z)
    cube = open_query(image)
    if (cube.height, cube.width) != x.shape:
        raise InputError(
            geolocation,
            f"geolocation is {x.shape[1]} x {x.shape[0]} px but the query is "
            f"{cube.width} x {cube.height}",
        )
    f = {
        k: out_dir / v
        for k, v in {
            "elevation": "elevation.tif",
            "fused": "fused.tif",
            "segmentation": "segmentation.tif",
            "segmentation_geo": "segmentation_geo.tif",
            "segmentation_legend": "segmentation_legend.png",
            "class_areas": "class_areas.csv",
            "footprint_geojson": "footprint.geojson",
            "footprint_kml": "footprint.kml",
            "points_spectra": "points_spectra.laz",
        }.items()
    }
    if not c["fused"]:
        f.pop("fused")
    if not c["points"]["enabled"]:
        f.pop("points_spectra")
    m: dict[str, Any] = {"query": name, "status": "registered", "crs": crs}
    skipped: dict[str, str] = {}

    elev = sample_elevation(geolocation, mosaics, crs, f["elevation"])
    m["elevation"] = elev
    no_heights = None
    if not map_heights:
        no_heights = "the map has no elevation (neither map.lidar nor map.dem)"
    elif not elev["dsm"]["valid_fraction"]:
        no_heights = "the map has no elevation under the query's footprint"
    m["heights"] = {"available": no_heights is None, "reason": no_heights}
    if no_heights:
        log.warning("%s: %s: height bands are nodata", name, no_heights)
        skipped["elevation heights"] = f"dsm/dtm/ndsm bands nodata (lon/lat kept): {no_heights}"
        if c["fused"]:
            skipped["fused heights"] = f"the 3 height bands are nodata: {no_heights}"
    timings["elevation"] = time.perf_counter() - t

    t = time.perf_counter()
    if c["fused"]:
        write_fused(f["fused"], cube, f["elevation"], gcps, crs, int(c["chunk_bands"]))
    timings["fused"] = time.perf_counter() - t

    t = time.perf_counter()
    inv = _inverse(x, y, c)
    if no_heights:
        skipped["segmentation"] = f"its height classes need the nDSM: {no_heights}"
    else:
        try:  # the cube must have a band in every spectral window of the indices
            seg.window_bands(cube.wavelengths_nm)
        except InputError as exc:
            skipped["segmentation"] = str(exc)
    if "segmentation" not in skipped:
        grid = product_grid(x, y, crs, c["grid"], c["gsd_m"], map_raster)
        m["segmentation"] = _segmentation(cube, c, x, y, f, gcps, crs, grid, inv, labels)
    if "segmentation" in skipped:
        for k in SEGMENTATION_FILES:
            f.pop(k)
        log.warning("%s: segmentation skipped: %s", name, skipped["segmentation"])
    timings["segmentation"] = time.perf_counter() - t

    t = time.perf_counter()
    m["footprint"] = write_footprint(
        x, y, crs, name, f["footprint_geojson"], f["footprint_kml"], {"query": name}
    )
    timings["footprint"] = time.perf_counter() - t

    if c["points"]["enabled"] and not map_heights:
        skipped["points_spectra"] = "the map has no point cloud (neither map.lidar nor map.dem)"
        f.pop("points_spectra")
    elif c["points"]["enabled"]:
        t = time.perf_counter()
        m["points"] = fuse_points(
            list(point_tiles),
            inv,
            cube,
            f["points_spectra"],
            c["points"]["bands"],
            grid_json,
            int(c["points"]["chunk_points"]),
        )
        timings["points"] = time.perf_counter() - t
    m["skipped"] = skipped
    m["files"] = {k: _rel(v, out_dir) for k, v in f.items()}
    m["timings_s"] = {k: round(v, 2) for k, v in timings.items()}
    write_json(out_manifest, m)
    return m
