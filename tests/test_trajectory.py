"""Video trajectory geo-referencing end to end (issue 10) on a small demo city and flight:
keyframes -> SfM -> anchors by the single-frame method -> Sim(3) -> ICP -> every frame, checked
against the demo's truth poses; and a video of another place is not_found."""

from __future__ import annotations

import json

import laspy
import numpy as np
import pytest

pytestmark = pytest.mark.slow  # the module's georeferenced video: about 80 s

VIDEO = {"n_frames": 90, "width": 480, "height": 360, "fx": 390.0}


@pytest.fixture(scope="module")
def small_map(small_demo_map):
    from georeg.demo.video import generate_video

    tmp, paths, tdir, outs = small_demo_map
    truth = generate_video(paths["scene"], tmp / "video", VIDEO, seed=10)
    return tmp, tdir, outs, truth


@pytest.fixture(scope="module")
def georeferenced(small_map):
    from georeg.frames.localize import MapSources
    from georeg.trajectory.pipeline import georeference_video

    tmp, tdir, outs, truth = small_map
    it = truth[0]["intrinsics"]
    fs = {"video": str(tmp / "video" / "flight.mp4"),
          "camera": {k: it[k] for k in ("fx", "fy", "cx", "cy", "dist")}}  # fmt: skip
    maps = MapSources(tmp / "index", tdir / "ortho.tif", outs["dsm"], [])
    out = tmp / "trajectory_out"
    poses = georeference_video(fs, maps, {"refine": {"enabled": False}}, {"seed": 3}, out, None,
                               str(tmp / "video" / "truth.json"))  # fmt: skip
    return out, poses, json.loads((out / "trajectory.json").read_text())


def test_every_frame_located_against_truth(georeferenced, small_map):
    out, poses, info = georeferenced
    assert len(poses) == VIDEO["n_frames"]
    assert [p["frame"] for p in poses] == list(range(VIDEO["n_frames"]))
    ev = info["evaluation"]
    assert ev["registered"] >= 0.95 * VIDEO["n_frames"], info
    after = ev["after_icp"]
    # a 1 m map seen from ~150 m: about a map pixel, no drift along the path
    assert after["position_m"]["mean"] < 2.0 and after["position_m"]["p90"] < 3.0, after
    assert after["rotation_deg"]["mean"] < 1.0, after
    # the Sim(3) scale of the SfM frame agrees with the truth within 1 %
    assert abs(info["sim3"]["scale"] / ev["true_scale"] - 1) < 0.01, (info["sim3"], ev["true_scale"])
    # keyframes come from the reconstruction, the frames between them from tracking
    kf = [p for p in poses if p["keyframe"]]
    assert 3 <= len(kf) < len(poses) / 2
    assert {p.get("source") for p in poses if p["status"] == "registered"} <= {
        "sfm", "tracking", "relocalisation"}
    assert not (out / ".work").exists()
    # the keyframes tried alone (anchors) carry their single-frame result beside the sequence's
    sf = info["single_frame"]
    assert sf["tried"] == len(info["anchors"]) >= 1
    assert sf["registered"] == sum(a["status"] == "registered" for a in info["anchors"]) >= 1
    assert sf["located_by_sequence_only"] == sf["tried"] - sf["registered"]
    assert sf["median_centre_diff_m"] < 3.0, sf  # both poses of a keyframe agree within ~3 map px


def test_outputs_agree_with_poses(georeferenced):
    out, poses, info = georeferenced
    rows = (out / "trajectory.csv").read_text().splitlines()
    assert len(rows) == len(poses) + 1
    fc = json.loads((out / "trajectory.geojson").read_text())
    path = next(f for f in fc["features"] if f["properties"]["kind"] == "path")
    reg = [p for p in poses if p["status"] == "registered"]
    assert np.allclose(path["geometry"]["coordinates"], [p["camera_center_xyz"] for p in reg])
    assert "<Camera>" in (out / "trajectory.kml").read_text()
    las = laspy.read(out / "sfm_points.laz")
    desc = np.load(out / "sfm_points_descriptors.npy")
    assert len(las.x) == len(desc) == info["sfm"]["points"] > 100
    assert las.track_len.min() >= 4
    # the geo-registered SfM points lie on the map surface (DSM) within a couple of metres
    import rasterio

    with rasterio.open(out.parent / "tiles" / "r000_c000" / "dsm.tif") as ds:
        z = np.array([v[0] for v in ds.sample(np.c_[las.x, las.y])], float)
    dz = (np.asarray(las.z) - z)[np.isfinite(z)]
    # no vertical bias; most points within a 1 m map cell's height spread (edges, trees: more)
    assert abs(np.median(dz)) < 0.75 and np.mean(np.abs(dz) < 1.5) > 0.6, np.percentile(dz, [10, 50, 90])
    assert len(list((out / "overlays").glob("*.png"))) >= 3


