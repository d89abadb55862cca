"""Figure of the evaluation: the registration error against the dense truth over the query."""

from __future__ import annotations

import logging
from pathlib import Path

import numpy as np

from georeg.report.plotting import QueryData, pyplot, save_figure

log = logging.getLogger(__name__)


def fig_error(q: QueryData, out: Path, dpi: int) -> str | None:
    """Error heat-map over the query (fused) and each part's own homography, one scale."""
    if q.truth is None or not q.registered:
        return None
    plt = pyplot()
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
    save_figure(fig, out, dpi)
    return (
        "Distance between where each query pixel was placed and where it truly is: the fused "
        "registration first, then each part's own homography applied to the whole query "
        "(dashed cyan: the rows that part was matched on). The gain of fusing shows as less "
        "error away from each part's own rows."
    )
