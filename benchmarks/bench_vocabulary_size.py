"""The paper's vocabulary size on a large map: k-means time, word assignment, index, retrieval.

For a finished large-map run (``bench_scaling.py --keep``), builds a second index of the same
tile features with another vocabulary size, with the library functions the rules call
(``build_vocabulary`` -> ``save_word_quantizer`` -> ``assign_tile_words`` per tile ->
``build_from_grid``), timing each step, into ``<out>/results/index/...``; the run's map grid and
query band are linked in, so ``bench_true_tile_rank.py`` then compares the retrieval of both::

    nice -n 15 python benchmarks/bench_vocabulary_size.py --run /work/scale/run_16384 \\
        --k 100000 --iterations 5 --out /work/scale/run_16384_k100k
    python benchmarks/bench_true_tile_rank.py --run /work/scale/run_16384 \\
        --truth /work/scale/map_16384/queries/q0_truth.tif \\
        --index /work/scale/run_16384/results/index/map /work/scale/run_16384_k100k/results/index/map
"""

from __future__ import annotations

import argparse
import json
import resource
import time
from pathlib import Path

from georeg.index.map_index import assign_tile_words, build_from_grid, save_word_quantizer
from georeg.index.vocabulary import build_vocabulary


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawTextHelpFormatter)
    ap.add_argument("--run", type=Path, required=True)
    ap.add_argument("--out", type=Path, required=True)
    ap.add_argument("--k", type=int, default=100000)
    ap.add_argument("--sample-size", type=int, default=500000)
    ap.add_argument("--iterations", type=int, default=20)
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--seed", type=int, default=42)
    a = ap.parse_args()
    feats = sorted(p for p in (a.run / "results/index/features").iterdir() if p.is_dir())
    idx = a.out / "results/index"
    rec: dict = {"run": str(a.run), "k": a.k, "sample_size": a.sample_size,
                 "iterations": a.iterations, "tiles": len(feats)}  # fmt: skip
    t0 = time.perf_counter()
    conf = {"k": a.k, "sample_size": a.sample_size, "iterations": a.iterations}
    build_vocabulary(feats, idx / "vocabulary", conf, a.seed, a.threads)
    rec["kmeans_s"] = round(time.perf_counter() - t0, 1)
    print(json.dumps(rec), flush=True)
    cent = idx / "vocabulary/centroids.npy"
    qpath = idx / "vocabulary/quantizer.faiss"
    t0 = time.perf_counter()
    rec["quantizer"] = save_word_quantizer(cent, qpath)
    rec["quantizer_s"] = round(time.perf_counter() - t0, 1)
    t0 = time.perf_counter()
    words = [assign_tile_words(d, cent, idx / "words" / f"{d.name}.npy", qpath) for d in feats]
    rec["tile_words_s"] = round(time.perf_counter() - t0, 1)
    rec["features"] = int(sum(len(w) for w in words))
    t0 = time.perf_counter()
    files = sorted((idx / "words").glob("*.npy"))
    build_from_grid(a.run / "results/map/grid.json", feats, cent, idx / "map", files, qpath)
    rec["build_index_s"] = round(time.perf_counter() - t0, 1)
    ru = resource.getrusage(resource.RUSAGE_SELF)
    rec["cpu_s"] = round(ru.ru_utime + ru.ru_stime, 1)
    rec["peak_rss_mb"] = round(ru.ru_maxrss / 1024, 1)
    for sub in ("results/map", "results/queries"):  # the same map and query for the comparison
        (a.out / sub).parent.mkdir(parents=True, exist_ok=True)
        if not (a.out / sub).exists():
            (a.out / sub).symlink_to(a.run / sub)
    print(json.dumps(rec), flush=True)


if __name__ == "__main__":
    main()
