"""The "3D hyperspectral" point cloud: LiDAR points of the footprint carrying their pixel's spectrum.

Every filtered map point (``results/map/tiles/{tile}/points.laz``, map CRS, metres) inside the
query footprint is located in the query through :class:`~georeg.products.cube_resample.InverseGeolocation`
(map x, y -> query col, row; nearest pixel) and written to a LAS 1.4 / LAZ file with the source
point format (RGB kept) plus extra dimensions (LAS 1.4 "extra bytes"):

* ``b<wavelength>nm`` (e.g. ``b1203nm``): the cube's value (native type, e.g. int16 reflectance
  x 10000) at the point's pixel, one per selected band; the description holds the exact
  wavelength and FWHM. Names made unique with ``_<band index>`` when two bands round alike.
* ``query_col``, ``query_row``: the pixel (0-based) the spectrum comes from.

Points are streamed tile by tile and chunk by chunk (never all in memory); where map tiles overlap
a point is kept only by the tile whose *core* holds it, so no point is written twice.
"""

from __future__ import annotations

import logging
import os
from pathlib import Path
from typing import Any

import laspy
import numpy as np

from georeg.io.atomic import atomic_path
from georeg.io.errors import InputError
from georeg.io.query import Cube
from georeg.products.cube_resample import InverseGeolocation, gather_spectra, native_dtype

log = logging.getLogger(__name__)


def select_bands(cube: Cube, bands: str | int | None) -> np.ndarray:
    """``all`` / None -> every band; an integer N -> N bands evenly spread over the cube."""
    if bands in (None, "all") or (isinstance(bands, int) and bands >= cube.count):
        return np.arange(cube.count)
    n = int(bands)  # type: ignore[arg-type]
    if n < 1:
        raise InputError(None, f"products.points.bands = {bands}: need 'all' or an integer >= 1")
    return np.unique(np.linspace(0, cube.count - 1, n).round().astype(np.int64))


def band_dim_names(cube: Cube, bands: np.ndarray) -> list[str]:
    """Extra-dimension names ``b1203nm`` (unique), or ``band<i>`` without wavelengths."""
    if cube.wavelengths_nm is None:
        return [f"band{int(b) + 1}" for b in bands]
    names = [f"b{cube.wavelengths_nm[b]:.0f}nm" for b in bands]
    seen: dict[str, int] = {}
    for n in names:
        seen[n] = seen.get(n, 0) + 1
    return [n if seen[n] == 1 else f"{n}_{int(b)}" for n, b in zip(names, bands, strict=True)]


def _describe(cube: Cube, b: int) -> str:
    if cube.wavelengths_nm is None:
        return f"band {b + 1}"
    s = f"{cube.wavelengths_nm[b]:.2f} nm"
    if cube.fwhm_nm is not None:
        s += f" fwhm {cube.fwhm_nm[b]:.2f}"
    return s[:31]


def _core_bounds(
    grid_json: str | os.PathLike | None,
) -> dict[str, tuple[float, float, float, float]]:
    """Map bounds of each tile's core (x0, y0, x1, y1), by tile id; {} without a grid."""
    if not grid_json or not Path(grid_json).exists():
        return {}
    from rasterio.transform import array_bounds

    from georeg.map.grid import MapGrid

    g = MapGrid.load(grid_json)
    out = {}
    for tid, t in g.tiles.items():
        tr = g.transform * type(g.transform).translation(t.core.col_off, t.core.row_off)
        w, s, e, n = array_bounds(int(t.core.height), int(t.core.width), tr)
        out[tid] = (w, s, e, n)
    return out


def _dim_type(dtype: np.dtype) -> np.dtype:
    return (
        dtype
        if dtype.name
        in ("int16", "uint16", "int32", "uint32", "float32", "float64", "uint8", "int8")
        else np.dtype(np.float32)
    )


