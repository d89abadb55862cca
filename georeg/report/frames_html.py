"""The report's "frames" section: per frame set, pose errors against truth and overlay thumbnails.

Reads ``results/frames/{set}/poses.json`` (single frames; a video writes the same format, one entry per
video frame, with ``frame`` and maybe ``keyframe`` / ``source``) and the set's ``overlays/*.png``.
A set of at most ``MAX_ROWS`` entries gets one row per frame (status vs expected, PnP-only and
refined errors from ``evaluation``, inliers, reprojection, seconds) and a mean row; a longer set
(a video) gets summary statistics, a plot of the estimated vs truth camera path and at most
``MAX_VIDEO_OVERLAYS`` overlays. Thumbnails are downscaled JPEG data URIs. Every number of the
tables carries ``data-key`` / ``data-value`` (the exact value) as in the summary table.
"""

from __future__ import annotations

import base64
import html
import io
import json
import logging
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from georeg.report.html_parts import cell, table

log = logging.getLogger(__name__)

MAX_ROWS = 20  # longer sets (videos) get statistics instead of one row per frame
MAX_VIDEO_OVERLAYS = 6
THUMB_WIDTH = 360  # px of the embedded overlay thumbnails
ERR_KEYS = ("horizontal_m", "vertical_m", "rotation_deg")


def read_poses(path: str | Path) -> list[dict[str, Any]]:
    """The entries of a poses.json (empty, with a warning, when absent or not a list)."""
    try:
        data = json.loads(Path(path).read_text())
    except (OSError, json.JSONDecodeError) as exc:
        log.warning("cannot read %s: %s", path, exc)
        return []
    return [p for p in data if isinstance(p, dict)] if isinstance(data, list) else []


def frame_name(p: Mapping[str, Any]) -> str:
    """Display name: the image stem, or ``video#index`` entries by their frame index."""
    img = str(p.get("image", "?"))
    if p.get("frame") is not None and ("#" in img or not Path(img).suffix):
        return f"{Path(img.split('#')[0]).stem}#{p['frame']}"
    return Path(img).stem


def _err(p: Mapping[str, Any], key: str) -> dict[str, float] | None:
    e = (p.get("evaluation") or {}).get(key)
    return e if isinstance(e, dict) and e.get("horizontal_m") is not None else None


def mean_errors(poses: list[dict[str, Any]], key: str) -> dict[str, float | int] | None:
    """Means of horizontal / vertical / rotation errors over the entries evaluated for ``key``
    ("pnp" or "final"), with their count ``n``; None when none is."""
    errs = [e for p in poses if (e := _err(p, key))]
    if not errs:
        return None
    out: dict[str, float | int] = {k: float(np.mean([e[k] for e in errs])) for k in ERR_KEYS}
    out["n"] = len(errs)
    return out


def error_stats(poses: list[dict[str, Any]], key: str = "final") -> dict[str, Any]:
    """Mean and 90th percentile of position (3-D), horizontal and rotation errors for ``key``."""
    errs = [e for p in poses if (e := _err(p, key))]
    out: dict[str, Any] = {"n": len(errs)}
    for k in ("position_m", "horizontal_m", "rotation_deg"):
        v = [float(e[k]) for e in errs if e.get(k) is not None]
        out[f"{k}_mean"] = float(np.mean(v)) if v else None
        out[f"{k}_p90"] = float(np.percentile(v, 90)) if v else None
    return out


def thumbnail_uri(path: Path, width: int = THUMB_WIDTH) -> str | None:
    """An image file downscaled to ``width`` px (never up) as a JPEG data URI."""
    img = cv2.imread(str(path), cv2.IMREAD_COLOR)
    if img is None:
        log.warning("cannot read overlay %s", path)
        return None
    if img.shape[1] > width:
        h = max(1, round(img.shape[0] * width / img.shape[1]))
        img = cv2.resize(img, (width, h), interpolation=cv2.INTER_AREA)
    ok, buf = cv2.imencode(".jpg", img, [cv2.IMWRITE_JPEG_QUALITY, 80])
    return (
        "data:image/jpeg;base64," + base64.b64encode(buf.tobytes()).decode("ascii") if ok else None
    )


def _status_cell(p: Mapping[str, Any]) -> str:
    st = str(p.get("status"))
    exp = (p.get("evaluation") or {}).get("expected")
    cls = "na" if exp is None else ("ok" if exp == st else "bad")
    txt = html.escape(st) + ("" if exp is None else f" ({html.escape(str(exp))})")
    return f'<td class="{cls}" data-key="status" data-value="{html.escape(st)}">{txt}</td>'


