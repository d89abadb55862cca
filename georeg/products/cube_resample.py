"""Geo-referenced cube: every band of the query resampled onto a north-up grid in the map CRS.

Driven by ``geolocation.tif`` (map x, y of every query pixel centre), never by the homography, so
a later per-pixel refinement of the geometry needs no change here.

* :class:`InverseGeolocation` inverts the per-pixel forward map (col, row) -> (x, y): a coarse
  inverse grid (local first-order inverse from a decimated set of pixel centres) gives a first
  guess, then Newton steps on the bilinear interpolant of the forward map make it exact.
  It serves the output raster (``inverse_maps``) and arbitrary points (LiDAR, map locations).
* :func:`resample_cube` streams the cube in band chunks: one chunk of query bands and one chunk
  of output bands in memory at a time (never the whole cube, let alone twice), writes a tiled
  GeoTIFF and an ENVI BSQ copy (sequential writes), then converts the GeoTIFF to a COG.
"""

from __future__ import annotations

import contextlib
import logging
import math
import os
import time
import warnings
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import rasterio
import rasterio.shutil
from rasterio.crs import CRS
from rasterio.transform import Affine

from georeg.io.atomic import atomic_path
from georeg.io.errors import InputError
from georeg.io.query import Cube, EnviCube, RasterCube
from georeg.io.raster import DEFLATE_LEVEL, tiled_profile

log = logging.getLogger(__name__)

#: GDAL block cache while writing products (MB); None = GDAL's default (5 % of the RAM). Every
#: product raster is band interleaved and written band chunk by band chunk, so a small cache costs
#: no time: rule `products` on the paper's cube 0.80 -> 0.78 GB peak, 51 -> 35 s (one run each,
#: loaded machine; docs/BENCHMARKS.md "Products").
GDAL_CACHE_MB: int | None = 128
#: GDAL block cache of the band-interleaved COG copy (MB): it streams band by band, so a small
#: cache costs no time (docs/SCALING.md "Products memory")
COG_CACHE_MB: int = 128

ENVI_TYPE_CODES = {"uint8": 1, "int16": 2, "int32": 3, "float32": 4, "float64": 5, "uint16": 12}


# ----------------------------------------------------------------------------- geolocation


def read_geolocation(path: str | os.PathLike) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Map x, y, z (float64, (rows, cols)) of every query pixel centre from ``geolocation.tif``."""
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", rasterio.errors.NotGeoreferencedWarning)
            with rasterio.open(path) as ds:
                if ds.count < 2:
                    raise InputError(path, f"geolocation raster has {ds.count} band(s), need x, y")
                x = ds.read(1).astype(np.float64)
                y = ds.read(2).astype(np.float64)
                z = ds.read(3).astype(np.float64) if ds.count >= 3 else np.full_like(x, np.nan)
    except rasterio.errors.RasterioIOError as exc:
        raise InputError(path, f"cannot read the geolocation raster: {exc}") from exc
    return x, y, z


def pixel_spacing(x: np.ndarray, y: np.ndarray) -> float:
    """Median ground distance between neighbouring pixel centres (map units), NaN-robust."""
    d = np.concatenate(
        [
            np.hypot(np.diff(x, axis=1), np.diff(y, axis=1)).ravel(),
            np.hypot(np.diff(x, axis=0), np.diff(y, axis=0)).ravel(),
        ]
    )
    d = d[np.isfinite(d) & (d > 0)]
    if d.size == 0:
        raise InputError(None, "geolocation has no two neighbouring valid pixels")
    return float(np.median(d))


def _bilinear_with_grad(
    a: np.ndarray, c: np.ndarray, r: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Bilinear value and partial derivatives (d/dcol, d/drow) of ``a`` at (c, r).

    The cell is clamped to the array, and the interpolant extrapolates linearly beyond it (so a
    point half a pixel outside the outer pixel centres still inverts). NaN where a corner is NaN.
    """
    h, w = a.shape
    c0 = np.clip(np.floor(c), 0, max(w - 2, 0)).astype(np.int64)
    r0 = np.clip(np.floor(r), 0, max(h - 2, 0)).astype(np.int64)
    c1 = np.minimum(c0 + 1, w - 1)
    r1 = np.minimum(r0 + 1, h - 1)
    fc, fr = c - c0, r - r0
    v00, v01, v10, v11 = a[r0, c0], a[r0, c1], a[r1, c0], a[r1, c1]
    top = v00 + (v01 - v00) * fc
    bot = v10 + (v11 - v10) * fc
    val = top + (bot - top) * fr
    dc = (v01 - v00) * (1 - fr) + (v11 - v10) * fr
    dr = bot - top
    return val, dc, dr


