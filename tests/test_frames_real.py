"""Frame geo-localisation on real frames (../shared/data/frames_dev, surveyed truth poses).

Each case's map (orthophoto + DEM/DSM) is built in a tmp dir as the workflow builds it
(benchmarks/bench_frames.py ``build_case_map``), then every query frame is localised with the
default settings except the stages after a verified direct pose (render-match-PnP and the
intensity refinement, off: on these frames they reach the direct pose's score at best, and
cost ~25 s a frame; the demo tests cover them). Bars: one map GSD in position, 0.5 deg in rotation (measured well inside, see
docs/BENCHMARKS.md "Frame geo-localisation on real frames"). The same frames against a
panchromatic (1-band) copy of the map orthophoto, and the drone frames against the map without
its DSM (a flat ground), are checked too.
"""

from __future__ import annotations

import importlib.util
import json
from pathlib import Path

import numpy as np
import pytest

REPO = Path(__file__).resolve().parents[1]
FRAMES_DEV = REPO.parent / "shared" / "data" / "frames_dev"
CONF = {"refine": {"enabled": False}, "render_after_direct": False}

pytestmark = [
    pytest.mark.shared,
    pytest.mark.skipif(not FRAMES_DEV.is_dir(), reason="../shared/data/frames_dev is absent"),
]


def _bench():
    spec = importlib.util.spec_from_file_location("bench_frames", REPO / "benchmarks" / "bench_frames.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


@pytest.fixture(scope="module")
def bench():
    return _bench()


def _localise(bench, case: str, maps: dict, frames: list[str] | None = None, ground_z: float = 0.0):
    out = []
    for frame, cam, truth in bench.case_frames(case):
        if frames and frame.stem not in frames:
            continue
        rec = bench.ours(frame, cam, maps, CONF, ground_z=ground_z)
        pos, rot = bench.pose_errors(rec.get("R_world_to_cam"), rec.get("camera_center_xyz"), truth)
        print(case, frame.stem, rec["status"], rec.get("path"), f"{pos:.2f} m {rot:.3f} deg",
              (rec.get("verification") or {}).get("score"), rec["timings_s"])  # fmt: skip
        out.append((frame.stem, rec, pos, rot))
    return out


@pytest.fixture(scope="module", params=["ngi", "odm"])
def case_map(request, bench, tmp_path_factory):
    case = request.param
    cdir = FRAMES_DEV / case
    maps = bench.build_case_map(cdir / "map_ortho.tif", cdir / "elevation.tif",
                                tmp_path_factory.mktemp(f"map_{case}"))  # fmt: skip
    return case, maps, json.loads((cdir / "case.json").read_text())["map_resolution_m"]


def test_real_frames_within_one_map_gsd(bench, case_map):
    case, maps, gsd = case_map
    for name, rec, pos, rot in _localise(bench, case, maps):
        assert rec["status"] == "registered", (name, rec.get("reason"))
        assert pos < gsd and rot < 0.5, (name, pos, rot)
        v = rec["verification"]
        assert rec["path"] in [c["path"] for c in v["candidates"]]
        assert v["score"] == max(c["score"] for c in v["candidates"])
        assert v["score"] > 100 * max(v["chance"], 1.0)  # far above what chance matches give
        assert rec["ground"] == {"source": "dsm"}


def test_panchromatic_map(bench, case_map, tmp_path):
    """A 1-band orthophoto: the map stage, the index and the frames stage all take it."""
    case, _, gsd = case_map
    cdir = FRAMES_DEV / case
    pan = bench.panchromatic(cdir / "map_ortho.tif", tmp_path / "pan.tif")
    import rasterio

    with rasterio.open(pan) as s:
        assert s.count == 1
    maps = bench.build_case_map(pan, cdir / "elevation.tif", tmp_path / "map")
    first = sorted(p.stem for p in (cdir / "queries").glob("*.png"))[:1]
    for name, rec, pos, rot in _localise(bench, case, maps, first):
        assert rec["status"] == "registered", (name, rec.get("reason"))
        assert pos < gsd and rot < 0.5, (name, pos, rot)


def test_drone_frames_without_dsm_on_flat_ground(bench, tmp_path):
    """The drone map without its DSM: a flat ground at the DSM's median height. Poorer (the
    frames are 30 deg oblique over buildings) but located, and the record says so."""
    import rasterio

    cdir = FRAMES_DEV / "odm"
    with rasterio.open(cdir / "elevation.tif") as s:
        z0 = float(np.nanmedian(s.read(1, masked=True).filled(np.nan)))
    maps = bench.build_case_map(cdir / "map_ortho.tif", None, tmp_path / "map")
    assert maps["dsm"] is None
    for name, rec, pos, rot in _localise(bench, "odm", maps, ["0142"], ground_z=z0):
        assert rec["status"] == "registered", (name, rec.get("reason"))
        assert rec["ground"] == {"source": "flat (no DSM given)", "z": z0}
        assert pos < 5.0 and rot < 3.0, (name, pos, rot)


def test_whole_map_direct_when_the_coarse_step_fails(bench, case_map):
    """No coarse pose and no vote start (forced): on a small map the direct matching runs on the
    whole map, like the baseline, and still lands within one map GSD."""
    case, maps, gsd = case_map
    if case != "ngi":
        pytest.skip("one case is enough (the coarse step is forced to fail)")
    frame, cam, truth = bench.case_frames(case)[1]
    conf = {**CONF, "vote_starts": 0, "coarse": {"min_inliers": 10**6},
            "direct": {"whole_map_first_px": 0}}  # fmt: skip
    rec = bench.ours(frame, cam, maps, conf)
    pos, rot = bench.pose_errors(rec.get("R_world_to_cam"), rec.get("camera_center_xyz"), truth)
    print(rec["status"], rec.get("path"), pos, rot, rec["timings_s"])
    assert not rec["coarse"]["ok"] and rec["coarse"]["candidates"]  # the coarse step ran, failed
    assert rec["status"] == "registered" and rec["path"] == "direct 2D-3D (whole map)"
    assert pos < gsd and rot < 0.5
