"""Per-query figures of the report: where the query landed, how well, and how it was found.

Every figure is a PNG (matplotlib Agg, ``dpi`` from ``report.figure_dpi``) sized to be read
without zooming (about 1300 px wide, 11-13 pt text). Map panels are drawn in map coordinates
(``imshow`` with the map extent), so footprints, candidate regions and correspondences are
plotted directly in map x, y. Rasters are read through windowed, decimated reads of the mosaics
(``results/map/mosaic/*.vrt``): the cost does not grow with the map.

``make_query_figures`` writes the figures that apply to a query into one directory plus
``figures.json`` (file, title, caption of each, in display order), which the HTML report reads.
"""

from __future__ import annotations

import json
import logging
import math
import textwrap
import warnings
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from georeg.io.atomic import atomic_path, write_json

log = logging.getLogger(__name__)

Bounds = tuple[float, float, float, float]

PART_COLOURS = ["#1f77b4", "#ff7f0e", "#9467bd", "#8c564b", "#e377c2", "#17becf"]
FUSED_COLOUR = "#00e000"
TRUTH_COLOUR = "#ff00ff"


def _plt() -> Any:
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


# ----------------------------------------------------------------------------- map reads


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


# ----------------------------------------------------------------------------- geometry


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


# ----------------------------------------------------------------------------- drawing helpers


def _save(fig: Any, path: Path, dpi: int) -> None:
    """Save as PNG, quantised to a 256-colour palette (3-5x smaller, same look)."""
    import io

    plt = _plt()
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


def _show_band(ax: Any, band: np.ndarray, title: str) -> None:
    img = np.ma.masked_equal(band, 0)
    ax.imshow(img, cmap="gray", vmin=1, vmax=255, interpolation="antialiased")
    ax.set_facecolor("#dddddd")
    ax.set_title(title)
    ax.set_xlabel("query column (px)")
    ax.set_ylabel("query row (px)")


def _map_axes(ax: Any, crop: MapCrop | None, title: str, units: str = "m") -> None:
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


def _plot_outline(ax: Any, pts: np.ndarray | None, **kw: Any) -> None:
    if pts is None:
        return
    ok = np.isfinite(pts).all(axis=1)
    if ok.sum() >= 2:
        ax.plot(pts[ok, 0], pts[ok, 1], **kw)


def _text_panel(ax: Any, title: str, lines: Sequence[str], colour: str = "#b00020") -> None:
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


# ----------------------------------------------------------------------------- the figures


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


def fig_match(q: QueryData, out: Path, dpi: int) -> str:
    """Query band | the orthophoto resampled into query geometry | the map crop it landed on."""
    plt = _plt()
    h, w = q.shape
    fp = q.fused_outline()
    b = grow(bounds_of(fp) or (0, 0, 1, 1), 0.1)
    crop = read_crop(q.ortho, b, 1000)
    fig, axes = plt.subplots(1, 3, figsize=(16, 6.5), gridspec_kw={"width_ratios": [1, 1, 1.25]})
    _show_band(
        axes[0],
        q.band,
        f"query band ({float(q.reg['band']['wavelength_nm']):.0f} nm)"
        if isinstance(q.reg.get("band"), dict) and q.reg["band"].get("wavelength_nm") is not None
        else "query band",
    )
    if crop is not None:
        under = crop_to_query(crop_gray(crop), q.H, crop, w, h)
        axes[1].imshow(np.ma.masked_equal(under, 0), cmap="gray", vmin=1, vmax=255)
    axes[1].set_facecolor("#dddddd")
    axes[1].set_title("orthophoto under each query pixel")
    axes[1].set_xlabel("query column (px)")
    _map_axes(axes[2], crop, "map crop where it landed (north up)", q.units)
    _plot_outline(axes[2], fp, color=FUSED_COLOUR, lw=2.5, label="registered footprint")
    _plot_outline(axes[2], q.truth_outline(), color=TRUTH_COLOUR, lw=1.5, ls="--", label="truth")
    # mark the query's first row (flight direction)
    top = apply_h(q.H, np.array([[0.0, 0.0], [w - 1.0, 0.0]]))
    axes[2].plot(top[:, 0], top[:, 1], color="red", lw=3, label="query row 0")
    axes[2].legend(loc="lower right", framealpha=0.85)
    fig.suptitle(f"{q.name}: query next to the map where it was registered")
    fig.tight_layout()
    _save(fig, out, dpi)
    return (
        "The query band (left), the orthophoto resampled into the query's geometry through the "
        "registration (middle: both should show the same scene, pixel for pixel), and the "
        "north-up map crop with the registered footprint (green; red = the query's first row)."
    )


