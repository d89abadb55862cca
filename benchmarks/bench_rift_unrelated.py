"""Calibration of the RIFT source (georeg.register.rift) on SRIF: every query against an
unrelated reference (the reference of the pair ``shift`` places further in the same half, so the
two are different scenes; a pair whose optical references overlap by plain SIFT, crops of one
scene, is skipped) must be rejected; prints the lowest log10 NFA seen.

    nice -n 10 python benchmarks/bench_rift_unrelated.py --modalities oi,od --half tuning --n 10
    nice -n 10 python benchmarks/bench_rift_unrelated.py --pipeline ...   # the workflow, rift on

``--pipeline``: the workflow's registration (georeg.register.fuse.register_query, config.yaml with
``register.rift.enabled``) instead of the source alone, so the rift NFA also counts the tests of
the sources that ran before it (``QueryInput.tests_before``); prints what accepted, if anything.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
import bench_crossspectral as bx  # noqa: E402
import bench_devset as bd  # noqa: E402


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--modalities", default="oi,od")
    ap.add_argument("--half", choices=("tuning", "checking"), default="tuning")
    ap.add_argument("--n", type=int, default=10, help="first N pairs of the half")
    ap.add_argument("--shift", type=int, default=5)
    ap.add_argument("--pipeline", action="store_true", help="the workflow with rift enabled")
    a = ap.parse_args(argv)
    from georeg.register import rift

    acc = bx.workflow_register_conf()["acceptance"]
    for mod in a.modalities.split(","):
        idx = [i for i in bd.srif_pairs(mod) if bd.srif_half(i) == a.half][: a.n]
        data = {i: bd.srif_images(mod, i) for i in idx}
        lows = []
        for k, i in enumerate(idx):
            j = idx[(k + a.shift) % len(idx)]
            ref, (_, q, A0) = data[j][0], data[i]
            if bd.overlaps({i: data[i][0], j: ref}):  # crops of one scene: not unrelated
                print(f"{mod} query {i} on reference {j}: references overlap (SIFT), skipped")
                continue
            s = float(np.sqrt(abs(np.linalg.det(A0[:2, :2]))))
            if a.pipeline:
                sc = bx.Scene(f"{mod}_{j}_ref", {}, 1.0, np.maximum(ref, 1), 1.0, lambda p: p, mod)
                qq = bx.Query(f"{mod}_{i}_on_{j}", sc.name, sc.name, {"band": q}, 1.0 / s, None,
                              None)  # fmt: skip
                spec = {"pipeline": {"rift": {"enabled": True}}, "bands": 1}
                r = bx.run_method(qq, sc, spec, 11)
                r.setdefault("log10_nfa", float("inf"))
                r["log10_nfa"] = float("inf") if r["log10_nfa"] is None else r["log10_nfa"]
            else:
                r = rift.register(q, np.maximum(ref, 1), 1.0 / s, acc, {})
            lows.append(r["log10_nfa"])
            print(f"{mod} query {i} on reference {j}: accepted {r['accepted']} "
                  f"log10 NFA {r['log10_nfa']:.1f}", flush=True)  # fmt: skip
        print(f"{mod} {a.half}: {len(lows)} unrelated pairs, lowest log10 NFA {min(lows):.1f}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
