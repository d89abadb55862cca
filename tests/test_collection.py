"""Unordered photo collections (issue 33 item 3; georeg.trajectory.collection).

Synthetic: every 8th frame of the small demo video written as PNG photos under shuffled names
(name order is not flight order), plus one photo of no place (blurred noise): the
collection poses the flight's photos within the sequence path's tolerance (tests/test_trajectory:
mean < 2 m, p90 < 3 m, rotation < 1 deg), the noise one is not_found, and listing the photos
in another order gives the same poses. Real (../shared/data/brighton, skipped without it): five
photos of the second half of the flight at half size, as a collection, pose at least as many
photos within 3 m of GPS as each photo alone; the collection's exports load in pycolmap and
parse as ODM's formats."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from test_trajectory import VIDEO

REPO = Path(__file__).resolve().parents[1]
BRIGHTON = REPO.parent / "shared" / "data" / "brighton"
FL = {"refine": {"enabled": False}, "search": {"enabled": False}}


@pytest.fixture(scope="module")
def photo_set(small_demo_map):
    """(maps, photo paths in shuffled-name order, truth by photo name, camera)."""
    import cv2

    from georeg.demo.video import generate_video
    from georeg.frames.localize import MapSources

    tmp, paths, tdir, outs = small_demo_map
    vdir = tmp / "collection_video"
    truth = generate_video(paths["scene"], vdir, VIDEO, seed=10)
    cap = cv2.VideoCapture(str(vdir / "flight.mp4"))
    frames = []
    while True:
        ok, bgr = cap.read()
        if not ok:
            break
        frames.append(bgr)
    take = list(range(0, len(frames), 8))
    names = np.random.default_rng(5).permutation(len(take))  # name order != flight order
    pdir = tmp / "collection_photos"
    pdir.mkdir(exist_ok=True)
    by_name = {}
    for k, i in enumerate(take):
        nm = f"photo_{names[k]:02d}.png"
        cv2.imwrite(str(pdir / nm), frames[i])
        by_name[nm] = truth[i]
    noise = np.random.default_rng(3).integers(0, 256, (VIDEO["height"], VIDEO["width"], 3), dtype=np.uint8)
    cv2.imwrite(str(pdir / "elsewhere.png"), cv2.GaussianBlur(noise, (0, 0), 2.0))  # no place at all
    it = truth[0]["intrinsics"]
    cam = {k: it[k] for k in ("fx", "fy", "cx", "cy", "dist")}
    maps = MapSources(tmp / "index", tdir / "ortho.tif", outs["dsm"], [])
    return maps, sorted(pdir.glob("*.png")), by_name, cam


@pytest.fixture(scope="module")
def collection(photo_set, tmp_path_factory):
    from georeg.trajectory.collection import georeference_collection

    maps, photos, _, cam = photo_set
    out = tmp_path_factory.mktemp("collection")
    order = [str(photos[i]) for i in np.random.default_rng(1).permutation(len(photos))]
    poses = georeference_collection({"images": order, "camera": cam}, maps, FL, {"anchors": 3}, out)
    return out, poses


def test_collection_poses_the_flight_and_not_the_other_place(collection, photo_set):
    from georeg.frames.localize import evaluate

    out, poses = collection
    _, photos, truth, _ = photo_set
    info = json.loads((out / "collection.json").read_text())
    assert [Path(p["image"]).name for p in poses] == sorted(p.name for p in photos)  # name order
    other = next(p for p in poses if Path(p["image"]).name == "elsewhere.png")
    assert other["status"] == "not_found" and other["posed_by"] == "not_found"
    assert info["posed_by"]["sfm+sim3"] >= len(truth) - 1, info["posed_by"]
    assert len(info["anchors"]) >= 2 and info["sim3"]["n_inliers"] >= 50
    ev = [evaluate(p, truth[Path(p["image"]).name])["final"] for p in poses
          if Path(p["image"]).name in truth and p["status"] == "registered"]  # fmt: skip
    assert len(ev) == len(truth)
    pos = np.array([e["position_m"] for e in ev])
    rot = np.array([e["rotation_deg"] for e in ev])
    assert pos.mean() < 2.0 and np.percentile(pos, 90) < 3.0, pos
    assert rot.mean() < 1.0, rot
    sfm = [p for p in poses if p["posed_by"] == "sfm+sim3"]
    assert all(
        p["intrinsics"]["width"] == VIDEO["width"] and p["reprojection_px"] < 2.0 for p in sfm
    )
    # each SfM pose is scored against the map as the single-frame path scores its poses (recorded)
    assert np.median([p["verification"]["score"] for p in sfm]) >= 15, [p["verification"] for p in sfm]
    fc = json.loads((out / "cameras.geojson").read_text())
    assert fc["features"] and (out / "cameras.kml").exists() and (out / "sfm_points.laz").exists()
    assert not (out / ".work").exists()


def test_collection_does_not_depend_on_the_listing_order(collection, photo_set, tmp_path):
    from georeg.trajectory.collection import georeference_collection

    _, poses = collection
    maps, photos, _, cam = photo_set
    again = georeference_collection({"images": [str(p) for p in reversed(photos)], "camera": cam}, maps,
                                    FL, {"anchors": 3}, tmp_path / "out")  # fmt: skip
    assert [p["image"] for p in again] == [p["image"] for p in poses]
    for a, b in zip(poses, again, strict=True):
        assert a["posed_by"] == b["posed_by"]
        if a["status"] == "registered":
            assert np.allclose(a["camera_center_xyz"], b["camera_center_xyz"], atol=1e-6)


def test_duplicate_photo_names_are_refused(tmp_path):
    from georeg.io.errors import InputError
    from georeg.trajectory.collection import collection_photos

    with pytest.raises(InputError, match="twice"):
        collection_photos([str(tmp_path / "a" / "x.jpg"), str(tmp_path / "b" / "x.jpg")])


@pytest.fixture(scope="module")
def brighton(tmp_path_factory):
    """The brighton map, and photos 10-14 (DJI_0027-0031) at half size with their EXIF."""
    if not BRIGHTON.is_dir():
        pytest.skip("../shared/data/brighton is absent")
    import benchmark_module
    from PIL import Image

    from georeg.frames.localize import MapSources

    work = tmp_path_factory.mktemp("brighton_collection")
    maps = benchmark_module.load("bench_frames").build_case_map(
        BRIGHTON / "map_ortho.tif", BRIGHTON / "elevation.tif", work / "map"
    )
    photos = []
    for p in sorted((BRIGHTON / "frames").glob("DJI_*.JPG"))[9:14]:
        with Image.open(p) as im:
            small = im.resize((im.width // 2, im.height // 2), Image.LANCZOS)
            small.save(work / p.name, exif=im.info.get("exif", b""), quality=95)
        photos.append(work / p.name)
    ms = MapSources(maps["index"], maps["ortho"], maps["dsm"])
    return work, ms, photos, json.loads((BRIGHTON / "gps.json").read_text())


@pytest.mark.shared
@pytest.mark.slow
def test_brighton_collection_poses_as_many_as_single_photos_and_exports(brighton):
    from export_checks import check_colmap, check_gcp_list, parse_geo_txt

    from georeg.export.frame_set import export_frame_set
    from georeg.trajectory.collection import georeference_collection

    work, ms, photos, gps = brighton
    fl = _frame_loc()
    order = [str(photos[i]) for i in (3, 0, 4, 2, 1)]
    poses = georeference_collection({"images": order, "camera": None}, ms, fl, {}, work / "coll")

    def h(C, name):
        g = gps["frames"][Path(name).stem]
        return float(np.hypot(*(np.asarray(C[:2]) - g["gps_xy"])))

    coll = sum(
        p["status"] == "registered" and h(p["camera_center_xyz"], p["image"]) < 3.0 for p in poses
    )
    single = sum(p["single_frame"]["status"] == "registered"
                 and h(p["single_frame"]["camera_center_xyz"], p["image"]) < 3.0
                 for p in poses if "single_frame" in p)  # fmt: skip
    print([(Path(p["image"]).name, p["posed_by"], round(h(p["camera_center_xyz"], p["image"]), 2))
           for p in poses if p["status"] == "registered"], single)  # fmt: skip
    assert all(
        "single_frame" in p for p in poses if p["posed_by"] == "sfm+sim3"
    )  # anchors: every photo
    assert coll >= single >= 3
    exp = work / "coll" / "export"
    info = export_frame_set(
        work / "coll" / "poses.json", exp, ms.crs_wkt, sfm_laz=work / "coll" / "sfm_points.laz"
    )
    assert info["odm_ready"], info
    check_gcp_list(exp, poses)
    m = check_colmap(exp / "colmap")
    crs, rows = parse_geo_txt(exp / "geo.txt")
    reg = sum(p["status"] == "registered" for p in poses)
    assert crs.to_epsg() == 32615 and len(rows) == info["registered"] == m["images"] == reg


def _frame_loc() -> dict:
    import yaml

    cfg = yaml.safe_load((REPO / "config" / "config.yaml").read_text())
    return {k: v for k, v in cfg["frame_loc"].items() if k != "demo_frames"}
