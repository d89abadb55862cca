"""The learned source (``register.learned``: ALIKED features in rift's search, georeg.register.rift):
a real SRIF optical-optical pair the feature search and rift miss registers within the benchmark's
tolerance, the same query on another reference is refused, and ``enabled`` says what happens when
ALIKED is not installed. The ALIKED tests skip without the extra (``.ci/install-learned``)."""

from __future__ import annotations

import math
from pathlib import Path

import cv2
import numpy as np
import pytest
import yaml

from georeg.io.errors import ConfigError
from georeg.register import matching, rift

ROOT = Path(__file__).resolve().parents[1]
needs_aliked = pytest.mark.skipif(
    rift.learned_import_error() is not None, reason=f"ALIKED unusable ({rift.learned_import_error()})"
)


def _acc() -> dict:
    return yaml.safe_load((ROOT / "config" / "config.yaml").read_text())["register"]["acceptance"]


def _srif_oo(shared: Path, i: int):
    """(reference u8, query u8 with 0 = nodata, 3 x 3 reference px -> query px, 0-based)."""
    d = shared / "srif_dev" / "Optical-Optical"
    if not (d / f"pair{i}_1.jpg").exists():
        pytest.skip(f"{d} absent")
    ref = cv2.imread(str(d / f"pair{i}_1.jpg"), cv2.IMREAD_GRAYSCALE)
    q = cv2.imread(str(d / f"pair{i}_2.jpg"), cv2.IMREAD_GRAYSCALE)
    A = np.vstack([np.loadtxt(d / f"gt_{i}.txt"), [0, 0, 1.0]])
    one = np.array([[1, 0, 1], [0, 1, 1], [0, 0, 1.0]])
    q = np.where(cv2.erode((cv2.blur(q, (5, 5)) > 3).astype(np.uint8), np.ones((5, 5))) > 0, np.maximum(q, 1), 0)
    return np.maximum(ref, 1), q.astype(np.uint8), np.linalg.inv(one) @ A @ one


def test_enabled_auto_true_false_without_the_extra(monkeypatch):
    """``auto`` without ALIKED: not run, and the record says why; ``true``: a ConfigError naming
    the extra to install; ``false``: not run."""
    monkeypatch.setattr(rift, "learned_import_error", lambda: "ModuleNotFoundError: No module named 'torch'")
    q = type("Q", (), {"gsd": 1.0, "u8": np.zeros((8, 8), np.uint8), "tests_before": 0})()
    parts, rec = rift.learned_source(q, None, [], {"learned": {"enabled": "auto"}})
    assert parts == [] and not rec["ran"] and "not installed" in rec["reason"] and "torch" in rec["reason"]
    with pytest.raises(ConfigError, match="install-learned"):
        rift.learned_source(q, None, [], {"learned": {"enabled": True}})
    _, rec = rift.learned_source(q, None, [], {"learned": {"enabled": False}})
    assert rec == {"ran": False, "reason": "disabled"}


def test_input_check_names_the_missing_extra_when_learned_is_forced_on(monkeypatch):
    """``enabled: true`` without ALIKED stops the run at the input check, before any job;
    ``auto`` and ``false`` do not."""
    from georeg.register import inputs

    monkeypatch.setattr(inputs, "learned_import_error", lambda: "ModuleNotFoundError: No module named 'torch'")
    def learned_problems(on):
        return [p for p in inputs.check_inputs({"register": {"learned": {"enabled": on}}})
                if "learned" in p]  # the empty config's other problems (no map) aside

    (problem,) = learned_problems(True)
    assert "register.learned.enabled" in problem and "install-learned" in problem
    assert "torch" in problem
    assert learned_problems("auto") == [] and learned_problems(False) == []


def test_registration_record_says_when_learned_did_not_run(monkeypatch):
    """``fuse.run_sources`` keeps the learned source's record in ``split`` whether or not it ran,
    so a result tells whether it depended on the extra being installed."""
    from georeg.register import fuse

    monkeypatch.setattr(rift, "learned_import_error", lambda: "ModuleNotFoundError: No module named 'torch'")
    calls = []

    def stub(name):
        def fn(q, view, parts, conf):
            calls.append(name)
            return parts, ({"ran": False, "reason": "stub"} if name != "whole_query"
                           else {"ran": False, "candidates": 0, "plan": {}})  # fmt: skip
        return fn

    sources = tuple((n, stub(n)) if n != "learned" else (n, f) for n, f in fuse.SOURCES)
    monkeypatch.setattr(fuse, "SOURCES", sources)
    q = fuse.QueryInput(np.arange(1, 65, dtype=np.uint8).reshape(8, 8), None, 1.0, [1.0], 0)  # type: ignore[arg-type]
    _, split, ran, _ = fuse.run_sources(q, None, [], {"learned": {"enabled": "auto"}})  # type: ignore[arg-type]
    assert "not installed" in split["learned"]["reason"] and not split["learned"]["ran"]
    assert [r["name"] for r in ran] == ["features"]



