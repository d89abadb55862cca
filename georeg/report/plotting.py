"""Drawing helpers shared by the report's figures: map crops read by windows, outlines, the
query data a figure needs (``QueryData``, ``load_query_data``), matplotlib set-up and saving.

Map panels are drawn in map coordinates (``imshow`` with the map extent), so footprints,
candidate regions and correspondences are plotted directly in map x, y. Rasters are read through
windowed, decimated reads of the mosaics (``results/map/mosaic/*.vrt``): the cost does not grow
with the map.
"""

from __future__ import annotations

import logging
import math
import textwrap
import warnings
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from georeg.io.atomic import atomic_path

log = logging.getLogger(__name__)


Bounds = tuple[float, float, float, float]


PART_COLOURS = ["#1f77b4", "#ff7f0e", "#9467bd", "#8c564b", "#e377c2", "#17becf"]


FUSED_COLOUR = "#00e000"


TRUTH_COLOUR = "#ff00ff"


def pyplot() -> Any:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    plt.rcParams.update(
        {
            "font.size": 11,
            "axes.titlesize": 12,
            "axes.labelsize": 11,
            "legend.fontsize": 10,
            "figure.titlesize": 14,
        }
    )
    return plt


@dataclass
class MapCrop:
    """A decimated read of a map raster over bounds: image, its map extent and pixel size."""

    data: np.ndarray  # (bands, rows, cols)
    valid: np.ndarray  # (rows, cols) bool
    bounds: Bounds  # west, south, east, north of the pixels read
    res: float  # map units per crop pixel

    @property
    def extent(self) -> tuple[float, float, float, float]:
        """matplotlib ``imshow`` extent (left, right, bottom, top)."""
        w, s, e, n = self.bounds
        return (w, e, s, n)

    def to_px(self, xy: np.ndarray) -> np.ndarray:
        """Map x, y -> crop pixel-centre (col, row)."""
        w, _, _, n = self.bounds
        return np.c_[(xy[:, 0] - w) / self.res - 0.5, (n - xy[:, 1]) / self.res - 0.5]

    def px_matrix(self) -> np.ndarray:
        """3x3 matrix map (x, y, 1) -> crop pixel-centre (col, row, 1)."""
        w, _, _, n = self.bounds
        r = self.res
        return np.array([[1 / r, 0, -w / r - 0.5], [0, -1 / r, n / r - 0.5], [0, 0, 1.0]])


def read_crop(path: str | Path, bounds: Bounds | None = None, max_px: int = 1024) -> MapCrop | None:
    """Read ``path`` over ``bounds`` (map units; None = everything) at most ``max_px`` per side.

    Returns None when the bounds miss the raster or the file is absent.
    """
    import rasterio
    from rasterio.enums import Resampling
    from rasterio.windows import Window, from_bounds

    if not Path(path).exists():
        return None
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        with rasterio.open(path) as ds:
            if bounds is None:
                win = Window(0, 0, ds.width, ds.height)
            else:
                win = from_bounds(*bounds, transform=ds.transform)
                c0 = max(0, math.floor(win.col_off))
                r0 = max(0, math.floor(win.row_off))
                c1 = min(ds.width, math.ceil(win.col_off + win.width))
                r1 = min(ds.height, math.ceil(win.row_off + win.height))
                if c1 <= c0 or r1 <= r0:
                    return None
                win = Window(c0, r0, c1 - c0, r1 - r0)
            f = max(1.0, max(win.width, win.height) / max_px)
            shape = (max(1, round(win.height / f)), max(1, round(win.width / f)))
            data = ds.read(window=win, out_shape=(ds.count, *shape), resampling=Resampling.average)
            valid = ds.dataset_mask(window=win, out_shape=shape) > 0
            if ds.nodata is not None and data.dtype.kind == "f":
                valid &= data[0] != ds.nodata
            if data.dtype.kind == "f":
                valid &= np.isfinite(data[0])
            tr = ds.window_transform(win)
    west, north = tr.c, tr.f
    east = west + tr.a * win.width
    south = north + tr.e * win.height
    return MapCrop(data, valid, (west, south, east, north), abs(tr.a) * win.width / shape[1])