@dataclass
class InverseGeolocation:
    """Inverse of the per-pixel geolocation: map (x, y) -> query (col, row) at pixel centres."""

    xr: np.ndarray  # (rows, cols) map x - x0 (float64, NaN where unknown)
    yr: np.ndarray  # (rows, cols) map y - y0
    x0: float
    y0: float
    gsd: float  # median pixel spacing (map units)
    node_x0: float  # coarse inverse grid: first node (relative coordinates) and spacing
    node_y0: float
    node_step: float
    node_col: np.ndarray  # (ny, nx) query col at each node (nearest-filled outside the footprint)
    node_row: np.ndarray

    @classmethod
    def build(cls, x: np.ndarray, y: np.ndarray, step: int = 8) -> InverseGeolocation:
        """Build from the geolocation arrays; ``step`` = decimation of the forward samples (px).

        Coarse inverse grid (nodes every ``step`` ground pixels): each node takes the nearest
        decimated pixel centre (k-d tree) and moves from it by the local inverse Jacobian, a
        first-order local inverse good to a fraction of a pixel on a smooth geolocation; the
        Newton steps of ``__call__`` then make it exact. (A Delaunay ``griddata`` on the regular
        decimated lattice is degenerate for Qhull and can take seconds to minutes.)
        """
        from scipy.spatial import cKDTree

        valid = np.isfinite(x) & np.isfinite(y)
        if valid.sum() < 4:
            raise InputError(None, "geolocation has fewer than 4 valid pixels: nothing to resample")
        x0, y0 = float(np.mean(x[valid])), float(np.mean(y[valid]))
        xr, yr = x - x0, y - y0
        gsd = pixel_spacing(x, y)
        h, w = x.shape
        rows = np.unique(np.r_[np.arange(0, h, step), h - 1])
        cols = np.unique(np.r_[np.arange(0, w, step), w - 1])
        rr, cc = np.meshgrid(rows, cols, indexing="ij")
        rr, cc = rr.ravel(), cc.ravel()
        # local Jacobian d(x, y)/d(col, row) at the samples, one-sided at the edges
        cp, cm = np.minimum(cc + 1, w - 1), np.maximum(cc - 1, 0)
        rp, rm = np.minimum(rr + 1, h - 1), np.maximum(rr - 1, 0)
        xc = (xr[rr, cp] - xr[rr, cm]) / np.maximum(cp - cm, 1)
        yc = (yr[rr, cp] - yr[rr, cm]) / np.maximum(cp - cm, 1)
        xw = (xr[rp, cc] - xr[rm, cc]) / np.maximum(rp - rm, 1)
        yw = (yr[rp, cc] - yr[rm, cc]) / np.maximum(rp - rm, 1)
        det = xc * yw - xw * yc
        ok = valid[rr, cc] & np.isfinite(det) & (np.abs(det) > 1e-12 * gsd * gsd)
        if ok.sum() < 1:
            raise InputError(None, "geolocation has no usable pixel neighbourhood to invert")
        sx, sy = xr[rr, cc][ok], yr[rr, cc][ok]
        sc, sr = cc[ok].astype(np.float64), rr[ok].astype(np.float64)
        ixc, ixw = yw[ok] / det[ok], -xw[ok] / det[ok]  # inverse Jacobian rows
        iyc, iyw = -yc[ok] / det[ok], xc[ok] / det[ok]
        node_step = step * gsd
        lo = np.array([sx.min(), sy.min()]) - node_step
        hi = np.array([sx.max(), sy.max()]) + node_step
        nx = int(np.ceil((hi[0] - lo[0]) / node_step)) + 1
        ny = int(np.ceil((hi[1] - lo[1]) / node_step)) + 1
        GX, GY = np.meshgrid(lo[0] + node_step * np.arange(nx), lo[1] + node_step * np.arange(ny))
        _, k = cKDTree(np.column_stack([sx, sy])).query(np.column_stack([GX.ravel(), GY.ravel()]))
        dx, dy = GX.ravel() - sx[k], GY.ravel() - sy[k]
        node_col = sc[k] + ixc[k] * dx + ixw[k] * dy
        node_row = sr[k] + iyc[k] * dx + iyw[k] * dy
        return cls(
            xr=xr,
            yr=yr,
            x0=x0,
            y0=y0,
            gsd=gsd,
            node_x0=float(lo[0]),
            node_y0=float(lo[1]),
            node_step=float(node_step),
            node_col=node_col.reshape(ny, nx),
            node_row=node_row.reshape(ny, nx),
        )

    @property
    def shape(self) -> tuple[int, int]:
        return self.xr.shape  # type: ignore[return-value]

    def __call__(
        self, x: np.ndarray, y: np.ndarray, iterations: int = 4, tol_px: float = 0.01
    ) -> tuple[np.ndarray, np.ndarray]:
        """Query (col, row) (float64, pixel-centre convention) of map points; NaN outside.

        A point is inside when it inverts to -0.5 <= col < cols - 0.5 (same for rows) with a
        forward residual below ``tol_px`` pixels, and the four pixels around it are valid.
        """
        from scipy.ndimage import map_coordinates

        x = np.asarray(x, np.float64)
        y = np.asarray(y, np.float64)
        shape = x.shape
        xr = x.ravel() - self.x0
        yr = y.ravel() - self.y0
        gi = (xr - self.node_x0) / self.node_step
        gj = (yr - self.node_y0) / self.node_step
        coords = np.vstack([gj, gi])
        c = map_coordinates(self.node_col, coords, order=1, mode="nearest")
        r = map_coordinates(self.node_row, coords, order=1, mode="nearest")
        h, w = self.shape
        for _ in range(iterations):
            fx, xc, xrr = _bilinear_with_grad(self.xr, c, r)
            fy, yc, yrr = _bilinear_with_grad(self.yr, c, r)
            ex, ey = xr - fx, yr - fy
            det = xc * yrr - xrr * yc
            with np.errstate(divide="ignore", invalid="ignore"):
                dc = (yrr * ex - xrr * ey) / det
                dr = (-yc * ex + xc * ey) / det
            dc = np.clip(np.nan_to_num(dc, nan=0.0), -8 * (w + h), 8 * (w + h))
            dr = np.clip(np.nan_to_num(dr, nan=0.0), -8 * (w + h), 8 * (w + h))
            c, r = c + dc, r + dr
            # keep the iterate near the image so that a far point does not diverge
            c = np.clip(c, -2.0, w + 1.0)
            r = np.clip(r, -2.0, h + 1.0)
        fx, _, _ = _bilinear_with_grad(self.xr, c, r)
        fy, _, _ = _bilinear_with_grad(self.yr, c, r)
        res = np.hypot(xr - fx, yr - fy) / self.gsd
        inside = (c >= -0.5) & (c < w - 0.5) & (r >= -0.5) & (r < h - 0.5) & (res < tol_px)
        c = np.where(inside, c, np.nan)
        r = np.where(inside, r, np.nan)
        return c.reshape(shape), r.reshape(shape)


