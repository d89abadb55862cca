"""The development set's pooled wide-area mosaic (benchmarks/bench_devset.py ``--pool``): one
mosaic per half holding the references of several SRIF modalities, each query's truth landing on
its own reference's pixels there, the left-out references absent."""

from __future__ import annotations

import benchmark_module
import numpy as np
import pytest


@pytest.fixture(scope="module")
def pooled(shared_data, tmp_path_factory):
    bd = benchmark_module.load("bench_devset")
    with pytest.MonkeyPatch.context() as mp:  # the overlap cache goes there, not in the tree
        mp.setattr(bd, "ROOT", tmp_path_factory.mktemp("devset"))
        scenes, queries = bd.build_srif(["oi", "od"], wide=True, pair=False, per_half=5, pool=True)
    return bd, scenes, queries


def test_one_mosaic_per_half_with_both_modalities(pooled):
    bd, scenes, queries = pooled
    assert sorted(s.name for s in scenes) == ["oi_od_mosaic_checking", "oi_od_mosaic_tuning"]
    for half in ("tuning", "checking"):
        qs = [q for q in queries if q.half == half]
        assert {q.name.split("_")[1] for q in qs} == {"oi", "od"}
        assert {q.map_scene for q in qs} == {f"oi_od_mosaic_{half}"}
        # per modality, the 5th pair of the half is left out, as without pooling
        assert sorted(q.name for q in qs if q.name.endswith("_leftout")) == sorted(
            f"wide_{m}_{bd.srif_pairs(m)[4 + (half == 'checking') * 50]}_leftout"
            for m in ("oi", "od")
        )


def test_truth_lands_on_the_query_reference_in_the_mosaic(pooled):
    bd, scenes, queries = pooled
    by = {s.name: s.map_gray for s in scenes}
    checked = 0
    for q in queries:
        if q.name.endswith("_leftout"):
            continue
        mod, i = q.name.split("_")[1], int(q.name.split("_")[2])
        ref, _, A0 = bd.srif_images(mod, i)
        rp = bd.bx.matching.apply_h(np.linalg.inv(A0), q.truth)  # reference px of the grid
        ok = (rp[:, 0] >= 0) & (rp[:, 1] >= 0) & (rp[:, 0] < ref.shape[1] - 1) & (rp[:, 1] < ref.shape[0] - 1)
        mp = q.alts[0][ok]  # its own reference's place comes first
        r = np.rint(rp[ok]).astype(int)
        m = np.rint(mp).astype(int)
        got = by[q.map_scene][m[:, 1], m[:, 0]]
        assert np.array_equal(got, np.maximum(ref[r[:, 1], r[:, 0]], 1)), q.name
        checked += 1
    assert checked == 16
