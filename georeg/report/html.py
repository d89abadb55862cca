"""The self-contained HTML report: one page a person can open to judge a run at a glance.

``results/report/index.html`` embeds every figure as a base64 data URI and its CSS inline; it
loads nothing from the network and runs no script. Content: a summary table of all queries
(status, outcome, inliers, error median / p90, time), one section per query (numbers, parts
before / after fusing, figures with captions), the frame sets' poses against truth and their
overlays when ``frames`` are configured (``georeg.report.frames_html``), per-stage timings parsed from
the rule logs (``rule X done in N s``) and Snakemake benchmark files, the benchmark table when
``results/benchmark/summary.csv`` exists, and the configuration used (YAML).

Every number of the summary table is written with ``data-key`` / ``data-value`` attributes
holding the exact JSON value, so tests (and scripts) can check the page against the JSON files.
"""

from __future__ import annotations

import csv
import datetime as _dt
import html
import json
import logging
import os
import re
from collections.abc import Iterable, Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from georeg.io.atomic import write_text
from georeg.io.versions import differing, library_versions, untested
from georeg.register.ortho_check import POLISHED_SOURCES
from georeg.report.frames_html import frames_section
from georeg.report.html_parts import cell, fmt, png_data_uri, table, td

log = logging.getLogger(__name__)

RULE_DONE = re.compile(r"rule (?P<rule>[\w.-]+) done in (?P<s>[0-9.]+) s")

OUTCOME_TEXT = {
    "success": "success",
    "false_accept": "FALSE ACCEPT",
    "correct_not_found": "correct not found",
    "missed": "MISSED",
    "no_truth": "no truth",
}
OUTCOME_CLASS = {
    "success": "ok",
    "correct_not_found": "ok",
    "false_accept": "bad",
    "missed": "bad",
    "no_truth": "na",
}

CSS = """
body{font-family:system-ui,-apple-system,"Segoe UI",Roboto,Helvetica,Arial,sans-serif;margin:0;
 color:#1d1d1f;background:#fafafa;line-height:1.45}
header{background:#14325c;color:#fff;padding:18px 32px}
header h1{margin:0 0 4px 0;font-size:26px}
header p{margin:0;opacity:.85}
main{padding:8px 32px 48px 32px;max-width:1500px}
h2{border-bottom:2px solid #14325c;padding-bottom:4px;margin-top:36px}
h3{margin-top:26px}
table{border-collapse:collapse;margin:8px 0 16px 0;background:#fff;font-size:14px;
 display:block;max-width:100%;overflow-x:auto}
th,td{border:1px solid #c9ced6;padding:5px 10px;text-align:left;vertical-align:top}
th{background:#e8edf4}
td.num{text-align:right;font-variant-numeric:tabular-nums}
.ok{color:#0a7a2f;font-weight:600}.bad{color:#b00020;font-weight:700}.na{color:#666}
figure{margin:14px 0 26px 0;background:#fff;border:1px solid #d6dae0;padding:10px;
 max-width:1400px}
figure img{max-width:100%;height:auto;display:block}
figcaption{font-size:14px;color:#333;margin-top:6px}
pre{background:#f0f2f5;border:1px solid #d6dae0;padding:10px;overflow-x:auto;font-size:13px;
 max-width:100%;box-sizing:border-box}
nav a{margin-right:14px}
.note{color:#555;font-size:14px}
#benchmark{font-size:13px}#benchmark td,#benchmark th{padding:3px 6px}
#benchmark th.strategy{text-align:center;background:#d5dfee}
#benchmark td.note{min-width:200px;font-size:12px}
summary{cursor:pointer;color:#14325c;margin:6px 0}
.overlays{display:flex;flex-wrap:wrap;gap:10px;align-items:flex-start}
figure.overlay{margin:0;padding:6px;max-width:372px}figure.path-plot{max-width:420px}
table.frames td,table.frames th{padding:3px 7px}
"""


@dataclass
class QueryInputs:
    """The files of one query that the report reads."""

    name: str
    registration: Path
    evaluation: Path | None = None
    figures_dir: Path | None = None
    extra: dict[str, Any] = field(default_factory=dict)


# ----------------------------------------------------------------------------- readers


