"""The map view: ``results/report/map.html``, an interactive map that works from the file system.

The page draws, on the decimated orthophoto, each registered query's band warped into the map
frame (opacity or swipe slider), the query footprints and truth outlines, the frame cameras with
their footprints and look directions, the video trajectories, and shows a query's or a frame's
status and errors on a click (``georeg.report.map_data`` computes all of it). It uses Leaflet
(bundled under ``georeg/report/static/``, copied beside the page with the images into
``results/report/map/``): no server, no network, no CDN. The data is one JSON object embedded in
the page (``<script type="application/json" id="map-data">``), every layer in map pixel
coordinates of ``results/map/grid.json``.
"""

from __future__ import annotations

import html
import json
import logging
import os
import re
import shutil
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from georeg.io.atomic import atomic_path, write_text
from georeg.report.frames_html import read_poses
from georeg.report.map_data import (
    MapFrame,
    frame_set_features,
    query_features,
    query_info,
    read_raster,
    render_ortho,
    warp_query,
    write_image,
)

log = logging.getLogger(__name__)

STATIC = Path(__file__).resolve().parent / "static"
#: files copied beside map.html (relative to STATIC)
ASSETS = ("leaflet/leaflet.js", "leaflet/leaflet.css", "leaflet/LICENSE",
          "leaflet/images/layers.png", "leaflet/images/layers-2x.png",
          "leaflet/images/marker-icon.png", "leaflet/images/marker-icon-2x.png",
          "leaflet/images/marker-shadow.png", "mapview.js", "mapview.css")  # fmt: skip


@dataclass
class QuerySource:
    """The files of one query the map view reads (truth optional)."""

    name: str
    registration: Path
    evaluation: Path | None
    band: Path
    geolocation: Path | None
    truth: Path | None = None


@dataclass
class FrameSetSource:
    """One frame set: its poses.json, truth.json and, for a video, trajectory.json."""

    name: str
    poses: Path
    truth: Path | None = None
    trajectory: Path | None = None


def _json(path: Path | None) -> dict[str, Any]:
    if path is None or not Path(path).exists():
        return {}
    try:
        data = json.loads(Path(path).read_text())
    except (OSError, json.JSONDecodeError) as exc:
        log.warning("cannot read %s: %s", path, exc)
        return {}
    return data if isinstance(data, dict) else {}


def _xy(path: Path | None) -> tuple[Any, Any] | None:
    a = read_raster(path)
    return None if a is None or a.shape[0] < 2 else (a[0], a[1])


def _query_entry(q: QuerySource, frame: MapFrame, out_dir: Path, overlay_px: int) -> tuple[dict, list[dict]]:  # fmt: skip
    reg, ev = _json(q.registration), _json(q.evaluation)
    geo = _xy(q.geolocation) if reg.get("status") == "registered" else None
    truth = _xy(q.truth)
    entry: dict[str, Any] = {"id": f"query:{q.name}", "name": q.name,
                             "status": str(reg.get("status")),
                             "outcome": str(ev.get("outcome", "no_truth")),
                             "info": query_info(q.name, reg, ev), "overlay": None}  # fmt: skip
    if reg.get("status") == "registered":
        band = read_raster(q.band)
        warped = None if band is None else warp_query(band[0], geo, reg.get("homography"),
                                                      frame, overlay_px)  # fmt: skip
        if warped is not None:
            fname = f"query_{re.sub(r'[^A-Za-z0-9_.-]', '_', q.name)}.png"
            write_image(out_dir / fname, warped[0], ".png")
            entry["overlay"] = {"file": fname, "bounds": [round(v, 3) for v in warped[1]]}
    return entry, query_features(q.name, reg, ev, geo, truth, frame)


def _set_entry(s: FrameSetSource, frame: MapFrame) -> tuple[dict, list[dict]]:
    poses = read_poses(s.poses)
    truth = read_poses(s.truth) if s.truth and Path(s.truth).exists() else []
    traj = _json(s.trajectory) if s.trajectory else None
    feats = frame_set_features(s.name, poses, truth, frame, traj)
    video = s.trajectory is not None or any(f["properties"].get("kind") == "path" for f in feats)
    entry = {"id": f"set:{s.name}", "name": s.name, "kind": "video" if video else "frames",
             "entries": len(poses),
             "registered": sum(p.get("status") == "registered" for p in poses),
             "frames": [] if video else
             [{"id": f["properties"]["id"], "name": f["properties"]["name"],
               "status": f["properties"]["status"]}
              for f in feats if f["properties"]["kind"] in ("camera", "truth_camera")]}  # fmt: skip
    seen: set[str] = set()
    entry["frames"] = [f for f in entry["frames"] if not (f["id"] in seen or seen.add(f["id"]))]
    return entry, feats