# ----------------------------------------------------------------------------- output grid


@dataclass(frozen=True)
class ProductGrid:
    """A north-up grid in the map CRS."""

    transform: Affine
    width: int
    height: int
    crs_wkt: str

    @property
    def gsd(self) -> float:
        return float(self.transform.a)

    def to_json(self) -> dict[str, Any]:
        return {
            "transform": list(self.transform)[:6],
            "width": self.width,
            "height": self.height,
            "gsd": self.gsd,
        }


def product_grid(
    x: np.ndarray,
    y: np.ndarray,
    crs_wkt: str,
    mode: str = "query_gsd",
    gsd_m: float | None = None,
    map_raster: str | os.PathLike | None = None,
) -> ProductGrid:
    """The grid covering the footprint (pixel centres + half a pixel).

    ``mode="query_gsd"``: square pixels of the query's own ground spacing (or ``gsd_m``), origin
    snapped to a multiple of the pixel size. ``mode="map"``: the pixel size and lattice of
    ``map_raster`` (the orthophoto mosaic), so the product overlays the map pixel for pixel.
    """
    ok = np.isfinite(x) & np.isfinite(y)
    if not ok.any():
        raise InputError(None, "geolocation is all NaN: no footprint to grid")
    spacing = pixel_spacing(x, y)
    xmin, xmax = float(x[ok].min()) - spacing / 2, float(x[ok].max()) + spacing / 2
    ymin, ymax = float(y[ok].min()) - spacing / 2, float(y[ok].max()) + spacing / 2
    if mode == "map":
        if map_raster is None:
            raise InputError(None, "products.grid = map needs the map mosaic")
        with rasterio.open(map_raster) as ds:
            t = ds.transform
        px, py = abs(t.a), abs(t.e)
        ox, oy = t.c, t.f
        c0 = math.floor((xmin - ox) / px)
        c1 = math.ceil((xmax - ox) / px)
        r0 = math.floor((oy - ymax) / py)
        r1 = math.ceil((oy - ymin) / py)
        tr = Affine(px, 0.0, ox + c0 * px, 0.0, -py, oy - r0 * py)
        return ProductGrid(tr, int(c1 - c0), int(r1 - r0), crs_wkt)
    g = float(gsd_m) if gsd_m else float(f"{spacing:.3g}")
    c0, c1 = math.floor(xmin / g), math.ceil(xmax / g)
    r0, r1 = math.floor(ymin / g), math.ceil(ymax / g)
    tr = Affine(g, 0.0, c0 * g, 0.0, -g, r1 * g)
    return ProductGrid(tr, int(c1 - c0), int(r1 - r0), crs_wkt)


