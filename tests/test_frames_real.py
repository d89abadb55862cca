"""Frame geo-localisation on real frames (../shared/data/frames_dev, surveyed truth poses).

Each case's map (orthophoto + DEM/DSM) is built in a tmp dir as the workflow builds it
(benchmarks/bench_frames.py ``build_case_map``), then every query frame is localised with the
default settings: the direct 2D-3D pose verifies strong on every one, so the adaptive pipeline
skips render-match-PnP and the intensity refinement (they reached the direct pose's score at
best on these frames, for ~25 s a frame; the demo tests cover them). Bars: one map GSD in
position, 0.5 deg in rotation (measured well inside, see docs/BENCHMARKS.md "Frame
geo-localisation on real frames"). The same frames against a panchromatic (1-band) copy of the
map orthophoto, the drone frames against the map without its DSM (a flat ground), an odm frame
upsampled to 11 Mpx and stored rotated (pyramid level, EXIF orientation), and the drone camera
table are checked too.
"""

from __future__ import annotations

import json
from pathlib import Path

import benchmark_module
import numpy as np
import pytest

REPO = Path(__file__).resolve().parents[1]
FRAMES_DEV = REPO.parent / "shared" / "data" / "frames_dev"
CONF: dict = {}  # the defaults

pytestmark = [
    pytest.mark.shared,
    pytest.mark.skipif(not FRAMES_DEV.is_dir(), reason="../shared/data/frames_dev is absent"),
]


def _bench():
    return benchmark_module.load("bench_frames")


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
        assert rec["adaptive"]["strong"] and "refine" not in rec and "pnp_attempts" not in rec
        assert rec["timings_s"]["total_s"] < 30.0  # measured 6-9 s (2 shared cores)
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
        assert rec["ground"]["source"] == "flat (no DSM given)" and rec["ground"]["z"] == z0
        assert "flat ground" in rec["ground"]["warning"]  # said in the record and the report
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


def _upsampled_jpeg(src: Path, dst: Path, factor: int, orientation: int | None, tags: dict) -> None:
    """``src`` upsampled ``factor`` x (bicubic), written as a JPEG; with EXIF ``orientation`` 6
    the pixels are stored rotated 90 deg counter-clockwise (displayed upright); ``tags`` go to the
    IFD0 (int keys < 0x8000) or the Exif IFD."""
    import cv2
    from PIL import Image

    rgb = cv2.cvtColor(cv2.imread(str(src), cv2.IMREAD_COLOR), cv2.COLOR_BGR2RGB)
    if factor != 1:
        rgb = cv2.resize(rgb, None, fx=factor, fy=factor, interpolation=cv2.INTER_CUBIC)
    ex = Image.Exif()
    if orientation == 6:
        rgb = np.ascontiguousarray(np.rot90(rgb, 1))
        ex[0x0112] = 6
    for k, v in tags.items():
        (ex if k < 0x8000 else ex.get_ifd(0x8769))[k] = v
    Image.fromarray(rgb).save(dst, quality=92, exif=ex)


def test_large_rotated_jpeg_on_a_pyramid_level(bench, case_map, tmp_path):
    """An odm frame upsampled x3 (4104 x 2736 px, 11 Mpx), stored rotated with EXIF orientation 6,
    intrinsics x3: read upright, localised on pyramid level 2 (1026 x 684 px, GSD 0.15 m, finer
    than the map's 0.2 m; intrinsics / 4) within one map GSD, in about the time of the frame as it
    came."""
    case, maps, gsd = case_map
    if case != "odm":
        pytest.skip("the drone frames are the ones that come large")
    frame, cam, truth = bench.case_frames(case)[1]
    small = bench.ours(frame, cam, maps, CONF)
    jpg = tmp_path / f"{frame.stem}_x3.jpg"
    _upsampled_jpeg(frame, jpg, 3, 6, {})
    cam3 = {"fx": cam["fx"] * 3, "fy": cam["fy"] * 3, "cx": (cam["cx"] + 0.5) * 3 - 0.5,
            "cy": (cam["cy"] + 0.5) * 3 - 0.5, "dist": cam["dist"]}  # fmt: skip
    rec = bench.ours(jpg, cam3, maps, CONF)
    pos, rot = bench.pose_errors(rec.get("R_world_to_cam"), rec.get("camera_center_xyz"), truth)
    print(rec["status"], rec["pyramid"], f"{pos:.3f} m {rot:.3f} deg", rec["timings_s"],
          "small frame:", small["timings_s"])  # fmt: skip
    assert rec["pyramid"]["full_size"] == [4104, 2736] and rec["pyramid"]["level"] == 2
    assert rec["intrinsics"]["width"] == 1026
    assert rec["intrinsics"]["fx"] == pytest.approx(0.75 * cam["fx"])
    assert rec["status"] == "registered" and pos < gsd and rot < 0.5, (pos, rot)
    assert rec["seconds"] < 1.5 * small["seconds"] + 3.0


