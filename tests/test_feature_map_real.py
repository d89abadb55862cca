"""Feature maps and exports on a real flight (../shared/data/brighton: 18 DJI photos in three
strips, GPS kept apart as rough truth, a photogrammetric map of the same flight).

The first 9 photos (strip 1 and half of strip 2) as an ordered sequence build the feature map
(rule trajectory's pipeline), as in benchmarks/bench_feature_maps.py; three of the other photos
(one of strip 2, two of strip 3) are localised alone, map-only and against the feature map. The feature-map path must register at least as many, within the map-only path's distance of
GPS (+ 1 m) and within 10 m of GPS; its pose is verified against the map (score recorded).
The sequence's exports load in pycolmap (reprojection RMS < 2 px) and parse as ODM's formats
(every gcp_list row within 2 px through its pose, >= 5 points each in >= 3 images); a grown
feature map adds the single photos' points to the sequence's."""

from __future__ import annotations

import json
from pathlib import Path

import benchmark_module
import numpy as np
import pytest
import yaml

REPO = Path(__file__).resolve().parents[1]
BRIGHTON = REPO.parent / "shared" / "data" / "brighton"

pytestmark = [
    pytest.mark.shared,
    pytest.mark.slow,
    pytest.mark.skipif(not BRIGHTON.is_dir(), reason="../shared/data/brighton is absent"),
]


def _conf() -> tuple[dict, dict]:
    cfg = yaml.safe_load((REPO / "config" / "config.yaml").read_text())
    return ({k: v for k, v in cfg["frame_loc"].items() if k != "demo_frames"},
            {k: v for k, v in cfg["trajectory"].items() if k != "demo_video"})  # fmt: skip


def _gps_h(rec: dict, gps: dict) -> float:
    g = gps["frames"][Path(rec["image"]).stem]
    return float(np.hypot(*(np.asarray(rec["camera_center_xyz"][:2]) - g["gps_xy"])))


@pytest.fixture(scope="module")
def flight(tmp_path_factory):
    from georeg.frames.localize import MapSources
    from georeg.trajectory.pipeline import georeference_video

    work = tmp_path_factory.mktemp("brighton")
    bench = benchmark_module.load("bench_frames")
    maps = bench.build_case_map(BRIGHTON / "map_ortho.tif", BRIGHTON / "elevation.tif", work / "map")
    ms = MapSources(maps["index"], maps["ortho"], maps["dsm"])
    fl, tr = _conf()
    photos = sorted((BRIGHTON / "frames").glob("DJI_*.JPG"))
    seq = georeference_video({"images": [str(p) for p in photos[:9]], "trajectory": True, "camera": None,
                              "fps": 1.0}, ms, fl, tr, work / "sequence")  # fmt: skip
    return {"work": work, "maps": maps, "ms": ms, "fl": fl, "seq": seq, "photos": photos,
            "gps": json.loads((BRIGHTON / "gps.json").read_text())}  # fmt: skip


def test_feature_map_path_on_a_later_strip(flight):
    from georeg.frames.feature_map import load_feature_maps
    from georeg.frames.localize import localize_frame

    ms, fl, gps = flight["ms"], flight["fl"], flight["gps"]
    assert sum(p["status"] == "registered" for p in flight["seq"]) >= 7
    fmap = load_feature_maps([flight["work"] / "sequence" / "sfm_points.laz"], ms.crs_wkt, ms.bounds())
    served = 0
    for photo in (flight["photos"][9], flight["photos"][12], flight["photos"][16]):
        ms.feature_map = None
        base, _ = localize_frame(str(photo), None, ms, fl)
        ms.feature_map = fmap
        rec, _ = localize_frame(str(photo), None, ms, fl)
        ms.feature_map = None
        print(photo.name, base["status"], base.get("path"), rec["status"], rec.get("path"), rec["feature_map"])
        assert "feature_map" in rec and ("used" in rec["feature_map"])
        if base["status"] == "registered":
            assert rec["status"] == "registered"
        if rec["status"] == "registered":
            h = _gps_h(rec, gps)
            assert h < 10.0
            if base["status"] == "registered":
                assert h <= _gps_h(base, gps) + 1.0
        if str(rec.get("path", "")).startswith("feature map"):
            served += 1
            assert rec["verification"]["score"] >= int(fl["min_inliers"])
            fm = rec["feature_map"]  # polished on the map when that verifies 1.5 x higher (or strong)
            assert fm["polished"] >= (fm["polished_score"] >= 1.5 * max(fm["raw_score"], 1))
            assert not fm["polished"] or fm["polished_score"] > fm["raw_score"]
            # on this small map (whole-map matching is the cheap map-only path) only a strong one
            # ends the search, a weaker one competed with the map-only poses and won
            assert fm["served"] == fm["strong"] and (fm["score"] >= 100 or not fm["strong"])
            if fm["served"]:
                assert rec["coarse"]["reason"].startswith("not run: the feature map")
                assert "direct_attempts" not in rec and "pnp_attempts" not in rec
    assert served >= 1


def test_exports_of_the_flight_load_in_colmap_and_odm(flight, tmp_path):
    from export_checks import check_colmap, check_gcp_list, parse_geo_txt

    from georeg.export.frame_set import export_frame_set

    seq_dir = flight["work"] / "sequence"
    info = export_frame_set(seq_dir / "poses.json", tmp_path / "export", flight["ms"].crs_wkt,
                            sfm_laz=seq_dir / "sfm_points.laz")  # fmt: skip
    assert info["odm_ready"]
    g = check_gcp_list(tmp_path / "export", flight["seq"])
    m = check_colmap(tmp_path / "export" / "colmap")
    crs, rows = parse_geo_txt(tmp_path / "export" / "geo.txt")
    assert crs.to_epsg() == 32615 and len(rows) == info["registered"] == m["images"]
    print(info, g, m)


def test_grown_feature_map_adds_the_single_photos(flight, tmp_path):
    from georeg.frames.feature_map import load_feature_maps
    from georeg.frames.feature_map_grow import grow_feature_map
    from georeg.frames.localize import localize_frame
    from georeg.io.atomic import write_json

    ms, fl = flight["ms"], flight["fl"]
    laz = flight["work"] / "sequence" / "sfm_points.laz"
    rec, _ = localize_frame(str(flight["photos"][9]), None, ms, fl)
    assert rec["status"] == "registered"
    write_json(tmp_path / "poses.json", [rec])
    info = grow_feature_map(tmp_path / "feature_map.laz", ms.crs_wkt, [laz], poses_json=tmp_path / "poses.json",
                            dsm=flight["maps"]["dsm"])  # fmt: skip
    base = load_feature_maps([laz], ms.crs_wkt)
    grown = load_feature_maps([tmp_path / "feature_map.laz"], ms.crs_wkt, ms.bounds())
    assert info["own_frame_points"] > 100 and len(grown) == len(base) + info["own_frame_points"]