def _read_json(path: Path | None) -> dict[str, Any]:
    if path is None or not Path(path).exists():
        return {}
    try:
        return json.loads(Path(path).read_text())
    except (OSError, json.JSONDecodeError) as exc:
        log.warning("cannot read %s: %s", path, exc)
        return {}


def parse_timings(roots: Iterable[str | Path]) -> list[dict[str, Any]]:
    """Per-rule timings from rule logs (``rule X done in N s``) and Snakemake benchmark TSVs.

    Benchmark files are read from a root whose path contains "benchmark", laid out as
    ``<root>/<stage>/<rule>.tsv`` or ``<root>/<stage>/<rule>/<wildcards>.tsv``.

    Returns one row per rule: stage (first folder under the root), rule, jobs, total / max
    seconds and the source ("log" or "benchmark"), sorted by stage then rule.
    """
    acc: dict[tuple[str, str, str], list[float]] = {}
    for root in roots:
        r = Path(root)
        if not r.is_dir():
            continue
        for p in sorted(r.rglob("*")):
            if not p.is_file():
                continue
            rel = p.relative_to(r).parts
            stage = rel[0] if len(rel) > 1 else "-"
            if p.suffix == ".log":
                try:
                    text = p.read_text(errors="replace")
                except OSError:
                    continue
                for m in RULE_DONE.finditer(text):
                    acc.setdefault((stage, m["rule"], "log"), []).append(float(m["s"]))
            elif p.suffix in (".tsv", ".txt") and "benchmark" in str(p):
                # <root>/<stage>/<rule>.tsv or <root>/<stage>/<rule>/<wildcards>.tsv
                s = _benchmark_seconds(p)
                if s is not None:
                    rule = rel[1] if len(rel) > 2 else p.stem
                    acc.setdefault((stage, rule, "benchmark"), []).append(s)
    rows = []
    for (stage, rule, src), v in sorted(acc.items()):
        rows.append(
            {
                "stage": stage,
                "rule": rule,
                "jobs": len(v),
                "total_s": sum(v),
                "max_s": max(v),
                "source": src,
            }
        )
    return rows


def _benchmark_seconds(path: Path) -> float | None:
    """Mean wall seconds (column ``s``) of a Snakemake benchmark TSV."""
    try:
        with path.open() as f:
            rows = list(csv.DictReader(f, delimiter="\t"))
        vals = [float(r["s"]) for r in rows if r.get("s") not in (None, "", "NA")]
    except (OSError, ValueError, KeyError):
        return None
    return sum(vals) / len(vals) if vals else None


def query_seconds(reg: Mapping[str, Any]) -> float | None:
    """Compute seconds of one query: band extraction + every part's search + fusion."""
    t = reg.get("timings_s") or {}
    parts = t.get("search_parts") or {}
    vals = [t.get("query_band"), *parts.values(), t.get("fuse_total")]
    vals = [float(v) for v in vals if isinstance(v, (int, float))]
    return sum(vals) if vals else None


def summary_row(name: str, reg: Mapping[str, Any], ev: Mapping[str, Any]) -> dict[str, Any]:
    """The numbers of one query in the summary table (raw JSON values)."""
    err = (ev.get("error") or {}) if ev else {}
    px = err.get("px") or {}
    m = err.get("m") or {}
    return {
        "query": name,
        "status": reg.get("status"),
        "outcome": (ev or {}).get("outcome", "no_truth"),
        "inliers": reg.get("inliers"),
        "candidates_tried": reg.get("candidates_tried"),
        "error_median_px": px.get("median"),
        "error_p90_px": px.get("p90"),
        "error_max_px": px.get("max"),
        "error_median_m": m.get("median"),
        "error_p90_m": m.get("p90"),
        "lidar_check": (reg.get("lidar_check") or {}).get("outcome"),  # fit vs the map's elevation
        "time_s": query_seconds(reg),
    }


def read_benchmark(path: str | Path | None) -> list[dict[str, str]]:
    """Rows of ``results/benchmark/summary.csv`` (empty when absent)."""
    if not path or not Path(path).exists():
        return []
    with Path(path).open() as f:
        return list(csv.DictReader(f))


# ----------------------------------------------------------------------------- HTML pieces