def inverse_maps(
    inv: InverseGeolocation, grid: ProductGrid, block_rows: int = 128
) -> tuple[np.ndarray, np.ndarray]:
    """Query (col, row) (float32, NaN outside) of every output pixel centre, in row blocks."""
    col = np.full((grid.height, grid.width), np.nan, np.float32)
    row = np.full((grid.height, grid.width), np.nan, np.float32)
    t = grid.transform
    xs = t.c + t.a * (np.arange(grid.width) + 0.5)
    for r0 in range(0, grid.height, block_rows):
        r1 = min(grid.height, r0 + block_rows)
        ys = t.f + t.e * (np.arange(r0, r1) + 0.5)
        X, Y = np.meshgrid(xs, ys)
        c, r = inv(X, Y)
        col[r0:r1], row[r0:r1] = c, r
    return col, row


def nearest_index(col: np.ndarray, row: np.ndarray, width: int) -> np.ndarray:
    """Flat query pixel index (int64) of each output pixel, -1 where there is none."""
    ok = np.isfinite(col) & np.isfinite(row)
    idx = np.full(col.shape, -1, np.int64)
    idx[ok] = np.rint(row[ok]).astype(np.int64) * width + np.rint(col[ok]).astype(np.int64)
    return idx


# ----------------------------------------------------------------------------- cube access


def native_dtype(cube: Cube) -> np.dtype:
    """The dtype the cube stores (native byte order); float32 for non-ENVI images."""
    if isinstance(cube, EnviCube):
        return np.dtype(cube.dtype).newbyteorder("=")
    if isinstance(cube, RasterCube):
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", rasterio.errors.NotGeoreferencedWarning)
            with rasterio.open(cube.path) as ds:
                return np.dtype(ds.dtypes[0])
    return np.dtype(np.float32)


def read_band_chunk(cube: Cube, b0: int, b1: int) -> np.ndarray:
    """Bands ``b0..b1-1`` as (nb, rows, cols) in the cube's native dtype (one pass for ENVI)."""
    if isinstance(cube, EnviCube):
        mm = cube._memmap()
        if cube.interleave == "bsq":
            a = mm[b0:b1]
        elif cube.interleave == "bil":
            a = mm[:, b0:b1, :].transpose(1, 0, 2)
        else:
            a = mm[:, :, b0:b1].transpose(2, 0, 1)
        out = np.array(a, dtype=native_dtype(cube))
        del mm
        return out
    if isinstance(cube, RasterCube):
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", rasterio.errors.NotGeoreferencedWarning)
            with rasterio.open(cube.path) as ds:
                return ds.read(list(range(b0 + 1, b1 + 1)))
    return np.stack([cube.read_band(i) for i in range(b0, b1)])


