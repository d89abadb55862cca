"""Shared raster helpers: open with clear errors, window reads, COG and VRT writing.

Every stage that reads or writes rasters goes through these so that a missing file, a corrupt
file or a raster without a CRS is reported as one :class:`~georeg.io.errors.InputError` naming the
file. GDAL reads a ``.aux.xml`` side-car (PAM) automatically, so a JPEG whose CRS lives only in
its side-car opens with a CRS.
"""

from __future__ import annotations

import contextlib
import logging
import os
from collections.abc import Iterator, Sequence
from pathlib import Path
from xml.sax.saxutils import escape

import numpy as np
import rasterio
import rasterio.shutil
from rasterio.crs import CRS
from rasterio.enums import Resampling
from rasterio.errors import RasterioError
from rasterio.io import DatasetReader, MemoryFile
from rasterio.transform import Affine
from rasterio.vrt import WarpedVRT
from rasterio.windows import Window, from_bounds

from georeg.io.atomic import atomic_path
from georeg.io.errors import InputError

log = logging.getLogger(__name__)

#: nodata value of every float elevation raster written by georeg
ELEV_NODATA: float = -9999.0


@contextlib.contextmanager
def open_raster(path: str | os.PathLike, require_crs: bool = True) -> Iterator[DatasetReader]:
    """Open a raster for reading; missing file, unreadable file or missing CRS -> InputError."""
    p = Path(path)
    if not p.exists():
        raise InputError(p, "file not found", "check the path in the config")
    try:
        ds = rasterio.open(p)
    except RasterioError as exc:
        raise InputError(
            p, f"not a readable raster ({exc})", "is the file truncated or corrupt?"
        ) from exc
    try:
        if require_crs and ds.crs is None:
            raise InputError(
                p,
                "raster has no CRS",
                "add one (e.g. a .aux.xml side-car or `rio edit-info --crs`) or set map.crs",
            )
        yield ds
    finally:
        ds.close()


#: DEFLATE level of every product GeoTIFF. Level 1 against GDAL's default 6 on the demo's fused
#: cube (64 float32 bands, predictor 3): write 1.47 vs 2.92 s, read 0.72 vs 1.84 s, +2.9 % bytes
#: (docs/BENCHMARKS.md "products"); any DEFLATE reader decodes either.
DEFLATE_LEVEL = 1


def tiled_profile(width: int, height: int, count: int, dtype: str | np.dtype,
                  nodata: float | None) -> dict:  # fmt: skip
    """GeoTIFF profile of a georeg product: 256 px tiles, band interleave, deflate with the
    predictor of the data type, BigTIFF when needed (add ``crs``/``transform`` if geo-referenced)."""
    dt = np.dtype(dtype)
    return {
        "driver": "GTiff",
        "width": width,
        "height": height,
        "count": count,
        "dtype": dt.name,
        "nodata": nodata,
        "tiled": True,
        "blockxsize": 256,
        "blockysize": 256,
        "interleave": "band",
        "compress": "deflate",
        "zlevel": DEFLATE_LEVEL,
        "predictor": 3 if dt.kind == "f" else 2,
        "BIGTIFF": "IF_SAFER",
    }


def read(
    ds: DatasetReader | WarpedVRT,
    window: Window | None = None,
    out_shape: tuple[int, ...] | None = None,
    masked: bool = False,
    resampling: Resampling = Resampling.nearest,
    boundless: bool = False,
    fill_value: float | None = None,
    path: str | os.PathLike | None = None,
    indexes: list[int] | None = None,
) -> np.ndarray:
    """``ds.read`` that turns GDAL read errors (truncated/corrupt data) into an InputError;
    ``indexes``: only these 1-based bands (all when None)."""
    try:
        return ds.read(
            indexes=indexes,
            window=window,
            out_shape=out_shape,
            masked=masked,
            resampling=resampling,
            boundless=boundless,
            fill_value=fill_value,
        )
    except RasterioError as exc:
        raise InputError(
            path or ds.name, f"cannot read pixels ({exc})", "truncated or corrupt?"
        ) from exc


def read_masks(
    ds: DatasetReader | WarpedVRT,
    window: Window | None = None,
    out_shape: tuple[int, int] | None = None,
    path: str | os.PathLike | None = None,
    indexes: list[int] | None = None,
) -> np.ndarray:
    """Validity mask (0 = nodata, 255 = valid) of a window, with clear errors.

    ``indexes``: the union of these bands' masks (valid where any is), which is GDAL's dataset
    mask restricted to them; without it GDAL evaluates every band (seconds for a 224-band cube).
    """
    try:
        if indexes:
            masks = [ds.read_masks(i, window=window, out_shape=out_shape) for i in indexes]
            return np.maximum.reduce(masks)
        return ds.dataset_mask(window=window, out_shape=out_shape)
    except RasterioError as exc:
        raise InputError(
            path or ds.name, f"cannot read pixels ({exc})", "truncated or corrupt?"
        ) from exc