def _err_cells(prefix: str, e: Mapping[str, Any] | None) -> list[str]:
    e = e or {}
    return [cell(f"{prefix}_{k}", e.get(k)) for k in ERR_KEYS]


def _path_cell(p: Mapping[str, Any]) -> str:
    v = str(p.get("path") or "")
    return f'<td data-key="path" data-value="{html.escape(v)}">{html.escape(v) or "-"}</td>'


def frame_table(poses: list[dict[str, Any]], set_name: str) -> str:
    """One row per frame and a mean row over the frames evaluated (refined errors)."""
    rows = []
    for p in poses:
        name = frame_name(p)
        rows.append(
            [f'<td data-key="frame" data-value="{html.escape(name)}">{html.escape(name)}</td>',
             _status_cell(p), *_err_cells("pnp", _err(p, "pnp")),
             *_err_cells("final", _err(p, "final")), _path_cell(p),
             cell("verification_score", (p.get("verification") or {}).get("score"), 0),
             cell("inliers", p.get("inliers")), cell("reprojection_px", p.get("reprojection_px")),
             cell("seconds", (p.get("timings_s") or {}).get("total_s"), 1)]
        )  # fmt: skip
    mp, mf = mean_errors(poses, "pnp"), mean_errors(poses, "final")
    n = (mf or mp or {}).get("n", 0)
    rows.append(
        [f'<th data-key="frame" data-value="mean">mean ({n} evaluated)</th>', "<td></td>",
         *_err_cells("pnp", mp), *_err_cells("final", mf), *["<td></td>"] * 5]
    )  # fmt: skip
    head = (
        '<thead><tr><th rowspan="2">frame</th><th rowspan="2">status (expected)</th>'
        '<th colspan="3">PnP only</th><th colspan="3">refined (final)</th>'
        '<th rowspan="2">winning path</th><th rowspan="2">verification score</th>'
        '<th rowspan="2">inliers</th><th rowspan="2">reproj. (px)</th><th rowspan="2">s</th></tr>'
        "<tr>" + "<th>h (m)</th><th>v (m)</th><th>rot (deg)</th>" * 2 + "</tr></thead>"
    )
    body = "".join("<tr>" + "".join(r) + "</tr>" for r in rows)
    sid = html.escape(set_name)
    return f'<table class="frames" data-set="{sid}">{head}<tbody>{body}</tbody></table>'


def video_summary(poses: list[dict[str, Any]], set_name: str) -> str:
    """Counts (one row) and error statistics (a row each for PnP only and final) of a long set."""
    wrong = sum(
        (p.get("evaluation") or {}).get("expected") not in (None, p.get("status")) for p in poses
    )
    secs = [t for p in poses if isinstance(t := (p.get("timings_s") or {}).get("total_s"), (int, float))]  # fmt: skip
    counts = [("entries", "entries", len(poses), 0),
              ("registered", "registered", sum(p.get("status") == "registered" for p in poses), 0),
              ("status not as expected", "status_wrong", wrong, 0)]  # fmt: skip
    if any("keyframe" in p for p in poses):
        counts.append(("keyframes", "keyframes", sum(bool(p.get("keyframe")) for p in poses), 0))
    sf = [p["single_frame"] for p in poses if isinstance(p.get("single_frame"), dict)]
    if sf:  # keyframes also tried by the single-frame method (a video's anchors)
        counts += [("keyframes tried alone", "single_tried", len(sf), 0),
                   ("registered alone", "single_registered",
                    sum(r.get("status") == "registered" for r in sf), 0),
                   ("located by the sequence only", "sequence_only",
                    sum(bool(r.get("located_by_sequence_only")) for r in sf), 0)]  # fmt: skip
    counts.append(("s per entry, mean", "seconds_mean", float(np.mean(secs)) if secs else None, 2))
    sid = html.escape(set_name)
    out = table([c[0] for c in counts], [[cell(k, v, d) for _, k, v, d in counts]],
                 f'class="frames-summary" data-set="{sid}"')  # fmt: skip
    rows = []
    for key, label in (("pnp", "PnP only"), ("final", "final")):
        st = error_stats(poses, key)
        if st["n"]:
            rows.append([f"<th>{label}</th>", cell(f"{key}_n", st["n"], 0)]
                        + [cell(f"{key}_{k}", st[k]) for k in STAT_KEYS])  # fmt: skip
    if rows:
        heads = ["", "evaluated"] + [
            f"{q} {s}" for q in ("position 3-D (m)", "horizontal (m)", "rotation (deg)")
            for s in ("mean", "p90")
        ]  # fmt: skip
        out += table(heads, rows, f'class="frames-summary" data-set="{sid}"')
    return out