def page_html(data: dict[str, Any], assets: str) -> str:
    """The page: the data embedded as JSON, Leaflet and the view's script from ``assets``/."""
    blob = json.dumps(data, separators=(",", ":")).replace("<", "\\u003c")  # no "</script>"
    a = html.escape(assets)
    return (
        '<!DOCTYPE html>\n<html lang="en"><head><meta charset="utf-8">'
        '<meta name="viewport" content="width=device-width, initial-scale=1">'
        f"<title>georeg map view</title>"
        f'<link rel="stylesheet" href="{a}/leaflet/leaflet.css">'
        f'<link rel="stylesheet" href="{a}/mapview.css"></head><body>\n'
        '<header><h1>georeg map view</h1><span id="verdict"></span>'
        '<a id="back" href="index.html">back to the report</a></header>\n'
        '<div id="layout"><aside id="side"></aside><div id="map"></div></div>\n'
        "<noscript>The map view needs JavaScript (it runs locally, nothing is downloaded).</noscript>\n"
        f'<script type="application/json" id="map-data">{blob}</script>\n'
        f'<script src="{a}/leaflet/leaflet.js"></script>\n'
        f'<script src="{a}/mapview.js"></script>\n'
        "</body></html>\n"
    )


def write_map_view(out_html: str | Path, out_dir: str | Path, grid: str | Path,
                   ortho: str | Path, queries: Sequence[QuerySource],
                   frame_sets: Sequence[FrameSetSource] = (), max_px: int = 2048,
                   overlay_px: int = 1024) -> dict[str, Any]:  # fmt: skip
    """Write ``out_html`` and its folder ``out_dir`` (Leaflet, the view's script, the orthophoto
    and the query images); the folder is built under a temporary name and renamed, the page
    last. Returns the embedded data."""
    out_html, out_dir = Path(out_html), Path(out_dir)
    frame = MapFrame.from_grid(grid)
    with atomic_path(out_dir) as tmp:
        for rel in ASSETS:
            dst = tmp / rel
            dst.parent.mkdir(parents=True, exist_ok=True)
            shutil.copyfile(STATIC / rel, dst)
        ortho_info = render_ortho(ortho, frame, tmp / "ortho.jpg", max_px)
        entries, sets, feats = [], [], []
        for q in queries:
            e, f = _query_entry(q, frame, tmp, overlay_px)
            entries.append(e)
            feats += f
        for s in frame_sets:
            e, f = _set_entry(s, frame)
            sets.append(e)
            feats += f
        if out_dir.exists():
            shutil.rmtree(out_dir)
    rel = os.path.relpath(out_dir, out_html.parent).replace(os.sep, "/")
    for e in entries:
        if e["overlay"]:
            e["overlay"]["src"] = f"{rel}/{e['overlay'].pop('file')}"
    data = {
        "size": [frame.width, frame.height],
        "crs": {"name": frame.crs_name(), "transform": list(frame.transform)},
        "pixel_m": frame.pixel_m,
        "ortho": {"src": f"{rel}/ortho.jpg", **ortho_info},
        "queries": entries,
        "sets": sets,
        "features": {"type": "FeatureCollection", "features": feats},
        "report": "index.html",
    }
    write_text(out_html, page_html(data, rel))
    log.info("map view %s: %d queries (%d drawn), %d frame sets, %d features", out_html,
             len(entries), sum(e["overlay"] is not None for e in entries), len(sets), len(feats))  # fmt: skip
    return data


def run_map_view(out_html: str | Path, out_dir: str | Path, grid: str | Path, ortho: str | Path,
                 names: Sequence[str], registrations: Sequence[str], evaluations: Sequence[str],
                 bands: Sequence[str], geolocations: Sequence[str],
                 truths: Sequence[str | None], frame_sets: Sequence[str] = (),
                 poses: Sequence[str] = (), frame_truths: Sequence[str | None] = (),
                 video_sets: Sequence[str] = (),
                 sizes: dict[str, int] | None = None) -> dict[str, Any]:  # fmt: skip
    """Rule report_map: lists aligned by query and by frame set; a video set's trajectory.json
    is read beside its poses.json. ``sizes``: ``map_max_px``, ``map_query_px``."""
    qs = [QuerySource(n, Path(r), Path(e), Path(b), Path(g), Path(t) if t else None)
          for n, r, e, b, g, t in zip(names, registrations, evaluations, bands, geolocations,
                                      truths, strict=True)]  # fmt: skip
    sets = [FrameSetSource(s, Path(p), Path(t) if t else None,
                           Path(p).with_name("trajectory.json") if s in video_sets else None)
            for s, p, t in zip(frame_sets, poses, frame_truths, strict=True)]  # fmt: skip
    sz = sizes or {}
    return write_map_view(out_html, out_dir, grid, ortho, qs, sets,
                          int(sz.get("map_max_px", 2048)), int(sz.get("map_query_px", 1024)))
