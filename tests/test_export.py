"""Exports of a registered frame set: ODM gcp_list.txt / geo.txt, the COLMAP text model.

Synthetic poses (a strip of oblique and nadir views with distortion, one localised on a pyramid
level) and points; the checks are independent of the exporter (tests/export_checks.py)."""

from __future__ import annotations

import json

import numpy as np
import pytest
import rasterio
from export_checks import check_colmap, check_gcp_list, parse_geo_txt
from rasterio.transform import from_origin

from georeg.export.colmap import quaternion
from georeg.export.frame_set import export_frame_set
from georeg.trajectory.outputs import write_point_map

CRS = "EPSG:32615"
X0, Y0 = 500_000.0, 4_000_000.0


def _look_at(C, target, up=(0, 1, 0)):
    z = np.asarray(target, float) - C
    z /= np.linalg.norm(z)
    x = np.cross(z, up)
    if np.linalg.norm(x) < 1e-6:
        x = np.cross(z, (1, 0, 0))
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    return np.array([x, y, z])


def _poses(n=6, pyramid=True) -> list[dict]:
    rng = np.random.default_rng(3)
    out = []
    for i in range(n):
        C = np.array([X0 + 20.0 * i, Y0 + rng.normal(0, 2), 120.0 + rng.normal(0, 2)])
        R = _look_at(C, [X0 + 20.0 * i + 40 * (i % 2), Y0 + 30, 10.0])
        rec = {"image": f"IMG_{i:04d}.JPG", "status": "registered", "camera_center_xyz": C.tolist(),
               "R_world_to_cam": R.tolist(),
               "intrinsics": {"fx": 800.0, "fy": 800.0, "cx": 479.3, "cy": 359.6,
                              "dist": [-0.08, 0.02, 0.0004, -0.0002, 0.0], "width": 960, "height": 720}}  # fmt: skip
        if pyramid and i == 2:  # localised on level 1 of a 1920 x 1440 photo
            rec["pyramid"] = {"level": 1, "full_size": [1920, 1440], "size": [960, 720], "scale": 0.5}
        out.append(rec)
    out.append({"image": "IMG_lost.JPG", "status": "not_found", "camera_center_xyz": None,
                "R_world_to_cam": None})  # fmt: skip
    return out


def _write(tmp_path, poses):
    p = tmp_path / "poses.json"
    p.write_text(json.dumps(poses))
    return p


@pytest.mark.parametrize("R", [np.eye(3), np.diag([1, -1, -1]), np.diag([-1, 1, -1]), np.diag([-1, -1, 1])])
def test_quaternion_roundtrip(R):
    from scipy.spatial.transform import Rotation

    rng = np.random.default_rng(0)
    for Rr in [R, *Rotation.random(20, random_state=rng).as_matrix()]:
        q = quaternion(Rr)
        back = Rotation.from_quat([q[1], q[2], q[3], q[0]]).as_matrix()
        assert np.allclose(back, Rr, atol=1e-9)


def test_export_from_sfm_points(tmp_path):
    import pycolmap

    poses = _poses()
    rng = np.random.default_rng(1)
    xyz = np.c_[rng.uniform(X0 - 60, X0 + 160, 3000), rng.uniform(Y0 - 40, Y0 + 100, 3000),
                rng.uniform(5, 25, 3000)]  # fmt: skip
    laz = tmp_path / "sfm_points.laz"
    write_point_map(laz, xyz, rng.integers(0, 255, (3000, 3)), np.full(3000, 4), np.zeros((3000, 128)), CRS)
    out = tmp_path / "export"
    info = export_frame_set(_write(tmp_path, poses), out, CRS, sfm_laz=laz)
    assert info["registered"] == 6 and info["odm_ready"] and info["gcps"] >= 5
    g = check_gcp_list(out, poses)
    assert g["points"] == info["gcps"]
    m = check_colmap(out / "colmap")
    assert m["images"] == 6 and m["points"] == info["model_points"] > 100
    # the model's camera centres and the full-size camera go back to poses.json
    rec = pycolmap.Reconstruction(str(out / "colmap"))
    geo = json.loads((out / "colmap" / "georef.json").read_text())
    by = {p["image"]: p for p in poses}
    for img in rec.images.values():
        C = np.asarray(img.projection_center()) / geo["unit_m"] + geo["offset_xyz"]
        assert np.allclose(C, by[img.name]["camera_center_xyz"], atol=1e-4)
    big = rec.find_image_with_name("IMG_0002.JPG")
    assert (big.camera.width, big.camera.height) == (1920, 1440)
    assert big.camera.focal_length_x == pytest.approx(1600.0)
    crs, geo_rows = parse_geo_txt(out / "geo.txt")
    assert crs.to_epsg() == 32615 and set(geo_rows) == {f"IMG_{i:04d}.JPG" for i in range(6)}
    assert geo_rows["IMG_0001.JPG"][:3] == pytest.approx(by["IMG_0001.JPG"]["camera_center_xyz"], abs=1e-3)