STAT_KEYS = [
    f"{k}_{s}" for k in ("position_m", "horizontal_m", "rotation_deg") for s in ("mean", "p90")
]


def _truth_centres(poses: list[dict[str, Any]], truth: list[dict[str, Any]]) -> list[Any]:
    """Truth camera centre per entry: ``evaluation.truth_center_xyz``, else the truth record of
    the same frame index or image name."""
    by_frame = {t["frame"]: t for t in truth if t.get("frame") is not None}
    by_name = {Path(str(t.get("image", ""))).name: t for t in truth}
    out = []
    for p in poses:
        c = (p.get("evaluation") or {}).get("truth_center_xyz")
        if c is None:
            t = by_frame.get(p.get("frame")) or by_name.get(Path(str(p.get("image", ""))).name)
            c = (t or {}).get("camera_center_xyz")
        out.append(c)
    return out


def path_plot_uri(poses: list[dict[str, Any]], truth: list[dict[str, Any]] | None = None) -> str:
    """A small PNG (data URI) of the estimated vs truth camera path in map x, y."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    order = sorted(range(len(poses)), key=lambda i: (poses[i].get("frame") is None,
                                                     poses[i].get("frame") or 0, i))  # fmt: skip
    ps = [poses[i] for i in order]
    tc = _truth_centres(ps, truth or [])
    fig, ax = plt.subplots(figsize=(5.0, 4.0), dpi=80)
    t = np.array([c[:2] for c in tc if c is not None], float).reshape(-1, 2)
    if len(t):
        ax.plot(t[:, 0], t[:, 1], "-", color="0.55", lw=2, label="truth")
    est = [p.get("camera_center_xyz") if p.get("status") == "registered" else None for p in ps]
    e = np.array([c[:2] for c in est if c is not None], float).reshape(-1, 2)
    if len(e):
        ax.plot(e[:, 0], e[:, 1], ".", color="#b00020", ms=3, label="estimated")
    kf = np.array([c[:2] for c, p in zip(est, ps, strict=True) if c is not None and p.get("keyframe")],
                  float).reshape(-1, 2)  # fmt: skip
    if len(kf):
        ax.plot(kf[:, 0], kf[:, 1], "o", mfc="none", color="#14325c", ms=5, label="keyframes")
    ax.set_aspect("equal", adjustable="datalim")
    ax.set_xlabel("x (m)")
    ax.set_ylabel("y (m)")
    ax.ticklabel_format(useOffset=False, style="plain")
    ax.tick_params(labelsize=7)
    ax.legend(fontsize=7, loc="best")
    fig.tight_layout()
    buf = io.BytesIO()
    fig.savefig(buf, format="png")
    plt.close(fig)
    return "data:image/png;base64," + base64.b64encode(buf.getvalue()).decode("ascii")


def overlay_files(poses: list[dict[str, Any]], overlay_dir: Path, limit: int | None) -> list[Path]:
    """The set's overlay PNGs in entry order (those of no entry after), evenly thinned to
    ``limit``."""
    files = sorted(Path(overlay_dir).glob("*.png")) if Path(overlay_dir).is_dir() else []
    rank = {Path(str(p.get("image", ""))).stem: i for i, p in enumerate(poses)}
    files.sort(key=lambda f: (rank.get(f.stem, len(rank)), f.name))
    if limit is not None and len(files) > limit:
        files = [files[int(i)] for i in np.linspace(0, len(files) - 1, limit).round()]
    return files


def overlays_html(files: list[Path]) -> str:
    out = []
    for f in files:
        uri = thumbnail_uri(f)
        if uri:
            out.append(
                f'<figure class="overlay" data-file="{html.escape(f.name)}"><img alt="overlay '
                f'{html.escape(f.stem)}" src="{uri}"><figcaption>{html.escape(f.stem)}</figcaption>'
                "</figure>"
            )
    return f'<div class="overlays">{"".join(out)}</div>' if out else ""


def feature_map_note(poses: list[dict]) -> str:
    """Which frames the earlier sets' feature maps served (issue 33), and their coverage; '' when
    the set used none."""
    tried = [p for p in poses if p.get("feature_map")]
    if not tried:
        return ""
    served = [p for p in tried if str(p.get("path", "")).startswith("feature map")]
    names = ", ".join(html.escape(Path(str(p["image"])).name) for p in served[:12]) or "none"
    more = f" and {len(served) - 12} more" if len(served) > 12 else ""
    src = ", ".join(html.escape(s) for s in tried[0]["feature_map"].get("sources", []))
    pts = tried[0]["feature_map"].get("map_points")
    falls = sum(1 for p in tried if not p["feature_map"].get("used"))
    cls = "note" if served else "note bad"
    return (f'<p class="{cls}" data-key="feature_map_served" data-value="{len(served)}">feature maps '
            f"{src} ({pts} points): served {len(served)} of {len(tried)} frames tried ({names}{more}); "
            f"{falls} not covered or not verified took the map-only path (feature_map.fallback in "
            "poses.json).</p>")


def set_section(name: str, poses_json: str | Path, truth_json: str | Path | None = None) -> str:
    """One frame set: the table (or the video summary and path plot) and the overlays."""
    poses = read_poses(poses_json)
    sid = html.escape(name)
    parts = [f'<section id="frames-{sid}"><h3>frame set {sid}</h3>']
    if not poses:
        parts.append('<p class="note">no entries in poses.json</p></section>')
        return "\n".join(parts)
    flat = [p for p in poses if (p.get("ground") or {}).get("warning")]
    if flat:  # no elevation in the map: say so above the figures
        parts.append(f'<p class="note bad" data-key="flat_ground" data-value="{len(flat)}">'
                     f"{len(flat)} of {len(poses)} entries localised on a flat ground (the map has "
                     f"no elevation): {html.escape(str(flat[0]['ground']['warning']))}.</p>")  # fmt: skip
    fm_note = feature_map_note(poses)
    if fm_note:
        parts.append(fm_note)
    if len(poses) <= MAX_ROWS:
        parts.append(frame_table(poses, name))
        files = overlay_files(poses, Path(poses_json).parent / "overlays", None)
    else:
        truth = read_poses(truth_json) if truth_json and Path(truth_json).exists() else []
        parts.append(video_summary(poses, name))
        parts.append(
            f'<figure class="path-plot"><img alt="camera path {sid}" '
            f'src="{path_plot_uri(poses, truth)}"><figcaption><b>camera path.</b> Estimated '
            "(registered entries) and truth camera centres in map x, y.</figcaption></figure>"
        )
        files = overlay_files(poses, Path(poses_json).parent / "overlays", MAX_VIDEO_OVERLAYS)
    parts.append(overlays_html(files))
    parts.append("</section>")
    return "\n".join(parts)


FRAMES_NOTE = (
    '<p class="note">Single-frame geo-localisation: status against the expected one '
    '(<span class="ok">green</span> = as expected, <span class="bad">red</span> = not), errors of '
    "the camera centre (horizontal h, vertical v) and of the rotation against the truth pose, "
    "of the winning path's PnP pose and of the final pose; winning path = the hypothesis chosen "
    "(direct 2D-3D matching, render-match-PnP, either + intensity refinement) by its verification "
    "score = distinct frame keypoints whose guided match in the map reprojects within the "
    "tolerance (a frame nothing else places may be found by the intensity pose search, accepted "
    "by its own similarity bound: `similarity` in poses.json); inliers = distinct frame keypoints "
    "of the winning PnP; s = wall seconds per frame. Means over the frames "
    "with an evaluation. Overlays: the map rendered at the found pose on the frame. Sets of more "
    f"than {MAX_ROWS} entries (videos): statistics, the camera path and "
    f"{MAX_VIDEO_OVERLAYS} overlays.</p>"
)


def frames_section(sets: Mapping[str, Mapping[str, Any]]) -> str:
    """The whole section for ``{set: {"poses": path, "truth": path or None}}``; '' when empty."""
    if not sets:
        return ""
    body = [f'<h2 id="frames">frames</h2>{FRAMES_NOTE}']
    for name in sorted(sets):
        s = sets[name]
        body.append(set_section(name, s["poses"], s.get("truth")))
    return "\n".join(body)
