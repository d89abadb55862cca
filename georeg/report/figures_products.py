"""Figures of the products stage: the nDSM under the footprint and the segmentation."""

from __future__ import annotations

import logging
from pathlib import Path

import numpy as np

from georeg.report.plotting import (
    QueryData,
    bounds_of,
    grow,
    map_axes,
    plot_outline,
    pyplot,
    read_crop,
    save_figure,
)

log = logging.getLogger(__name__)


def fig_ndsm(q: QueryData, out: Path, dpi: int) -> str | None:
    """nDSM draped on the footprint: in query geometry over the band, and on the map."""
    if not q.ndsm or not Path(q.ndsm).exists():
        return None
    plt = pyplot()
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
    map_axes(axes[1], None, "map nDSM with the footprint", q.units)
    if crop is not None:
        a = np.where(crop.valid, crop.data[0].astype(np.float64), np.nan)
        im2 = axes[1].imshow(a, extent=crop.extent, cmap="turbo", vmin=0, vmax=vmax)
        fig.colorbar(im2, ax=axes[1], fraction=0.046, pad=0.02, label="nDSM (m)")
        axes[1].set_xlim(crop.extent[0], crop.extent[1])
        axes[1].set_ylim(crop.extent[2], crop.extent[3])
    plot_outline(axes[1], fp, color="white", lw=2.5)
    valid = np.isfinite(z) & (q.band > 0)
    frac = float(valid.sum() / max(1, (q.band > 0).sum()))
    fig.suptitle(
        f"{q.name}: elevation fused onto the query ({frac:.0%} of its pixels have a height)"
    )
    fig.tight_layout()
    save_figure(fig, out, dpi)
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
    plt = pyplot()
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
    save_figure(fig, out, dpi)
    return (
        "The products stage's per-pixel segmentation of the query (from its SWIR spectra and the "
        "nDSM), with its legend, next to the truth labels translated to the same classes."
    )