def degree_pixel_ground_m(lon: float, lat: float, width_deg: float, height_deg: float) -> tuple[float, float]:
    """The ground size (m, WGS84 geodesics) of a ``width_deg`` x ``height_deg`` pixel centred at
    ``lon``, ``lat``: (across, along the meridian)."""
    from pyproj import Geod

    geod = Geod(ellps="WGS84")
    a, e = abs(float(width_deg)), abs(float(height_deg))
    across = geod.inv(lon - a / 2, lat, lon + a / 2, lat)[2]
    along = geod.inv(lon, lat - e / 2, lon, lat + e / 2)[2]
    return float(across), float(along)


def same_grid(ds: DatasetReader, crs: CRS, transform: Affine, tol: float = 1e-6) -> bool:
    """True if ``ds`` shares ``crs``, pixel size and pixel alignment with ``transform``."""
    if ds.crs != crs:
        return False
    a, b = ds.transform, transform
    if abs(a.b) > tol or abs(a.d) > tol or abs(b.b) > tol or abs(b.d) > tol:
        return False
    if abs(a.a - b.a) > tol * abs(b.a) or abs(a.e - b.e) > tol * abs(b.e):
        return False
    fx = (a.c - b.c) / b.a
    fy = (a.f - b.f) / b.e
    return abs(fx - round(fx)) < 1e-6 and abs(fy - round(fy)) < 1e-6


@contextlib.contextmanager
def on_grid(
    ds: DatasetReader,
    crs: CRS,
    transform: Affine,
    width: int,
    height: int,
    resampling: Resampling = Resampling.bilinear,
) -> Iterator[tuple[DatasetReader | WarpedVRT, Window]]:
    """Yield ``(reader, window)`` that reads ``ds`` on the target grid (``width`` x ``height``).

    Same CRS and aligned pixels: the dataset itself and the matching (possibly partly outside)
    window, read with ``boundless=True``; no resampling. Otherwise a :class:`WarpedVRT` onto the
    target grid (only the needed source blocks are read), with window ``(0, 0, width, height)``.
    """
    if same_grid(ds, crs, transform):
        col = round((transform.c - ds.transform.c) / ds.transform.a)
        row = round((transform.f - ds.transform.f) / ds.transform.e)
        yield ds, Window(col, row, width, height)
        return
    with WarpedVRT(
        ds,
        crs=crs,
        transform=transform,
        width=width,
        height=height,
        resampling=resampling,
        src_nodata=ds.nodata,
        nodata=ds.nodata,
    ) as vrt:
        yield vrt, Window(0, 0, width, height)


def write_cog(
    path: str | os.PathLike,
    data: np.ndarray,
    crs: CRS | str,
    transform: Affine,
    nodata: float | None = None,
    mask: np.ndarray | None = None,
    blocksize: int = 256,
    compress: str = "deflate",
    overview_resampling: str = "average",
    descriptions: Sequence[str] | None = None,
    units: str | None = None,
) -> None:
    """Write ``data`` (bands, rows, cols) or (rows, cols) as a Cloud Optimized GeoTIFF, atomically.

    The array goes into an in-memory tiled GeoTIFF, then GDAL's COG driver copies it out with
    internal tiling and overviews. ``mask`` (bool, True = valid) is stored as an internal mask
    when ``nodata`` is None.
    """
    arr = data[np.newaxis] if data.ndim == 2 else data
    count, height, width = arr.shape
    profile = {
        "driver": "GTiff",
        "width": width,
        "height": height,
        "count": count,
        "dtype": arr.dtype,
        "crs": crs,
        "transform": transform,
        "nodata": nodata,
        "tiled": True,
        "blockxsize": blocksize,
        "blockysize": blocksize,
    }
    predictor = 3 if np.issubdtype(arr.dtype, np.floating) else 2
    with MemoryFile() as mem, mem.open(**profile) as tmp_ds:
        tmp_ds.write(arr)
        if mask is not None and nodata is None:
            tmp_ds.write_mask(np.where(mask, 255, 0).astype(np.uint8))
        for i, d in enumerate(descriptions or [], start=1):
            tmp_ds.set_band_description(i, d)
        if units:
            tmp_ds.units = [units] * count
        with atomic_path(path) as out:
            rasterio.shutil.copy(
                tmp_ds,
                out,
                driver="COG",
                compress=compress,
                level=DEFLATE_LEVEL,
                predictor=predictor,
                blocksize=blocksize,
                overview_resampling=overview_resampling,
                overviews="AUTO",
            )


