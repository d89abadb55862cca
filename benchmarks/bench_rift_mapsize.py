"""The rift source's cost against the map's size: what ``register.rift.max_map_px`` buys.

    . /work/main/.venv/bin/activate
    nice -n 5 python benchmarks/bench_rift_mapsize.py --mpx 16,32 --queries 6 \
        --out benchmarks/out/rift_mapsize.json -v

SRIF references (../shared/data/srif_dev; optical-optical, optical-infrared and optical-depth,
both halves, every pair in the map) laid side by side (``bench_devset.pack``, 1 m pixels): the
first references holding ``--mpx`` million pixels, modalities interleaved (shelf packing leaves
nodata between them: the mosaic itself, whose size ``max_map_px`` compares, is about twice
that; the record gives it, ``mpx``); per mosaic: the map's features (once, CPU s) and
``georeg.register.rift.register`` of the same ``--queries`` queries (their references are in
every mosaic: the smallest mosaic's first pairs, taken in turn from each modality), CPU seconds
and outcome (``bench_devset.judge``: success within the query's tolerance of its own
reference). Overlaps between references are not searched (``bench_devset --sets srif_wide``
does that): a query accepted on an overlapping copy of its place counts as a false accept here.
"""

from __future__ import annotations

import argparse
import logging
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
import bench_crossspectral as bx  # noqa: E402
import bench_devset as bd  # noqa: E402

from georeg.io.atomic import write_json  # noqa: E402


def references() -> list[tuple[str, int, tuple[np.ndarray, np.ndarray, np.ndarray]]]:
    """Every SRIF pair's (modality, pair, (reference, query, truth)), modalities interleaved."""
    per = {m: [(m, i, bd.srif_images(m, i)) for i in bd.srif_pairs(m)] for m in ("oo", "oi", "od")}
    out = []
    for k in range(max(len(v) for v in per.values())):
        out += [v[k] for v in per.values() if k < len(v)]
    return out


def first(items: list, mpx: float) -> list:
    """The first ``items`` whose references hold ``mpx`` million pixels."""
    take, total = [], 0
    for it in items:
        if total >= mpx * 1e6:
            break
        take.append(it)
        total += it[2][0].size
    return take


def mosaic(take: list, mpx: float) -> tuple[bx.Scene, dict[tuple[str, int], np.ndarray]]:
    """The references of ``take`` packed: the scene and each reference's 3 x 3 reference px ->
    map px."""
    offs, (H, W) = bd.pack([it[2][0].shape for it in take])
    img = np.zeros((H, W), np.uint8)
    place = {}
    for (m, i, (ref, _, _)), (r, c) in zip(take, offs, strict=True):
        img[r : r + ref.shape[0], c : c + ref.shape[1]] = np.maximum(ref, 1)
        place[(m, i)] = np.array([[1, 0, c], [0, 1, r], [0, 0, 1.0]])
    name = f"srif_all_{mpx:g}mpx"
    return bx.Scene(name, {}, bd.MOSAIC_GSD, img, bd.MOSAIC_GSD, lambda p: p, "mixed"), place


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawTextHelpFormatter)
    ap.add_argument("--mpx", default="16,32", help="million reference px a mosaic (about half its size)")
    ap.add_argument("--queries", type=int, default=6)
    ap.add_argument("--out", default="benchmarks/out/rift_mapsize.json")
    ap.add_argument("-v", action="store_true")
    a = ap.parse_args(argv)
    logging.basicConfig(level=logging.INFO if a.v else logging.WARNING, format="%(message)s")
    items = references()
    sizes = [float(s) for s in a.mpx.split(",")]
    picks = [(m, i) for m, i, _ in first(items, min(sizes))[: a.queries]]  # oo, oi, od, oo, ...
    data = {(m, i): d for m, i, d in items}
    spec = {"rift": {"polish": False}}  # rift alone, as rift.register decides
    rows = []
    for mpx in sizes:
        sc, place = mosaic(first(items, mpx), mpx)
        for m, i in picks:
            _, q, A0 = data[(m, i)]
            qq = bd.srif_query(m, i, q, A0, [place[(m, i)]], sc.name)
            c0 = time.process_time()
            r = bd.run_rift(qq, sc, spec, 0)  # the map's features built on its first query
            cpu = time.process_time() - c0 - r["map_cpu_seconds"]
            if r["map_cpu_seconds"]:
                map_s, n_kp = r["map_cpu_seconds"], len(next(iter(bd._RIFT_MAPS.values()))[0])
                print(f"{sc.name}: {sc.map_gray.size / 1e6:.1f} Mpx, {len(place)} references, "
                      f"{n_kp} map keypoints, features {map_s:.0f} CPU s", flush=True)  # fmt: skip
            j = bd.judge(qq, sc, r)
            rows.append({"mpx": round(sc.map_gray.size / 1e6, 1), "references": len(place),
                         "map_keypoints": n_kp, "map_cpu_seconds": map_s, "query": qq.name,
                         "outcome": j["outcome"], "error_px": j["error_px"], "cpu_seconds": cpu,
                         "log10_nfa": r["log10_nfa"]})  # fmt: skip
            print(f"  {qq.name:12s} {j['outcome']:12s} {cpu:6.1f} CPU s  log10 NFA {r['log10_nfa']:.1f}",
                  flush=True)  # fmt: skip
        write_json(a.out, rows)  # after each mosaic: a long run cut short keeps what it measured
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
