"""The benchmark suite (benchmarks/run.py): warps keep the truth consistent; a real case runs."""

from __future__ import annotations

import csv
from pathlib import Path

import benchmark_module
import numpy as np
import pytest

REPO = Path(__file__).resolve().parents[1]


def _bench():
    return benchmark_module.load("run", "bench_run")


def test_warp_moves_band_and_truth_together() -> None:
    from rasterio.transform import Affine

    run = _bench()
    rng = np.random.default_rng(0)
    band = rng.integers(1, 255, (60, 80)).astype(np.uint8)
    q = run._georef_query(band, Affine(2.0, 0, 500_000.0, 0, -2.0, 4_000_000.0), 2.0, None)
    w = run.apply_warp(q, {"rotate_deg": 30, "scale": 0.5}, rng)
    assert w.gsd_m == pytest.approx(4.0)
    # the truth still places each warped pixel where the original pixel with that value was:
    # a pixel's neighbour one column away is 4 m away on the ground (GSD after scaling)
    ok = np.isfinite(w.tx) & np.isfinite(w.ty)
    r, c = np.argwhere(ok[:, :-1] & ok[:, 1:])[len(np.argwhere(ok)) // 2]
    d = np.hypot(w.tx[r, c + 1] - w.tx[r, c], w.ty[r, c + 1] - w.ty[r, c])
    assert d == pytest.approx(4.0, rel=1e-3)
    # centre of the warped query = centre of the original (rotation about the centre)
    assert np.nanmean(w.tx[ok]) == pytest.approx(q.tx.mean(), abs=3.0)
    assert (w.band[~ok] == 0).all()
    inv = run.apply_warp(q, {"invert": True}, rng)
    assert (inv.band.astype(int) + band.astype(int) == 256).all()


@pytest.mark.shared
def test_real_case_runs(shared_data: Path, tmp_path: Path) -> None:
    run = _bench()
    rc = run.main(
        ["--only", "enmap_swir_to_visible", "--strategies", "index", "--out", str(tmp_path)]
    )
    assert rc == 0
    rows = list(csv.DictReader((tmp_path / "summary.csv").open()))
    assert [r["scenario"] for r in rows] == ["enmap_swir_to_visible"]
    assert rows[0]["index_outcome"] in ("success", "false_accept", "missed")
    assert (tmp_path / "summary.json").exists()