def is_cog(path: str | os.PathLike) -> bool:
    """COG check: internally tiled, overviews when larger than one block, and the COG layout:
    every IFD (image and overviews) before the image data, the overviews' data before the
    full-resolution data (what GDAL's validate_cloud_optimized_geotiff checks, read from GDAL's
    TIFF metadata domain)."""
    with rasterio.open(path) as ds:
        bh, bw = ds.block_shapes[0]
        tiled = bw < ds.width or bh < ds.height or (bw == ds.width and bw % 16 == 0)
        needs_ovr = max(ds.width, ds.height) > max(bw, bh)
        n_ovr = len(ds.overviews(1))
        if not tiled or (needs_ovr and not n_ovr):
            return False

        def item(key: str, ovr: int | None) -> int | None:
            v = ds.get_tag_item(key, "TIFF", bidx=1, ovr=ovr)
            return int(v) if v not in (None, "") else None

        levels = [None, *range(n_ovr)]
        ifds = [item("IFD_OFFSET", o) for o in levels]
        data = [item("BLOCK_OFFSET_0_0", o) for o in levels]
        if None in ifds or None in data:
            return True  # offsets not exposed (e.g. not a GTiff): tiling and overviews only
        return max(ifds) < min(data) and all(d < data[0] for d in data[1:])


_GDAL_TYPES = {
    "uint8": "Byte",
    "int8": "Int8",
    "uint16": "UInt16",
    "int16": "Int16",
    "uint32": "UInt32",
    "int32": "Int32",
    "float32": "Float32",
    "float64": "Float64",
}


def write_vrt(
    path: str | os.PathLike,
    sources: Sequence[tuple[str | os.PathLike, Window, Window]],
    crs: CRS | str,
    transform: Affine,
    width: int,
    height: int,
    count: int,
    dtype: str,
    nodata: float | None = None,
    mask_band: bool = False,
    resampling: str = "nearest",
) -> None:
    """Write a GDAL VRT mosaic by hand (no GDAL bindings needed), atomically.

    ``sources`` are ``(file, src_window, dst_window)``: the pixels ``src_window`` of ``file`` go
    to ``dst_window`` of the mosaic (same size: no resampling). File paths are written relative
    to the VRT when possible, so the results tree can be moved. Later sources are drawn over
    earlier ones. ``mask_band`` adds a per-dataset mask built from the sources' masks.
    """
    vrt_path = Path(path)
    crs_wkt = CRS.from_user_input(crs).to_wkt()
    gt = ", ".join(repr(float(v)) for v in transform.to_gdal())
    gdal_type = _GDAL_TYPES[str(np.dtype(dtype))]
    lines = [f'<VRTDataset rasterXSize="{width}" rasterYSize="{height}">']
    lines.append(f"  <SRS>{escape(crs_wkt)}</SRS>")
    lines.append(f"  <GeoTransform>{gt}</GeoTransform>")

    def _src(
        tag: str, file: str | os.PathLike, band: str, sw: Window, dw: Window, extra: str
    ) -> str:
        rel, relflag = _relative(file, vrt_path.parent)
        return (
            f"    <{tag}{extra}>\n"
            f'      <SourceFilename relativeToVRT="{relflag}">{escape(rel)}</SourceFilename>\n'
            f"      <SourceBand>{band}</SourceBand>\n"
            f'      <SrcRect xOff="{int(sw.col_off)}" yOff="{int(sw.row_off)}" '
            f'xSize="{int(sw.width)}" ySize="{int(sw.height)}"/>\n'
            f'      <DstRect xOff="{int(dw.col_off)}" yOff="{int(dw.row_off)}" '
            f'xSize="{int(dw.width)}" ySize="{int(dw.height)}"/>\n'
            f"    </{tag}>"
        )

    if mask_band:
        lines.append("  <MaskBand>")
        lines.append('    <VRTRasterBand dataType="Byte">')
        for file, sw, dw in sources:
            lines.append(_src("SimpleSource", file, "mask,1", sw, dw, ""))
        lines.append("    </VRTRasterBand>")
        lines.append("  </MaskBand>")
    for b in range(1, count + 1):
        lines.append(f'  <VRTRasterBand dataType="{gdal_type}" band="{b}">')
        if nodata is not None:
            lines.append(f"    <NoDataValue>{nodata!r}</NoDataValue>")
        tag = "ComplexSource" if nodata is not None else "SimpleSource"
        extra = f' resampling="{resampling}"'
        for file, sw, dw in sources:
            src = _src(tag, file, str(b), sw, dw, extra)
            if nodata is not None:
                src = src.replace(
                    f"    </{tag}>", f"      <NODATA>{nodata!r}</NODATA>\n    </{tag}>"
                )
            lines.append(src)
        lines.append("  </VRTRasterBand>")
    lines.append("</VRTDataset>")
    with atomic_path(vrt_path) as tmp:
        tmp.write_text("\n".join(lines) + "\n")


def _relative(file: str | os.PathLike, base: Path) -> tuple[str, int]:
    try:
        return os.path.relpath(Path(file).resolve(), base.resolve()), 1
    except ValueError:  # different drive
        return str(Path(file).resolve()), 0


def window_of_bounds(ds: DatasetReader, bounds: Sequence[float]) -> Window:
    """Window of ``ds`` covering ``bounds`` (left, bottom, right, top) in its CRS, rounded out."""
    w = from_bounds(*bounds, transform=ds.transform)
    return w.round_offsets(op="floor").round_lengths(op="ceil")
