"""Demo drone video (issue 10): the MP4 and its truth poses agree with the map, the flight is
smooth and inside the map, keyframes cover it.

A 640 m demo scene and a 40-frame 320 x 240 video over it are generated in a tmp dir. The truth
is checked against the scene's own map products (orthophoto, truth DSM / DTM), not against the
renderer that made the video.
"""

from __future__ import annotations

import json
from pathlib import Path

import cv2
import numpy as np
import pytest
import rasterio

from georeg.frames.render import PinholeCamera, read_heightfield, render
from georeg.io.errors import ConfigError
from georeg.io.video import FrameSource

CONF = {"n_frames": 40, "width": 320, "height": 240, "fx": 260.0}


@pytest.fixture(scope="module")
def demo_video(tmp_path_factory, small_demo_map):
    from georeg.demo.video import generate_video

    tmp = tmp_path_factory.mktemp("video")
    paths = small_demo_map[1]
    truth = generate_video(paths["scene"], tmp / "video", CONF, seed=10)
    return tmp, paths, truth


def _cam(t: dict) -> tuple[PinholeCamera, np.ndarray]:
    it = t["intrinsics"]
    R, C = np.array(t["R_world_to_cam"]), np.array(t["camera_center_xyz"])
    cam = PinholeCamera(it["fx"], it["fy"], it["cx"], it["cy"], it["width"], it["height"], R, C)
    return cam, np.array(it["dist"], float)


def _gray(tmp, indices) -> dict[int, np.ndarray]:
    src = FrameSource(tmp / "video" / "flight.mp4")
    return {i: cv2.cvtColor(rgb, cv2.COLOR_RGB2GRAY) for i, _, rgb in src if i in indices}


def test_mp4_decodes_to_the_truth_frames(demo_video):
    tmp, _, truth = demo_video
    src = FrameSource(tmp / "video" / "flight.mp4")
    assert (len(src), src.fps, src.width, src.height) == (40, 10.0, 320, 240)
    names = [n for _, n, rgb in src if rgb.std() > 10]  # decodes, not blank
    assert names == [t["image"] for t in truth] and names[12] == "flight.mp4#000012"
    saved = json.loads((tmp / "video" / "truth.json").read_text())
    assert saved == json.loads(json.dumps(truth))
    t = saved[12]
    assert (t["frame"], t["time_s"], t["status"]) == (12, pytest.approx(1.2), "registered")
    assert set(t["intrinsics"]) >= {"fx", "fy", "cx", "cy", "width", "height", "dist"}
    flight = json.loads((tmp / "video" / "flight.json").read_text())
    assert flight["conf"]["n_frames"] == 40 and flight["flight"]["z_m"] > 0