def summary_table(rows: list[dict[str, Any]]) -> str:
    """The summary table of all queries."""
    out = []
    for r in rows:
        oc = r["outcome"]
        out.append(
            [
                f'<td data-key="query" data-value="{html.escape(r["query"])}">'
                f'<a href="#q-{html.escape(r["query"])}">'
                f"{html.escape(r['query'])}</a></td>",
                f'<td data-key="status" data-value="{html.escape(str(r["status"]))}">'
                f"{html.escape(str(r['status']))}</td>",
                f'<td class="{OUTCOME_CLASS.get(oc, "na")}" data-key="outcome" '
                f'data-value="{html.escape(oc)}">{OUTCOME_TEXT.get(oc, oc)}</td>',
                cell("inliers", r["inliers"]),
                cell("candidates_tried", r["candidates_tried"]),
                cell("error_median_px", r["error_median_px"]),
                cell("error_p90_px", r["error_p90_px"]),
                cell("error_max_px", r["error_max_px"]),
                cell("error_median_m", r["error_median_m"]),
                cell("error_p90_m", r["error_p90_m"]),
                cell("lidar_check", r["lidar_check"], cls=""),
                cell("time_s", r["time_s"], 1),
            ]
        )
    return table(
        [
            "query",
            "status",
            "outcome",
            "inliers",
            "candidates tried",
            "error median (px)",
            "error p90 (px)",
            "error max (px)",
            "error median (m)",
            "error p90 (m)",
            "LiDAR check",
            "time (s)",
        ],
        out,
        'id="summary"',
    )


def parts_table(reg: Mapping[str, Any], ev: Mapping[str, Any]) -> str:
    """Per part: rows, accepted, candidates, inliers, error of its own homography vs the fused."""
    evp = {p.get("part"): p for p in (ev.get("parts") or [])} if ev else {}
    after = (reg.get("fuse") or {}).get("disagreement_after") or {}
    rows = []
    for p in reg.get("parts") or []:
        e = evp.get(p.get("part"), {})

        def med(d: Mapping[str, Any] | None) -> Any:
            return ((d or {}).get("px") or {}).get("median")

        rows.append(
            [
                td(p.get("part")),
                td(f"{p['rows'][0]}-{p['rows'][1]}" if p.get("rows") else None),
                td(bool(p.get("accepted"))),
                td(p.get("candidates_tried"), num=True),
                td(p.get("inliers"), num=True),
                td(p.get("log10_nfa"), 1, num=True),
                td(p.get("seconds"), 1, num=True),
                td(med(e.get("error_own_rows")), num=True),
                td(med(e.get("error_whole")), num=True),
                td(med(e.get("fused_error_own_rows")), num=True),
                td((after.get(str(p.get("part"))) or {}).get("inliers"), num=True),
            ]
        )
    if not rows:
        return ""
    return table(
        [
            "part",
            "rows",
            "accepted",
            "candidates tried",
            "inliers",
            "log10 NFA",
            "time (s)",
            "own H error, own rows (px)",
            "own H error, whole query (px)",
            "fused error, own rows (px)",
            "fused inliers in its rows",
        ],
        rows,
    )


def pooled_text(pooled: Any) -> str | None:
    """``registration.json``'s pooled bands as "1199.0 nm (39), 2200.0 nm (113)"."""
    if not pooled:
        return None
    out = []
    for b in pooled:
        wl = b.get("wavelength_nm")
        what = "mean" if b.get("index") is None else f"index {b['index']}"
        out.append(f"{float(wl):.1f} nm ({what})" if wl is not None else what)
    return ", ".join(out)


def level_text(level: Any) -> str | None:
    """``registration.json``'s ``level`` (georeg.register.level) as one line; None: no level."""
    if not level:
        return None
    if level.get("features") is None:
        return f"not used: {level.get('reason')}"
    return (f"orthophoto averaged to {float(level['gsd']):.3g} map units: {level.get('width')} x "
            f"{level.get('height')} px, {level['features']} features")  # fmt: skip