def gather_spectra(cube: Cube, rows: np.ndarray, cols: np.ndarray, bands: np.ndarray) -> np.ndarray:
    """Spectra (n, len(bands)) at query pixels (rows, cols), native dtype; random access for ENVI."""
    bands = np.asarray(bands, np.int64)
    if isinstance(cube, EnviCube):
        mm = cube._memmap()
        if cube.interleave == "bil":
            out = mm[rows, :, cols][:, bands]
        elif cube.interleave == "bip":
            out = mm[rows, cols, :][:, bands]
        else:
            out = np.stack([mm[b][rows, cols] for b in bands], axis=1)
        res = np.array(out, dtype=native_dtype(cube))
        del mm
        return res
    return np.stack([cube.read_band(int(b))[rows, cols] for b in bands], axis=1)


def output_nodata(cube: Cube, dtype: np.dtype) -> float:
    """Nodata of the products: the cube's own, else NaN (float) or the dtype's extreme (int)."""
    if cube.nodata is not None:
        return float(cube.nodata)
    if dtype.kind == "f":
        return float("nan")
    info = np.iinfo(dtype)
    return float(info.min if dtype.kind == "i" else info.max)


def band_labels(cube: Cube) -> list[str]:
    """'1203.5 nm' per band (or 'band i' without wavelengths)."""
    if cube.wavelengths_nm is None:
        return [f"band {i + 1}" for i in range(cube.count)]
    return [f"{w:.1f} nm" for w in cube.wavelengths_nm]


def band_tags(cube: Cube, i: int) -> dict[str, str]:
    """Per-band GeoTIFF metadata: wavelength / fwhm in nm (+ GDAL IMAGERY-domain style keys)."""
    tags: dict[str, str] = {}
    if cube.wavelengths_nm is not None:
        tags["wavelength"] = f"{cube.wavelengths_nm[i]:.4f}"
        tags["wavelength_units"] = "nm"
        tags["CENTRAL_WAVELENGTH_UM"] = f"{cube.wavelengths_nm[i] / 1000.0:.6f}"
    if cube.fwhm_nm is not None:
        tags["fwhm"] = f"{cube.fwhm_nm[i]:.4f}"
        tags["FWHM_UM"] = f"{cube.fwhm_nm[i] / 1000.0:.6f}"
    return tags


# ----------------------------------------------------------------------------- ENVI header


def envi_map_info(crs_wkt: str, transform: Affine) -> tuple[str, str]:
    """``map info`` and ``coordinate system string`` values for an ENVI header."""
    import pyproj

    crs = pyproj.CRS.from_wkt(crs_wkt)
    px, py = transform.a, -transform.e
    x0, y0 = transform.c, transform.f
    units = "Meters"
    unit = crs.axis_info[0].unit_name if crs.axis_info else "metre"
    if unit not in ("metre", "meter"):
        units = "Feet" if "foot" in unit.lower() else unit
    utm = crs.utm_zone
    datum = (crs.datum.name if crs.datum else "") or ""
    if utm and "WGS" in datum.upper() and "84" in datum:
        zone, hemi = int(utm[:-1]), "North" if utm[-1].upper() == "N" else "South"
        info = (
            f"{{UTM, 1.000, 1.000, {x0:.6f}, {y0:.6f}, {px:.10g}, {py:.10g}, {zone}, {hemi}, "
            f"WGS-84, units={units}}}"
        )
    else:
        info = f"{{Arbitrary, 1.000, 1.000, {x0:.6f}, {y0:.6f}, {px:.10g}, {py:.10g}, 0, North, units={units}}}"
    esri = crs.to_wkt(pyproj.enums.WktVersion.WKT1_ESRI)
    return info, "{" + esri + "}"


def _envi_list(values: list[str]) -> str:
    return (
        "{\n " + ",\n ".join(", ".join(values[i : i + 8]) for i in range(0, len(values), 8)) + "}"
    )