def test_flight_is_smooth_inside_the_map_and_clear_of_buildings(demo_video):
    tmp, paths, truth = demo_video
    C = np.array([t["camera_center_xyz"] for t in truth])
    R = np.array([t["R_world_to_cam"] for t in truth])
    dt = 0.1
    v = np.diff(C, axis=0) / dt
    assert np.allclose(np.linalg.norm(v, axis=1), 10.0, rtol=0.01)  # speed_mps
    assert np.ptp(C[:, 2]) < 1e-6  # constant altitude
    assert np.abs(np.diff(v, axis=0) / dt).max() < 1.0  # gentle: 10^2 / 300 m/s^2 centripetal
    for Ra, Rb in zip(R[:-1], R[1:], strict=True):
        assert np.allclose(Ra @ Ra.T, np.eye(3), atol=1e-9) and np.linalg.det(Ra) > 0
        step = np.degrees(np.linalg.norm(cv2.Rodrigues(Rb @ Ra.T)[0]))
        assert 0.01 < step < 0.5  # < 5 deg/s, never static
    # off-nadir ~30 deg: the optical axis
    tilt = np.degrees(np.arccos(-R[:, 2, 2]))
    assert np.all(np.abs(tilt - 30.0) < 1.5)
    scene = json.loads(Path(paths["scene"]).read_text())
    x0, y0, x1, y1 = scene["map"]["bounds"]
    with rasterio.open(paths["dtm"]) as dtm, rasterio.open(paths["dsm"]) as dsm:
        zg = np.array([z[0] for z in dtm.sample(C[:, :2])])
        top = dsm.read(1)
        tr = dsm.transform
    assert np.all((C[:, 2] - zg > 110) & (C[:, 2] - zg < 150))  # agl_m 130 over the mean ground
    for t, z in zip(truth, zg, strict=True):
        cam, _ = _cam(t)
        w, h = cam.width - 1, cam.height - 1
        border = np.r_[[(u, 0) for u in np.linspace(0, w, 9)], [(u, h) for u in np.linspace(0, w, 9)],
                       [(0, r) for r in np.linspace(0, h, 7)], [(w, r) for r in np.linspace(0, h, 7)]]  # fmt: skip
        d = cam.rays(border)
        fp = cam.C[:2] + ((z - cam.C[2]) / d[:, 2])[:, None] * d[:, :2]
        assert fp[:, 0].min() > x0 + 14 and fp[:, 0].max() < x1 - 14
        assert fp[:, 1].min() > y0 + 14 and fp[:, 1].max() < y1 - 14
        # >= 30 m above every surface within 60 m (map-epoch DSM: allow 5 m for changes)
        c, r = ~tr * (cam.C[0], cam.C[1])
        win = top[max(0, int(r) - 60) : int(r) + 61, max(0, int(c) - 60) : int(c) + 61]
        assert cam.C[2] - np.nanmax(win) > 25


def test_frames_match_the_map_best_at_the_truth_pose(demo_video):
    """Rendering the orthophoto + truth DSM at the truth pose and at poses 3 m off: the truth
    pose correlates best with the (undistorted) video frame."""
    tmp, paths, truth = demo_video
    frames = _gray(tmp, {0, 39})
    for i, g in frames.items():
        cam, dist = _cam(truth[i])
        und = cv2.undistort(g, cam.K, dist)
        fp = np.array(truth[i]["footprint_xy"])
        cloud = read_heightfield(
            paths["orthophoto"], paths["dsm"], (*(fp.min(0) - 60), *(fp.max(0) + 60))
        )
        small = cam.scaled(0.5)
        ref = cv2.resize(und, (small.width, small.height), interpolation=cv2.INTER_AREA)
        ref = ref.astype(float)

        def ncc(c, ref=ref, cloud=cloud):
            r = render(cloud, c)
            a, b = r.gray()[r.mask].astype(float), ref[r.mask]
            a, b = a - a.mean(), b - b.mean()
            return float((a * b).sum() / np.sqrt((a * a).sum() * (b * b).sum()))

        scores = {(dx, dy): ncc(small.with_pose(cam.R, cam.C + [dx, dy, 0]))
                  for dx in (-3, 0, 3) for dy in (-3, 0, 3)}  # fmt: skip
        print(i, {k: round(v, 3) for k, v in scores.items()})
        assert max(scores, key=scores.get) == (0, 0) and scores[(0, 0)] > 0.45


def test_tracked_features_follow_the_truth_poses(demo_video):
    """Features tracked from frame 0 to 12 land where the truth poses, the truth DSM and the
    lens distortion put them (sub-pixel), and clearly not where a 2 m error would."""
    tmp, paths, truth = demo_video
    g = _gray(tmp, {0, 12})
    ca, dist = _cam(truth[0])
    cb, _ = _cam(truth[12])
    fp = np.array(truth[0]["footprint_xy"])
    cloud = read_heightfield(
        paths["orthophoto"], paths["dsm"], (*(fp.min(0) - 60), *(fp.max(0) + 60))
    )
    p0 = cv2.goodFeaturesToTrack(g[0], 200, 0.01, 8)
    p1, st, _ = cv2.calcOpticalFlowPyrLK(g[0], g[12], p0, None, winSize=(21, 21), maxLevel=3)
    X, ok = render(cloud, ca).points_at(cv2.undistortPoints(p0, ca.K, dist, P=ca.K).reshape(-1, 2))
    ok &= st.ravel() == 1
    assert ok.sum() > 80

    def err(C, d):
        uv, _ = cv2.projectPoints(X[ok], cb.rvec, -cb.R @ C, cb.K, d)
        return float(np.median(np.linalg.norm(uv.reshape(-1, 2) - p1.reshape(-1, 2)[ok], axis=1)))

    e = err(cb.C, dist)
    print("median px: truth", e, "2 m off", err(cb.C + [2, 0, 0], dist), "no dist", err(cb.C, None))
    assert e < 1.0
    assert err(cb.C + [2, 0, 0], dist) > e + 1.5 and err(cb.C, None) > e + 0.4


