"""The dense check of an accepted fit against the orthophoto (georeg/register/ortho_check.py).

Synthetic: an orthophoto of boxes, and a small query rendered from the same boxes with other,
independent brightnesses (another band: the check may not rely on the spectrum), 2 map px per
query px, rotated, with the true homography known. Real: the two distorted fits of the tiny
development set (``bench_crossspectral.py --set tiny``) and a right one (skipped when
../shared/data is absent).
"""

from __future__ import annotations

from pathlib import Path

import benchmark_module
import cv2
import numpy as np
import pytest
from rasterio.transform import Affine

from georeg.register import ortho_check as oc
from georeg.register.geolocation import apply_h
from georeg.register.refine import MapImage

ROOT = Path(__file__).resolve().parents[1]
DATA = ROOT.parent / "shared" / "data" / "swir_dates"
N = 360
TR = Affine(1, 0, 0, 0, -1, N)  # map x = col + 0.5 at pixel centres, y up
W, H_ = 70, 60  # query px


@pytest.fixture(scope="module")
def scene():
    rng = np.random.default_rng(5)
    vis = rng.normal(0.3, 0.02, (N, N)).astype(np.float32)
    swir = rng.normal(0.5, 0.02, (N, N)).astype(np.float32)
    for _ in range(260):
        w, h = rng.integers(5, 24, 2)
        c, r = rng.integers(0, N - 20, 2)
        box = cv2.boxPoints(((float(c), float(r)), (float(w), float(h)), float(rng.uniform(0, 180))))
        cv2.fillPoly(vis, [box.astype(np.int32)], float(rng.uniform(0.05, 0.6)))
        cv2.fillPoly(swir, [box.astype(np.int32)], float(rng.uniform(0.05, 0.9)))
    a, s = np.radians(35.0), 2.0
    # query px (col, row) -> map (x, y): rotation, 2 map px per query px, y up
    H = np.array([[s * np.cos(a), -s * np.sin(a), 150.0], [-s * np.sin(a), -s * np.cos(a), 250.0],
                  [0, 0, 1.0]])  # fmt: skip
    x, y = apply_h(H, *np.meshgrid(np.arange(W, dtype=float), np.arange(H_, dtype=float)))
    sw = cv2.GaussianBlur(swir, (0, 0), 1.0)  # the coarser band
    g = MapImage(sw, TR).render(x, y) + rng.normal(0, 0.01, (H_, W))
    lo, hi = np.nanpercentile(g, [1, 99])
    q = np.where(np.isfinite(g), np.clip((g - lo) / (hi - lo), 0, 1) * 254 + 1, 0).astype(np.uint8)
    return q, H, MapImage(vis, TR)


def _about_centre(H: np.ndarray, M: np.ndarray) -> np.ndarray:
    """H followed by M (3 x 3, map units) applied about the footprint's centre."""
    cx, cy = apply_h(H, np.array([W / 2]), np.array([H_ / 2]))
    T = np.array([[1, 0, cx[0]], [0, 1, cy[0]], [0, 0, 1.0]])
    return T @ M @ np.linalg.inv(T) @ H


def distorted(H: np.ndarray, k: float = 0.2) -> np.ndarray:
    """Right at the centre, ~15 map px off at the corners (shear + anisotropy, as an affine fit
    through a few inliers)."""
    return _about_centre(H, np.array([[1 + k, k, 0], [0, 1 - k, 0], [0, 0, 1.0]]))


def moved(H: np.ndarray, dx: float, dy: float = 0.0, deg: float = 0.0) -> np.ndarray:
    c, s = np.cos(np.radians(deg)), np.sin(np.radians(deg))
    R = np.array([[c, -s, dx], [s, c, dy], [0, 0, 1.0]])
    return _about_centre(H, R)


def footprint_error(Ha: np.ndarray, Hb: np.ndarray) -> float:
    """Largest distance (map px) between two fits over the query's corners."""
    u = np.array([0, W - 1, 0, W - 1], float)
    v = np.array([0, 0, H_ - 1, H_ - 1], float)
    a, b = apply_h(Ha, u, v), apply_h(Hb, u, v)
    return float(np.hypot(a[0] - b[0], a[1] - b[1]).max())