def test_video_of_another_place_is_not_found(small_map, tmp_path):
    """The SfM works, but no keyframe registers to the map: every frame not_found."""
    import cv2

    from georeg.frames.localize import MapSources
    from georeg.trajectory.pipeline import georeference_video

    tmp, tdir, outs, truth = small_map
    # the same flight mirrored left-right: the same textures, a city that is not on the map
    src = cv2.VideoCapture(str(tmp / "video" / "flight.mp4"))
    path = tmp_path / "mirrored.mp4"
    w = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"mp4v"), 10, (VIDEO["width"], VIDEO["height"]))
    n = 0
    while n < 40:
        ok, im = src.read()
        if not ok:
            break
        w.write(np.ascontiguousarray(im[:, ::-1]))
        n += 1
    w.release()
    maps = MapSources(tmp / "index", tdir / "ortho.tif", outs["dsm"], [])
    it = truth[0]["intrinsics"]
    cam = {k: it[k] for k in ("fx", "fy", "cx", "cy")}
    poses = georeference_video({"video": str(path), "camera": cam}, maps, {"refine": {"enabled": False}},
                               {"anchor_tries": 2}, tmp_path / "out")  # fmt: skip
    assert len(poses) == n and all(p["status"] == "not_found" for p in poses)
    info = json.loads((tmp_path / "out" / "trajectory.json").read_text())
    assert info["reason"]


def test_video_with_corrupt_last_frames_uses_the_good_ones_and_lists_the_bad(small_map, tmp_path):
    """Issue 30: the last frames of the flight corrupt: the others are geo-referenced as usual,
    the bad ones are in poses.json (status unreadable), the CSV and trajectory.json."""
    from test_video_io import corrupt_video

    from georeg.frames.localize import MapSources
    from georeg.trajectory.pipeline import georeference_video

    tmp, tdir, outs, truth = small_map
    bad = tmp_path / "flight corrupt.mp4"
    corrupt_video(tmp / "video" / "flight.mp4", bad, 0.9, 1.0)
    it = truth[0]["intrinsics"]
    fs = {"video": str(bad), "camera": {k: it[k] for k in ("fx", "fy", "cx", "cy", "dist")}}
    maps = MapSources(tmp / "index", tdir / "ortho.tif", outs["dsm"], [])
    out = tmp_path / "out"
    poses = georeference_video(fs, maps, {"refine": {"enabled": False}}, {"seed": 3}, out, None,
                               str(tmp / "video" / "truth.json"))  # fmt: skip
    n = VIDEO["n_frames"]
    assert [p["frame"] for p in poses] == list(range(n))
    unreadable = [p["frame"] for p in poses if p["status"] == "unreadable"]
    assert unreadable and min(unreadable) >= 0.8 * n, unreadable
    assert unreadable == list(range(min(unreadable), n))  # the corrupt tail, not more
    good = [p for p in poses if p["status"] != "unreadable"]
    assert sum(p["status"] == "registered" for p in good) >= 0.95 * len(good)
    info = json.loads((out / "trajectory.json").read_text())
    assert [b["frame"] for b in info["unreadable_frames"]] == unreadable
    assert info["frames"] == len(good)
    on_disk = json.loads((out / "poses.json").read_text())
    on_disk = on_disk["poses"] if isinstance(on_disk, dict) else on_disk
    assert [p["status"] for p in on_disk] == [p["status"] for p in poses]
    rows = (out / "trajectory.csv").read_text().splitlines()
    assert len(rows) == n + 1 and sum(",unreadable" in r for r in rows) == len(unreadable)