def sources_text(reg: Mapping[str, Any]) -> str | None:
    """``registration.json``'s ``sources`` (which sources of candidates ran, what each tried,
    which was accepted) as one line, with the phase-congruency source's decision when it ran and
    the second pass when the verifier refused the first pass's candidate (``fuse.decide``)."""
    ran = reg.get("sources") or []
    if not ran:
        return None
    out = []
    for s in ran:
        t = f"{s.get('name')} ({s.get('candidates', 0)} tried{', accepted' if s.get('accepted') else ''})"
        rift = (reg.get("split") or {}).get(s.get("name")) if s.get("name") in POLISHED_SOURCES else None
        if rift:
            one = lambda v: "none" if v is None else f"{float(v):.1f}"  # noqa: E731
            t += (f": log10 NFA {one(rift.get('log10_nfa'))}, other rotations' best "
                  f"{one(rift.get('null_log10_nfa'))}, {rift.get('matches', 0)} cells")  # fmt: skip
            if rift.get("search"):  # the reversed source: which of its searches gave the pose
                t += f", by its {rift['search']} search"
            if rift.get("gsd_guesses"):  # the query's GSD unknown: each guess searched
                tried = ", ".join(f"{float(x.get('guess', x['gsd'])):.3g}" for x in rift["gsd_guesses"])
                t += f"; GSD unknown: {tried} map units a pixel searched, this pose at {float(rift['gsd']):.3g}"
            if not rift.get("accepted") and rift.get("reason"):
                t += f"; {rift['reason']}"
        out.append(t)
    sp = reg.get("second_pass")
    if sp:  # the verifier refused the first pass's candidate: the skipped sources ran after it
        out.append(f"second pass ({', '.join(sp.get('sources') or [])}) after the verifier "
                   f"refused the first candidate: {sp.get('refused')}")  # fmt: skip
        if sp.get("elsewhere"):  # its candidate lay at another place: refused too
            out.append(f"not kept: {sp['elsewhere'].get('reason')}")
    return "; ".join(out)


def query_section(q: QueryInputs, reg: Mapping[str, Any], ev: Mapping[str, Any]) -> str:
    """One query: key numbers, parts table, figures."""
    name = html.escape(q.name)
    oc = (ev or {}).get("outcome", "no_truth")
    err = (ev or {}).get("error") or {}
    kv = [
        ("status", reg.get("status")),
        ("outcome", OUTCOME_TEXT.get(oc, oc)),
        ("reason", reg.get("reason")),
        ("query image", reg.get("query")),
        (
            "band",
            f"{float(reg['band']['wavelength_nm']):.1f} nm (index {reg['band'].get('index')})"
            if isinstance(reg.get("band"), dict) and reg["band"].get("wavelength_nm") is not None
            else reg.get("band"),
        ),
        ("bands pooled (features)", pooled_text(reg.get("pooled_bands"))),
        ("size (cols x rows)", f"{reg.get('width')} x {reg.get('height')}"),
        ("strategy / acceptance", f"{reg.get('strategy')} / {reg.get('acceptance')}"),
        ("fusion method", (reg.get("fuse") or {}).get("method")),
        ("inliers / matches", f"{reg.get('inliers', 0)} / {reg.get('matches') or 0}"),
        ("residual (feature px, RMS)", reg.get("residual_px")),
        ("log10 NFA", reg.get("log10_nfa")),
        ("candidates tried", reg.get("candidates_tried")),
        ("sources of candidates", sources_text(reg)),
    ]
    kv.append(("map level (query much coarser than the map)", level_text(reg.get("level"))))
    if err.get("px"):
        px, m = err["px"], err.get("m") or {}
        for k in ("median", "p90", "max", "rmse"):
            kv.append((f"error {k}", f"{fmt(px.get(k))} px = {fmt(m.get(k))} m"))
        kv.append(("pixels with truth", err.get("pixels")))
    if ev and ev.get("inside_fraction") is not None:
        kv.append(("share of the query inside the map (truth)", f"{ev['inside_fraction']:.0%}"))
    gain = (ev or {}).get("fusion_gain")
    if gain:
        kv.append(
            (
                "fusion gain (best part's H vs fused, median px over the whole query)",
                f"{fmt(gain.get('best_part_median_px'))} -> {fmt(gain.get('fused_median_px'))}",
            )
        )
    seg = (ev or {}).get("segmentation") or {}
    if seg.get("overall_accuracy") is not None:
        kv.append(("segmentation overall accuracy", f"{seg['overall_accuracy']:.1%}"))
        kv.append(("segmentation mean IoU", seg.get("mean_iou")))
    for product, why in sorted(((ev or {}).get("products_skipped") or {}).items()):
        kv.append((f"skipped: {product}", why))
    t = reg.get("timings_s") or {}
    kv.append(("time (s): band + parts + fuse", fmt(query_seconds(reg), 1)))
    if t:
        kv.append(
            (
                "timings (s)",
                ", ".join(
                    f"{k} {v:.1f}" if isinstance(v, (int, float)) else f"{k} {v}"
                    for k, v in t.items()
                    if not isinstance(v, dict)
                ),
            )
        )
    rows = [[f"<th>{html.escape(k)}</th>", td(v, 3)] for k, v in kv if v is not None]
    parts = [f'<section id="q-{name}"><h2>query {name}</h2>', table(None, rows)]
    pt = parts_table(reg, ev)
    if pt:
        parts.append("<h3>parts, before and after fusing</h3>" + pt)
    parts.append(figures_html(q.figures_dir))
    parts.append("</section>")
    return "\n".join(parts)


