"""The log-Gabor filter banks kept per image size (``rift._filters``, ``FILTER_MEMO_BYTES``)
against building them for every image (``rift._filter_bank``), same process, same inputs.

    nice python benchmarks/bench_rift_filters.py --repeats 3

Case: real data (brighton, bench_elevation's query 0: an optical crop against the DSM, at its
true pose): ``structure_check`` (about 150 windows of one size) and the query's ``features``. Prints
the median seconds of each over ``--repeats`` runs, both ways, and whether the results agree.
"""

from __future__ import annotations

import argparse
import statistics
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
import bench_elevation as be  # noqa: E402

from georeg.register import rift  # noqa: E402


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--repeats", type=int, default=3)
    a = ap.parse_args()
    _, z, g, (q,) = be.queries("brighton", 1, 11)
    u8 = q.bands["gray"]
    # the true pose: query px -> map x, y (x = col g, y = -row g), from the truth grid
    Ht = np.linalg.lstsq(np.c_[q.truth, np.ones(len(q.truth))], q.truth_map * np.array([g, -g]), rcond=None)[0].T
    H = np.vstack([Ht, [0, 0, 1.0]])
    read = be.height_reader(z, g)
    c = rift.rift_conf({})
    memo = rift._filters
    out: dict[str, dict[str, list[float]]] = {}
    got = {}
    for way in ("built each time", "kept per size"):
        rift._filters = memo if way == "kept per size" else rift._filter_bank
        rift._FILTER_MEMO.clear()
        for _ in range(a.repeats):
            t0 = time.perf_counter()
            st = rift.structure_check(u8, H, read, q.gsd, c, 11)
            t1 = time.perf_counter()
            xy, _ = rift.features(u8, c)
            t2 = time.perf_counter()
            out.setdefault(way, {}).setdefault("structure_check", []).append(t1 - t0)
            out[way].setdefault("features", []).append(t2 - t1)
            got[way] = (st["z"] if st else None, np.round(xy, 6).tolist())
    rift._filters = memo
    base = out["built each time"]
    for k in ("structure_check", "features"):
        m0, m1 = statistics.median(base[k]), statistics.median(out["kept per size"][k])
        print(f"{k:16s} built each time {m0:6.2f} s   kept per size {m1:6.2f} s   ratio {m1 / m0:.2f}")
    print("same results:", got["built each time"] == got["kept per size"])


if __name__ == "__main__":
    main()
