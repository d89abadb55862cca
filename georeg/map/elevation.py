"""Elevation rasters on a map tile: DSM, DTM, nDSM and point density, from LiDAR or a DEM.

All rasters are float32, in metres, on exactly the orthophoto tile's grid, nodata
:data:`~georeg.io.raster.ELEV_NODATA` (density: points per m2, 0 where no point, no nodata).

LiDAR: DSM = highest point per cell, small gaps (up to ``dsm_fill_max_m`` from a measured cell)
interpolated. DTM = mean height of ground-class (2) points per cell when the tile has any, else a
lowest-point surface (grey opening of the per-cell minimum with a ``dtm_window_m`` window); its
gaps (under buildings, trees) are interpolated wherever the DSM is defined. nDSM = DSM - DTM,
clipped at 0. Rasterization runs on the tile grown by ``point_margin_m`` so the outlier filter and
the interpolation see context across the tile edge, then is cropped.

Point clouds are read and filtered by laspy + open3d or, with ``map.lidar_backend`` pdal (auto:
when PDAL imports), by PDAL and the user's ``map.pdal_pipeline``, which can also classify ground
(SMRF) for clouds without a ground class (:mod:`georeg.map.pdal_points`).

DEM (``map.dem``, no LiDAR): the DEM is resampled onto the tile grid; DSM = DTM = DEM, nDSM = 0,
density = DEM posts per m2 where the DEM is valid.
"""

from __future__ import annotations

import logging
import math
import os
from dataclasses import dataclass
from typing import Any

import numpy as np
import rasterio
from pyproj import CRS as PCRS
from rasterio.crs import CRS
from rasterio.enums import Resampling
from rasterio.transform import Affine, array_bounds
from scipy import ndimage
from scipy.interpolate import griddata
from scipy.spatial import Delaunay

from georeg.io.raster import ELEV_NODATA, on_grid, open_raster, read, read_masks, write_cog
from georeg.map import lidar, pdal_points

log = logging.getLogger(__name__)

LAYERS = ("dsm", "dtm", "ndsm", "density")
GROUND = 2
_MAX_SUPPORT = 300_000  # interpolation support points (boundary cells) per gap fill


@dataclass(frozen=True)
class Grid:
    """A raster grid: CRS, affine transform, size."""

    crs: CRS
    transform: Affine
    width: int
    height: int

    @classmethod
    def of(cls, path: str | os.PathLike) -> Grid:
        with open_raster(path) as ds:
            return cls(ds.crs, ds.transform, ds.width, ds.height)

    @property
    def bounds(self) -> tuple[float, float, float, float]:
        return array_bounds(self.height, self.width, self.transform)

    @property
    def pcrs(self) -> PCRS:
        return PCRS.from_wkt(self.crs.to_wkt())

    def grown(self, px: int) -> Grid:
        return Grid(
            self.crs,
            self.transform @ Affine.translation(-px, -px),
            self.width + 2 * px,
            self.height + 2 * px,
        )

    def metres_per_unit(self) -> tuple[float, float]:
        """Metres per CRS unit along x and y (geographic: at the grid centre)."""
        pc = self.pcrs
        if pc.is_geographic:
            b = self.bounds
            lat = math.radians(0.5 * (b[1] + b[3]))
            return 111_320.0 * math.cos(lat), 110_574.0
        u = lidar.horizontal_unit_m(lidar.split_crs(pc)[0])
        return u, u

    def cell_area_m2(self) -> float:
        sx, sy = self.metres_per_unit()
        return abs(self.transform.a * sx * self.transform.e * sy)