def figures_html(fig_dir: Path | None) -> str:
    """Every figure listed in ``figures.json`` of the directory, embedded, with its caption."""
    if fig_dir is None:
        return ""
    man = _read_json(Path(fig_dir) / "figures.json")
    out = []
    for f in man.get("figures", []):
        p = Path(fig_dir) / f["file"]
        if not p.exists():
            log.warning("figure %s listed but missing", p)
            continue
        out.append(
            f'<figure data-file="{html.escape(f["file"])}"><img alt="{html.escape(f["title"])}" '
            f'src="{png_data_uri(p)}"><figcaption><b>{html.escape(f["title"])}.</b> '
            f"{html.escape(f['caption'])}</figcaption></figure>"
        )
    return "\n".join(out)


def timings_table(rows: list[dict[str, Any]]) -> str:
    """Per-stage / per-rule timings."""
    if not rows:
        return '<p class="note">no rule log with timings found</p>'
    stages: dict[str, float] = {}
    for r in rows:
        stages[r["stage"]] = stages.get(r["stage"], 0.0) + r["total_s"]
    body = [
        [
            td(r["stage"]),
            td(r["rule"]),
            td(r["jobs"], num=True),
            td(r["total_s"], 1, num=True),
            td(r["max_s"], 1, num=True),
            td(r["source"]),
        ]
        for r in rows
    ]
    st = [[td(k), td(v, 1, num=True)] for k, v in stages.items()]
    return table(["stage", "total (s, summed over jobs)"], st, 'id="stage-timings"') + table(
        ["stage", "rule", "jobs", "total (s)", "max (s)", "from"], body, 'id="rule-timings"'
    )


BENCH_FIELDS = [
    ("outcome", "outcome"),
    ("error_median_px", "median err (px)"),
    ("error_p90_px", "p90 err (px)"),
    ("inliers", "inliers"),
    ("candidates", "cand. tried"),
    ("time_s", "time (s)"),
]


def benchmark_table(rows: list[dict[str, str]]) -> str:
    """The benchmark summary CSV as a table, the strategies side by side (bad outcomes red)."""
    if not rows:
        return (
            '<p class="note">no benchmark yet: run <code>python benchmarks/run.py</code> '
            "(a few minutes) to write results/benchmark/summary.csv; the next "
            "<code>snakemake</code> run adds it here</p>"
        )
    cols = list(rows[0])
    strategies = [c[: -len("_outcome")] for c in cols if c.endswith("_outcome")]
    fixed = [c for c in ("scenario", "group", "map", "inside_fraction") if c in cols]
    used = set(fixed) | {f"{st}_{k}" for st in strategies for k, _ in BENCH_FIELDS}
    rest = [c for c in cols if c not in used]
    head1 = "".join(f'<th rowspan="2">{html.escape(c.replace("_", " "))}</th>' for c in fixed)
    head1 += "".join(
        f'<th colspan="{len(BENCH_FIELDS)}" class="strategy">{html.escape(st)}</th>'
        for st in strategies
    )
    head1 += "".join(f'<th rowspan="2">{html.escape(c)}</th>' for c in rest)
    head2 = "".join(f"<th>{t}</th>" for _ in strategies for _, t in BENCH_FIELDS)
    body = []
    for r in rows:
        cells = [f"<td>{html.escape(r.get(c, ''))}</td>" for c in fixed]
        for st in strategies:
            for k, _ in BENCH_FIELDS:
                v = r.get(f"{st}_{k}", "")
                if k == "outcome":
                    cls = OUTCOME_CLASS.get(v, "")
                    cells.append(f'<td class="{cls}">{html.escape(OUTCOME_TEXT.get(v, v))}</td>')
                else:
                    cells.append(f'<td class="num">{html.escape(v)}</td>')
        cells += [f'<td class="note">{html.escape(r.get(c, ""))}</td>' for c in rest]
        body.append("<tr>" + "".join(cells) + "</tr>")
    return (
        f'<table id="benchmark"><thead><tr>{head1}</tr><tr>{head2}</tr></thead>'
        f"<tbody>{''.join(body)}</tbody></table>"
    )