def test_the_right_fit_agrees_distorted_and_wrong_fits_do_not(scene):
    q, H, ortho = scene
    assert footprint_error(H, distorted(H)) > 12.0
    right = oc.check(q, H, ortho)
    assert right["outcome"] == "agrees", right
    assert right["supported"] >= 3 * max(right["supported_moved"])
    for wrong in (distorted(H), moved(H, 8.0, 6.0), moved(H, 60.0), moved(H, 0.0, deg=90.0)):
        r = oc.check(q, wrong, ortho)
        assert r["outcome"] == "disagrees", r
        assert r["supported"] < right["supported"] / 2


def test_verify_corrects_a_distorted_fit_or_rejects_it_and_rejects_a_wrong_place(scene):
    q, H, ortho = scene
    Hu, rec = oc.verify(q, H, ortho)
    assert rec["outcome"] == "agrees" and footprint_error(Hu, H) < 1.5
    Hu, rec = oc.verify(q, distorted(H), ortho)
    if rec["outcome"] == "agrees":  # the dense refit found the truth
        assert rec["refit"]["kept"] and footprint_error(Hu, H) < 2.0, rec
        assert rec["refit"]["moved_corners_map_px"] > 10.0
    for wrong in (moved(H, 60.0), moved(H, 0.0, deg=90.0)):
        Hu, rec = oc.verify(q, wrong, ortho)
        assert rec["outcome"] == "disagrees", rec


def _reader(ortho: MapImage):
    """fuse.ortho_window_reader on the array: bounds -> (gray window, pixel centre -> map)."""
    g = ortho.gray

    def read(b):
        c0, c1 = max(0, int(np.floor(b[0]))), min(N, int(np.ceil(b[2])) + 1)
        r0, r1 = max(0, int(np.floor(N - b[3]))), min(N, int(np.ceil(N - b[1])) + 1)
        if c1 - c0 < 8 or r1 - r0 < 8:
            return None
        A = np.array([[1, 0, c0 + 0.5], [0, -1, N - r0 - 0.5], [0, 0, 1.0]])
        return g[r0:r1, c0:c1], A

    return read


def test_apply_in_the_fuse_step_rejects_or_skips_never_changes_the_fit(scene):
    q, H, ortho = scene
    read = _reader(ortho)
    conf = {"ortho_check": {"mode": "reject", "max_inliers": 30}}
    fused = {"status": "registered", "homography": H.tolist(), "inliers": 8}
    out, rec = oc.apply(q, fused, read, conf)
    assert out["status"] == "registered" and rec["outcome"] == "agrees"
    assert out["homography"] == H.tolist()
    wrong = {**fused, "homography": moved(H, 60.0).tolist()}
    out, rec = oc.apply(q, wrong, read, conf)
    assert out["status"] == "not_found" and out["homography"] is None and "ortho_check" in out["reason"]
    # record mode without the gain veto: written, decision unchanged; many inliers: not due; off: nothing
    out, rec = oc.apply(q, wrong, read, {"ortho_check": {"mode": "record", "veto_gain": 0}})
    assert out["status"] == "registered" and rec["outcome"] == "disagrees"
    assert out["homography"] == wrong["homography"]
    # the default: record, with the gain veto (2): the moved fit is supported no better than
    # poses moved from it, so it is not_found; a rift pose is left to its own polish
    assert oc.ortho_conf({})["mode"] == "record"
    out, rec = oc.apply(q, wrong, read, {})
    assert rec["gain"] < 2.0 and out["status"] == "not_found" and "veto_gain" in out["reason"]
    out, rec = oc.apply(q, {**wrong, "pose_source": "rift"}, read, {})
    assert out["status"] == "registered" and rec["veto_gain"] == 0.0
    # a feature re-match guided by a rift pose is a feature fit: the floor applies
    out, rec = oc.apply(q, {**wrong, "best_source": "rift", "pose_source": "features"}, read, {})
    assert out["status"] == "not_found" and rec["veto_gain"] == 2.0
    out, rec = oc.apply(q, fused, read, {})  # the right fit: as it was
    assert rec["gain"] >= 2.0 and out["status"] == "registered" and out["homography"] == H.tolist()
    out, rec = oc.apply(q, {**fused, "homography": distorted(H).tolist()}, read, {"ortho_check": {"veto_gain": 0}})
    assert out["homography"] == distorted(H).tolist()
    out, rec = oc.apply(q, {**wrong, "inliers": 31}, read, conf)
    assert out["status"] == "registered" and rec["outcome"] == "skipped"
    assert oc.apply(q, wrong, read, {"ortho_check": {"mode": "off"}}) == (wrong, None)
    assert oc.apply(q, fused, None, conf)[1]["outcome"] == "skipped"
    with pytest.raises(ValueError):
        oc.ortho_conf({"ortho_check": {"mode": "veto"}})