def fuse_points(
    tiles: list[str | os.PathLike],
    inv: InverseGeolocation,
    cube: Cube,
    out_path: str | os.PathLike,
    bands: str | int | None = "all",
    grid_json: str | os.PathLike | None = None,
    chunk_points: int = 100_000,
) -> dict[str, Any]:
    """Write ``points_spectra.laz``; returns counts and the extra dimension names."""
    sel = select_bands(cube, bands)
    names = band_dim_names(cube, sel)
    dtype = _dim_type(native_dtype(cube))
    cores = _core_bounds(grid_json)
    h, w = inv.shape
    xs, ys = inv.xr + inv.x0, inv.yr + inv.y0
    ok = np.isfinite(xs) & np.isfinite(ys)
    pad = inv.gsd
    bx0, bx1 = float(xs[ok].min()) - pad, float(xs[ok].max()) + pad
    by0, by1 = float(ys[ok].min()) - pad, float(ys[ok].max()) + pad
    idx_t = np.uint16 if max(h, w) < 65535 else np.uint32
    writer = None
    n_in = n_out = 0
    used = []
    with atomic_path(out_path) as tmp:
        try:
            for path in tiles:
                tid = Path(path).parent.name
                core = cores.get(tid)
                try:
                    reader = laspy.open(str(path))
                except (OSError, laspy.errors.LaspyException) as exc:
                    raise InputError(path, f"cannot read the point cloud: {exc}") from exc
                with reader:
                    hd = reader.header
                    if hd.maxs[0] < bx0 or hd.mins[0] > bx1 or hd.maxs[1] < by0 or hd.mins[1] > by1:
                        continue
                    used.append(str(path))
                    if writer is None:
                        header = laspy.LasHeader(point_format=hd.point_format.id, version="1.4")
                        header.scales, header.offsets = hd.scales, hd.offsets
                        for v in hd.vlrs:
                            if not isinstance(v, laspy.vlrs.known.ExtraBytesVlr):
                                header.vlrs.append(v)
                        header.add_extra_dims(
                            [
                                laspy.ExtraBytesParams(n, dtype, _describe(cube, int(b)))
                                for n, b in zip(names, sel, strict=True)
                            ]
                            + [
                                laspy.ExtraBytesParams("query_col", idx_t, "query pixel column"),
                                laspy.ExtraBytesParams("query_row", idx_t, "query pixel row"),
                            ]
                        )
                        writer = laspy.open(str(tmp), mode="w", header=header)
                    std = [d for d in hd.point_format.standard_dimension_names
                           if d in header.point_format.standard_dimension_names
                           and d not in ("X", "Y", "Z")]  # fmt: skip
                    for pts in reader.chunk_iterator(chunk_points):
                        x, y = np.asarray(pts.x), np.asarray(pts.y)
                        keep = (x >= bx0) & (x <= bx1) & (y >= by0) & (y <= by1)
                        if core is not None:
                            keep &= (x >= core[0]) & (x < core[2]) & (y > core[1]) & (y <= core[3])
                        n_in += int(keep.sum())
                        if not keep.any():
                            continue
                        k = np.flatnonzero(keep)
                        c, r = inv(x[k], y[k])
                        good = np.isfinite(c) & np.isfinite(r)
                        if not good.any():
                            continue
                        k = k[good]
                        ci = np.clip(np.rint(c[good]), 0, w - 1).astype(np.int64)
                        ri = np.clip(np.rint(r[good]), 0, h - 1).astype(np.int64)
                        spec = gather_spectra(cube, ri, ci, sel).astype(dtype, copy=False)
                        rec = laspy.ScaleAwarePointRecord.zeros(len(k), header=header)
                        rec.x, rec.y, rec.z = x[k], y[k], np.asarray(pts.z)[k]
                        for d in std:
                            rec[d] = np.asarray(pts[d])[k]
                        for j, name in enumerate(names):
                            rec[name] = spec[:, j]
                        rec["query_col"] = ci.astype(idx_t)
                        rec["query_row"] = ri.astype(idx_t)
                        writer.write_points(rec)
                        n_out += len(k)
            if writer is None:  # no tile overlaps: an empty but valid file
                header = laspy.LasHeader(point_format=7, version="1.4")
                writer = laspy.open(str(tmp), mode="w", header=header)
        finally:
            if writer is not None:
                writer.close()
    log.info("points with spectra: %d of %d footprint-box points, %d bands", n_out, n_in, len(sel))
    return {
        "points": n_out,
        "points_in_box": n_in,
        "tiles": used,
        "bands": [int(b) for b in sel],
        "extra_dims": names + ["query_col", "query_row"],
        "dim_type": np.dtype(dtype).name,
    }
