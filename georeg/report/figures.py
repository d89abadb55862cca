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
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from georeg.io.atomic import write_json
from georeg.report.figures_evaluation import fig_error
from georeg.report.figures_products import fig_ndsm, fig_segmentation
from georeg.report.figures_register import (
    fig_checkerboard,
    fig_footprints,
    fig_inliers,
    fig_match,
    fig_not_found,
    fig_refine,
    fig_search,
)
from georeg.report.plotting import QueryData

log = logging.getLogger(__name__)


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