class GridAccumulator:
    """Per-cell max/min/count and ground mean, accumulated chunk by chunk (memory ~ the grid)."""

    def __init__(self, grid: Grid) -> None:
        self.grid = grid
        n = grid.width * grid.height
        self.zmax = np.full(n, -np.inf, np.float32)
        self.zmin = np.full(n, np.inf, np.float32)
        self.count = np.zeros(n, np.int64)
        self.gsum = np.zeros(n, np.float64)
        self.gcount = np.zeros(n, np.int64)

    def cells(self, x: np.ndarray, y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Flat cell index of each point and a mask of points inside the grid."""
        inv = ~self.grid.transform
        col = np.floor(inv.a * x + inv.b * y + inv.c).astype(np.int64)
        row = np.floor(inv.d * x + inv.e * y + inv.f).astype(np.int64)
        inside = (col >= 0) & (col < self.grid.width) & (row >= 0) & (row < self.grid.height)
        return row * self.grid.width + col, inside

    def add(
        self, x: np.ndarray, y: np.ndarray, z: np.ndarray, ground: np.ndarray | None = None
    ) -> None:
        idx, inside = self.cells(x, y)
        if not inside.all():
            idx, z = idx[inside], z[inside]
            ground = ground[inside] if ground is not None else None
        zf = z.astype(np.float32)
        n = self.count.size
        np.maximum.at(self.zmax, idx, zf)
        np.minimum.at(self.zmin, idx, zf)
        self.count += np.bincount(idx, minlength=n)
        if ground is not None and ground.any():
            gi = idx[ground]
            self.gsum += np.bincount(gi, weights=z[ground], minlength=n)
            self.gcount += np.bincount(gi, minlength=n)

    def shaped(self, a: np.ndarray) -> np.ndarray:
        return a.reshape(self.grid.height, self.grid.width)


def grow_fill(arr: np.ndarray, known: np.ndarray, need: np.ndarray, steps: int) -> np.ndarray:
    """Fill ``need`` cells ring by ring (``steps`` rings) with the mean of known 8-neighbours.

    Normalized convolution: O(cells) per ring, for small holes between sparse points. Returns
    the updated known mask; ``arr`` is filled in place.
    """
    k = known.copy()
    todo = need & ~k
    ones = np.ones((3, 3))
    for _ in range(steps):
        if not todo.any():
            break
        v = np.where(k, arr, 0.0)
        num = ndimage.convolve(v, ones, mode="constant")
        den = ndimage.convolve(k.astype(np.float64), ones, mode="constant")
        ring = todo & (den > 0)
        if not ring.any():
            break
        arr[ring] = num[ring] / den[ring]
        k |= ring
        todo &= ~ring
    return k


def linear_from_support(
    rr: np.ndarray, cc: np.ndarray, values: np.ndarray, nr: np.ndarray, nc: np.ndarray
) -> np.ndarray:
    """Linear interpolation on the Delaunay triangulation of the support cells (NaN outside it).

    The values of ``scipy.interpolate.griddata(..., method="linear")`` (the same qhull
    triangulation; equal to ~1e-13), but each target's triangle is found by matplotlib's
    trapezoid map: scipy's walk stalls on the grid-aligned, cocircular support of a raster
    (3-10 CPU s per demo tile for the call alone, against 0.05-1.1 s; a whole tile -16 %).
    """
    from matplotlib.tri import LinearTriInterpolator, Triangulation

    pts = np.column_stack([rr, cc]).astype(np.float64)
    tri = Delaunay(pts)
    try:
        mesh = Triangulation(pts[:, 0], pts[:, 1], tri.simplices)
        interp = LinearTriInterpolator(mesh, values)
        return np.ma.filled(interp(nr.astype(np.float64), nc.astype(np.float64)), np.nan)
    except (ValueError, RuntimeError) as exc:  # a triangulation matplotlib refuses
        log.debug("trapezoid map refused the triangulation (%s): scipy's walk", exc)
        return griddata((rr, cc), values, (nr, nc), method="linear")


def fill_gaps(
    arr: np.ndarray,
    known: np.ndarray,
    target: np.ndarray,
    method: str = "linear",
    grow_steps: int = 2,
) -> np.ndarray:
    """Fill ``target & ~known`` cells of ``arr`` from the ``known`` cells.

    ``linear``: holes up to ``grow_steps`` cells from data are closed by neighbour averaging
    (:func:`grow_fill`); larger gaps (under buildings) by Delaunay interpolation supported by the
    cells bordering them (few points: fast even on big grids); cells outside their hull and
    ``nearest``: nearest known cell (Euclidean distance transform).
    """
    out = arr.astype(np.float64, copy=True)
    out[~known] = np.nan
    need = target & ~known
    if not need.any() or not known.any():
        return out
    if method == "linear":
        k = grow_fill(out, known, need, grow_steps)
        rest = need & ~k
        if rest.any():
            border = k & ndimage.binary_dilation(rest, structure=np.ones((3, 3), bool))
            rr, cc = np.nonzero(border)
            if rr.size > _MAX_SUPPORT:
                step = math.ceil(rr.size / _MAX_SUPPORT)
                rr, cc = rr[::step], cc[::step]
            nr, nc = np.nonzero(rest)
            if rr.size >= 3:
                try:
                    out[nr, nc] = linear_from_support(rr, cc, out[rr, cc], nr, nc)
                except Exception as exc:  # qhull: collinear support etc.
                    log.debug("linear fill fell back to nearest (%s)", exc)
    elif method != "nearest":
        raise ValueError(f"unknown fill method {method!r}")
    still = need & np.isnan(out)
    if still.any():
        _, (ir, ic) = ndimage.distance_transform_edt(~known, return_indices=True)
        out[still] = out[ir[still], ic[still]]
    return out


def surfaces_from_accumulator(
    acc: GridAccumulator,
    dsm_fill_max_m: float = 2.0,
    dtm_fill: str = "linear",
    dtm_window_m: float = 30.0,
) -> dict[str, np.ndarray]:
    """DSM, DTM, nDSM (NaN = nodata) and density (points/m2) on the accumulator's grid."""
    g = acc.grid
    sx, _ = g.metres_per_unit()
    px_m = abs(g.transform.a) * sx
    count = acc.shaped(acc.count)
    has = count > 0
    zmax = acc.shaped(acc.zmax).astype(np.float64)
    density = (count / g.cell_area_m2()).astype(np.float32)
    if not has.any():
        nan = np.full(has.shape, np.nan)
        return {"dsm": nan, "dtm": nan.copy(), "ndsm": nan.copy(), "density": density}
    dist = ndimage.distance_transform_edt(~has)
    dsm_target = dist * px_m <= max(dsm_fill_max_m, px_m * 0.5)
    dsm = fill_gaps(
        zmax, has, dsm_target, "linear", grow_steps=math.ceil(dsm_fill_max_m / px_m) + 1
    )
    dsm_ok = dsm_target & np.isfinite(dsm)
    gcount = acc.shaped(acc.gcount)
    if gcount.any():
        dtm_known = gcount > 0
        dtm_raw = acc.shaped(acc.gsum) / np.maximum(gcount, 1)
        log.info("DTM from ground class: %d ground cells", int(dtm_known.sum()))
    else:
        win = max(3, int(round(dtm_window_m / px_m)) | 1)
        zmin = acc.shaped(acc.zmin).astype(np.float64)  # +inf where empty
        ero = ndimage.minimum_filter(zmin, size=win, mode="nearest")
        ero[~np.isfinite(ero)] = -np.inf
        dtm_raw = ndimage.maximum_filter(ero, size=win, mode="nearest")
        dtm_known = has & np.isfinite(dtm_raw)
        log.info("no ground class: DTM from lowest points, opening window %d px", win)
    dtm = fill_gaps(dtm_raw, dtm_known, dsm_ok, dtm_fill)
    dtm[~dsm_ok] = np.nan
    dsm[~dsm_ok] = np.nan
    dtm = np.minimum(dtm, dsm)  # ground never above the surface
    ndsm = np.clip(dsm - dtm, 0.0, None)
    return {"dsm": dsm, "dtm": dtm, "ndsm": ndsm, "density": density}


def _metric_xyz(pts: lidar.Points, grid: Grid) -> np.ndarray:
    sx, sy = grid.metres_per_unit()
    b = grid.bounds
    return np.column_stack([(pts.x - b[0]) * sx, (pts.y - b[1]) * sy, pts.z])


def lidar_tile(
    grid: Grid,
    lidar_files: list[str],
    lidar_crs: str | None = None,
    point_margin_m: float = 20.0,
    outlier: dict[str, Any] | None = None,
    dsm_fill_max_m: float = 2.0,
    dtm_fill: str = "linear",
    dtm_window_m: float = 30.0,
    chunk_points: int = 1_000_000,
    drop_classes: tuple[int, ...] = (7, 18),
    backend: str = "laspy",
    pdal_pipeline: Any = None,
    pdal_ground: Any = None,
) -> tuple[dict[str, np.ndarray], lidar.Points]:
    """Surfaces on ``grid`` and the filtered points inside it, from the overlapping point clouds.

    ``backend`` ``laspy``: LAS/LAZ read by laspy, open3d outlier removal (``outlier``).
    ``pdal`` (``auto`` when it imports): read by PDAL, then the filter stages ``pdal_pipeline``
    (null: the PDAL twin of ``outlier``) and, where no point is ground, ``pdal_ground``
    (:mod:`georeg.map.pdal_points`). Pipeline errors are raised before anything is read.
    The rule passes the backend ``map.lidar_backend`` resolves to; the library default is laspy.
    """
    outlier = outlier or {}
    backend = pdal_points.resolve_backend(backend)
    if backend == "pdal":
        stages = pdal_points.resolve_pipeline(pdal_pipeline, outlier)
        ground = pdal_points.resolve_ground(pdal_ground)
        pdal_points.check_stages(stages)
        if ground is not None:
            pdal_points.check_stages([ground], "map.pdal_ground")
    sx, _ = grid.metres_per_unit()
    margin_px = math.ceil(point_margin_m / (abs(grid.transform.a) * sx))
    big = grid.grown(margin_px)
    pcrs = lidar.split_crs(grid.pcrs)[0]
    infos = [pdal_points.scan_any(p, lidar_crs, backend) for p in lidar_files]
    hits = [i for i in infos if lidar.overlaps(lidar.bounds_in(i, pcrs), big.bounds)]
    if not hits:
        log.warning(
            "no LiDAR file overlaps this tile (%s): empty coverage",
            ", ".join(lidar_files) or "no map.lidar",
        )
    reader = pdal_points.read_points if backend == "pdal" else lidar.read_points
    pts = reader(hits, pcrs, big.bounds, chunk_points)
    if drop_classes and len(pts):
        noise = np.isin(pts.classification, np.asarray(drop_classes, np.uint8))
        if noise.any():
            log.info(
                "dropped %d points of classes %s (noise)", int(noise.sum()), list(drop_classes)
            )
            pts = pts.take(~noise)
    n0 = len(pts)
    if n0 and backend == "pdal":
        b = big.bounds
        pts = pdal_points.filter_points(
            pts, stages, ground, (b[0], b[1]), grid.metres_per_unit(), [i.path for i in hits]
        )
    elif n0 and outlier.get("enabled", True):
        keep = lidar.remove_outliers(
            _metric_xyz(pts, grid), outlier.get("nb_neighbors", 8), outlier.get("std_ratio", 3.0)
        )
        pts = pts.take(keep)
        log.info(
            "outlier removal: %d of %d points removed (%.2f%%)",
            n0 - len(pts),
            n0,
            100.0 * (n0 - len(pts)) / n0,
        )
    elif n0 == 0 and hits:
        log.warning("LiDAR files overlap the tile's bounds but no point falls inside it")
    acc = GridAccumulator(big)
    acc.add(pts.x, pts.y, pts.z, pts.classification == GROUND)
    surf = surfaces_from_accumulator(acc, dsm_fill_max_m, dtm_fill, dtm_window_m)
    m = margin_px
    surf = {k: v[m : m + grid.height, m : m + grid.width] for k, v in surf.items()}
    b = grid.bounds
    inside = (pts.x >= b[0]) & (pts.x < b[2]) & (pts.y > b[1]) & (pts.y <= b[3])
    return surf, pts.take(inside)


def _dem_z_to_m(units: str | None) -> float:
    u = (units or "").strip().lower()
    if u in ("us survey foot", "us-ft", "ftus", "us_survey_foot", "us survey feet"):
        return 1200.0 / 3937.0
    if u in ("ft", "foot", "feet", "international foot"):
        return 0.3048
    return 1.0


def dem_tile(grid: Grid, dem_path: str, resampling: str = "bilinear") -> dict[str, np.ndarray]:
    """Resample a DEM onto ``grid``: DSM = DTM = DEM (metres), nDSM = 0, density = DEM posts/m2."""
    with open_raster(dem_path) as ds:
        f = _dem_z_to_m(ds.units[0] if ds.units else None)
        dem_cell_m2 = Grid(ds.crs, ds.transform, ds.width, ds.height).cell_area_m2()
        with on_grid(
            ds, grid.crs, grid.transform, grid.width, grid.height, Resampling[resampling]
        ) as (
            src,
            win,
        ):
            boundless = src is ds
            z = read(src, window=win, boundless=boundless, masked=True, path=dem_path)
            m = read_masks(src, window=win, path=dem_path) if not boundless else None
    z = np.ma.filled(z[0].astype(np.float64), np.nan)
    if m is not None:
        z[m[0] == 0 if m.ndim == 3 else m == 0] = np.nan
    z *= f
    ok = np.isfinite(z)
    if not ok.any():
        log.warning("%s does not overlap this tile: empty coverage", dem_path)
    density = np.where(ok, 1.0 / dem_cell_m2, 0.0).astype(np.float32)  # DEM posts per m2
    log.info(
        "DEM %s resampled (z factor %.6g): %.1f%% of the tile valid", dem_path, f, 100 * ok.mean()
    )
    return {"dsm": z, "dtm": z.copy(), "ndsm": np.where(ok, 0.0, np.nan), "density": density}


def dem_points(grid: Grid, surf: dict[str, np.ndarray]) -> lidar.Points:
    """One ground point per valid pixel centre (the DEM's 'point cloud')."""
    rr, cc = np.nonzero(np.isfinite(surf["dsm"]))
    x, y = rasterio.transform.xy(grid.transform, rr, cc, offset="center")
    n = rr.size
    one = np.ones(n, np.uint8)
    return lidar.Points(
        np.asarray(x, np.float64),
        np.asarray(y, np.float64),
        surf["dsm"][rr, cc],
        np.full(n, GROUND, np.uint8),
        one,
        one.copy(),
        np.zeros(n, np.uint16),
    )


def sample_rgb(ortho_path: str | os.PathLike, pts: lidar.Points) -> np.ndarray:
    """RGB (uint8, n x 3) of the orthophoto pixel under each point (0 where invalid/outside)."""
    rgb = np.zeros((len(pts), 3), np.uint8)
    if not len(pts):
        return rgb
    with open_raster(ortho_path) as ds:
        img = read(ds, path=ortho_path)
        mask = read_masks(ds, path=ortho_path) > 0
        # the inverse affine on the arrays (rasterio's rowcol loops in Python: 0.57 s a demo tile)
        col, row = ~ds.transform * (np.asarray(pts.x, np.float64), np.asarray(pts.y, np.float64))
        r, c = np.floor(row).astype(np.int64), np.floor(col).astype(np.int64)
        ok = (r >= 0) & (r < ds.height) & (c >= 0) & (c < ds.width)
        ok[ok] &= mask[r[ok], c[ok]]
        bands = [0, 1, 2] if img.shape[0] >= 3 else [0, 0, 0]
        for j, b in enumerate(bands):
            rgb[ok, j] = _to_u8(img[b])[r[ok], c[ok]]
    return rgb


def _to_u8(band: np.ndarray) -> np.ndarray:
    if band.dtype == np.uint8:
        return band
    lo, hi = np.nanpercentile(band, [1, 99]) if band.size else (0, 1)
    return np.clip((band - lo) / max(hi - lo, 1e-12) * 255, 0, 255).astype(np.uint8)


def write_surfaces(grid: Grid, surf: dict[str, np.ndarray], outputs: dict[str, str]) -> None:
    """Write each layer as a float32 COG on ``grid`` (NaN -> ELEV_NODATA; density: no nodata)."""
    for layer in LAYERS:
        a = surf[layer].astype(np.float32)
        if layer == "density":
            write_cog(outputs[layer], a, grid.crs, grid.transform, nodata=None, units="1/m2")
        else:
            a = np.where(np.isfinite(a), a, ELEV_NODATA).astype(np.float32)
            write_cog(
                outputs[layer], a, grid.crs, grid.transform, nodata=ELEV_NODATA, units="metre"
            )


def make_elevation_tile(
    ortho_tile: str,
    outputs: dict[str, str],
    lidar_files: list[str] | None = None,
    dem: str | None = None,
    lidar_crs: str | None = None,
    settings: dict[str, Any] | None = None,
    chunk_points: int = 1_000_000,
) -> None:
    """Rule body of ``map_tile_elevation``: surfaces + textured points of one tile.

    ``outputs`` maps ``dsm``, ``dtm``, ``ndsm``, ``density`` and ``points`` to paths.
    ``settings`` holds the ``map_prep`` keys that change the result (see config/README.md).
    """
    s = settings or {}
    grid = Grid.of(ortho_tile)
    if lidar_files:
        surf, pts = lidar_tile(
            grid,
            list(lidar_files),
            lidar_crs,
            point_margin_m=s.get("point_margin_m", 20.0),
            outlier=s.get("outlier"),
            dsm_fill_max_m=s.get("dsm_fill_max_m", 2.0),
            dtm_fill=s.get("dtm_fill", "linear"),
            dtm_window_m=s.get("dtm_window_m", 30.0),
            chunk_points=chunk_points,
            drop_classes=tuple(s.get("drop_classes", (7, 18))),
            backend=s.get("backend", "laspy"),
            pdal_pipeline=s.get("pdal_pipeline"),
            pdal_ground=s.get("pdal_ground", pdal_points.DEFAULT_GROUND),
        )
    elif dem:
        surf = dem_tile(grid, dem, s.get("dem_resampling", "bilinear"))
        pts = dem_points(grid, surf)
    else:  # orthophoto-only map: registration needs no heights; the height layers are nodata
        log.info("tile %s: map without elevation (no map.lidar, no map.dem): heights nodata", ortho_tile)
        nan = np.full((grid.height, grid.width), np.nan, np.float32)
        surf = {"dsm": nan, "dtm": nan.copy(), "ndsm": nan.copy(), "density": np.zeros_like(nan)}
        pts = lidar.Points.empty()
    rgb = sample_rgb(ortho_tile, pts)
    ok = np.isfinite(surf["dsm"])
    log.info(
        "tile %s: %d points kept, DSM valid %.1f%%, DSM %s m, nDSM max %s m",
        ortho_tile,
        len(pts),
        100.0 * ok.mean(),
        f"{np.nanmin(surf['dsm']):.2f}..{np.nanmax(surf['dsm']):.2f}" if ok.any() else "-",
        f"{np.nanmax(surf['ndsm']):.2f}" if ok.any() else "-",
    )
    write_surfaces(grid, surf, outputs)
    lidar.write_textured_laz(outputs["points"], pts, rgb, grid.pcrs)