def crop_rgb(crop: MapCrop) -> np.ndarray:
    """RGBA uint8 of an orthophoto crop (gray repeated; stretched when not uint8)."""
    d = crop.data[:3] if crop.data.shape[0] >= 3 else np.repeat(crop.data[:1], 3, 0)
    rgb = np.moveaxis(d, 0, -1)
    if rgb.dtype != np.uint8:
        v = rgb[crop.valid]
        lo, hi = np.percentile(v, [1, 99]) if v.size else (0.0, 1.0)
        rgb = np.clip((rgb - lo) / max(hi - lo, 1e-12) * 255, 0, 255).astype(np.uint8)
    return np.dstack([rgb, np.where(crop.valid, 255, 0).astype(np.uint8)])


def crop_gray(crop: MapCrop) -> np.ndarray:
    """uint8 luminance of an orthophoto crop (0 where invalid)."""
    rgb = crop_rgb(crop)[..., :3].astype(np.float64)
    g = 0.299 * rgb[..., 0] + 0.587 * rgb[..., 1] + 0.114 * rgb[..., 2]
    return np.where(crop.valid, np.clip(g, 1, 255), 0).astype(np.uint8)


def apply_h(H: np.ndarray, pts: np.ndarray) -> np.ndarray:
    """Apply a 3x3 homography to (n, 2) points."""
    p = np.c_[pts, np.ones(len(pts))] @ np.asarray(H, np.float64).T
    with np.errstate(divide="ignore", invalid="ignore"):
        return p[:, :2] / p[:, 2:3]


def outline(
    width: int, height: int, rows: tuple[int, int] | None = None, n: int = 20
) -> np.ndarray:
    """Closed outline (query pixel (col, row)) of the query or of rows [r0, r1)."""
    r0, r1 = rows if rows is not None else (0, height)
    c0, c1 = -0.5, width - 0.5
    ra, rb = r0 - 0.5, r1 - 0.5
    top = np.c_[np.linspace(c0, c1, n), np.full(n, ra)]
    right = np.c_[np.full(n, c1), np.linspace(ra, rb, n)]
    bottom = np.c_[np.linspace(c1, c0, n), np.full(n, rb)]
    left = np.c_[np.full(n, c0), np.linspace(rb, ra, n)]
    return np.vstack([top, right, bottom, left, top[:1]])


def footprint(H: Any, width: int, height: int, rows: tuple[int, int] | None = None) -> np.ndarray:
    """Map outline of the query (or rows) through H."""
    return apply_h(np.asarray(H, np.float64), outline(width, height, rows))


def truth_outline(tx: np.ndarray, ty: np.ndarray) -> np.ndarray | None:
    """Map outline of the query from its truth raster (border pixels), None without truth."""
    h, w = tx.shape
    if h == 0 or w == 0:
        return None
    idx = np.r_[
        [(0, c) for c in range(w)],
        [(r, w - 1) for r in range(h)],
        [(h - 1, c) for c in range(w - 1, -1, -1)],
        [(r, 0) for r in range(h - 1, -1, -1)],
    ]
    step = max(1, len(idx) // 200)
    idx = idx[::step]
    x, y = tx[idx[:, 0], idx[:, 1]], ty[idx[:, 0], idx[:, 1]]
    ok = np.isfinite(x) & np.isfinite(y)
    if ok.sum() < 4:
        return None
    pts = np.c_[x[ok], y[ok]]
    return np.vstack([pts, pts[:1]])


def grow(b: Bounds, f: float = 0.15, min_pad: float = 0.0) -> Bounds:
    """Bounds grown by a fraction of their larger side (at least ``min_pad``)."""
    pad = max(min_pad, f * max(b[2] - b[0], b[3] - b[1]))
    return (b[0] - pad, b[1] - pad, b[2] + pad, b[3] + pad)


def bounds_of(*arrays: np.ndarray | None) -> Bounds | None:
    """Bounding box of point arrays (finite points only)."""
    pts = [a[np.isfinite(a).all(axis=1)] for a in arrays if a is not None and len(a)]
    pts = [p for p in pts if len(p)]
    if not pts:
        return None
    p = np.vstack(pts)
    return (float(p[:, 0].min()), float(p[:, 1].min()), float(p[:, 0].max()), float(p[:, 1].max()))


def warp_to_crop(band: np.ndarray, H: Any, crop: MapCrop) -> np.ndarray:
    """Query band (uint8, 0 = nodata) warped onto the crop's pixel grid through H (0 outside)."""
    import cv2

    A = crop.px_matrix() @ np.asarray(H, np.float64)
    h, w = crop.valid.shape
    return cv2.warpPerspective(band, A, (w, h), flags=cv2.INTER_LINEAR, borderValue=0)


def crop_to_query(img: np.ndarray, H: Any, crop: MapCrop, width: int, height: int) -> np.ndarray:
    """A crop image resampled into query geometry through H (what the map shows under each pixel)."""
    import cv2

    A = crop.px_matrix() @ np.asarray(H, np.float64)
    return cv2.warpPerspective(
        img, A, (width, height), flags=cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP, borderValue=0
    )


def save_figure(fig: Any, path: Path, dpi: int) -> None:
    """Save as PNG, quantised to a 256-colour palette (3-5x smaller, same look)."""
    import io

    plt = pyplot()
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=dpi, bbox_inches="tight", facecolor="white")
    plt.close(fig)
    data = buf.getvalue()
    try:
        from PIL import Image

        im = Image.open(io.BytesIO(data)).convert("RGB")
        q = im.quantize(colors=256, method=Image.Quantize.FASTOCTREE, dither=Image.Dither.NONE)
        out = io.BytesIO()
        q.save(out, format="PNG", optimize=True)
        data = out.getvalue()
    except ImportError:  # pragma: no cover - Pillow ships with matplotlib
        pass
    with atomic_path(path) as tmp:
        tmp.write_bytes(data)


