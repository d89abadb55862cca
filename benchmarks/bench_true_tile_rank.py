"""Rank of the true tile in the TF-IDF retrieval of a query, for one or more indexes (vocabularies).

For a finished large-map run (``bench_scaling.py --keep``): the query band the workflow wrote
(``results/queries/q0/band.tif``), features as the search computes them (one resize factor =
query GSD / feature GSD), the tile whose bounds hold the median truth position of each half and of
the whole query, and that tile's rank among all tiles in ``MapIndex.rank_tiles`` of each index.

    python benchmarks/bench_true_tile_rank.py --run /work/scale/run_16384 \
        --truth /work/scale/map_16384/queries/q0_truth.tif \
        --index /work/scale/run_16384/results/index/map /work/scale/run_16384_k10k/results/index/map
"""

from __future__ import annotations

import argparse
import warnings

import numpy as np
import rasterio

from georeg.index.map_index import MapIndex
from georeg.register.band import read_query_band
from georeg.register.search import query_features


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawTextHelpFormatter)
    ap.add_argument("--run", required=True)
    ap.add_argument("--truth", required=True)
    ap.add_argument("--index", nargs="+", required=True)
    ap.add_argument("--factor", type=float, default=0.8, help="query GSD / feature GSD")
    a = ap.parse_args()
    band = read_query_band(f"{a.run}/results/queries/q0/band.tif")
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        with rasterio.open(a.truth) as ds:
            tx, ty = ds.read(1), ds.read(2)
    h = band.shape[0]
    print("| index | words | rows 0-h/2 | rows h/2-h | whole query | tiles |\n|---|---:|---:|---:|---:|---:|")
    for d in a.index:
        ix = MapIndex.load(d)
        tb = np.asarray(ix.tile_bounds)
        ranks = []
        for r0, r1 in ((0, h // 2), (h // 2, h), (0, h)):
            qf = query_features(band, (r0, r1), [a.factor], {"rootsift": True})
            cx, cy = np.nanmedian(tx[r0:r1]), np.nanmedian(ty[r0:r1])
            true = {i for i, b in enumerate(tb) if b[0] <= cx <= b[2] and b[1] <= cy <= b[3]}
            r = [k for k, (t, _) in enumerate(ix.rank_tiles(qf.desc, None)) if t in true]
            ranks.append(str(min(r) + 1) if r else "-")
        print(f"| {d} | {len(ix.idf) if hasattr(ix, 'idf') else '?'} | {' | '.join(ranks)} | {len(tb)} |")


if __name__ == "__main__":
    main()
