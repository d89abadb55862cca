"""Feature maps on a demo flight against its truth poses (issue 33's demo criterion).

A small demo city (seed 7) and a 90-frame flight over it: the first half, geo-referenced as a
video (rule trajectory's pipeline), writes its feature map; frames of the second half are
localised alone, map-only and against that feature map. Where the feature map covers a frame and
its pose verifies against the map, it serves the frame (at least 2 of the 3 frames; 3 measured):
path "feature map 2D-3D" in the record, the pose as the feature map gives it (polished on the map
window only when that verifies 1.5 x higher, or higher and strong), none of the map-only stages
run (coarse search, direct matching, render-match-PnP, intensity refinement), the pose within 2
map pixels of the truth and as close to it as the map-only one (within half a map pixel); the
frames it does not serve take the map-only path."""

from __future__ import annotations

import numpy as np
import pytest

pytestmark = pytest.mark.slow

VIDEO = {"n_frames": 90, "width": 480, "height": 360, "fx": 390.0}
# the map-only path of a large map (coarse search, direct, render, refinement), not the whole-map
# matching of a small one: where a verified feature-map pose ends the search
FRAME_LOC = {"refine": {"enabled": True}, "direct": {"whole_map_first_px": 0}}


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
    want = {46, 50, 54}
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
        if not fm.get("served"):  # not covered, not verified, or polished weak: the map-only path
            assert "direct_attempts" in rec or "pnp_attempts" in rec
            continue
        # served: at least as accurate as the map-only path (within half a map pixel)
        e_fm, e_base = _error_m(rec, t), _error_m(base, t)
        assert e_fm <= e_base + 0.5 * gsd, (e_fm, e_base)
        served += 1
        # served by the feature map, verified against the map by the common score
        assert rec["path"] == "feature map 2D-3D" and fm["served"]
        assert rec["verification"]["score"] == fm["score"] >= 15
        # the pose is the feature map's, moved on the map window only when that verifies higher
        moved = np.linalg.norm(
            np.subtract(rec["camera_center_xyz"], fm["pose"]["camera_center_xyz"])
        )
        assert moved < 1e-6 if not fm["polished"] else fm["polished_score"] > fm["raw_score"]
        # nothing of the map-only path ran after it
        assert rec["coarse"]["reason"] == "not run: the feature map gave a pose"
        assert not {"direct_attempts", "pnp_attempts", "refine", "search_attempts"} & set(rec)
        assert "feature_map_s" in rec["timings_s"] and "pnp_s" not in rec["timings_s"]
        assert e_fm < 2 * gsd, e_fm
    assert served >= 2
