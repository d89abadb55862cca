"""Per-frame location against geo-registered points (georeg.trajectory.relocalize) and the trajectory
outputs (georeg.trajectory.outputs), on a synthetic textured height field with known poses."""

from __future__ import annotations

import json
import xml.etree.ElementTree as ET

import cv2
import laspy
import numpy as np
import pyproj
import pytest
from rasterio.transform import from_origin

from georeg.frames.render import PinholeCamera, heightfield_cloud, pose_from_angles, render
from georeg.trajectory.outputs import (
    look_point,
    view_angles,
    write_csv,
    write_geojson,
    write_kml,
    write_point_map,
)
from georeg.trajectory.relocalize import PointMapLocalizer, Tracker

CRS = pyproj.CRS.from_epsg(32611).to_wkt()
X0, Y0 = 500_000.0, 3_700_000.0


@pytest.fixture(scope="module")
def scene():
    """A 400 m textured height field (0.5 m) with box buildings, and a camera path over it."""
    rng = np.random.default_rng(3)
    n = 800
    tex = cv2.GaussianBlur(rng.uniform(0, 255, (n, n)).astype(np.float32), (0, 0), 2.0)
    tex += cv2.GaussianBlur(rng.uniform(-80, 80, (n, n)).astype(np.float32), (0, 0), 8.0)
    dsm = np.full((n, n), 100.0)
    for _ in range(40):
        r, c = rng.integers(20, n - 60, 2)
        hgt, s = rng.uniform(5, 25), rng.integers(15, 50)
        dsm[r : r + s, c : c + s] += hgt
        tex[r : r + s, c : c + s] = rng.uniform(60, 200) + 0.5 * tex[r : r + s, c : c + s]
    g = np.clip(tex, 0, 255).astype(np.uint8)
    cloud = heightfield_cloud(np.dstack([g, g, g]), dsm, from_origin(X0, Y0 + 200, 0.5, 0.5),
                              wall_step_m=0.5)  # fmt: skip
    cams = []
    for k in range(12):
        C = np.array([X0 + 140 + 4.0 * k, Y0 + 60 + 1.5 * k, 220.0])
        R = pose_from_angles(C, 70.0 + 0.3 * k, 20.0)
        cams.append(PinholeCamera(420.0, 420.0, 319.5, 239.5, 640, 480, R, C))
    frames = [render(cloud, cam).gray() for cam in cams]
    return cloud, cams, frames


def _err(R, C, cam):
    dR = np.degrees(np.arccos(np.clip((np.trace(R @ cam.R.T) - 1) / 2, -1, 1)))
    return float(np.linalg.norm(C - cam.C)), float(dR)


def _keyframe_points(frame, cam, cloud):
    """Good features of the keyframe and their map points from the depth buffer."""
    uv = cv2.goodFeaturesToTrack(frame, 600, 0.01, 8).reshape(-1, 2).astype(np.float64)
    xyz, ok = render(cloud, cam).points_at(uv)
    return uv[ok], xyz[ok]


def test_tracker_locates_frames_without_drift(scene):
    cloud, cams, frames = scene
    K = cams[0].K
    uv, xyz = _keyframe_points(frames[0], cams[0], cloud)
    tr = Tracker(K, {"seed": 1})
    tr.reset(frames[0], uv, xyz)
    errs = []
    for f, cam in zip(frames[1:], cams[1:], strict=True):
        pose = tr.step(f)
        assert pose.ok, f"tracking lost with {tr.n_tracks} tracks"
        errs.append(_err(pose.R, pose.C, cam))
    pos = np.array([e[0] for e in errs])
    rot = np.array([e[1] for e in errs])
    # 0.5 m map cells seen from ~230 m: a few decimetres, no growth along the path
    assert pos.max() < 1.0 and rot.max() < 0.3, (pos, rot)
    assert pos[-3:].mean() < 3 * pos[:3].mean() + 0.3


def test_tracker_reports_lost_tracks(scene):
    _, cams, frames = scene
    tr = Tracker(cams[0].K, {"min_inliers": 12})
    tr.reset(frames[0], np.zeros((5, 2)), np.zeros((5, 3)))
    assert not tr.step(frames[1]).ok


def test_relocalisation_with_and_without_prior(scene):
    from georeg.trajectory.relocalize import colmap_sift

    cloud, cams, frames = scene
    extract = colmap_sift(3000)
    xy, d = extract(frames[0])
    xyz, ok = render(cloud, cams[0]).points_at(xy)
    loc = PointMapLocalizer(xyz[ok], d[ok].astype(np.uint8), cams[0].K, (640, 480), {"seed": 2})
    for prior in (None, (cams[5].R, cams[5].C + [8.0, -6.0, 3.0])):
        pose, uv, pts = loc.locate(frames[6], prior)
        assert pose.ok and len(uv) == len(pts) >= 12
        pos, rot = _err(pose.R, pose.C, cams[6])
        assert pos < 1.0 and rot < 0.3, (prior is None, pos, rot)
    # a frame of another place: nothing consistent
    rng = np.random.default_rng(99)
    other = cv2.GaussianBlur(rng.uniform(0, 255, (480, 640)).astype(np.float32), (0, 0), 2.0)
    pose, _, _ = loc.locate(other.astype(np.uint8), None)
    assert not pose.ok