def test_export_from_map_corners_with_occlusion(tmp_path):
    """Single frames: orthophoto corners with DSM heights; a tall block hides what is behind it."""
    poses = _poses(pyramid=False)
    rng = np.random.default_rng(2)
    h, w, px = 400, 600, 0.5
    tr = from_origin(X0 - 100, Y0 + 150, px, px)
    img = (rng.random((3, h, w)) > 0.97).astype(np.uint8) * 200 + 30
    img = np.repeat(np.repeat(img[:, ::4, ::4], 4, 1), 4, 2)[:, :h, :w].astype(np.uint8)
    dsm = np.full((h, w), 10.0, np.float32)
    dsm[150:200, 300:330] = 60.0  # a 50 m block
    kw = {"driver": "GTiff", "height": h, "width": w, "crs": CRS, "transform": tr}
    with rasterio.open(tmp_path / "o.tif", "w", count=3, dtype="uint8", **kw) as ds:
        ds.write(img)
    with rasterio.open(tmp_path / "d.tif", "w", count=1, dtype="float32", **kw) as ds:
        ds.write(dsm, 1)
    out = tmp_path / "export"
    info = export_frame_set(_write(tmp_path, poses), out, CRS, ortho=tmp_path / "o.tif",
                            dsm=tmp_path / "d.tif")  # fmt: skip
    assert info["odm_ready"], info
    check_gcp_list(out, poses)
    check_colmap(out / "colmap")
    # no exported observation is hidden by the block
    from georeg.export.points import read_map_window, unoccluded
    from georeg.export.views import views_from_poses

    win = read_map_window(tmp_path / "o.tif", tmp_path / "d.tif", (X0 - 100, Y0 - 50, X0 + 200, Y0 + 150), 0.0)
    vis = unoccluded(win, 1.0)
    views = {v.name: v for v in views_from_poses(poses)}
    for line in (out / "gcp_list.txt").read_text().split("\n")[1:]:
        if line:
            f = line.split()
            X = np.array([[float(f[0]), float(f[1]), float(f[2])]])
            assert vis(views[f[5]], X, np.array([True]))[0]


def test_too_few_views_is_recorded_not_hidden(tmp_path):
    poses = _poses(n=2)
    rng = np.random.default_rng(1)
    xyz = np.c_[rng.uniform(X0, X0 + 40, 500), rng.uniform(Y0, Y0 + 60, 500), np.full(500, 10.0)]
    laz = tmp_path / "sfm_points.laz"
    write_point_map(laz, xyz, np.zeros((500, 3)), np.full(500, 2), np.zeros((500, 128)), CRS)
    info = export_frame_set(_write(tmp_path, poses), tmp_path / "e", CRS, sfm_laz=laz)
    assert not info["odm_ready"] and "ODM needs 5" in info["reason"]
    assert (tmp_path / "e" / "gcp_list.txt").read_text().strip() == "EPSG:32615"


def test_bad_poses_file_names_the_file(tmp_path):
    from georeg.io.errors import InputError

    p = tmp_path / "poses.json"
    p.write_text("{not json")
    with pytest.raises(InputError, match="poses.json"):
        export_frame_set(p, tmp_path / "e", CRS)
    poses = _poses(n=3)
    del poses[1]["intrinsics"]
    with pytest.raises(InputError, match="no intrinsics"):
        export_frame_set(_write(tmp_path, poses), tmp_path / "e", CRS)