@needs_aliked
def test_aliked_srif_oo_pair_found_and_unrelated_reference_refused(shared_data):
    """SRIF optical-optical 37 (the query 1.7x finer than its reference, turned, another date: a
    tuning-half query the 40-reference mosaic's feature search and rift miss): ALIKED
    (``aliked-n16rot``) in rift's search at 8 rotations registers it pair by pair within the
    benchmark's tolerance (median <= 8 query px); on pair 39's reference it is not accepted."""
    conf = rift.rift_conf(rift.LEARNED)
    ref, q, A0 = _srif_oo(shared_data, 37)
    s = math.sqrt(abs(np.linalg.det(A0[:2, :2])))
    r = rift.register(q, ref, 1.0 / s, _acc(), conf)
    assert r["accepted"], r["decision"]
    assert r["tests"] == 8
    uu, vv = np.meshgrid(np.linspace(20, q.shape[1] - 20, 12), np.linspace(20, q.shape[0] - 20, 12))
    qp = np.c_[uu.ravel(), vv.ravel()]
    qp = qp[q[qp[:, 1].astype(int), qp[:, 0].astype(int)] > 0]
    err = np.linalg.norm(matching.apply_h(r["H"], qp) - matching.apply_h(np.linalg.inv(A0), qp), axis=1)
    assert np.median(err) * s <= 8.0, np.median(err)
    other, _, _ = _srif_oo(shared_data, 39)
    r = rift.register(q, other, 1.0 / s, _acc(), conf)
    assert not r["accepted"], r["decision"]


@needs_aliked
def test_aliked_keypoints_unit_descriptors_away_from_nodata_deterministic(shared_data):
    _, q, _ = _srif_oo(shared_data, 37)
    conf = rift.rift_conf(rift.LEARNED)
    xy, d = rift.aliked_features(q, conf)
    assert len(xy) > 500 and d.shape == (len(xy), 128)
    assert np.allclose(np.linalg.norm(d, axis=1), 1.0, atol=1e-4)
    far = cv2.distanceTransform((q > 0).astype(np.uint8), cv2.DIST_L2, 5)
    r, c = np.round(xy[:, 1]).astype(int), np.round(xy[:, 0]).astype(int)
    assert far[r, c].min() >= rift.LEARNED_EDGE_PX - 1
    again, d2 = rift.aliked_features(q, conf)
    assert np.array_equal(xy, again) and np.array_equal(d, d2)


def _ref_reader(ref: np.ndarray):
    """A window reader over a reference image whose map units are its pixels (centres at i)."""
    def read(box):
        x0, y0, x1, y1 = box
        c0, r0 = max(0, int(np.floor(x0))), max(0, int(np.floor(y0)))
        c1, r1 = min(ref.shape[1], int(np.ceil(x1)) + 1), min(ref.shape[0], int(np.ceil(y1)) + 1)
        if c1 <= c0 or r1 <= r0:
            return None
        return ref[r0:r1, c0:c1].astype(np.float32), np.array([[1, 0, c0], [0, 1, r0], [0, 0, 1.0]])
    return read


@needs_aliked
def test_context_refit_moves_a_shifted_pose_back_and_leaves_the_truth(shared_data):
    """SRIF optical-optical 193 (whose pose our matching laid on the roofs, 25-35 px off): the
    GT moved 25 px is brought back within the benchmark's tolerance by LightGlue's context
    matching; at the GT itself nothing moves."""
    ref, q, A0 = _srif_oo(shared_data, 193)
    G = np.linalg.inv(A0)  # query px -> reference px
    uu, vv = np.meshgrid(np.linspace(0, q.shape[1] - 1, 9), np.linspace(0, q.shape[0] - 1, 9))
    qp = np.c_[uu.ravel(), vv.ravel()]

    def err(H):
        return float(np.median(np.linalg.norm(matching.apply_h(H, qp) - matching.apply_h(G, qp), axis=1)))

    shifted = np.array([[1, 0, 0], [0, 1, -25.0], [0, 0, 1]]) @ G
    H, rec = rift.context_refit(q, shifted, _ref_reader(ref))
    assert rec["taken"] and rec["inliers"] >= rift.CONTEXT["min_inliers"], rec
    assert err(H) < 8.0, (err(H), rec)
    H, rec = rift.context_refit(q, G, _ref_reader(ref))
    assert not rec["taken"] and err(H) == 0.0, rec
