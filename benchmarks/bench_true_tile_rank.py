"""Where the true place ranks: TF-IDF tiles (the baseline) vs the Hough vote, per index.

For a finished large-map run (``bench_scaling.py --keep``): the query band the workflow wrote
(``results/queries/q0/band.tif``), features exactly as the search computes them (the index's
``features_conf``, resize factor = query GSD / feature GSD from ``band.json``), for each half and
the whole query:

* ``tiles``: the rank of the tile holding the median truth position in ``MapIndex.rank_tiles``
  (TF-IDF of visual words; ``register.index.rank: tiles``);
* ``hough``: the rank of the first region holding that position among the regions of
  ``georeg.register.hough.hough_regions`` (``register.index.rank: hough``), with its seconds.

    python benchmarks/bench_true_tile_rank.py --run /work/scale/run_16384 \\
        --truth /work/scale/map_16384/queries/q0_truth.tif \\
        --index /work/scale/run_16384/results/index/map /work/scale/run_16384_k10k/results/index/map \\
        --nprobe 4 8 16 --knn 10

(An earlier version of this script described the query with other feature settings than the
index's, and reported ranks 4 and 7 at k = 1,000 that the workflow's own features do not give.)
"""

from __future__ import annotations

import argparse
import json
import time
import warnings

import numpy as np
import rasterio

from georeg.register.band import feature_scales, read_query_band
from georeg.register.hough import hough_regions
from georeg.register.search import (
    MapSource,
    footprint_diagonal_m,
    gsd_in_map_units,
    part_rows,
    query_features,
)

TOP = 50


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawTextHelpFormatter)
    ap.add_argument("--run", required=True)
    ap.add_argument("--truth", required=True)
    ap.add_argument("--index", nargs="+", required=True)
    ap.add_argument("--nprobe", type=int, nargs="+", default=[8])
    ap.add_argument("--knn", type=int, nargs="+", default=[10])
    a = ap.parse_args()
    band = read_query_band(f"{a.run}/results/queries/q0/band.tif")
    meta = json.loads(open(f"{a.run}/results/queries/q0/band.json").read())
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        with rasterio.open(a.truth) as ds:
            tx, ty = ds.read(1), ds.read(2)
    h = band.shape[0]
    parts = {"half 1": part_rows(h, 2, 0), "half 2": part_rows(h, 2, 1), "whole": (0, h)}
    print(
        "| index | words | method | half 1 | half 2 | whole query | s (half 1, half 2, whole) |\n"
        "|---|---:|---|---:|---:|---:|---|"
    )
    for d in a.index:
        src = MapSource.from_index(d)
        ix = src.index
        gsd = gsd_in_map_units(meta.get("gsd_m"), src.crs_wkt)
        factors = feature_scales(gsd, src.gsd_m, [1.0])
        tb = np.asarray(ix.tile_bounds)
        feats, truth = {}, {}
        for name, (r0, r1) in parts.items():
            feats[name] = query_features(band, (r0, r1), factors, src.features_conf)
            truth[name] = (np.nanmedian(tx[r0:r1]), np.nanmedian(ty[r0:r1]))
        row, secs = [], []
        for name, qf in feats.items():
            cx, cy = truth[name]
            t0 = time.perf_counter()
            ranked = ix.rank_tiles(qf.desc, None)
            secs.append(time.perf_counter() - t0)
            hit = [k for k, (t, _) in enumerate(ranked) if _inside(tb[t], cx, cy)]
            row.append(f"{hit[0] + 1} of {len(tb)}" if hit else "-")
        print(f"| {d} | {ix.n_words} | TF-IDF tiles | {' | '.join(row)} | "
              f"{', '.join(f'{s:.1f}' for s in secs)} |")  # fmt: skip
        for nprobe in a.nprobe:
            for knn in a.knn:
                row, secs = [], []
                for name, qf in feats.items():
                    cx, cy = truth[name]
                    diag = footprint_diagonal_m(qf, src.gsd_m, gsd)
                    t0 = time.perf_counter()
                    regions = hough_regions(
                        qf, ix, src.bounds, src.gsd_m, diag, TOP, {"nprobe": nprobe, "knn": knn}
                    )
                    secs.append(time.perf_counter() - t0)
                    hit = [k for k, (b, _) in enumerate(regions) if _inside(b, cx, cy)]
                    row.append(f"{hit[0] + 1}" if hit else f"> {TOP}")
                print(f"| {d} | {ix.n_words} | Hough, nprobe {nprobe}, knn {knn} | "
                      f"{' | '.join(row)} | {', '.join(f'{s:.1f}' for s in secs)} |")  # fmt: skip


def _inside(b, x: float, y: float) -> bool:
    return bool(b[0] <= x <= b[2] and b[1] <= y <= b[3])


if __name__ == "__main__":
    main()
