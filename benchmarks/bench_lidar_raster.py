"""LiDAR rasterization throughput (million points/s) and peak memory; writes docs/BENCHMARKS.md.

Cases, each in a fresh subprocess so that its peak RSS is its own:
  raster-demo   demo-size cloud (2048 m x 2048 m at 2 pts/m2 = 8.4 M points) -> DSM/DTM/nDSM/density
                on the 1 m demo grid (GridAccumulator.add + surfaces_from_accumulator)
  raster-large  a generated cloud of 40 M points over the same grid, streamed in 2 M-point
                chunks (only one chunk in memory; generation time excluded)
  tile-demo     the whole per-tile pipeline of rule map_tile_elevation on one 1024 px tile at demo
                density: LAZ in EPSG:2229 (US survey feet) -> chunked read + reprojection to UTM +
                open3d outlier removal + rasterization + gap filling
Throughput is the median of --runs runs.

    python benchmarks/bench_lidar_raster.py            # all cases, updates docs/BENCHMARKS.md
    python benchmarks/bench_lidar_raster.py --no-write # print only
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import resource
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

SECTION = "## LiDAR rasterization"
CHUNK = 2_000_000


def _grid(size_px: int = 2048):
    from rasterio.crs import CRS
    from rasterio.transform import from_origin

    from georeg.map.elevation import Grid

    return Grid(CRS.from_epsg(32611), from_origin(500_000, 3_760_000, 1.0, 1.0), size_px, size_px)


def _points(n: int, size_m: float, seed: int) -> tuple[np.ndarray, ...]:
    """Terrain + box buildings + trees: x, y (UTM), z (m), ground flag."""
    rng = np.random.default_rng(seed)
    x = rng.uniform(0, size_m, n)
    y = rng.uniform(0, size_m, n)
    ground = 100 + 5 * np.sin(x / 300) + 3 * np.cos(y / 200)
    bld = ((x // 40) % 3 == 0) & ((y // 40) % 3 == 0) & (x % 40 > 8) & (y % 40 > 8)
    tree = ~bld & (rng.random(n) < 0.1)
    z = ground + np.where(bld, 9.0, 0.0) + np.where(tree, rng.uniform(0, 15, n), 0.0)
    return 500_000 + x, 3_760_000 - size_m + y, z, ~bld & ~tree


def _rss_mb() -> float:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0


def case_raster(n_total: int) -> dict:
    from georeg.map.elevation import GridAccumulator, surfaces_from_accumulator

    grid = _grid()
    t_add = 0.0
    acc = GridAccumulator(grid)
    done, seed = 0, 0
    while done < n_total:
        n = min(CHUNK, n_total - done)
        x, y, z, g = _points(n, 2048.0, seed)
        t0 = time.perf_counter()
        acc.add(x, y, z, g)
        t_add += time.perf_counter() - t0
        done += n
        seed += 1
        del x, y, z, g
    t0 = time.perf_counter()
    surfaces_from_accumulator(acc)
    t_surf = time.perf_counter() - t0
    return {"points": n_total, "t_add": t_add, "t_surf": t_surf, "seconds": t_add + t_surf}


def case_tile() -> dict:
    import laspy
    from pyproj import CRS, Transformer
    from rasterio.crs import CRS as RCRS
    from rasterio.transform import from_origin

    from georeg.map.elevation import Grid, lidar_tile

    size = 1024
    margin = 20.0
    extent = size + 2 * margin
    n = int(extent * extent * 2.0)
    x, y, z, g = _points(n, extent, 3)
    x, y = x - margin, y + margin  # grid top-left at (500000, 3760000)
    tmp = Path(tempfile.mkdtemp())
    las_path = tmp / "tile.laz"
    tr = Transformer.from_crs("EPSG:32611", "EPSG:2229", always_xy=True)
    fx, fy = tr.transform(x, y)
    header = laspy.LasHeader(point_format=6, version="1.4")
    header.scales = np.array([0.01, 0.01, 0.01])
    header.offsets = np.array([np.floor(fx.min()), np.floor(fy.min()), 0.0])
    header.add_crs(CRS.from_epsg(2229))
    las = laspy.LasData(header)
    las.x, las.y, las.z = fx, fy, z / (1200 / 3937)
    las.classification = np.where(g, 2, 1).astype(np.uint8)
    las.write(str(las_path))
    del las, fx, fy, x, y, z, g
    grid = Grid(RCRS.from_epsg(32611), from_origin(500_000, 3_760_000, 1.0, 1.0), size, size)
    t0 = time.perf_counter()
    surf, pts = lidar_tile(grid, [str(las_path)], point_margin_m=margin, chunk_points=CHUNK)
    dt = time.perf_counter() - t0
    las_path.unlink()
    return {"points": n, "seconds": dt, "kept_in_tile": len(pts)}


def run_case(name: str) -> dict:
    if name == "raster-demo":
        out = case_raster(int(2048 * 2048 * 2.0))
    elif name == "raster-large":
        out = case_raster(40_000_000)
    elif name == "tile-demo":
        out = case_tile()
    else:
        raise SystemExit(f"unknown case {name}")
    out["peak_rss_mb"] = _rss_mb()
    return out


def measure(name: str, runs: int) -> dict:
    res = []
    for _ in range(runs):
        p = subprocess.run(
            [sys.executable, __file__, "--case", name], capture_output=True, text=True, check=True
        )
        res.append(json.loads(p.stdout.strip().splitlines()[-1]))
    secs = [r["seconds"] for r in res]
    med = float(np.median(secs))
    out = {
        "case": name,
        "points": res[0]["points"],
        "runs": runs,
        "median_s": med,
        "mpts_per_s": res[0]["points"] / med / 1e6,
        "peak_rss_mb": float(max(r["peak_rss_mb"] for r in res)),
    }
    if "t_add" in res[0]:
        out["add_mpts_per_s"] = res[0]["points"] / float(np.median([r["t_add"] for r in res])) / 1e6
        out["surf_s"] = float(np.median([r["t_surf"] for r in res]))
    print(json.dumps(out), flush=True)
    return out


def write_section(results: list[dict], runs: int, load: tuple[float, float]) -> None:
    doc = REPO / "docs" / "BENCHMARKS.md"
    lines = [
        SECTION,
        "",
        "Rule `map_tile_elevation` (`georeg/map/elevation.py`, `georeg/map/lidar.py`). Reproduce with",
        "`python benchmarks/bench_lidar_raster.py` (about 5 minutes on 2 cores; rewrites this section).",
        f"Machine: {platform.processor() or platform.machine()}, Python "
        f"{platform.python_version()}, {time.strftime('%Y-%m-%d')}; median of {runs} runs, each "
        "in a fresh process; peak memory = max RSS of the process (includes the Python/numpy/",
        f"open3d baseline of ~150-250 MB). Load average before/after: {load[0]:.1f} / {load[1]:.1f}",
        f"on {os.cpu_count()} cores (other jobs running slow every case down in proportion).",
        "",
        "| case | points | median time (s) | throughput (M pts/s) | binning only (M pts/s) | "
        "surfaces (s) | peak RSS (MB) |",
        "|---|---:|---:|---:|---:|---:|---:|",
    ]
    for r in results:
        add = f"{r['add_mpts_per_s']:.1f}" if "add_mpts_per_s" in r else "-"
        surf = f"{r['surf_s']:.2f}" if "surf_s" in r else "-"
        lines.append(
            f"| {r['case']} | {r['points'] / 1e6:.1f} M | {r['median_s']:.2f} | "
            f"{r['mpts_per_s']:.2f} | {add} | {surf} | {r['peak_rss_mb']:.0f} |"
        )
    lines += [
        "",
        "- `raster-demo`: demo-size cloud (2048 m square at 2 pts/m2) binned onto the 1 m grid,",
        "  then DSM gap fill, DTM interpolation, nDSM (`surfaces`).",
        "- `raster-large`: 40 M generated points streamed in 2 M chunks into the same grid: memory",
        "  stays at grid + one chunk (the accumulator is 32 bytes per cell).",
        "- `tile-demo`: the whole rule body for one 1024 px tile (+20 m margin) at demo density:",
        "  LAZ decode, ftUS -> UTM reprojection, open3d outlier removal, rasterization, gap",
        "  filling. Outlier removal and LAZ decoding dominate; binning itself is ~10x faster.",
        "",
    ]
    text = doc.read_text() if doc.exists() else "# Benchmarks\n\n"
    if SECTION in text:
        start = text.index(SECTION)
        nxt = text.find("\n## ", start + len(SECTION))
        text = text[:start] + "\n".join(lines) + (text[nxt + 1 :] if nxt >= 0 else "")
    else:
        text = text.rstrip("\n") + "\n\n" + "\n".join(lines)
    doc.write_text(text)
    print(f"updated {doc}")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawTextHelpFormatter)
    ap.add_argument("--case", help="run one case in this process and print JSON")
    ap.add_argument("--runs", type=int, default=3)
    ap.add_argument("--no-write", action="store_true")
    a = ap.parse_args()
    if a.case:
        print(json.dumps(run_case(a.case)))
        return
    load0 = os.getloadavg()[0]
    results = [measure(c, a.runs) for c in ("raster-demo", "raster-large", "tile-demo")]
    if not a.no_write:
        write_section(results, a.runs, (load0, os.getloadavg()[0]))


if __name__ == "__main__":
    main()