# ----------------------------------------------------------------------------- real data


def _bench():
    return benchmark_module.load("bench_crossspectral")


needs_data = pytest.mark.skipif(not DATA.is_dir(), reason="../shared/data/swir_dates absent")


@needs_data
def test_tiny_sentinel2_distorted_fits_are_not_accepted_and_a_right_one_is():
    """The tiny set's two false accepts (6 and 12 inliers, at the right place but 20-24 map px
    off at p90) are not registered with the check; a right tiny fit (5 inliers) stays
    registered within 5 map px."""
    from georeg.index.features import merged_conf
    from georeg.register.fuse import register_query
    from georeg.register.search import MapSource

    bc = _bench()
    cv2.setNumThreads(1)
    scenes, qs = bc.build_small_set(5, 11, bc.TINY_SIDES, "tiny_", 600)
    by = {s.name: s for s in scenes}
    seeds = {q.name: 11 + i for i, q in enumerate(qs)}
    # the ortho check alone: the null scan's check of small fits (on by default) fixes these two
    # as well (tests/test_register_small.py), so it is off on both sides here
    base = bc._deep(bc.workflow_register_conf(), {"small": {"null_test": {"check": False}}})
    on = bc._deep(base, {"ortho_check": {"mode": "reject"}})
    off = bc._deep(base, {"ortho_check": {"mode": "off"}})
    out = {}
    for name in ("tiny_s2_abudhabi_103_2.2um", "tiny_s2_saclay_e_103_1.6um",
                 "tiny_s2_saclay_w_102_1.6um"):  # fmt: skip
        q = next(x for x in qs if x.name == name)
        sc = by[q.map_scene]
        g = sc.map_gsd
        mxy, mdesc, mang, msize = bc.map_features(sc, g, merged_conf(bc.FEATURES))
        src = MapSource(mxy, mdesc, g, angle=mang, scale=msize * g)
        u8 = bc.query_stack(q, "auto")
        for key, conf in (("off", off), ("on", on)):
            res = register_query(u8, src, conf, q.gsd, [q.gsd / g], seeds[name],
                                 bc.plain_window_reader(sc))  # fmt: skip
            Hr = None if res.get("homography") is None else np.array(res["homography"])
            out[name, key] = (res, bc.judge(q, sc, {"accepted": Hr is not None, "H": Hr}))
    for name in ("tiny_s2_abudhabi_103_2.2um", "tiny_s2_saclay_e_103_1.6um"):
        assert out[name, "off"][1]["outcome"] == "false_accept"  # without the check
        res, j = out[name, "on"]
        assert j["outcome"] != "false_accept", res.get("ortho_check")
    res, j = out["tiny_s2_saclay_w_102_1.6um", "on"]
    assert j["outcome"] == "success" and res["ortho_check"]["outcome"] == "agrees"
    assert j["p90_px"] <= out["tiny_s2_saclay_w_102_1.6um", "off"][1]["p90_px"] + 0.5