def test_view_angles_and_look_point():
    C = np.array([0.0, 0.0, 100.0])
    R = pose_from_angles(C, 90.0, 30.0)  # looking east, 30 deg off nadir
    h, p, r = view_angles(R)
    assert h == pytest.approx(90.0, abs=1e-6)
    assert p == pytest.approx(60.0, abs=1e-6)
    assert r == pytest.approx(0.0, abs=1e-6)
    g = look_point(C, R, 0.0, 1e4)
    assert g[2] == pytest.approx(0.0) and g[0] == pytest.approx(100 * np.tan(np.radians(30)))
    assert abs(g[1]) < 1e-9


def _poses(n=12):
    out = []
    for i in range(n):
        C = [X0 + 10.0 * i, Y0 + 5.0 * i, 250.0]
        R = pose_from_angles(np.asarray(C), 45.0, 25.0)
        st = "not_found" if i == 3 else "registered"
        out.append({"image": f"v.mp4#{i:06d}", "frame": i, "time_s": i / 10, "status": st,
                    "keyframe": i % 5 == 0, "source": "tracking", "inliers": 40,
                    "camera_center_xyz": C if st == "registered" else None,
                    "R_world_to_cam": R.tolist() if st == "registered" else None})  # fmt: skip
    return out


def test_csv_geojson_kml(tmp_path):
    poses = _poses()
    write_csv(tmp_path / "t.csv", poses, CRS)
    rows = (tmp_path / "t.csv").read_text().splitlines()
    assert len(rows) == 13 and rows[4].split(",")[3] == "not_found"
    head = rows[0].split(",")
    r1 = dict(zip(head, rows[2].split(","), strict=True))
    assert float(r1["x"]) == pytest.approx(X0 + 10) and float(r1["heading_deg"]) == pytest.approx(45)
    lon, lat = pyproj.Transformer.from_crs(CRS, "EPSG:4326", always_xy=True).transform(X0 + 10, Y0 + 5)
    assert float(r1["lon"]) == pytest.approx(lon, abs=1e-7)

    write_geojson(tmp_path / "t.geojson", poses, CRS, 100.0, look_every=5)
    fc = json.loads((tmp_path / "t.geojson").read_text())
    path = [f for f in fc["features"] if f["properties"]["kind"] == "path"]
    assert len(path) == 1 and len(path[0]["geometry"]["coordinates"]) == 11
    looks = [f for f in fc["features"] if f["properties"]["kind"] == "look"]
    assert looks and all(f["geometry"]["coordinates"][1][2] == pytest.approx(100.0) for f in looks)
    assert fc["crs"]["properties"]["name"].endswith("32611")

    write_kml(tmp_path / "t.kml", poses, CRS, 100.0, look_every=5)
    root = ET.parse(tmp_path / "t.kml").getroot()
    ns = {"k": "http://www.opengis.net/kml/2.2"}
    cams = root.findall(".//k:Camera", ns)
    assert cams
    assert float(cams[0].find("k:heading", ns).text) == pytest.approx(45.0, abs=1.0)  # grid vs true north
    assert float(cams[0].find("k:tilt", ns).text) == pytest.approx(25.0, abs=1e-3)


def test_point_map_roundtrip(tmp_path):
    rng = np.random.default_rng(0)
    xyz = np.c_[X0 + rng.uniform(0, 100, 50), Y0 + rng.uniform(0, 100, 50), rng.uniform(90, 130, 50)]
    desc = rng.integers(0, 255, (50, 128)).astype(np.uint8)
    dpath = write_point_map(tmp_path / "p.laz", xyz, rng.integers(0, 255, (50, 3)),
                            np.full(50, 5), desc, CRS)  # fmt: skip
    las = laspy.read(tmp_path / "p.laz")
    assert np.allclose(np.c_[las.x, las.y, las.z], xyz, atol=1e-3)
    assert las.header.parse_crs().sub_crs_list[0].to_epsg() == 32611
    assert np.array_equal(np.load(dpath)[las.point_id], desc)
    assert np.all(las.track_len == 5)


def test_single_frame_record_beside_the_sequence():
    from georeg.trajectory.pipeline import single_frame_record, single_frame_summary

    seq = {"status": "registered", "camera_center_xyz": [10.0, 0.0, 100.0]}
    ok = single_frame_record({"status": "registered", "camera_center_xyz": [13.0, 4.0, 100.0],
                              "inliers": 40}, seq)  # fmt: skip
    assert ok["centre_diff_m"] == 5.0 and not ok["located_by_sequence_only"]
    miss = single_frame_record({"status": "not_found", "reason": "no candidate verified"}, seq)
    assert miss["located_by_sequence_only"] and "centre_diff_m" not in miss
    poses = [{"single_frame": ok}, {"single_frame": miss}, {}]
    assert single_frame_summary(poses) == {"tried": 2, "registered": 1, "located_by_sequence_only": 1,
                                           "median_centre_diff_m": 5.0}  # fmt: skip
