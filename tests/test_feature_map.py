"""Feature maps as a map layer (issue 33): bad input is one clear error naming the file."""

from __future__ import annotations

import numpy as np
import pytest

from georeg.frames.feature_map import descriptor_path, load_feature_maps, write_feature_map
from georeg.io.errors import InputError

CRS = "EPSG:32615"
BOUNDS = (500_000.0, 4_000_000.0, 501_000.0, 4_001_000.0)


def _map(tmp_path, name="fm.laz", crs=CRS, x0=500_100.0, n=200):
    rng = np.random.default_rng(0)
    xyz = np.c_[rng.uniform(x0, x0 + 300, n), rng.uniform(4_000_100, 4_000_400, n), rng.uniform(0, 20, n)]
    p = tmp_path / name
    write_feature_map(p, xyz, rng.integers(0, 255, (n, 3)), rng.integers(0, 120, (n, 128)), crs)
    return p, xyz


def test_roundtrip_and_concatenation(tmp_path):
    a, xa = _map(tmp_path, "a.laz")
    b, xb = _map(tmp_path, "b.laz", n=50)
    fm = load_feature_maps([a, b], CRS, BOUNDS)
    assert len(fm) == 250 and fm.desc.shape == (250, 128)
    assert np.allclose(fm.xyz, np.r_[xa, xb], atol=1e-3)
    assert load_feature_maps([], CRS) is None


def test_feature_map_of_another_crs(tmp_path):
    p, _ = _map(tmp_path, crs="EPSG:32616")
    with pytest.raises(InputError, match=r"fm.laz: the feature map is in .*16N.*the map in .*15N"):
        load_feature_maps([p], CRS, BOUNDS)


def test_missing_descriptor_file(tmp_path):
    p, _ = _map(tmp_path)
    descriptor_path(p).unlink()
    with pytest.raises(InputError, match="fm_descriptors.npy: the feature map's descriptor file is missing"):
        load_feature_maps([p], CRS, BOUNDS)


def test_descriptors_that_do_not_fit(tmp_path):
    p, _ = _map(tmp_path)
    np.save(descriptor_path(p), np.zeros((10, 128), np.uint8))
    with pytest.raises(InputError, match="do not fit the 200 points"):
        load_feature_maps([p], CRS, BOUNDS)


def test_feature_map_off_the_map(tmp_path):
    p, _ = _map(tmp_path, x0=520_000.0)
    with pytest.raises(InputError, match="none of the feature maps' 200 points lies on the orthophoto"):
        load_feature_maps([p], CRS, BOUNDS)


def test_missing_feature_map(tmp_path):
    with pytest.raises(InputError, match="nothere.laz: the feature map does not exist"):
        load_feature_maps([tmp_path / "nothere.laz"], CRS, BOUNDS)


def test_surface_points_meet_the_dsm():
    from rasterio.transform import from_origin

    from georeg.frames.feature_map_grow import surface_points

    z = np.full((200, 200), 10.0)
    z[:, 100:] = 30.0  # a step: the east half 20 m higher
    tr = from_origin(0.0, 200.0, 1.0, 1.0)
    C = np.array([100.0, 100.0, 150.0])
    rng = np.random.default_rng(0)
    d = np.c_[rng.uniform(-0.5, 0.5, 400), rng.uniform(-0.5, 0.5, 400), -np.ones(400)]
    X, ok = surface_points(C, d, (z, ~tr), 0.0)
    expect = np.where(X[:, 0] >= 100, 30.0, 10.0)
    assert ok.mean() > 0.9
    assert np.allclose(X[ok, 2], expect[ok], atol=1e-6)
    # on its ray: X = C + s d
    s = (X[:, 2] - C[2]) / d[:, 2]
    assert np.allclose(X, C + s[:, None] * d)
    Xf, okf = surface_points(C, d, None, 5.0)
    assert okf.all() and np.allclose(Xf[:, 2], 5.0)


def test_grown_map_adds_own_points_and_never_overwrites(tmp_path):
    from georeg.frames.feature_map_grow import grow_feature_map

    a, xa = _map(tmp_path, "used.laz")
    b, xb = _map(tmp_path, "own.laz", n=30, x0=500_500.0)
    out = tmp_path / "grown.laz"
    info = grow_feature_map(out, CRS, [a], own=[b])
    assert info == {"used_points": 200, "own_sfm_points": 30, "points": 230}
    fm = load_feature_maps([out], CRS, BOUNDS)
    assert np.allclose(fm.xyz, np.r_[xa, xb], atol=1e-3)
    assert np.array_equal(fm.desc[:200], load_feature_maps([a], CRS).desc)
    with pytest.raises(InputError, match="overwrite one of its inputs"):
        grow_feature_map(a, CRS, [a])
