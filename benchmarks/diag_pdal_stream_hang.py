"""Reads a point cloud again and again through PDAL until one read hangs (or ``--reads`` pass).

``--via iterator``: python-pdal's ``Pipeline.iterator`` (the read georeg used before session 27),
``--via georeg``: :func:`georeg.map.pdal_points.iter_chunks`. A watchdog ends the process when no
read finished in ``--stall-s`` seconds and prints how many reads passed.

    python benchmarks/diag_pdal_stream_hang.py ../shared/data/autzen/autzen-thin.las --via iterator
    python benchmarks/diag_pdal_stream_hang.py ../shared/data/autzen/autzen-thin.las --via georeg --reads 3000
"""

from __future__ import annotations

import argparse
import json
import os
import threading
import time


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("path")
    ap.add_argument("--via", choices=("iterator", "georeg"), default="iterator")
    ap.add_argument("--reads", type=int, default=20000)
    ap.add_argument("--stall-s", type=float, default=10.0)
    ap.add_argument("--crs", default="EPSG:2994", help="the file's CRS when it has none")
    a = ap.parse_args(argv)

    import pdal

    from georeg.map import pdal_points

    done, t0 = [0], time.time()

    def watch() -> None:
        last = -1
        while True:
            time.sleep(a.stall_s)
            if done[0] == last:
                print(f"HANG after {done[0]} reads, {time.time() - t0:.0f} s", flush=True)
                os._exit(1)
            last = done[0]

    threading.Thread(target=watch, daemon=True).start()
    stages = json.dumps([pdal_points.reader_stage(a.path)])
    info = pdal_points.scan(a.path, a.crs)
    for _ in range(a.reads):
        if a.via == "iterator":
            for _arr in pdal.Pipeline(stages).iterator(chunk_size=1_000_000):
                pass
        else:
            for _pts in pdal_points.iter_chunks(info, info.crs, None, 1_000_000):
                pass
        done[0] += 1
    print(f"no hang: {done[0]} reads, {time.time() - t0:.0f} s")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
