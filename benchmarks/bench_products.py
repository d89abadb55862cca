"""Time and peak memory of the products for the paper-sized query (829 x 1163 x 260).

Usage (from the repository root, venv active)::

    python benchmarks/bench_products.py --workdir /tmp/bench_products [--scene DIR]

Generates the default demo scene (``georeg.demo.generate_scene({})``) unless ``--scene`` points
at one, stands in for the registration with the generator's truth (geolocation x, y; z from the
truth DSM) and for the map mosaics with the truth DSM / DTM / nDSM, converts the demo LiDAR to
map-CRS tiles, then runs ``make_cube`` and ``make_products`` and reports per step: wall time, peak
anonymous RSS (sampled from /proc every 0.1 s; file-backed pages of memory-mapped cubes are
reported apart, they are page cache) and the tracemalloc peak. Appends one JSON line to
``benchmarks/out/bench_products.jsonl``.
"""

from __future__ import annotations

import argparse
import json
import threading
import time
import tracemalloc
import warnings
from pathlib import Path

import numpy as np
import pyproj
import rasterio

from georeg.map import lidar
from georeg.products.make import make_cube, make_products
from georeg.register.geolocation import sample_raster


class MemSampler:
    """Peak RssAnon / RssFile (MiB) of this process, sampled in a thread."""

    def __init__(self, period: float = 0.1) -> None:
        self.period = period
        self.peak = {"RssAnon": 0, "RssFile": 0}
        self._stop = threading.Event()
        self._t = threading.Thread(target=self._run, daemon=True)

    def _run(self) -> None:
        while not self._stop.is_set():
            for line in Path("/proc/self/status").read_text().splitlines():
                k, _, v = line.partition(":")
                if k in self.peak:
                    self.peak[k] = max(self.peak[k], int(v.split()[0]) // 1024)
            time.sleep(self.period)

    def __enter__(self) -> MemSampler:
        self._t.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self._stop.set()
        self._t.join()


def stand_in(scene_dir: Path, work: Path) -> dict[str, Path]:
    """geolocation.tif + registration.json from the truth; map-CRS point tiles."""
    scene = json.loads((scene_dir / "scene.json").read_text())
    crs = scene["map"]["crs_wkt"]
    work.mkdir(parents=True, exist_ok=True)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", rasterio.errors.NotGeoreferencedWarning)
        with rasterio.open(scene_dir / "queries" / "demo_truth.tif") as ds:
            x, y = ds.read().astype(np.float64)
        z = sample_raster(scene_dir / "truth" / "dsm.tif", x, y)
        prof = {"driver": "GTiff", "width": x.shape[1], "height": x.shape[0], "count": 3,
                "dtype": "float64", "nodata": float("nan"), "tiled": True}  # fmt: skip
        with rasterio.open(work / "geolocation.tif", "w", **prof) as ds:
            ds.write(np.stack([x, y, z]))
    (work / "registration.json").write_text(json.dumps({"status": "registered", "crs": crs}))
    mcrs = pyproj.CRS.from_wkt(crs)
    tiles = []
    for i, t in enumerate(sorted((scene_dir / "lidar").glob("*.laz"))):
        p = work / "tiles" / f"r000_c{i:03d}" / "points.laz"
        if not p.exists():
            p.parent.mkdir(parents=True, exist_ok=True)
            pts = lidar.Points.concat(list(lidar.iter_chunks(lidar.scan(t), mcrs)))
            lidar.write_textured_laz(p, pts, np.full((len(pts), 3), 128, np.uint8), mcrs)
        tiles.append(p)
    return {"geolocation": work / "geolocation.tif", "registration": work / "registration.json",
            "tiles": tiles}  # fmt: skip


def measure(fn, *args, **kw) -> tuple[object, dict]:
    tracemalloc.start()
    t0 = time.perf_counter()
    with MemSampler() as ms:
        out = fn(*args, **kw)
    dt = time.perf_counter() - t0
    _, peak = tracemalloc.get_traced_memory()
    tracemalloc.stop()
    return out, {
        "seconds": round(dt, 1),
        "peak_rss_anon_mib": ms.peak["RssAnon"],
        "peak_rss_file_mib": ms.peak["RssFile"],
        "tracemalloc_peak_mib": round(peak / 2**20, 1),
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--workdir", type=Path, default=Path("/tmp/bench_products"))
    ap.add_argument("--scene", type=Path, default=None, help="existing demo scene directory")
    ap.add_argument("--conf", type=str, default="{}", help="products config as JSON")
    a = ap.parse_args()
    scene_dir = a.scene or a.workdir / "demo"
    if not (scene_dir / "scene.json").exists():
        from georeg.demo import generate_scene

        generate_scene({}, scene_dir)
    inp = stand_in(scene_dir, a.workdir / "in")
    out = a.workdir / "products" / "demo"
    conf = json.loads(a.conf)
    hdr = scene_dir / "queries" / "demo.hdr"
    m_cube, r_cube = measure(make_cube, inp["registration"], inp["geolocation"], hdr,
                             out / "cube.json", conf, None, "demo")  # fmt: skip
    mosaics = {k: scene_dir / "truth" / f"{k}.tif" for k in ("dsm", "dtm", "ndsm")}
    m, r_prod = measure(make_products, inp["registration"], inp["geolocation"], hdr,
                        out / "cube.json", mosaics, inp["tiles"], out / "products.json", conf,
                        None, "demo", scene_dir / "queries" / "demo_labels.tif")  # fmt: skip
    acc = m["segmentation"]["accuracy"]  # type: ignore[index]
    rec = {
        "query": "demo 829 x 1163 x 260",
        "cube": r_cube,
        "products": r_prod,
        "cube_timings_s": m_cube["timings_s"],  # type: ignore[index]
        "products_timings_s": m["timings_s"],  # type: ignore[index]
        "points": m["points"]["points"],  # type: ignore[index]
        "segmentation_overall": round(acc["overall"], 4),
        "segmentation_recall": {
            k: None if v["recall"] is None else round(v["recall"], 3)
            for k, v in acc["classes"].items()
        },
        "sizes_mb": {p.name: round(p.stat().st_size / 1e6, 1) for p in sorted(out.iterdir())},
    }
    print(json.dumps(rec, indent=1))
    log = Path(__file__).parent / "out" / "bench_products.jsonl"
    log.parent.mkdir(exist_ok=True)
    with open(log, "a") as fh:
        fh.write(json.dumps(rec) + "\n")


if __name__ == "__main__":
    main()