def versions_table() -> str:
    """The libraries' versions; where one differs from constraints.txt (the versions the suite and
    the benchmarks were last run with), the tested one beside it and a note above."""
    have = library_versions()
    other = differing(have)
    rows = [[td(k), td(v), td(other.get(k, ""))] for k, v in have.items()]
    note = ""
    if other:
        note = ('<p class="note">not the tested versions (constraints.txt): '
                + html.escape(untested(have, other)) + "; results at a decision's margin can differ.</p>")  # fmt: skip
    return note + table(["package", "version", "tested (constraints.txt), where other"], rows)


def config_yaml(config: Mapping[str, Any]) -> str:
    """The configuration as YAML text."""
    import yaml

    return yaml.safe_dump(json.loads(json.dumps(config, default=str)), sort_keys=False)


def build_report(
    queries: list[QueryInputs],
    config: Mapping[str, Any],
    out_html: str | Path,
    log_roots: Iterable[str | Path] = ("logs",),
    benchmark_csv: str | Path | None = None,
    overview_png: str | Path | None = None,
    frame_sets: Mapping[str, Mapping[str, Any]] | None = None,
    map_html: str | Path | None = None,
) -> dict[str, Any]:
    """Write the self-contained report; returns the summary rows (also embedded in the page).

    ``frame_sets``: ``{set: {"poses": poses.json, "truth": truth.json or None}}`` adds the frames
    section (``georeg.report.frames_html``); none: no section. ``map_html``: the map view
    (``georeg.report.map_view``), linked from the header and the navigation."""

    regs = {q.name: _read_json(q.registration) for q in queries}
    evs = {q.name: _read_json(q.evaluation) for q in queries}
    rows = [summary_row(q.name, regs[q.name], evs[q.name]) for q in queries]
    timings = parse_timings(log_roots)
    bench = read_benchmark(benchmark_csv)
    n_ok = sum(r["outcome"] in ("success", "correct_not_found") for r in rows)
    n_truth = sum(r["outcome"] != "no_truth" for r in rows)
    n_reg = sum(r["status"] == "registered" for r in rows)
    now = _dt.datetime.now().strftime("%Y-%m-%d %H:%M")
    verdict = f"{n_reg} of {len(rows)} queries registered; " + (
        f"{n_ok} of {n_truth} with truth judged correct." if n_truth else "no truth given."
    )
    map_href = (
        html.escape(os.path.relpath(map_html, Path(out_html).parent).replace(os.sep, "/"))
        if map_html
        else None
    )
    nav = (f'<a href="{map_href}"><b>map view</b></a>' if map_href else "") + "".join(
        f'<a href="#{a}">{t}</a>'
        for a, t in [
            ("summary-h", "summary"),
            *([("frames", "frames")] if frame_sets else []),
            ("timings", "timings"),
            ("benchmark-h", "benchmark"),
            ("config", "configuration"),
        ]
    )
    body = [
        f"<header><h1>georeg report</h1><p>{html.escape(verdict)} Built {now}.</p></header>",
        f"<main><nav>{nav}</nav>",
        '<h2 id="summary-h">summary</h2>',
        *(
            [
                f'<p class="note"><a href="{map_href}"><b>Open the map view</b></a>: the queries '
                "drawn on the orthophoto (opacity or swipe), footprints, frame cameras and "
                "trajectories; click one for its status and errors (works offline).</p>"
            ]
            if map_href
            else []
        ),
        '<p class="note">outcome: <span class="ok">success</span> = registered with error within '
        'the bound; <span class="bad">FALSE ACCEPT</span> = registered at the wrong place; '
        '<span class="ok">correct not found</span> = the query is not on the map and the system '
        'said so; <span class="bad">MISSED</span> = on the map but not found. Errors are over all '
        "query pixels with a truth, in map pixels and metres. Time = band + every part's search + "
        "fusion (compute seconds, parts run in parallel).</p>",
        summary_table(rows),
    ]
    if overview_png and Path(overview_png).exists():
        body.append(
            f'<figure><img alt="map overview" src="{png_data_uri(Path(overview_png))}">'
            "<figcaption><b>map overview.</b> The orthophoto with its tiles and the hillshaded "
            "DSM from the LiDAR.</figcaption></figure>"
        )
    for q in queries:
        body.append(query_section(q, regs[q.name], evs[q.name]))
    body.append(frames_section(frame_sets or {}))
    body += [
        '<h2 id="timings">per-stage timings</h2>',
        '<p class="note">from the rule logs ("rule X done in N s") and Snakemake benchmark files; '
        "times are summed over a rule's jobs.</p>",
        timings_table(timings),
        '<h2 id="benchmark-h">benchmark</h2>',
        '<p class="note">From <code>python benchmarks/run.py</code> (scenarios in '
        "benchmarks/scenarios.yaml): a ladder of synthetic difficulty built from the demo query "
        "and real cross-spectral cases, each registered with both search strategies through the "
        "library (parts searched one after the other; time = search + fusion). Outcomes as in the "
        "summary; errors in map pixels.</p>",
        benchmark_table(bench),
        '<h2 id="config">configuration used</h2>',
        f"<details open><summary>config (YAML, defaults filled in)</summary>"
        f"<pre>{html.escape(config_yaml(config))}</pre></details>",
        '<h2 id="versions">software versions</h2>',
        versions_table(),
        "</main>",
    ]
    page = (
        '<!DOCTYPE html>\n<html lang="en"><head><meta charset="utf-8">'
        '<meta name="viewport" content="width=device-width, initial-scale=1">'
        f"<title>georeg report</title><style>{CSS}</style></head><body>\n"
        + "\n".join(body)
        + "\n</body></html>\n"
    )
    write_text(out_html, page)
    return {"queries": rows, "timings": timings, "benchmark_rows": len(bench)}