def envi_header_text(
    cube: Cube,
    width: int,
    height: int,
    dtype: np.dtype,
    nodata: float,
    crs_wkt: str,
    transform: Affine,
    description: str,
) -> str:
    """ENVI header for a little-endian BSQ geo-referenced cube."""
    info, css = envi_map_info(crs_wkt, transform)
    rows = [
        "ENVI",
        "description = {" + description.replace("{", "(").replace("}", ")") + "}",
        f"samples = {width}",
        f"lines = {height}",
        f"bands = {cube.count}",
        "header offset = 0",
        "file type = ENVI Standard",
        f"data type = {ENVI_TYPE_CODES[np.dtype(dtype).name]}",
        "interleave = bsq",
        "byte order = 0",
        f"map info = {info}",
        f"coordinate system string = {css}",
    ]
    if not math.isnan(nodata):
        rows.append(f"data ignore value = {nodata:g}")
    if isinstance(cube, EnviCube) and "reflectance scale factor" in cube.header:
        rows.append(f"reflectance scale factor = {cube.header['reflectance scale factor']}")
    rows.append("band names = " + _envi_list(band_labels(cube)))
    if cube.wavelengths_nm is not None:
        rows.append("wavelength units = Nanometers")
        rows.append("wavelength = " + _envi_list([f"{w:.4f}" for w in cube.wavelengths_nm]))
    if cube.fwhm_nm is not None:
        rows.append("fwhm = " + _envi_list([f"{w:.4f}" for w in cube.fwhm_nm]))
    return "\n".join(rows) + "\n"


# ----------------------------------------------------------------------------- resampling


def _resample_chunk(
    cube: Cube,
    b0: int,
    b1: int,
    grid: ProductGrid,
    idx: np.ndarray | None,
    mx: np.ndarray | None,
    my: np.ndarray | None,
    valid: np.ndarray,
    nodata: float,
    dtype: np.dtype,
) -> np.ndarray:
    """Bands b0..b1-1 on the output grid: nearest (flat index gather) or bilinear (cv2.remap)."""
    import cv2

    src = read_band_chunk(cube, b0, b1)
    if idx is not None:
        flat = src.reshape(b1 - b0, -1)
        out = np.full((b1 - b0, grid.height, grid.width), nodata, dtype)
        ok = idx >= 0
        out[:, ok] = flat[:, idx[ok]]
        if cube.nodata is not None and cube.nodata != nodata:
            out[out == cube.nodata] = nodata
        return out
    out = np.empty((b1 - b0, grid.height, grid.width), np.float32)
    for k in range(b1 - b0):
        band = src[k].astype(np.float32)
        if cube.nodata is not None:
            band[band == cube.nodata] = np.nan
        out[k] = cv2.remap(
            band, mx, my, cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT, borderValue=np.nan
        )
    out[:, ~valid] = np.nan
    return out


def copy_band_interleaved_cog(
    stage: str | os.PathLike,
    out: str | os.PathLike,
    overview_resampling: str = "nearest",
    threads: int = 1,
    cache_mb: int = COG_CACHE_MB,
) -> None:
    """A band-interleaved tiled GeoTIFF -> a band-interleaved Cloud Optimized GeoTIFF, streaming.

    GDAL's COG driver (3.10) writes pixel interleave only: from a band-interleaved source every
    output block needs a block of every band, so a 260-band cube either holds a whole block row of
    all bands in the GDAL cache (~1.9 GB peak for the paper's cube) or re-reads blocks for minutes.
    Here the overviews are built band by band into the stage, then the GTiff driver copies it with
    ``COPY_SRC_OVERVIEWS=YES`` and ``INTERLEAVE=BAND`` (the COG layout: tiled, IFDs first,
    overviews before the full-resolution data), one band after the other under a small cache.
    """
    from rasterio.enums import Resampling

    with rasterio.Env(GDAL_CACHEMAX=cache_mb, GDAL_NUM_THREADS=str(max(1, threads))):
        with rasterio.open(stage, "r+") as ds:
            n = max(ds.width, ds.height)
            factors = []
            f = 2
            while n / f >= 256 / 2:  # down to a block, as the COG driver's AUTO
                factors.append(f)
                f *= 2
            if factors:
                ds.build_overviews(factors, Resampling[overview_resampling])
            predictor = 3 if np.dtype(ds.dtypes[0]).kind == "f" else 2
        rasterio.shutil.copy(
            stage, out, driver="GTiff", COPY_SRC_OVERVIEWS="YES", TILED="YES", BLOCKXSIZE=256,
            BLOCKYSIZE=256, INTERLEAVE="BAND", COMPRESS="DEFLATE", ZLEVEL=DEFLATE_LEVEL, PREDICTOR=predictor,
            BIGTIFF="IF_SAFER",
        )  # fmt: skip


