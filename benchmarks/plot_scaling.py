"""Log-log plots of the scaling records: CPU and peak memory per stage, query time to a decision.

Reads the JSON-lines records of ``bench_scaling.py`` (one per map size) and of
``bench_query_cost.py`` (one per map size, strategy and query) and draws one PNG with three
panels (the report's figure style, ``georeg.report.plotting``):

1. CPU seconds per stage (map, index, register) vs map size;
2. the peak RSS of the largest job of each stage vs map size (flat = bounded memory);
3. time to a decision for the in-map and the outside query, ``index`` vs ``paper``.

    python benchmarks/plot_scaling.py --scaling docs/data/scaling.jsonl \\
        --query-cost docs/data/query_cost.jsonl --out docs/scaling.png
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

from georeg.report.plotting import pyplot, save_figure

STAGE_COLOURS = {"map": "#1f77b4", "index": "#ff7f0e", "register": "#2ca02c", "generate": "#7f7f7f"}


def _read(path: str | None) -> list[dict]:
    if not path:
        return []
    return [json.loads(x) for x in Path(path).read_text().splitlines() if x.strip()]


def plot(scaling: list[dict], cost: list[dict], out: Path) -> None:
    """Draw the three panels into ``out`` (PNG)."""
    plt = pyplot()
    fig, axes = plt.subplots(1, 3, figsize=(15, 4.6))
    recs = sorted(scaling, key=lambda r: r["megapixels"])
    mpx = [r["megapixels"] for r in recs]
    for stage, colour in STAGE_COLOURS.items():
        pts = [
            (m, r["stages"][stage]) for m, r in zip(mpx, recs, strict=True) if stage in r["stages"]
        ]
        if not pts:
            continue
        xs = [m for m, _ in pts]
        axes[0].plot(xs, [s["cpu_s"] for _, s in pts], "o-", color=colour, label=stage)
        axes[1].plot(xs, [s["peak_rss_mb"] for _, s in pts], "o-", color=colour, label=stage)
    if mpx:  # a line of slope 1 through the largest map's map-stage CPU: linear cost
        ref = recs[-1]["stages"].get("map", {}).get("cpu_s")
        if ref:
            axes[0].plot(
                mpx, [ref * m / mpx[-1] for m in mpx], ":", color="#999999", label="linear"
            )
    axes[0].set(title="CPU per stage", xlabel="map size (Mpx)", ylabel="CPU seconds")
    axes[1].set(title="peak RSS of the largest job (getrusage: counts mapped files)",
                xlabel="map size (Mpx)", ylabel="MB")  # fmt: skip
    styles = {("index", "q0"): ("#2ca02c", "o-"), ("index", "outside"): ("#2ca02c", "s--"),
              ("paper", "q0"): ("#d62728", "o-"), ("paper", "outside"): ("#d62728", "s--")}  # fmt: skip
    for (strategy, query), (colour, style) in styles.items():
        pts = sorted(
            (r["map_mpx"], r["decision_s"], r["outcome"])
            for r in cost
            if r["strategy"] == strategy and r["query"] == query
        )
        if not pts:
            continue
        axes[2].plot([p[0] for p in pts], [p[1] for p in pts], style, color=colour,
                     label=f"{strategy}: {'in-map' if query == 'q0' else 'outside'} query")  # fmt: skip
        for m, s, outcome in pts:  # an in-map query not found is marked
            if query == "q0" and outcome != "success":
                axes[2].plot([m], [s], "x", color="black", ms=10)
    axes[2].set(title="query: time to a decision (x = in-map query missed)",
                xlabel="map size (Mpx)", ylabel="seconds")  # fmt: skip
    for ax in axes:
        ax.set_xscale("log")
        ax.set_yscale("log")
        ax.grid(True, which="both", alpha=0.3)
        ax.legend(fontsize=8)
    fig.tight_layout()
    save_figure(fig, out, 110)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawTextHelpFormatter)
    ap.add_argument("--scaling", nargs="+", default=[])
    ap.add_argument("--query-cost", nargs="+", default=[])
    ap.add_argument("--out", type=Path, default=Path("docs/scaling.png"))
    a = ap.parse_args()
    scaling = [r for p in a.scaling for r in _read(p)]
    cost = [r for p in a.query_cost for r in _read(p)]
    plot(scaling, cost, a.out)
    print(a.out)


if __name__ == "__main__":
    main()
