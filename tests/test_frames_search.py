"""Intensity pose search (georeg.frames.search), the last resort of a frame feature matching
cannot place: the demo's low oblique frame (35 deg off nadir, 100 m above ground, a tower facade
and a parking lot whose cars moved) from a start like a coarse vote (tens of metres and a few
degrees off), and the same search refusing a frame of another place and a wrong start."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

VIEWS = [{"name": "oblique35_100", "off_nadir_deg": 35.0, "agl_m": 100.0, "heading_deg": 200.0},
         {"name": "outside", "off_nadir_deg": 20.0, "agl_m": 150.0, "heading_deg": 300.0, "outside": True}]  # fmt: skip


@pytest.fixture(scope="module")
def scene(small_demo_map):
    import cv2

    from georeg.demo.frames import CAMERA, generate_frames
    from georeg.frames.localize import MapSources, camera_matrix
    from georeg.frames.render import PinholeCamera

    tmp, paths, tdir, outs = small_demo_map
    out = tmp / "frames_search"
    generate_frames(paths["scene"], out, VIEWS, seed=9)
    truth = {Path(t["image"]).stem: t for t in json.loads((out / "truth.json").read_text())}
    maps = MapSources(tmp / "index", tdir / "ortho.tif", outs["dsm"], [])
    cam = {k: CAMERA[k] for k in ("fx", "fy", "cx", "cy", "dist")}
    K, dist = camera_matrix(cam, 800, 600)
    grays = {}
    for v in VIEWS:
        rgb = cv2.cvtColor(cv2.imread(str(out / f"{v['name']}.png")), cv2.COLOR_BGR2RGB)
        grays[v["name"]] = cv2.cvtColor(cv2.undistort(rgb, K, dist), cv2.COLOR_RGB2GRAY)
    t = truth["oblique35_100"]
    cam_t = PinholeCamera(K[0, 0], K[1, 1], K[0, 2], K[1, 2], 800, 600, np.array(t["R_world_to_cam"]),
                          np.array(t["camera_center_xyz"]))  # fmt: skip
    return maps, grays, cam_t


def _rot_err(Ra, Rb) -> float:
    return float(np.degrees(np.arccos(np.clip((np.trace(Ra @ Rb.T) - 1) / 2, -1, 1))))


def _start(cam_t, pitch, heading, dx, dy):
    from georeg.frames.search import moved

    return moved(cam_t, pitch, heading, dx, dy)


def test_low_oblique_frame_found_from_a_coarse_like_start(scene):
    from georeg.frames.localize import DEFAULTS
    from georeg.frames.search import search_pose

    maps, grays, cam_t = scene
    cam0 = _start(cam_t, -5.0, 2.0, 22.0, -14.0)  # like the 2048 m scene's vote: 36 m, 5 deg
    cloud_at = lambda cm: maps.cloud_around(cm, {**DEFAULTS, "cloud_margin_m": 150.0})  # noqa: E731
    sr = search_pose(grays["oblique35_100"], cam0, cloud_at(cam0), None, cloud_at)
    print(json.dumps(sr.info, default=float))
    assert sr.cam is not None, sr.info.get("reason")
    err_m, err_deg = np.linalg.norm(sr.cam.C - cam_t.C), _rot_err(sr.cam.R, cam_t.R)
    print(f"error {err_m:.2f} m, {err_deg:.2f} deg")
    assert err_m < 3.0 and err_deg < 1.5
    assert sr.info["similarity"] >= 1.5 * max(sr.info["decoy_similarity"])  # its own chance level
    # without decoy starts the frame's chance level is unknown: refused
    assert search_pose(grays["oblique35_100"], cam0, cloud_at(cam0)).cam is None


@pytest.mark.parametrize("frame,shift", [("outside", (22.0, -14.0)), ("oblique35_100", (-180.0, 150.0))])
def test_other_place_or_wrong_start_is_refused(scene, frame, shift):
    from georeg.frames.localize import DEFAULTS
    from georeg.frames.search import search_pose

    maps, grays, cam_t = scene
    cam0 = _start(cam_t, -5.0, 2.0, *shift)
    cloud_at = lambda cm: maps.cloud_around(cm, {**DEFAULTS, "cloud_margin_m": 150.0})  # noqa: E731
    sr = search_pose(grays[frame], cam0, cloud_at(cam0), None, cloud_at)
    print(json.dumps(sr.info, default=float))
    assert sr.cam is None


def test_localize_frame_records_the_search(small_demo_map, scene):
    """Through ``localize_frame``, every feature path refused (``min_inliers`` out of reach): the
    low oblique frame is registered by the search from the coarse start, near the truth, and the
    record names the path, its similarity and bound, and the attempt."""
    from georeg.demo.frames import CAMERA
    from georeg.frames.localize import localize_frame

    tmp = small_demo_map[0]
    maps, _, cam_t = scene
    cam = {k: CAMERA[k] for k in ("fx", "fy", "cx", "cy", "dist")}
    rec, _ = localize_frame(str(tmp / "frames_search" / "oblique35_100.png"), cam, maps,
                            {"min_inliers": 100_000, "refine": {"enabled": False}})  # fmt: skip
    print(rec.get("path"), rec.get("verification"), json.dumps(rec.get("search_attempts"), default=float))
    assert rec["status"] == "registered", rec.get("reason")
    assert rec["path"].startswith("intensity search")
    assert np.linalg.norm(np.array(rec["camera_center_xyz"]) - cam_t.C) < 3.0
    v = rec["verification"]
    assert v["accepted_by"] == "intensity search" and v["similarity"] >= v["similarity_bound"]
    assert v["similarity"] >= 1.5 * max(rec["search_attempts"][-1]["decoy_similarity"])
    assert rec["search_attempts"][-1]["similarity"] == v["similarity"]
    assert rec["reprojection_px"] is None  # no PnP inliers behind this pose


def test_similarity_scores_a_batch_of_poses_as_one_at_a_time_and_the_truth_highest():
    """``similarity`` of many poses at once (the grid's path) equals each pose alone (the
    refinement's path), and on a textured ground the true pose scores highest."""
    import cv2

    from georeg.frames.refine import frame_channels, similarity
    from georeg.frames.render import PinholeCamera, look_at

    rng = np.random.default_rng(2)
    tex = cv2.GaussianBlur(rng.uniform(0, 255, (240, 320)).astype(np.float32), (0, 0), 2.5)
    tex = cv2.normalize(tex, None, 0, 255, cv2.NORM_MINMAX)
    C = np.array([10.0, 20.0, 100.0])
    cam = PinholeCamera(300.0, 300.0, 159.5, 119.5, 320, 240, look_at(C, C - [0, 0, 1], (0, 1, 0)), C)
    img3 = frame_channels(tex)
    rows, cols = np.mgrid[20:220:4, 20:300:4]
    uv = np.c_[cols.ravel(), rows.ravel()].astype(float)
    X = cam.backproject(uv, np.full(len(uv), 100.0))  # the ground plane z = 0
    ref3 = img3[rows.ravel(), cols.ravel()].astype(np.float64)
    shifts = np.array([[0, 0, 0], [1.5, 0, 0], [0, -2.0, 0], [3.0, 3.0, 0], [-6.0, 1.0, 0]])
    mi, gc, frac = similarity(img3, cam, cam.R, C + shifts, X, ref3, 32)
    for k, s in enumerate(shifts):
        one = similarity(img3, cam, cam.R, (C + s)[None], X, ref3, 32)
        np.testing.assert_allclose([one[0][0], one[1][0], one[2][0]], [mi[k], gc[k], frac[k]], atol=1e-9)
    assert np.argmax(mi + gc) == 0 and gc[0] > 0.99 and frac[0] == 1.0
    assert (mi[1:] + gc[1:] < mi[0] + gc[0] - 0.2).all()
