"""A query file without nodata: its dark fill (a rotated JPEG's black corners) is not the scene."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from georeg.io.query import open_query
from georeg.register.band import border_fill, select_band


def _rotated_jpeg(tmp_path, angle: float = 30.0, floor: int = 0):
    """A textured 240 px image (values from ``floor``) rotated by ``angle`` with black corners,
    saved as a JPEG (noisy zeros); returns the path and the true fill (before compression)."""
    rng = np.random.default_rng(3)
    img = cv2.GaussianBlur(rng.uniform(0, 255, (240, 240)).astype(np.float32), (0, 0), 3)
    img = cv2.normalize(img, None, 60, 250, cv2.NORM_MINMAX)
    img = np.clip(img, floor, 255).astype(np.uint8)
    R = cv2.getRotationMatrix2D((119.5, 119.5), angle, 0.8)
    rot = cv2.warpAffine(img, R, (240, 240), flags=cv2.INTER_LINEAR, borderValue=0)
    inside = cv2.warpAffine(np.ones_like(img), R, (240, 240), flags=cv2.INTER_NEAREST) > 0
    path = tmp_path / "q.jpg"
    cv2.imwrite(str(path), rot, [cv2.IMWRITE_JPEG_QUALITY, 85])
    return path, ~inside


def test_rotated_jpeg_corners_are_masked(tmp_path):
    path, truth = _rotated_jpeg(tmp_path)
    band, mask, info = select_band(open_query(path), 0)
    fill = ~mask
    assert truth.mean() > 0.1
    # the fill masked (but for a few pixels its edge's interpolation blends with the scene); the
    # content lost is the ring the compression smears
    assert (truth & mask).sum() <= 0.01 * truth.sum()
    ring = cv2.dilate(truth.astype(np.uint8), np.ones((9, 9), np.uint8)) > 0
    assert (fill & ~ring).sum() == 0
    assert info["fill_fraction"] == pytest.approx(fill.mean(), abs=1e-3)


def test_dark_content_is_not_fill():
    """A scene whose darkest pixels are far from zero (no fill), and one whose dark patch does
    not reach the edge, keep every pixel."""
    rng = np.random.default_rng(5)
    band = cv2.GaussianBlur(rng.uniform(80, 200, (200, 200)).astype(np.float32), (0, 0), 2)
    assert not border_fill(band, np.ones(band.shape, bool)).any()
    band[60:140, 60:140] = 0.0  # a black lake in the middle
    assert not border_fill(band, np.ones(band.shape, bool)).any()


def test_srif_query_fill_matches_its_valid_area(shared_data):
    """SRIF's optical-infrared queries (rotated, black fill, JPEG): the fill found agrees with the
    benchmark's own mask of them (blur > 3, eroded) within 1.5 % of the image."""
    d = shared_data / "srif_dev" / "Optical-Infrared"
    for i in (1, 29, 113):
        q = cv2.imread(str(d / f"pair{i}_2.jpg"), cv2.IMREAD_GRAYSCALE)
        ref = cv2.erode((cv2.blur(q, (5, 5)) > 3).astype(np.uint8), np.ones((5, 5), np.uint8)) > 0
        fill = border_fill(q.astype(np.float32), np.ones(q.shape, bool))
        assert (~ref).mean() > 0.1
        assert np.mean(fill != ~ref) < 0.015


def test_enmap_lakes_are_not_fill(shared_data):
    """A float cube without nodata (the EnMAP Potsdam tile): its lakes touch the edge and are
    near zero in the SWIR, but only an 8-bit file's border is taken for fill."""
    p = shared_data / "enmap_potsdam" / "enmap_potsdam_mosaic_subset.tif"
    cube = open_query(p)
    assert cube.nodata is None
    band, mask, info = select_band(cube, "1650nm")
    assert "fill_fraction" not in info
    assert mask.sum() == np.isfinite(band).sum()