def show_band(ax: Any, band: np.ndarray, title: str) -> None:
    img = np.ma.masked_equal(band, 0)
    ax.imshow(img, cmap="gray", vmin=1, vmax=255, interpolation="antialiased")
    ax.set_facecolor("#dddddd")
    ax.set_title(title)
    ax.set_xlabel("query column (px)")
    ax.set_ylabel("query row (px)")


def map_axes(ax: Any, crop: MapCrop | None, title: str, units: str = "m") -> None:
    if crop is not None:
        ax.imshow(crop_rgb(crop), extent=crop.extent, interpolation="antialiased")
        ax.set_xlim(crop.extent[0], crop.extent[1])
        ax.set_ylim(crop.extent[2], crop.extent[3])
    ax.set_facecolor("#dddddd")
    ax.set_title(title)
    ax.set_xlabel(f"map x ({units})")
    ax.set_ylabel(f"map y ({units})")
    ax.ticklabel_format(useOffset=False, style="plain")
    ax.tick_params(axis="x", labelrotation=30)
    ax.set_aspect("equal")


def plot_outline(ax: Any, pts: np.ndarray | None, **kw: Any) -> None:
    if pts is None:
        return
    ok = np.isfinite(pts).all(axis=1)
    if ok.sum() >= 2:
        ax.plot(pts[ok, 0], pts[ok, 1], **kw)


def text_panel(ax: Any, title: str, lines: Sequence[str], colour: str = "#b00020") -> None:
    ax.axis("off")
    ax.text(
        0.02,
        0.92,
        title,
        fontsize=20,
        weight="bold",
        color=colour,
        transform=ax.transAxes,
        va="top",
    )
    body = "\n".join(textwrap.fill(s, 75, subsequent_indent="    ") for s in lines)
    ax.text(0.02, 0.78, body, fontsize=13, transform=ax.transAxes, va="top", family="monospace")


@dataclass
class QueryData:
    """Everything the figures of one query need (loaded once)."""

    name: str
    reg: dict[str, Any]
    band: np.ndarray
    parts: list[dict[str, Any]]
    ortho: str
    ndsm: str | None = None
    evaluation: dict[str, Any] | None = None
    truth: tuple[np.ndarray, np.ndarray] | None = None
    geoloc: tuple[np.ndarray, np.ndarray] | None = None
    products: str | None = None
    labels: str | None = None
    units: str = "m"

    @property
    def registered(self) -> bool:
        return self.reg.get("status") == "registered" and self.reg.get("homography") is not None

    @property
    def H(self) -> np.ndarray:
        return np.asarray(self.reg["homography"], np.float64)

    @property
    def shape(self) -> tuple[int, int]:
        return self.band.shape  # type: ignore[return-value]

    def fused_outline(self) -> np.ndarray | None:
        h, w = self.shape
        return footprint(self.H, w, h) if self.registered else None

    def part_outlines(self) -> list[tuple[int, np.ndarray]]:
        h, w = self.shape
        out = []
        for p in self.reg.get("parts") or []:
            if p.get("homography") is not None:
                rows = tuple(p.get("rows") or (0, h))
                out.append((int(p["part"]), footprint(p["homography"], w, h, rows)))  # type: ignore[arg-type]
        return out

    def truth_outline(self) -> np.ndarray | None:
        return None if self.truth is None else truth_outline(*self.truth)
