"""Feature maps on a demo flight against its truth poses (issue 33's demo criterion).

A small demo city (seed 7) and a 90-frame flight over it: the first half, geo-referenced as a
video (rule trajectory's pipeline), writes its feature map; frames of the second half are
localised alone, map-only and against that feature map. Where the feature map covers a frame and
its pose verifies against the map, it serves the frame (at least 2 of the 3 frames): path
"feature map 2D-3D" in the record, the pose as the feature map gives it (not polished on the map
window), none of the map-only stages run (coarse search, direct matching, render-match-PnP,
intensity refinement), the pose within 2 map pixels of the truth; every frame, served or not, as
close to the truth as the map-only one (within half a map pixel)."""

from __future__ import annotations

import numpy as np
import pytest

pytestmark = pytest.mark.slow

VIDEO = {"n_frames": 90, "width": 480, "height": 360, "fx": 390.0}
FRAME_LOC = {"refine": {"enabled": True}}


@pytest.fixture(scope="module")
def first_half(small_demo_map):
    from georeg.demo.video import generate_video
    from georeg.frames.localize import MapSources
    from georeg.trajectory.pipeline import georeference_video

    tmp, paths, tdir, outs = small_demo_map
    truth = generate_video(paths["scene"], tmp / "fm_video", VIDEO, seed=10)
    it = truth[0]["intrinsics"]
    cam = {k: it[k] for k in ("fx", "fy", "cx", "cy", "dist")}
    maps = MapSources(tmp / "index", tdir / "ortho.tif", outs["dsm"], [])
    out = tmp / "fm_first_half"
    georeference_video({"video": str(tmp / "fm_video" / "flight.mp4"), "camera": cam}, maps, FRAME_LOC,
                       {"seed": 3, "max_frames": VIDEO["n_frames"] // 2}, out)  # fmt: skip
    return maps, cam, truth, out / "sfm_points.laz", tmp / "fm_video" / "flight.mp4"


def _error_m(rec: dict, truth: dict) -> float:
    from georeg.frames.localize import evaluate

    return evaluate(rec, truth)["final"]["position_m"]


def test_feature_map_serves_second_half_frames_at_least_as_accurately(first_half):
    from georeg.frames.feature_map import load_feature_maps
    from georeg.frames.localize import localize_image
    from georeg.io.video import FrameSource

    maps, cam, truth, laz, video = first_half
    fmap = load_feature_maps([laz], maps.crs_wkt, maps.bounds())
    want = {50, 60, 70}
    frames = {i: rgb for i, _, rgb in FrameSource(video) if i in want}
    assert set(frames) == want
    gsd, served = maps.gsd, 0
    for i in sorted(want):
        name, t = truth[i]["image"], truth[i]
        maps.feature_map = None
        base, _ = localize_image(frames[i], name, cam, maps, FRAME_LOC)
        maps.feature_map = fmap
        rec, _ = localize_image(frames[i], name, cam, maps, FRAME_LOC)
        maps.feature_map = None
        fm = rec["feature_map"]
        print(
            i,
            base.get("path"),
            _error_m(base, t) if base["status"] == "registered" else None,
            rec.get("path"),
            _error_m(rec, t),
            {k: fm.get(k) for k in ("inliers", "score", "used")},
        )
        assert base["status"] == rec["status"] == "registered"
        e_fm, e_base = _error_m(rec, t), _error_m(base, t)
        # at least as accurate as the map-only path (half a map pixel), served or not
        assert e_fm <= e_base + 0.5 * gsd, (e_fm, e_base)
        if not fm.get("used"):  # not covered, or not verified: the map-only path
            assert rec["path"] != "feature map 2D-3D" and (fm.get("score") or 0) < 15
            continue
        served += 1
        # served by the feature map, verified against the map by the common score
        assert rec["path"] == "feature map 2D-3D"
        assert rec["verification"]["score"] == fm["score"] >= 15
        # the pose is the feature map's, not moved on the map window
        assert np.allclose(rec["camera_center_xyz"], fm["pose"]["camera_center_xyz"])
        # nothing of the map-only path ran after it
        assert rec["coarse"]["reason"] == "not run: the feature map gave a pose"
        assert not {"direct_attempts", "pnp_attempts", "refine", "search_attempts"} & set(rec)
        assert "feature_map_s" in rec["timings_s"] and "pnp_s" not in rec["timings_s"]
        assert e_fm < 2 * gsd, e_fm
    assert served >= 2