def test_keyframes_of_the_demo_video(demo_video):
    from georeg.trajectory.keyframes import keyframe_stats

    tmp, _, truth = demo_video
    keys = keyframe_stats(FrameSource(tmp / "video" / "flight.mp4").gray())
    idx = [k.index for k in keys]
    print([(k.index, k.reason, round(k.overlap, 2), round(k.baseline_px, 1)) for k in keys])
    assert idx[0] == 0 and idx[-1] == 39 and np.all(np.diff(idx) > 0)
    assert 3 <= len(idx) <= 12
    assert all(k.overlap > 0.6 for k in keys[1:])  # consecutive keyframes share the view
    assert np.all(np.diff(idx) <= 30)  # max_gap


def test_flight_planning_is_seeded_and_checked(demo_video):
    from georeg.demo.frames import World
    from georeg.demo.video import Flight, generate_video, plan_flight, video_conf

    tmp, paths, truth = demo_video
    world = World(json.loads(Path(paths["scene"]).read_text()))
    c, intr = video_conf(CONF)
    a = plan_flight(world, c, intr, np.random.default_rng(3))
    assert a == plan_flight(world, c, intr, np.random.default_rng(3))
    assert a != plan_flight(world, c, intr, np.random.default_rng(4))
    flight = json.loads((tmp / "video" / "flight.json").read_text())["flight"]
    again = Flight(**flight).cameras(intr)[5]  # flight.json rebuilds the truth poses
    assert np.allclose(again.C, truth[5]["camera_center_xyz"], atol=1e-9)
    assert np.allclose(again.R, truth[5]["R_world_to_cam"], atol=1e-12)
    with pytest.raises(ConfigError, match="unknown"):
        video_conf({"n_frame": 10})
    with pytest.raises(ConfigError, match="n_frames"):
        video_conf({"n_frames": 1})
    with pytest.raises(ConfigError, match="no flight fits"):
        generate_video(paths["scene"], tmp / "none", {**CONF, "n_frames": 900}, seed=1)


def test_cloud_blocks_keep_every_point_in_view():
    from georeg.demo.video import CloudBlocks
    from georeg.frames.render import PointCloud, pose_from_angles

    rng = np.random.default_rng(0)
    xyz = np.c_[rng.uniform(0, 300, (20000, 2)), rng.uniform(0, 20, 20000)]
    rgb = rng.integers(0, 255, (20000, 3)).astype(np.uint8)
    C = np.array([150.0, 150, 150])
    cam = PinholeCamera(300, 300, 160, 120, 320, 240, pose_from_angles(C, 40, 30), C)

    def in_view(pts):
        uv, z = cam.project(pts)
        return (z > 0) & (uv[:, 0] >= 0) & (uv[:, 0] < 320) & (uv[:, 1] >= 0) & (uv[:, 1] < 240)

    sub = CloudBlocks(PointCloud(xyz, rgb, 0.5)).visible(cam)
    assert in_view(sub.xyz).sum() == in_view(xyz).sum() > 1000 and len(sub) < 0.8 * len(xyz)
    pairs = {tuple(p) + tuple(c) for p, c in zip(xyz.round(6), rgb, strict=True)}
    assert all(tuple(p) + tuple(c) in pairs for p, c in zip(sub.xyz.round(6), sub.rgb, strict=True))