def resample_cube(
    cube: Cube,
    col: np.ndarray,
    row: np.ndarray,
    grid: ProductGrid,
    out_tif: str | os.PathLike,
    out_envi_hdr: str | os.PathLike | None = None,
    resampling: str = "nearest",
    chunk_bands: int = 16,
    threads: int = 1,
) -> dict[str, Any]:
    """Resample every band onto ``grid`` through the inverse maps; COG + optional ENVI copy.

    ``nearest`` keeps the cube's dtype and copies each spectrum unchanged (pure spectra, the
    default); ``bilinear`` (cv2.remap) writes float32. Memory: one chunk of ``chunk_bands``
    query bands + the same bands of the output + the inverse maps.
    """
    t0 = time.perf_counter()
    src_dtype = native_dtype(cube)
    dtype = src_dtype if resampling == "nearest" else np.dtype(np.float32)
    nodata = output_nodata(cube, dtype)
    idx = nearest_index(col, row, cube.width) if resampling == "nearest" else None
    valid = np.isfinite(col) & np.isfinite(row)
    mx = my = None
    if resampling != "nearest":
        mx = np.where(valid, col, -10.0).astype(np.float32)
        my = np.where(valid, row, -10.0).astype(np.float32)
    out_tif = Path(out_tif)
    # the stage is read once by the COG copy: uncompressed (the cube's size on disk for a moment)
    # saves a compression and a decompression of every block
    profile = {**tiled_profile(grid.width, grid.height, cube.count, dtype, nodata),
               "crs": CRS.from_wkt(grid.crs_wkt), "transform": grid.transform}  # fmt: skip
    for key in ("compress", "zlevel", "predictor"):
        del profile[key]
    labels = band_labels(cube)
    tmp_gtiff = out_tif.with_name(f".{out_tif.stem}.stage-{os.getpid()}.tif")
    try:
        with contextlib.ExitStack() as stack:
            fh = None
            if out_envi_hdr:
                envi_tmp = stack.enter_context(atomic_path(Path(out_envi_hdr).with_suffix(".bsq")))
                fh = stack.enter_context(open(envi_tmp, "wb"))  # BSQ: band chunks in order
            with rasterio.open(tmp_gtiff, "w", **profile) as dst:
                for b0 in range(0, cube.count, chunk_bands):
                    b1 = min(cube.count, b0 + chunk_bands)
                    out = _resample_chunk(cube, b0, b1, grid, idx, mx, my, valid, nodata, dtype)
                    dst.write(out, indexes=list(range(b0 + 1, b1 + 1)))
                    if fh is not None:
                        fh.write(np.ascontiguousarray(out, dtype=dtype.newbyteorder("<")).tobytes())
                    del out
                for i in range(cube.count):
                    dst.set_band_description(i + 1, labels[i])
                    tags = band_tags(cube, i)
                    if tags:
                        dst.update_tags(i + 1, **tags)
                dst.update_tags(
                    CONTENT=f"query cube {cube.path.name} resampled ({resampling}) onto the map CRS",
                    RESAMPLING=resampling,
                    WAVELENGTH_UNITS="nm",
                )
        t_write = time.perf_counter() - t0
        with atomic_path(out_tif) as tmp:
            copy_band_interleaved_cog(
                tmp_gtiff, tmp, "nearest" if resampling == "nearest" else "average", threads
            )
    finally:
        if tmp_gtiff.exists():
            tmp_gtiff.unlink()
    if out_envi_hdr:
        description = f"georeg geo-referenced cube from {cube.path.name} ({resampling}); same pixels as the COG"
        hdr = envi_header_text(
            cube, grid.width, grid.height, dtype, nodata, grid.crs_wkt, grid.transform, description
        )
        with atomic_path(out_envi_hdr) as tmp:
            tmp.write_text(hdr)
    return {
        "dtype": dtype.name,
        "nodata": None if math.isnan(nodata) else nodata,
        "resampling": resampling,
        "valid_fraction": float(valid.mean()),
        "seconds_write": round(t_write, 2),
        "seconds_total": round(time.perf_counter() - t0, 2),
    }
