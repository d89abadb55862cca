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
