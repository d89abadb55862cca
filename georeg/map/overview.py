"""Quicklook PNG of the whole map: orthophoto with the tile grid, next to a hillshaded DSM."""

from __future__ import annotations

import logging
import math
import os

import numpy as np

from georeg.io.atomic import atomic_path
from georeg.io.raster import open_raster, read, read_masks
from georeg.map.grid import MapGrid

log = logging.getLogger(__name__)


def hillshade(
    z: np.ndarray, dx: float, dy: float, azimuth: float = 315.0, altitude: float = 45.0
) -> np.ndarray:
    """Lambertian hillshade in [0, 1] of a height grid (NaN stays NaN); dx, dy in z units."""
    gy, gx = np.gradient(z, dy, dx)
    slope = np.arctan(np.hypot(gx, gy))
    aspect = np.arctan2(-gx, gy)
    az, alt = math.radians(360.0 - azimuth + 90.0), math.radians(altitude)
    shade = np.sin(alt) * np.cos(slope) + np.cos(alt) * np.sin(slope) * np.cos(az - aspect)
    return np.clip(shade, 0.0, 1.0)


def _decimated(path: str, max_px: int, masked_float: bool) -> tuple[np.ndarray, np.ndarray, float]:
    """Read a raster shrunk to at most ``max_px`` on its long side (uses overviews)."""
    with open_raster(path) as ds:
        f = max(1.0, max(ds.width, ds.height) / max_px)
        shape = (max(1, round(ds.height / f)), max(1, round(ds.width / f)))
        arr = read(ds, out_shape=(ds.count, *shape), path=path)
        mask = read_masks(ds, out_shape=shape, path=path) > 0
        if masked_float and ds.nodata is not None:
            mask &= arr[0] != ds.nodata
        return arr, mask, f


def make_overview(
    grid_path: str | os.PathLike,
    ortho_vrt: str,
    dsm_vrt: str,
    out: str | os.PathLike,
    max_px: int = 1024,
) -> None:
    """Render the overview PNG from the mosaics with decimated reads (cheap for any map size)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.patches import Rectangle

    grid = MapGrid.load(grid_path)
    img, imask, f = _decimated(ortho_vrt, max_px, False)
    rgb = np.moveaxis(img[:3] if img.shape[0] >= 3 else np.repeat(img[:1], 3, 0), 0, -1)
    if rgb.dtype != np.uint8:
        lo, hi = np.percentile(rgb[imask], [1, 99]) if imask.any() else (0, 1)
        rgb = np.clip((rgb - lo) / max(hi - lo, 1e-12) * 255, 0, 255).astype(np.uint8)
    rgba = np.dstack([rgb, np.where(imask, 255, 0).astype(np.uint8)])
    z, zmask, fz = _decimated(dsm_vrt, max_px, True)
    z = np.where(zmask, z[0].astype(np.float64), np.nan)
    sx, _ = _units_m(grid)
    px_m = abs(grid.transform.a) * fz * sx
    shade = hillshade(
        np.where(np.isfinite(z), z, np.nanmean(z) if zmask.any() else 0.0), px_m, px_m
    )
    shade[~zmask] = np.nan

    aspect = grid.height / grid.width
    fig, axes = plt.subplots(1, 2, figsize=(12, max(3.0, 6 * aspect) + 0.6), dpi=110)
    ext = (0, grid.width, grid.height, 0)
    axes[0].imshow(rgba, extent=ext, interpolation="bilinear")
    for tid, t in grid.tiles.items():
        c = t.core
        axes[0].add_patch(
            Rectangle((c.col_off, c.row_off), c.width, c.height, fill=False, ec="yellow", lw=0.8)
        )
        if len(grid.tiles) <= 400:
            axes[0].text(
                c.col_off + c.width / 2,
                c.row_off + c.height / 2,
                tid,
                color="yellow",
                ha="center",
                va="center",
                fontsize=max(4, 9 - len(grid.tiles) // 40),
            )
    axes[0].set_title(
        f"orthophoto, {len(grid.tiles)} tiles ({grid.data['tile_size_px']} px, "
        f"overlap {grid.data['tile_overlap_px']} px)"
    )
    axes[1].imshow(shade, extent=ext, cmap="gray", vmin=0, vmax=1, interpolation="bilinear")
    if zmask.any():
        im = axes[1].imshow(z, extent=ext, cmap="terrain", alpha=0.45, interpolation="bilinear")
        fig.colorbar(im, ax=axes[1], fraction=0.046, pad=0.02, label="DSM height (m)")
    else:
        axes[1].text(grid.width / 2, grid.height / 2, "no elevation", ha="center")
    axes[1].set_title("hillshaded DSM")
    for ax in axes:
        ax.set_xlim(0, grid.width)
        ax.set_ylim(grid.height, 0)
        ax.set_xlabel("map column (px)")
    axes[0].set_ylabel("map row (px)")
    fig.tight_layout()
    with atomic_path(out) as tmp:
        fig.savefig(tmp, format="png")
    plt.close(fig)
    log.info("overview %s (ortho read at 1/%.1f, DSM at 1/%.1f)", out, f, fz)


def _units_m(grid: MapGrid) -> tuple[float, float]:
    from georeg.map.elevation import Grid

    return Grid(grid.crs, grid.transform, grid.width, grid.height).metres_per_unit()