def fig_checkerboard(q: QueryData, out: Path, dpi: int, squares: int = 8) -> str:
    """Checkerboard of the orthophoto and the warped query band over the footprint."""
    plt = _plt()
    fp = q.fused_outline()
    b = grow(bounds_of(fp) or (0, 0, 1, 1), 0.05)
    crop = read_crop(q.ortho, b, 1100)
    fig, ax = plt.subplots(1, 1, figsize=(10, 10))
    if crop is None:
        _text_panel(ax, "footprint outside the map", ["the orthophoto has no pixel there"])
        _save(fig, out, dpi)
        return "The registered footprint lies outside the orthophoto."
    gray = crop_gray(crop)
    warped = warp_to_crop(q.band, q.H, crop)
    h, w = gray.shape
    cell = max(8, int(max(h, w) / squares))
    yy, xx = np.mgrid[0:h, 0:w]
    board = ((yy // cell + xx // cell) % 2).astype(bool)
    show_q = board & (warped > 0)
    mix = np.where(show_q, warped, gray).astype(np.uint8)
    rgb = np.dstack([mix, mix, mix])
    # tint the query squares slightly so the two sources can be told apart
    rgb[show_q, 2] = np.clip(rgb[show_q, 2].astype(int) + 40, 0, 255).astype(np.uint8)
    ax.imshow(
        np.dstack([rgb, np.where(crop.valid | (warped > 0), 255, 0).astype(np.uint8)]),
        extent=crop.extent,
        interpolation="antialiased",
    )
    _map_axes(ax, None, "checkerboard: orthophoto / warped query band (bluish squares)", q.units)
    ax.set_xlim(crop.extent[0], crop.extent[1])
    ax.set_ylim(crop.extent[2], crop.extent[3])
    _plot_outline(ax, fp, color=FUSED_COLOUR, lw=2)
    fig.suptitle(f"{q.name}: do roads and roof edges continue across the squares?")
    fig.tight_layout()
    _save(fig, out, dpi)
    return (
        "Alternating squares of the orthophoto (grey) and of the query band warped onto it "
        "by the registration (bluish). A good registration shows edges that continue across "
        "square borders without a jump."
    )


def fig_footprints(q: QueryData, out: Path, dpi: int) -> str:
    """The footprints of the parts and of the fused result on the map overview (+ a zoom)."""
    plt = _plt()
    full = read_crop(q.ortho, None, 1024)
    fig, axes = plt.subplots(1, 2, figsize=(16, 7.8))
    _map_axes(axes[0], full, "map overview", q.units)
    fp = q.fused_outline()
    parts = q.part_outlines()
    tr = q.truth_outline()
    zb = bounds_of(fp, tr, *[p for _, p in parts])
    for ax in axes:
        for i, pts in parts:
            col = PART_COLOURS[i % len(PART_COLOURS)]
            ok = np.isfinite(pts).all(axis=1)
            ax.fill(pts[ok, 0], pts[ok, 1], color=col, alpha=0.3, lw=0)
            _plot_outline(ax, pts, color=col, lw=2, label=f"part {i} (own homography, own rows)")
        _plot_outline(ax, fp, color=FUSED_COLOUR, lw=2.5, label="fused registration")
        _plot_outline(ax, tr, color=TRUTH_COLOUR, lw=1.8, ls="--", label="truth")
    if full is not None and zb is not None:
        # keep the overview on the map, but include a footprint that lies beyond it
        fb = full.bounds
        pad = 0.03 * max(fb[2] - fb[0], fb[3] - fb[1])
        axes[0].set_xlim(min(fb[0], zb[0]) - pad, max(fb[2], zb[2]) + pad)
        axes[0].set_ylim(min(fb[1], zb[1]) - pad, max(fb[3], zb[3]) + pad)
    if zb is not None:
        zb = grow(zb, 0.1)
        zoom = read_crop(q.ortho, zb, 1000)
        _map_axes(axes[1], zoom, "zoom on the footprints", q.units)
        for i, pts in parts:
            col = PART_COLOURS[i % len(PART_COLOURS)]
            ok = np.isfinite(pts).all(axis=1)
            axes[1].fill(pts[ok, 0], pts[ok, 1], color=col, alpha=0.3, lw=0)
            _plot_outline(axes[1], pts, color=col, lw=2)
        _plot_outline(axes[1], fp, color=FUSED_COLOUR, lw=2.5)
        _plot_outline(axes[1], tr, color=TRUTH_COLOUR, lw=1.8, ls="--")
        axes[1].set_xlim(zb[0], zb[2])
        axes[1].set_ylim(zb[1], zb[3])
        if zoom is None:
            axes[1].text(
                0.5,
                0.5,
                "no orthophoto here:\nthe footprint lies outside the map",
                ha="center",
                va="center",
                fontsize=14,
                transform=axes[1].transAxes,
            )
    else:
        _text_panel(axes[1], "no footprint", ["no part was accepted and there is no truth"])
    h, _ = axes[0].get_legend_handles_labels()
    if h:
        axes[0].legend(loc="upper left", framealpha=0.85)
    fig.suptitle(f"{q.name}: footprints on the map")
    fig.tight_layout()
    _save(fig, out, dpi)
    return (
        "Footprints on the map: each accepted part's own rows through its own homography "
        "(before fusing), the fused registration of the whole query (green) and, when known, "
        "the true footprint (dashed magenta)."
    )


def _candidates(q: QueryData) -> list[tuple[int, dict[str, Any]]]:
    return [
        (int(p.get("part", i)), c) for i, p in enumerate(q.parts) for c in p.get("candidates", [])
    ]


def fig_search(q: QueryData, out: Path, dpi: int) -> str:
    """Candidate regions tried by each part, coloured by score (or inliers), the winner marked."""
    plt = _plt()
    from matplotlib import colormaps
    from matplotlib.colors import Normalize
    from matplotlib.patches import Rectangle

    full = read_crop(q.ortho, None, 900)
    n = max(1, len(q.parts))
    fig, axes = plt.subplots(1, n, figsize=(8 * n, 8.2), squeeze=False)
    axes = axes[0]
    cands = _candidates(q)
    scores = [c.get("score") for _, c in cands]
    by_score = any(s is not None for s in scores)
    vals = [(c.get("score") if by_score else c.get("inliers", 0)) for _, c in cands]
    finite = [v for v in vals if v is not None]
    norm = Normalize(min(finite) if finite else 0, max(finite) if finite else 1)
    if norm.vmin == norm.vmax:
        norm = Normalize(norm.vmin - 1, norm.vmax + 1)
    cmap = colormaps["viridis"]
    what = "TF-IDF score" if by_score else "inliers"
    for k, ax in enumerate(axes):
        part = q.parts[k] if k < len(q.parts) else {}
        pid = int(part.get("part", k))
        _map_axes(ax, full, "", q.units)
        mine = [c for i, c in cands if i == pid]
        xs, ys = [], []
        for c in sorted(mine, key=lambda c: c.get("accepted", False)):
            x0, y0, x1, y1 = c["bounds"]
            xs += [x0, x1]
            ys += [y0, y1]
            v = c.get("score") if by_score else c.get("inliers", 0)
            col = "#999999" if v is None else cmap(norm(v))
            acc = c.get("accepted")
            ax.add_patch(
                Rectangle(
                    (x0, y0),
                    x1 - x0,
                    y1 - y0,
                    fill=False,
                    ec=FUSED_COLOUR if acc else col,
                    lw=4 if acc else 1.6,
                    zorder=3 if acc else 2,
                )
            )
            if len(mine) <= 40:
                ax.text(
                    x0,
                    y1,
                    str(c.get("rank", "")),
                    color="white",
                    fontsize=9,
                    va="top",
                    bbox={"fc": col if not acc else FUSED_COLOUR, "ec": "none", "pad": 1},
                )
        h, w = q.shape
        rows = part.get("rows") or (0, h)
        sub = None
        if q.truth is not None:
            sub = truth_outline(q.truth[0][rows[0] : rows[1]], q.truth[1][rows[0] : rows[1]])
            _plot_outline(ax, sub, color=TRUTH_COLOUR, lw=2, ls="--")
            if sub is not None:
                ok = np.isfinite(sub).all(axis=1)
                xs += list(sub[ok, 0])
                ys += list(sub[ok, 1])
        if part.get("homography") is not None:
            own = footprint(part["homography"], w, h, tuple(rows))
            ok = np.isfinite(own).all(axis=1)
            ax.fill(own[ok, 0], own[ok, 1], color=FUSED_COLOUR, alpha=0.35, lw=0)
        if full is not None and xs:
            fb = full.bounds
            pad = 0.02 * (fb[2] - fb[0])
            ax.set_xlim(min(fb[0], min(xs)) - pad, max(fb[2], max(xs)) + pad)
            ax.set_ylim(min(fb[1], min(ys)) - pad, max(fb[3], max(ys)) + pad)
        status = "winner: green" if part.get("accepted") else "no candidate accepted"
        ax.set_title(
            f"part {pid} ({part.get('strategy', '?')}): {part.get('candidates_tried', len(mine))} "
            f"of {part.get('candidates_available', '?')} candidates tried, {status}"
        )
    sm = plt.cm.ScalarMappable(norm=norm, cmap=cmap)
    fig.colorbar(sm, ax=list(axes), fraction=0.025, pad=0.02, label=what)
    fig.suptitle(
        f"{q.name}: search (rectangles = candidate regions, number = order tried; "
        "dashed magenta = truth)"
    )
    _save(fig, out, dpi)
    return (
        f"The candidate regions each part verified, in the order tried (numbers), coloured by "
        f"{what}; the accepted one (the winner) is drawn thick green. Dashed magenta: where the "
        "part truly lies, when known."
    )


def fig_inliers(
    q: QueryData, out: Path, dpi: int, max_lines: int = 150, seed: int = 0
) -> str | None:
    """Inlier correspondences of the accepted parts: query band <-> map crop."""
    pairs = [
        (int(p.get("part", i)), np.asarray(p["inlier_query_xy"]), np.asarray(p["inlier_map_xy"]))
        for i, p in enumerate(q.parts)
        if p.get("accepted") and p.get("inlier_query_xy") and p.get("inlier_map_xy")
    ]
    if not pairs:
        return None
    plt = _plt()
    from matplotlib.patches import ConnectionPatch

    allm = np.vstack([m for _, _, m in pairs])
    b = grow(bounds_of(allm, q.fused_outline()) or (0, 0, 1, 1), 0.05)
    crop = read_crop(q.ortho, b, 1000)
    fig, axes = plt.subplots(1, 2, figsize=(16, 8), gridspec_kw={"width_ratios": [1, 1.3]})
    _show_band(axes[0], q.band, "query band")
    _map_axes(axes[1], crop, "orthophoto (north up)", q.units)
    rng = np.random.default_rng(seed)
    total = sum(len(a) for _, a, _ in pairs)
    for pid, qa, ma in pairs:
        col = PART_COLOURS[pid % len(PART_COLOURS)]
        k = len(qa)
        keep = np.arange(k)
        if total > max_lines:
            keep = np.sort(rng.choice(k, max(1, int(max_lines * k / total)), replace=False))
        axes[0].scatter(qa[:, 0], qa[:, 1], s=14, c=col, edgecolors="black", linewidths=0.3)
        axes[1].scatter(
            ma[:, 0],
            ma[:, 1],
            s=14,
            c=col,
            edgecolors="black",
            linewidths=0.3,
            label=f"part {pid}: {k} inliers",
        )
        for i in keep:
            fig.add_artist(
                ConnectionPatch(
                    xyA=qa[i],
                    coordsA=axes[0].transData,
                    xyB=ma[i],
                    coordsB=axes[1].transData,
                    color=col,
                    lw=0.6,
                    alpha=0.6,
                )
            )
    axes[1].legend(loc="lower right", framealpha=0.85)
    fig.suptitle(
        f"{q.name}: inlier correspondences of the accepted parts"
        + (f" ({max_lines} of {total} lines drawn)" if total > max_lines else "")
    )
    fig.tight_layout()
    _save(fig, out, dpi)
    return (
        "SIFT correspondences that the accepted parts' homographies kept (RANSAC inliers), "
        "query on the left, orthophoto on the right; one colour per part."
    )


def fig_ndsm(q: QueryData, out: Path, dpi: int) -> str | None:
    """nDSM draped on the footprint: in query geometry over the band, and on the map."""
    if not q.ndsm or not Path(q.ndsm).exists():
        return None
    plt = _plt()
    from georeg.register.geolocation import sample_raster

    h, w = q.shape
    if q.geoloc is not None:
        x, y = q.geoloc
    else:
        from georeg.register.geolocation import map_xy

        x, y = map_xy(q.H, w, h)
    z = sample_raster(q.ndsm, x, y)
    z = np.where(q.band > 0, z, np.nan)
    fp = q.fused_outline()
    b = grow(bounds_of(fp) or (0, 0, 1, 1), 0.1)
    crop = read_crop(q.ndsm, b, 900)
    finite = z[np.isfinite(z)]
    vmax = float(np.percentile(finite, 99)) if finite.size else 1.0
    vmax = max(vmax, 1.0)
    fig, axes = plt.subplots(1, 2, figsize=(16, 7.5), gridspec_kw={"width_ratios": [1, 1.2]})
    axes[0].imshow(np.ma.masked_equal(q.band, 0), cmap="gray", vmin=1, vmax=255)
    zm = np.ma.masked_where(~np.isfinite(z) | (z < 0.5), z)
    im = axes[0].imshow(zm, cmap="turbo", vmin=0, vmax=vmax, alpha=0.6)
    axes[0].set_title("nDSM sampled at every query pixel (over the band; < 0.5 m clear)")
    axes[0].set_xlabel("query column (px)")
    axes[0].set_ylabel("query row (px)")
    fig.colorbar(im, ax=axes[0], fraction=0.046, pad=0.02, label="height above ground (m)")
    _map_axes(axes[1], None, "map nDSM with the footprint", q.units)
    if crop is not None:
        a = np.where(crop.valid, crop.data[0].astype(np.float64), np.nan)
        im2 = axes[1].imshow(a, extent=crop.extent, cmap="turbo", vmin=0, vmax=vmax)
        fig.colorbar(im2, ax=axes[1], fraction=0.046, pad=0.02, label="nDSM (m)")
        axes[1].set_xlim(crop.extent[0], crop.extent[1])
        axes[1].set_ylim(crop.extent[2], crop.extent[3])
    _plot_outline(axes[1], fp, color="white", lw=2.5)
    valid = np.isfinite(z) & (q.band > 0)
    frac = float(valid.sum() / max(1, (q.band > 0).sum()))
    fig.suptitle(
        f"{q.name}: elevation fused onto the query ({frac:.0%} of its pixels have a height)"
    )
    fig.tight_layout()
    _save(fig, out, dpi)
    return (
        "Height above ground from the LiDAR (nDSM) attached to every query pixel through the "
        "registration (left), and the map's nDSM with the footprint (right)."
    )


def fig_segmentation(q: QueryData, out: Path, dpi: int) -> str | None:
    """The products' segmentation (query geometry) with its legend, next to the truth labels."""
    from georeg.report.evaluation import map_truth_labels, products_segmentation, read_labels

    seg = products_segmentation(q.products) if q.registered else None
    if seg is None:
        return None
    plt = _plt()
    from matplotlib import colormaps
    from matplotlib.colors import ListedColormap
    from matplotlib.patches import Patch

    pred = read_labels(seg.path)
    truth = read_labels(q.labels) if q.labels and Path(q.labels).exists() else None
    if truth is not None:
        truth = map_truth_labels(truth, seg.truth_lut) if truth.shape == pred.shape else None
    codes = sorted(
        {int(c) for c in np.unique(pred) if c > 0}
        | ({int(c) for c in np.unique(truth) if c > 0} if truth is not None else set())
        | set(seg.names)
    )
    if not codes:
        return None
    tab = colormaps["tab10"]
    cols = {
        c: (np.asarray(seg.colours[c], float) / 255.0 if c in seg.colours else tab(i % 10))
        for i, c in enumerate(codes)
    }
    lut = {c: i for i, c in enumerate(codes)}
    cmap = ListedColormap([cols[c] for c in codes])

    def idx(a: np.ndarray) -> np.ma.MaskedArray:
        o = np.full(a.shape, -1)
        for c, i in lut.items():
            o[a == c] = i
        return np.ma.masked_less(o, 0)

    n = 2 if truth is not None else 1
    fig, axes = plt.subplots(1, n, figsize=(6.5 * n + 2.5, 8), squeeze=False)
    axes = axes[0]
    kw = {"cmap": cmap, "vmin": -0.5, "vmax": len(codes) - 0.5, "interpolation": "nearest"}
    axes[0].imshow(idx(pred), **kw)
    acc = (q.evaluation or {}).get("segmentation") or {}
    sub = (
        f"\noverall accuracy {acc['overall_accuracy']:.1%}, mean IoU {acc['mean_iou']:.2f}"
        if acc.get("overall_accuracy") is not None and acc.get("mean_iou") is not None
        else ""
    )
    axes[0].set_title("segmentation (products stage)" + sub)
    if truth is not None:
        axes[1].imshow(idx(truth), **kw)
        axes[1].set_title("truth labels (in the same classes)")
    for ax in axes:
        ax.set_xlabel("query column (px)")
        ax.set_facecolor("#dddddd")
    axes[0].set_ylabel("query row (px)")
    handles = [Patch(fc=cols[c], ec="black", label=seg.names.get(c, str(c))) for c in codes]
    fig.legend(handles=handles, loc="center right", title="class", frameon=True)
    fig.suptitle(f"{q.name}: land-cover segmentation of the query")
    fig.tight_layout(rect=(0, 0, 0.84, 1))
    _save(fig, out, dpi)
    return (
        "The products stage's per-pixel segmentation of the query (from its SWIR spectra and the "
        "nDSM), with its legend, next to the truth labels translated to the same classes."
    )


def fig_error(q: QueryData, out: Path, dpi: int) -> str | None:
    """Error heat-map over the query (fused) and each part's own homography, one scale."""
    if q.truth is None or not q.registered:
        return None
    plt = _plt()
    from georeg.report.evaluation import error_field, map_xy

    tx, ty = q.truth
    h, w = tx.shape
    ev = q.evaluation or {}
    mpu = float(ev.get("m_per_map_unit") or 1.0)
    x, y = q.geoloc if q.geoloc is not None else map_xy(q.H, w, h)
    fields = [("fused", error_field(x, y, tx, ty) * mpu, None)]
    for p in q.reg.get("parts") or []:
        if p.get("homography") is not None:
            px_, py_ = map_xy(np.asarray(p["homography"]), w, h)
            fields.append(
                (f"part {p['part']} homography", error_field(px_, py_, tx, ty) * mpu, p.get("rows"))
            )
    f0 = fields[0][1]
    fin = f0[np.isfinite(f0)]
    bound_m = float((ev.get("bound") or {}).get("px", 5.0)) * float(ev.get("map_px_m") or 1.0)
    vmax = max(2 * bound_m, float(np.percentile(fin, 99)) if fin.size else 1.0)
    n = len(fields)
    fig, axes = plt.subplots(1, n, figsize=(5.2 * n + 1.5, 7.5), squeeze=False)
    axes = axes[0]
    im = None
    for ax, (title, e, rows) in zip(axes, fields, strict=True):
        em = np.ma.masked_invalid(np.where(q.band > 0, e, np.nan))
        im = ax.imshow(em, cmap="magma_r", vmin=0, vmax=vmax, interpolation="nearest")
        v = e[np.isfinite(e)]
        stat = f"median {np.median(v):.2f} m, p90 {np.percentile(v, 90):.2f} m" if v.size else ""
        ax.set_title(f"{title}\n{stat}")
        ax.set_xlabel("query column (px)")
        ax.set_facecolor("#dddddd")
        if rows is not None:
            for r in rows:
                ax.axhline(r - 0.5, color="cyan", lw=1.5, ls="--")
    axes[0].set_ylabel("query row (px)")
    fig.colorbar(
        im,
        ax=list(axes),
        fraction=0.03,
        pad=0.02,
        label=f"distance to the true position (m; clipped at {vmax:.1f})",
    )
    fig.suptitle(f"{q.name}: registration error per query pixel (parts: dashed cyan = own rows)")
    _save(fig, out, dpi)
    return (
        "Distance between where each query pixel was placed and where it truly is: the fused "
        "registration first, then each part's own homography applied to the whole query "
        "(dashed cyan: the rows that part was matched on). The gain of fusing shows as less "
        "error away from each part's own rows."
    )


def fig_refine(q: QueryData, out: Path, dpi: int, max_arrows: int = 2500) -> str | None:
    """Local refinement: tie points and their residual vectors, before and after (issue 12)."""
    r = q.reg.get("refine") or {}
    pts = r.get("points")
    if not q.registered or not pts:
        return None
    plt = _plt()
    col, row = np.asarray(pts["col"], float), np.asarray(pts["row"], float)
    panels = [
        ("against the global homography", np.asarray(pts["before"], float),
         np.asarray(pts["accepted"], bool), r.get("residual_before_px") or {}),
        (f"against the refined model ({r.get('model')})", np.asarray(pts["after"], float),
         np.asarray(pts["accepted_after"], bool), r.get("residual_after_px") or {}),
    ]  # fmt: skip
    ok_all = panels[0][2]
    mags = np.hypot(*panels[0][1][ok_all].T) if ok_all.any() else np.ones(1)
    scale = max(float(np.percentile(mags, 90)), 0.25)  # arrow length: p90 residual = 1 grid step
    step = float(np.median(np.diff(np.unique(col)))) if np.unique(col).size > 1 else 10.0
    k = step / scale
    sub = np.arange(col.size)
    if col.size > max_arrows:
        sub = np.random.default_rng(0).choice(col.size, max_arrows, replace=False)
    fig, axes = plt.subplots(1, 2, figsize=(14, 8.5))
    for ax, (title, v, ok, st) in zip(axes, panels, strict=True):
        _show_band(ax, q.band, "")
        s_ok, s_bad = sub[ok[sub]], sub[~ok[sub]]
        ax.plot(col[s_bad], row[s_bad], "x", color="#d62728", ms=3, label="rejected")
        ax.quiver(col[s_ok], row[s_ok], k * v[s_ok, 0], k * v[s_ok, 1], angles="xy",
                  scale_units="xy", scale=1, color="#ffcc00", width=0.003,
                  label=f"residual x {k:.0f}")  # fmt: skip
        med, p90 = st.get("median"), st.get("p90")
        stat = f"median {med:.2f} px, p90 {p90:.2f} px" if med is not None else "no tie point"
        ax.set_title(f"{title}\n{int(ok.sum())} tie points, {stat}")
        ax.set_xlabel("query column (px)")
    axes[0].set_ylabel("query row (px)")
    axes[0].legend(loc="lower right", fontsize=9)
    ev = r.get("evaluation") or {}
    b, a = ev.get("before_px") or {}, ev.get("after_px") or {}
    truth = ""
    if b.get("median") is not None and a.get("median") is not None:
        truth = (f"; true error median {b['median']:.2f} -> {a['median']:.2f}, "
                 f"p90 {b['p90']:.2f} -> {a['p90']:.2f} map px")  # fmt: skip
    fig.suptitle(f"{q.name}: local refinement, model {r.get('model')}{truth}")
    fig.tight_layout()
    _save(fig, out, dpi)
    return (
        "Tie points of the local refinement over the query band: the shift (query px, arrows "
        "exaggerated as marked) between each query window and the orthophoto rendered through "
        "the global homography (left) and through the refined geometry (right); red crosses are "
        "tie points rejected by score or by neighbour consistency."
    )


def fig_not_found(q: QueryData, out: Path, dpi: int) -> str:
    """A clear 'not found: reason' panel."""
    plt = _plt()
    fig, axes = plt.subplots(1, 2, figsize=(16, 5.5), gridspec_kw={"width_ratios": [1, 2]})
    _show_band(axes[0], q.band, "query band")
    ev = q.evaluation or {}
    lines = [f"reason: {q.reg.get('reason') or 'no part accepted'}"]
    lines.append(f"candidates tried: {q.reg.get('candidates_tried', 0)}")
    for p in q.parts:
        cands = p.get("candidates", [])
        nfa = [c["log10_nfa"] for c in cands if c.get("log10_nfa") is not None]
        lines.append(
            f"part {p.get('part')}: {p.get('candidates_tried', 0)} of "
            f"{p.get('candidates_available', '?')} candidates tried, best "
            f"{max([c.get('inliers', 0) for c in cands] or [0])} inliers"
            + (f", best log10 NFA {min(nfa):.1f}" if nfa else "")
        )
    if ev.get("outcome") in ("correct_not_found", "missed"):
        frac = ev.get("inside_fraction")
        verdict = (
            "correct: the query lies outside the map"
            if ev["outcome"] == "correct_not_found"
            else "MISSED: the query lies inside the map"
        )
        lines.append(f"truth: {verdict} ({(frac or 0):.0%} of it inside)")
    _text_panel(axes[1], "not found", lines)
    fig.suptitle(f"{q.name}: not registered")
    fig.tight_layout()
    _save(fig, out, dpi)
    return "The query was not registered; the reason is given, with the search effort."


# ----------------------------------------------------------------------------- all of them


FIGURE_TITLES = {
    "not_found": "not found",
    "match": "query next to the map",
    "checkerboard": "checkerboard overlay",
    "footprints": "footprints on the map",
    "search": "search",
    "inliers": "inlier correspondences",
    "ndsm": "nDSM draped on the footprint",
    "segmentation": "segmentation",
    "error": "error heat-map",
    "refine": "local refinement tie points",
}


def load_query_data(
    name: str,
    registration: str | Path,
    band: str | Path,
    parts: Sequence[str | Path],
    ortho: str | Path,
    ndsm: str | Path | None = None,
    evaluation: str | Path | None = None,
    truth: str | Path | None = None,
    geolocation: str | Path | None = None,
    products: str | Path | None = None,
    labels: str | Path | None = None,
    grid: str | Path | None = None,
) -> QueryData:
    """Read every input of one query's figures."""
    from georeg.register.band import read_query_band
    from georeg.report.evaluation import read_geolocation, read_truth

    reg = json.loads(Path(registration).read_text())
    ev = (
        json.loads(Path(evaluation).read_text())
        if evaluation and Path(evaluation).exists()
        else None
    )
    pj = sorted((json.loads(Path(p).read_text()) for p in parts), key=lambda p: p.get("part", 0))
    tr = read_truth(truth) if truth and Path(truth).exists() else None
    geo = None
    if geolocation and Path(geolocation).exists() and reg.get("status") == "registered":
        x, y, _ = read_geolocation(geolocation)
        geo = (x, y)
    units = "m"
    if ev and ev.get("m_per_map_unit") not in (None, 1.0):
        units = "map units"
    return QueryData(
        name=name,
        reg=reg,
        band=read_query_band(str(band)),
        parts=pj,
        ortho=str(ortho),
        ndsm=str(ndsm) if ndsm else None,
        evaluation=ev,
        truth=tr,
        geoloc=geo,
        products=str(products) if products else None,
        labels=str(labels) if labels else None,
        units=units,
    )


def make_query_figures(
    q: QueryData, out_dir: str | Path, conf: dict[str, Any] | None = None
) -> list[dict[str, str]]:
    """Write every figure that applies to ``q`` into ``out_dir`` and ``figures.json``.

    Returns the manifest: ``[{"file", "title", "caption"}]`` in display order. A figure that
    fails to draw is logged and left out (the report must not die on one picture).
    """
    c = conf or {}
    dpi = int(c.get("figure_dpi", 90))
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    plan: list[tuple[str, Any]] = []
    if q.registered:
        plan += [
            ("match", fig_match),
            (
                "checkerboard",
                lambda q_, p, d: fig_checkerboard(q_, p, d, int(c.get("checker_squares", 8))),
            ),
            ("footprints", fig_footprints),
            ("error", fig_error),
            ("refine", fig_refine),
            ("search", fig_search),
            (
                "inliers",
                lambda q_, p, d: fig_inliers(q_, p, d, int(c.get("max_inlier_lines", 150))),
            ),
            ("ndsm", fig_ndsm),
            ("segmentation", fig_segmentation),
        ]
    else:
        plan += [
            ("not_found", fig_not_found),
            ("search", fig_search),
            ("footprints", fig_footprints),
        ]
    manifest: list[dict[str, str]] = []
    for i, (key, fn) in enumerate(plan):
        path = out / f"{i:02d}_{key}.png"
        try:
            caption = fn(q, path, dpi)
        except Exception as exc:  # noqa: BLE001 - one broken figure must not stop the report
            log.warning("figure %s of %s failed: %s", key, q.name, exc, exc_info=True)
            continue
        if caption is None:
            log.info("figure %s of %s does not apply, skipped", key, q.name)
            continue
        manifest.append(
            {"file": path.name, "key": key, "title": FIGURE_TITLES[key], "caption": caption}
        )
    write_json(out / "figures.json", {"query": q.name, "figures": manifest})
    return manifest