SUMMARY_COLUMNS = [
    "query",
    "status",
    "outcome",
    "inliers",
    "candidates_tried",
    "error_median_px",
    "error_p90_px",
    "error_max_px",
    "error_median_m",
    "error_p90_m",
    "lidar_check",
    "time_s",
]


def write_summary_csv(rows: list[dict[str, Any]], path: str | Path) -> None:
    """The summary table as CSV (empty cell = not applicable)."""
    import io

    buf = io.StringIO()
    w = csv.DictWriter(buf, SUMMARY_COLUMNS, lineterminator="\n")
    w.writeheader()
    for r in rows:
        w.writerow({k: ("" if r.get(k) is None else r.get(k)) for k in SUMMARY_COLUMNS})
    write_text(path, buf.getvalue())


def run_report(
    names: list[str],
    registrations: list[str],
    evaluations: list[str],
    figure_dirs: list[str],
    config: Mapping[str, Any],
    out_html: str | Path,
    out_csv: str | Path | None = None,
    log_roots: Iterable[str | Path] = ("logs",),
    benchmark_csv: str | Path | None = None,
    overview_png: str | Path | None = None,
    frame_sets: Mapping[str, Mapping[str, Any]] | None = None,
    map_html: str | Path | None = None,
) -> dict[str, Any]:
    """Rule report_html: the page and, when asked, the summary CSV (lists aligned by query);
    ``frame_sets`` and ``map_html`` as in ``build_report``."""
    if not (len(names) == len(registrations) == len(evaluations) == len(figure_dirs)):
        raise ValueError("names, registrations, evaluations and figure_dirs differ in length")
    queries = [
        QueryInputs(n, Path(r), Path(e), Path(f))
        for n, r, e, f in zip(names, registrations, evaluations, figure_dirs, strict=True)
    ]
    res = build_report(
        queries, config, out_html, log_roots, benchmark_csv, overview_png, frame_sets, map_html
    )
    if out_csv:
        write_summary_csv(res["queries"], out_csv)
    log.info("report %s: %d queries, %d timing rows", out_html, len(queries), len(res["timings"]))
    return res
