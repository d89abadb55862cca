"""``register.small`` (georeg.register.small.small_register) in a region around the TRUE place
of each positive query of the small-query development subset (``bench_crossspectral.py --set
small``: tuning cities only): what the verifier accepts when the window is right, for a
``register.small`` override given as JSON (development only; never on the checking half).

The window is a square of 1.25 footprint diagonals whose centre is drawn (seeded per query)
within 0.3 diagonals of the true centre, like a Hough region; the NFA counts 3 windows.

    nice -n 10 python benchmarks/diag_small_true_region.py '{"ratio": 0.9}'
"""

from __future__ import annotations

import json
import math
import sys
import zlib
from pathlib import Path

import cv2
import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
import bench_crossspectral as bc  # noqa: E402

from georeg.register import matching  # noqa: E402
from georeg.register.dense import window_u8  # noqa: E402
from georeg.register.small import small_register  # noqa: E402


def main(argv: list[str]) -> int:
    extra = json.loads(argv[0]) if argv else {}
    cv2.setNumThreads(1)
    scenes, qs = bc.build_small_set(6, 11)
    by = {s.name: s for s in scenes}
    conf = bc._deep(bc.workflow_register_conf(), {"small": {"enabled": True, **extra}})
    n_acc = n_pos = 0
    for q in (x for x in qs if x.truth is not None):
        sc = by[q.map_scene]
        g = sc.map_gsd
        u8 = bc.query_stack(q, "auto")
        n = u8.shape[-1]
        truth_xy = np.c_[q.truth_map[:, 0] * g, -q.truth_map[:, 1] * g]
        Ht, _ = cv2.findHomography(q.truth, truth_xy, 0)
        c = matching.apply_h(Ht, np.array([[(n - 1) / 2, (n - 1) / 2]]))[0]
        rng = np.random.default_rng(zlib.crc32(q.name.encode()))
        c = c + rng.uniform(-0.3, 0.3, 2) * math.hypot(n, n) * q.gsd
        half = 0.625 * math.hypot(n, n) * q.gsd
        got = bc.plain_window_reader(sc)((c[0] - half, c[1] - half, c[0] + half, c[1] + half))
        if got is None:
            continue
        r = small_register(u8, q.gsd, window_u8(got[0]), got[1], g, conf, None, 1, 3)
        err = None
        if r["homography"] is not None:
            e = np.linalg.norm(matching.apply_h(np.array(r["homography"]), q.truth) - truth_xy,
                               axis=1) / g  # fmt: skip
            err = float(np.median(e))
        n_pos += 1
        n_acc += bool(r["accepted"])
        print(f"{q.name:34s} n {n:3d} accepted {r['accepted']!s:5s} inliers "
              f"{r['inliers']:3d}/{r.get('matches')} log10 NFA {r.get('log10_nfa')} "
              f"median err {err} {r.get('reason', '')[:50]}", flush=True)  # fmt: skip
    print(f"accepted {n_acc}/{n_pos}")
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
