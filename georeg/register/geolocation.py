"""Per-pixel geolocation of the query (x, y, z in the map CRS) and its evaluation against truth."""

from __future__ import annotations

import logging
import warnings
from pathlib import Path
from typing import Any

import numpy as np

from georeg.io.atomic import atomic_path
from georeg.io.errors import InputError

log = logging.getLogger(__name__)


def apply_h(H: np.ndarray, col: np.ndarray, row: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Map x, y of query pixels (col, row; any broadcastable arrays) through H; NaN behind the
    horizon (w <= 0)."""
    w = H[2, 0] * col + H[2, 1] * row + H[2, 2]
    with np.errstate(divide="ignore", invalid="ignore"):
        x = (H[0, 0] * col + H[0, 1] * row + H[0, 2]) / w
        y = (H[1, 0] * col + H[1, 1] * row + H[1, 2]) / w
    bad = w <= 0
    return np.where(bad, np.nan, x), np.where(bad, np.nan, y)


def ground_px(H: np.ndarray, width: int, height: int) -> float:
    """Map units per query pixel at the footprint's centre (sqrt of H's local Jacobian area)."""
    x, y = apply_h(H, np.array([width / 2, width / 2 + 1, width / 2]),
                   np.array([height / 2, height / 2, height / 2 + 1]))  # fmt: skip
    return float(np.sqrt(abs((x[1] - x[0]) * (y[2] - y[0]) - (x[2] - x[0]) * (y[1] - y[0]))))


def map_xy(H: np.ndarray, width: int, height: int) -> tuple[np.ndarray, np.ndarray]:
    """Map x, y (float64, (height, width)) of every query pixel centre (col, row) through H."""
    u = np.arange(width, dtype=np.float64)
    v = np.arange(height, dtype=np.float64)[:, None]
    return apply_h(H, u, v)


def sample_raster(path: str | Path, x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """Bilinear sample of band 1 of a raster (e.g. the DSM mosaic VRT) at map x, y; NaN outside.

    Reads only the window covering the points.
    """
    import rasterio
    from rasterio.windows import Window, from_bounds

    from georeg.index.features import map_to_pixel, sample_bilinear

    out = np.full(x.shape, np.nan, np.float64)
    ok = np.isfinite(x) & np.isfinite(y)
    if not ok.any():
        return out
    try:
        with rasterio.open(path) as ds:
            pad = 2 * max(abs(ds.transform.a), abs(ds.transform.e))
            win = from_bounds(
                x[ok].min() - pad,
                y[ok].min() - pad,
                x[ok].max() + pad,
                y[ok].max() + pad,
                ds.transform,
            )
            c0 = max(0, int(np.floor(win.col_off)))
            r0 = max(0, int(np.floor(win.row_off)))
            c1 = min(ds.width, int(np.ceil(win.col_off + win.width)))
            r1 = min(ds.height, int(np.ceil(win.row_off + win.height)))
            if c1 <= c0 or r1 <= r0:
                return out  # no overlap with the raster
            win = Window(c0, r0, c1 - c0, r1 - r0)
            band = ds.read(1, window=win, out_dtype="float32")
            nodata = ds.nodata
            tr = ds.window_transform(win)
    except rasterio.errors.RasterioIOError as exc:
        raise InputError(path, f"cannot read raster: {exc}") from exc
    c, r = map_to_pixel(tr, x[ok], y[ok])
    out[ok] = sample_bilinear(band, c, r, nodata)
    return out


def write_geolocation(
    path: str | Path,
    H: np.ndarray | None,
    width: int,
    height: int,
    dsm: str | Path | None,
    crs_wkt: str | None,
    xy: tuple[np.ndarray, np.ndarray] | None = None,
) -> dict[str, Any]:
    """Write the 3-band float64 (x, y, z) raster in query geometry; all NaN when H is None.

    ``xy``: per-pixel map x, y (e.g. the local refinement's) instead of H's.
    """
    import rasterio

    if H is None and xy is None:
        x = y = z = np.full((height, width), np.nan)
    else:
        x, y = xy if xy is not None else map_xy(H, width, height)
        z = sample_raster(dsm, x, y) if dsm and Path(dsm).exists() else np.full(x.shape, np.nan)
    profile = {
        "driver": "GTiff",
        "width": width,
        "height": height,
        "count": 3,
        "dtype": "float64",
        "nodata": float("nan"),
        "compress": "deflate",
        "predictor": 3,
        "tiled": True,
        "blockxsize": 256,
        "blockysize": 256,
    }
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", rasterio.errors.NotGeoreferencedWarning)
        with atomic_path(path) as tmp, rasterio.open(tmp, "w", **profile) as dst:
            dst.write(np.stack([x, y, z]))
            for i, d in enumerate(("x", "y", "z"), start=1):
                dst.set_band_description(i, d)
            dst.update_tags(
                CONTENT="map x, y, z of every query pixel centre (col, row)",
                MAP_CRS_WKT=crs_wkt or "",
            )
    valid_z = np.isfinite(z)
    return {"z_valid_fraction": float(valid_z.mean()) if z.size else 0.0}


def evaluate(
    H: np.ndarray | None,
    truth: str | Path,
    map_px_m: float,
    xy: tuple[np.ndarray, np.ndarray] | None = None,
) -> dict[str, Any]:
    """Error of the registration against a truth raster (2 bands: true map x, y per query pixel).

    Returns median / p90 / max / RMSE in metres and in map pixels over the pixels with a truth.
    """
    import rasterio

    with warnings.catch_warnings():
        warnings.simplefilter("ignore", rasterio.errors.NotGeoreferencedWarning)
        try:
            with rasterio.open(truth) as ds:
                tx, ty = ds.read(1).astype(np.float64), ds.read(2).astype(np.float64)
        except rasterio.errors.RasterioIOError as exc:
            raise InputError(truth, f"cannot read the truth raster: {exc}") from exc
    valid = np.isfinite(tx) & np.isfinite(ty)
    out: dict[str, Any] = {"truth": str(truth), "pixels": int(valid.sum()), "map_px_m": map_px_m}
    if H is None and xy is None:
        out["status"] = "no registration"
        return out
    x, y = xy if xy is not None else map_xy(H, tx.shape[1], tx.shape[0])  # type: ignore[arg-type]
    e = np.hypot(x - tx, y - ty)[valid]
    e = np.where(np.isfinite(e), e, np.inf)
    if e.size == 0:
        out["status"] = "truth has no valid pixel"
        return out
    stats = {
        "median": float(np.median(e)),
        "p90": float(np.percentile(e, 90)),
        "max": float(e.max()),
        "rmse": float(np.sqrt(np.mean(e**2))),
    }
    out["m"] = stats
    out["px"] = {k: v / map_px_m for k, v in stats.items()}
    return out
