"""Frame geo-localisation table (docs/BENCHMARKS.md "Frame geo-localisation") from poses.json.

    python benchmarks/bench_frames.py results/frames/demo/poses.json [more poses.json ...]

Each poses.json must come from a set with `truth` (the demo frames): prints one markdown row per
frame (status vs expected, PnP and refined errors, inliers, seconds) and the means.
"""

from __future__ import annotations

import json
import sys
from pathlib import Path


def rows(path: str) -> list[dict]:
    out = []
    for p in json.loads(Path(path).read_text()):
        ev = p.get("evaluation") or {}
        out.append({"frame": Path(p["image"]).stem, "status": p["status"], "expected": ev.get("expected"),
                    "pnp": ev.get("pnp"), "final": ev.get("final"), "inliers": p.get("inliers"),
                    "refine_kept": (p.get("refine") or {}).get("accepted"),
                    "seconds": (p.get("timings_s") or {}).get("total_s")})  # fmt: skip
    return out


def fmt(e: dict | None) -> str:
    if not e:
        return "-"
    return f"{e['horizontal_m']:.2f} / {e['vertical_m']:.2f} m, {e['rotation_deg']:.2f} deg"


def main(paths: list[str]) -> None:
    allr = [r for p in paths for r in rows(p)]
    print(
        "| frame | status (expected) | PnP error h / v, rot | refined error h / v, rot | inliers | refine kept | s |"
    )
    print("|---|---|---|---|---|---|---|")
    for r in allr:
        print(f"| {r['frame']} | {r['status']} ({r['expected']}) | {fmt(r['pnp'])} | {fmt(r['final'])} | "
              f"{r['inliers']} | {r['refine_kept']} | {r['seconds']:.1f} |")  # fmt: skip
    reg = [r for r in allr if r["final"]]
    for key in ("pnp", "final"):
        v = [r[key] for r in reg if r[key]]
        if v:
            n = len(v)
            print(f"mean {key}: position {sum(e['position_m'] for e in v) / n:.2f} m, horizontal "
                  f"{sum(e['horizontal_m'] for e in v) / n:.2f} m, vertical {sum(e['vertical_m'] for e in v) / n:.2f} m, "
                  f"rotation {sum(e['rotation_deg'] for e in v) / n:.2f} deg over {n} frames")  # fmt: skip


if __name__ == "__main__":
    main(sys.argv[1:])