def test_unknown_drone_camera_focal_from_the_sensor_table(bench, tmp_path):
    """camera: null, a JPEG with EXIF Make DJI, Model FC6310R, FocalLength 8.8 mm and no 35 mm
    equivalent (the odm frames are 5472 px Phantom 4 frames reduced 4x): fx from the drone
    sensor table (8.8 / 13.2 mm x 1368 px) within 1 % of the calibrated fx."""
    from georeg.frames.exif import exif_camera

    frame, cam, _ = bench.case_frames("odm")[0]
    jpg = tmp_path / f"{frame.stem}.jpg"
    _upsampled_jpeg(frame, jpg, 1, None, {0x010F: "DJI", 0x0110: "FC6310R", 37386: 8.8})
    got = exif_camera(jpg, 1368, 912)
    print(got, cam["fx"])
    assert got["source"] == "exif" and "FC6310R" in got["exif_tags"]
    assert got["fx"] == pytest.approx(cam["fx"], rel=0.01)


def test_unknown_camera_without_exif(bench, case_map):
    """camera: null on the metadata-free PNGs: the focal and k1 from PnP + a joint fit on the
    whole-map 2D-3D matches, then localised as with a known camera. Measured: odm 0136 fx 882
    (calibrated 912), k1 -0.17 (-0.26), 1.3 m; ngi 0182 fx 835 (833), 11.8 m: seen nearly
    straight down from 5 km, 0.2 % of focal is 10 m of camera height (docs/BENCHMARKS.md)."""
    case, maps, gsd = case_map
    frame, cam, truth = bench.case_frames(case)[0]
    rec = bench.ours(frame, None, maps, CONF)
    pos, rot = bench.pose_errors(rec.get("R_world_to_cam"), rec.get("camera_center_xyz"), truth)
    fm = rec["focal_from_matches"]
    print(case, frame.stem, rec["status"], f"{pos:.2f} m {rot:.3f} deg", rec["intrinsics"], fm)
    assert rec["status"] == "registered" and fm["fitted"], rec.get("reason")
    assert rec["intrinsics"]["source"].startswith("estimated (whole-map 2D-3D")
    assert rec["intrinsics"]["fx"] == pytest.approx(cam["fx"], rel=0.05)
    assert pos < (3.0 if case == "odm" else 4 * gsd) and rot < 1.0, (pos, rot)


@pytest.mark.slow
def test_unknown_camera_on_a_map_too_large_to_match_whole(bench, tmp_path):
    """camera: null with the whole-map step switched off (as on a map above
    ``direct.whole_map_first_px``): the coarse focal search finds the place, and the focal and k1
    are fitted on the 2D-3D matches of the coarse pose's window. Measured on odm 0136: fx 947
    (calibrated 912), k1 -0.22 (-0.26), 4.7 m (the searched focal and the render stage instead:
    38.7 m; docs/BENCHMARKS.md)."""
    cdir = FRAMES_DEV / "odm"
    frame, cam, truth = bench.case_frames("odm")[0]
    maps = bench.build_case_map(cdir / "map_ortho.tif", cdir / "elevation.tif", tmp_path / "map")
    rec = bench.ours(frame, None, maps, {"direct": {"whole_map_first_px": 0}})
    pos, rot = bench.pose_errors(rec.get("R_world_to_cam"), rec.get("camera_center_xyz"), truth)
    fm = rec["focal_from_matches"]
    print(frame.stem, rec["status"], f"{pos:.2f} m {rot:.3f} deg", fm)
    assert rec["status"] == "registered" and fm["where"] == "coarse-window" and fm["fitted"]
    assert rec["intrinsics"]["fx"] == pytest.approx(cam["fx"], rel=0.1)
    assert -0.35 < rec["intrinsics"]["dist"][0] < -0.1  # the lens' barrel distortion (-0.26)
    assert pos < 10.0 and rot < 2.0, (pos, rot)
