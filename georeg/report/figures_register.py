"""Figures of the register stage: the match, checkerboard, footprints, search, inliers, local
refinement and the not-found panel."""

from __future__ import annotations

import logging
from pathlib import Path
from typing import Any

import numpy as np

from georeg.report.plotting import (
    FUSED_COLOUR,
    PART_COLOURS,
    TRUTH_COLOUR,
    QueryData,
    apply_h,
    bounds_of,
    crop_gray,
    crop_to_query,
    footprint,
    grow,
    map_axes,
    plot_outline,
    pyplot,
    read_crop,
    save_figure,
    show_band,
    text_panel,
    truth_outline,
    warp_to_crop,
)

log = logging.getLogger(__name__)


def fig_match(q: QueryData, out: Path, dpi: int) -> str:
    """Query band | the orthophoto resampled into query geometry | the map crop it landed on."""
    plt = pyplot()
    h, w = q.shape
    fp = q.fused_outline()
    b = grow(bounds_of(fp) or (0, 0, 1, 1), 0.1)
    crop = read_crop(q.ortho, b, 1000)
    fig, axes = plt.subplots(1, 3, figsize=(16, 6.5), gridspec_kw={"width_ratios": [1, 1, 1.25]})
    show_band(
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
    map_axes(axes[2], crop, "map crop where it landed (north up)", q.units)
    plot_outline(axes[2], fp, color=FUSED_COLOUR, lw=2.5, label="registered footprint")
    plot_outline(axes[2], q.truth_outline(), color=TRUTH_COLOUR, lw=1.5, ls="--", label="truth")
    # mark the query's first row (flight direction)
    top = apply_h(q.H, np.array([[0.0, 0.0], [w - 1.0, 0.0]]))
    axes[2].plot(top[:, 0], top[:, 1], color="red", lw=3, label="query row 0")
    axes[2].legend(loc="lower right", framealpha=0.85)
    fig.suptitle(f"{q.name}: query next to the map where it was registered")
    fig.tight_layout()
    save_figure(fig, out, dpi)
    return (
        "The query band (left), the orthophoto resampled into the query's geometry through the "
        "registration (middle: both should show the same scene, pixel for pixel), and the "
        "north-up map crop with the registered footprint (green; red = the query's first row)."
    )


def fig_checkerboard(q: QueryData, out: Path, dpi: int, squares: int = 8) -> str:
    """Checkerboard of the orthophoto and the warped query band over the footprint."""
    plt = pyplot()
    fp = q.fused_outline()
    b = grow(bounds_of(fp) or (0, 0, 1, 1), 0.05)
    crop = read_crop(q.ortho, b, 1100)
    fig, ax = plt.subplots(1, 1, figsize=(10, 10))
    if crop is None:
        text_panel(ax, "footprint outside the map", ["the orthophoto has no pixel there"])
        save_figure(fig, out, dpi)
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
    map_axes(ax, None, "checkerboard: orthophoto / warped query band (bluish squares)", q.units)
    ax.set_xlim(crop.extent[0], crop.extent[1])
    ax.set_ylim(crop.extent[2], crop.extent[3])
    plot_outline(ax, fp, color=FUSED_COLOUR, lw=2)
    fig.suptitle(f"{q.name}: do roads and roof edges continue across the squares?")
    fig.tight_layout()
    save_figure(fig, out, dpi)
    return (
        "Alternating squares of the orthophoto (grey) and of the query band warped onto it "
        "by the registration (bluish). A good registration shows edges that continue across "
        "square borders without a jump."
    )


def fig_footprints(q: QueryData, out: Path, dpi: int) -> str:
    """The footprints of the parts and of the fused result on the map overview (+ a zoom)."""
    plt = pyplot()
    full = read_crop(q.ortho, None, 1024)
    fig, axes = plt.subplots(1, 2, figsize=(16, 7.8))
    map_axes(axes[0], full, "map overview", q.units)
    fp = q.fused_outline()
    parts = q.part_outlines()
    tr = q.truth_outline()
    zb = bounds_of(fp, tr, *[p for _, p in parts])
    for ax in axes:
        for i, pts in parts:
            col = PART_COLOURS[i % len(PART_COLOURS)]
            ok = np.isfinite(pts).all(axis=1)
            ax.fill(pts[ok, 0], pts[ok, 1], color=col, alpha=0.3, lw=0)
            plot_outline(ax, pts, color=col, lw=2, label=f"part {i} (own homography, own rows)")
        plot_outline(ax, fp, color=FUSED_COLOUR, lw=2.5, label="fused registration")
        plot_outline(ax, tr, color=TRUTH_COLOUR, lw=1.8, ls="--", label="truth")
    if full is not None and zb is not None:
        # keep the overview on the map, but include a footprint that lies beyond it
        fb = full.bounds
        pad = 0.03 * max(fb[2] - fb[0], fb[3] - fb[1])
        axes[0].set_xlim(min(fb[0], zb[0]) - pad, max(fb[2], zb[2]) + pad)
        axes[0].set_ylim(min(fb[1], zb[1]) - pad, max(fb[3], zb[3]) + pad)
    if zb is not None:
        zb = grow(zb, 0.1)
        zoom = read_crop(q.ortho, zb, 1000)
        map_axes(axes[1], zoom, "zoom on the footprints", q.units)
        for i, pts in parts:
            col = PART_COLOURS[i % len(PART_COLOURS)]
            ok = np.isfinite(pts).all(axis=1)
            axes[1].fill(pts[ok, 0], pts[ok, 1], color=col, alpha=0.3, lw=0)
            plot_outline(axes[1], pts, color=col, lw=2)
        plot_outline(axes[1], fp, color=FUSED_COLOUR, lw=2.5)
        plot_outline(axes[1], tr, color=TRUTH_COLOUR, lw=1.8, ls="--")
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
        text_panel(axes[1], "no footprint", ["no part was accepted and there is no truth"])
    h, _ = axes[0].get_legend_handles_labels()
    if h:
        axes[0].legend(loc="upper left", framealpha=0.85)
    fig.suptitle(f"{q.name}: footprints on the map")
    fig.tight_layout()
    save_figure(fig, out, dpi)
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
    plt = pyplot()
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
    rank = next((p.get("rank") for p in q.parts if p.get("rank")), "tiles")
    what = ("Hough votes" if rank == "hough" else "TF-IDF score") if by_score else "inliers"
    for k, ax in enumerate(axes):
        part = q.parts[k] if k < len(q.parts) else {}
        pid = int(part.get("part", k))
        map_axes(ax, full, "", q.units)
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
        if rows[1] <= rows[0]:  # a part merged into the whole-query search
            rows = (0, h)
        sub = None
        if q.truth is not None:
            sub = truth_outline(q.truth[0][rows[0] : rows[1]], q.truth[1][rows[0] : rows[1]])
            plot_outline(ax, sub, color=TRUTH_COLOUR, lw=2, ls="--")
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
    save_figure(fig, out, dpi)
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
    plt = pyplot()
    from matplotlib.patches import ConnectionPatch

    allm = np.vstack([m for _, _, m in pairs])
    b = grow(bounds_of(allm, q.fused_outline()) or (0, 0, 1, 1), 0.05)
    crop = read_crop(q.ortho, b, 1000)
    fig, axes = plt.subplots(1, 2, figsize=(16, 8), gridspec_kw={"width_ratios": [1, 1.3]})
    show_band(axes[0], q.band, "query band")
    map_axes(axes[1], crop, "orthophoto (north up)", q.units)
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
    save_figure(fig, out, dpi)
    return (
        "SIFT correspondences that the accepted parts' homographies kept (RANSAC inliers), "
        "query on the left, orthophoto on the right; one colour per part."
    )


def fig_refine(q: QueryData, out: Path, dpi: int, max_arrows: int = 2500) -> str | None:
    """Local refinement: tie points and their residual vectors, before and after."""
    r = q.reg.get("refine") or {}
    pts = r.get("points")
    if not q.registered or not pts:
        return None
    plt = pyplot()
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
        show_band(ax, q.band, "")
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
    save_figure(fig, out, dpi)
    return (
        "Tie points of the local refinement over the query band: the shift (query px, arrows "
        "exaggerated as marked) between each query window and the orthophoto rendered through "
        "the global homography (left) and through the refined geometry (right); red crosses are "
        "tie points rejected by score or by neighbour consistency."
    )


def fig_not_found(q: QueryData, out: Path, dpi: int) -> str:
    """A clear 'not found: reason' panel."""
    plt = pyplot()
    fig, axes = plt.subplots(1, 2, figsize=(16, 5.5), gridspec_kw={"width_ratios": [1, 2]})
    show_band(axes[0], q.band, "query band")
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
    text_panel(axes[1], "not found", lines)
    fig.suptitle(f"{q.name}: not registered")
    fig.tight_layout()
    save_figure(fig, out, dpi)
    return "The query was not registered; the reason is given, with the search effort."
