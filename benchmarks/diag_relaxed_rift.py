"""Diagnostic (session 29): would rift's refusals by the far-rotation null and the guided
re-match be needed once the structure check verifies a pose? Every Landsat Pucallpa query
(and its blanked-map negative) through ``rift.register`` with ``null_margin`` and
``confirm_log_p_max`` off, polished, then ``rift.structure_check`` at the pose: for each pose
below ``log_nfa_max``, its error (map px) against the truth, its z, and what the default would
have decided.

    python benchmarks/diag_relaxed_rift.py SEED swir|visible > out.log
"""

from __future__ import annotations

import math
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "benchmarks"))

import bench_devset as bd  # noqa: E402
from diag_lookalike import register_conf  # noqa: E402

from georeg.register import matching, rift  # noqa: E402


def main() -> int:
    seed, kind = int(sys.argv[1]), sys.argv[2]
    scenes, queries = bd.build_pucallpa(seed, True, query=kind)
    scene = {s.name: s for s in scenes}
    acc, rconf = register_conf()
    relaxed = {**rconf, "null_margin": 0, "confirm_log_p_max": 0}
    feats: dict[str, tuple[np.ndarray, np.ndarray]] = {}
    for q in queries:
        sc = scene[q.map_scene]
        if sc.name not in feats:
            feats.clear()
            feats[sc.name] = rift.map_features(sc.map_gray, rift.rift_conf(relaxed))
        u8 = next(iter(q.bands.values()))
        r = rift.register(u8, sc.map_gray, q.gsd / sc.map_gsd, acc, relaxed, feats[sc.name], q.gsd, sc.map_gsd)
        if r["H"] is None or not r["log10_nfa"] < -2.0:
            print(f"{q.name:34s} {q.half:8s} none", flush=True)
            continue
        g = sc.map_gsd
        H = np.diag([g, -g, 1.0]) @ r["H"]
        reader = bd.bx.plain_window_reader(sc)
        H, pol = rift.polish(u8, H, reader, bd.bx.workflow_register_conf())
        err = math.nan
        if q.truth is not None:
            Hp = np.diag([1 / g, -1 / g, 1.0]) @ H
            err = float(np.median(np.linalg.norm(matching.apply_h(Hp, q.truth) - q.truth_map, axis=1)))
        st = rift.structure_check(u8, H, reader, q.gsd, relaxed)
        null_ok = r["log10_nfa"] <= r["null_log10_nfa"] - rift.DEFAULTS["null_margin"]
        print(f"{q.name:34s} {q.half:8s} nfa {r['log10_nfa']:7.2f} null {r['null_log10_nfa']:6.2f} "
              f"null_ok {int(null_ok)} moved_better {int(bool(pol and pol['moved_better']))} "
              f"err {err:8.2f} z {st['z'] if st else math.nan:6.2f}", flush=True)  # fmt: skip
    return 0


if __name__ == "__main__":
    sys.exit(main())
