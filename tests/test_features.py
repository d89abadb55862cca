"""Map features: map coordinates, elevations, overlap handling, descriptor variants."""

from __future__ import annotations

import numpy as np
import pytest
import rasterio
from rasterio.transform import Affine

from georeg.index.features import (
    DESC_SCALE,
    dequantize,
    detect_and_describe,
    extract_tile,
    load_tile_features,
    map_to_pixel,
    merged_conf,
    pixel_to_map,
    quantize_desc,
    rgb_to_gray,
    sample_bilinear,
    save_tile_features,
    tile_features,
)

CONF = merged_conf({"max_features_per_mpx": None})
# a non-trivial geotransform: rotated and sheared, non-square pixels, far from the origin
TRANSFORM = Affine(0.48, 0.07, 512345.25, 0.05, -0.52, 4181234.75)


def _blobs(h: int, w: int, centres: list[tuple[float, float]], sigma: float = 3.0) -> np.ndarray:
    yy, xx = np.mgrid[0:h, 0:w].astype(np.float64)
    img = np.full((h, w), 50.0)
    for cx, cy in centres:
        img += 160 * np.exp(-((xx - cx) ** 2 + (yy - cy) ** 2) / (2 * sigma**2))
    return np.clip(img, 0, 255).astype(np.uint8)


def _texture(h: int, w: int, seed: int) -> np.ndarray:
    """Random rectangles and discs: a SIFT-rich, non-repetitive synthetic 'city'."""
    import cv2

    rng = np.random.default_rng(seed)
    img = np.full((h, w), 110, np.uint8)
    for _ in range(h * w // 900):
        x, y = int(rng.integers(0, w)), int(rng.integers(0, h))
        c = int(rng.integers(0, 256))
        if rng.random() < 0.5:
            dx, dy = (int(v) for v in rng.integers(4, 30, 2))
            cv2.rectangle(img, (x, y), (x + dx, y + dy), c, -1)
        else:
            cv2.circle(img, (x, y), int(rng.integers(3, 14)), c, -1)
    return cv2.GaussianBlur(img, (0, 0), 1.0)


def _write(path, arr: np.ndarray, transform: Affine, nodata=None) -> None:
    arr = arr if arr.ndim == 3 else arr[None]
    with rasterio.open(
        path,
        "w",
        driver="GTiff",
        width=arr.shape[2],
        height=arr.shape[1],
        count=arr.shape[0],
        dtype=arr.dtype,
        crs="EPSG:32611",
        transform=transform,
        nodata=nodata,
    ) as ds:
        ds.write(arr)


def test_pixel_map_roundtrip():
    col, row = np.array([0.0, 10.25, -3.5]), np.array([0.0, 7.75, 100.0])
    x, y = pixel_to_map(TRANSFORM, col, row)
    # pixel-centre convention: the centre of pixel (0, 0) is transform * (0.5, 0.5)
    assert (x[0], y[0]) == pytest.approx(TRANSFORM @ (0.5, 0.5))
    c2, r2 = map_to_pixel(TRANSFORM, x, y)
    np.testing.assert_allclose(c2, col, atol=1e-9)
    np.testing.assert_allclose(r2, row, atol=1e-9)


def test_blob_keypoints_land_at_known_map_coordinates(tmp_path):
    centres = [(40.3, 50.7), (130.6, 45.2), (85.45, 120.85), (160.1, 140.4)]
    gray = _blobs(180, 200, centres)
    rgb = np.stack([gray, gray, gray])
    _write(tmp_path / "ortho.tif", rgb, TRANSFORM)
    tf, meta = extract_tile(tmp_path / "ortho.tif", CONF)
    assert meta["n"] == len(tf) > 0
    gsd = float(np.sqrt(abs(TRANSFORM.determinant)))
    for cx, cy in centres:
        tx, ty = TRANSFORM @ (cx + 0.5, cy + 0.5)  # known map location of the blob centre
        d = np.hypot(tf.xy[:, 0] - tx, tf.xy[:, 1] - ty)
        # within a tenth of a pixel (a half-pixel convention error or OpenCV's +0.25 px
        # first-octave bias would fail this)
        assert d.min() < 0.1 * gsd, (cx, cy, d.min() / gsd)


def test_blob_coordinates_at_coarser_feature_gsd(tmp_path):
    """Extraction at a coarser feature GSD (a pyramid level) still maps to the right place."""
    centres = [(60.0, 70.0), (250.5, 90.5), (160.0, 220.0)]
    gray = _blobs(300, 320, centres, sigma=6.0)
    tr = Affine(0.5, 0.0, 1000.0, 0.0, -0.5, 2000.0)
    conf = merged_conf({"gsd_m": 1.0, "max_features_per_mpx": None})
    tf = tile_features(gray, None, tr, conf)
    for cx, cy in centres:
        tx, ty = tr @ (cx + 0.5, cy + 0.5)
        d = np.hypot(tf.xy[:, 0] - tx, tf.xy[:, 1] - ty)
        assert d.min() < 0.1, d.min()  # metres; feature pixels are 1 m
    assert np.median(tf.scale) > 4.0  # keypoint diameters in metres, not feature pixels


def test_elevations_agree_with_dsm(tmp_path):
    gray = _texture(160, 200, seed=3)
    _write(tmp_path / "ortho.tif", np.stack([gray] * 3), TRANSFORM)
    # DSM/nDSM on their own (coarser, larger) grid; planes so that bilinear sampling is exact
    dtr = Affine(1.1, 0.0, 512300.0, 0.0, -1.1, 4181300.0)
    yy, xx = np.mgrid[0:200, 0:200].astype(np.float64)
    gx, gy = dtr @ (xx + 0.5, yy + 0.5)
    dsm = (100 + 0.02 * (gx - 512300) - 0.03 * (gy - 4181000)).astype(np.float32)
    ndsm = (5 + 0.01 * (gx - 512300)).astype(np.float32)
    dsm[:3, :3] = -9999  # a nodata corner far from the ortho
    _write(tmp_path / "dsm.tif", dsm, dtr, nodata=-9999)
    _write(tmp_path / "ndsm.tif", ndsm, dtr)
    tf, _ = extract_tile(
        tmp_path / "ortho.tif", CONF, None, tmp_path / "dsm.tif", tmp_path / "ndsm.tif"
    )
    assert len(tf) > 50
    x, y = tf.xy[:, 0], tf.xy[:, 1]
    np.testing.assert_allclose(tf.z, 100 + 0.02 * (x - 512300) - 0.03 * (y - 4181000), atol=1e-3)
    np.testing.assert_allclose(tf.ndsm, 5 + 0.01 * (x - 512300), atol=1e-3)


def test_sample_bilinear_nodata_falls_back_to_nearest():
    band = np.array([[1.0, 2.0], [3.0, -9999.0]], np.float32)
    v = sample_bilinear(band, np.array([0.5, 0.1, 5.0]), np.array([0.5, 0.1, 0.0]), -9999.0)
    assert np.isnan(v[0]) or v[0] == -9999.0 or v[0] in (1.0, 2.0, 3.0)
    assert v[1] == pytest.approx(1.0)  # nearest valid pixel (0, 0)
    assert np.isnan(v[2])  # outside


def test_overlap_keypoints_kept_once():
    gray = _texture(256, 520, seed=5)
    tr = Affine(1.0, 0.0, 0.0, 0.0, -1.0, 256.0)
    overlap, split = 80, 260
    # tile A = cols [0, split + overlap/2), tile B = cols [split - overlap/2, 520)
    a0, a1, b0, b1 = 0, split + overlap // 2, split - overlap // 2, 520
    ta, tb = tr @ Affine.translation(a0, 0), tr @ Affine.translation(b0, 0)
    core_a = (0, 0, split - a0, 256)
    core_b = (split - b0, 0, b1 - split, 256)
    fa = tile_features(gray[:, a0:a1], None, ta, CONF, core_a)
    fb = tile_features(gray[:, b0:b1], None, tb, CONF, core_b)
    assert fa.xy[:, 0].max() < split <= fb.xy[:, 0].min()

    def cross_duplicates(p: np.ndarray, q: np.ndarray) -> int:
        d = np.hypot(p[:, None, 0] - q[None, :, 0], p[:, None, 1] - q[None, :, 1])
        return int((d < 0.5).sum())

    assert cross_duplicates(fa.xy, fb.xy) == 0
    # without the core windows the overlap would be counted twice (the check above can fail)
    ua = tile_features(gray[:, a0:a1], None, ta, CONF)
    ub = tile_features(gray[:, b0:b1], None, tb, CONF)
    assert cross_duplicates(ua.xy, ub.xy) > 20
    # and the union matches what the whole image gives away from the tile borders
    whole = tile_features(gray, None, tr, CONF)
    union = np.concatenate([fa.xy, fb.xy])
    inner = whole.xy[(whole.xy[:, 0] > split - 15) & (whole.xy[:, 0] < split + 15)]
    d = np.hypot(inner[:, None, 0] - union[None, :, 0], inner[:, None, 1] - union[None, :, 1])
    assert (d.min(axis=1) < 0.5).mean() > 0.9


@pytest.mark.parametrize("rootsift", [False, True])
def test_descriptors_unit_norm_and_quantisation(rootsift):
    gray = _texture(128, 128, seed=1)
    f = detect_and_describe(gray, None, merged_conf({"rootsift": rootsift}))
    assert f.desc.dtype == np.float32 and f.desc.shape[1] == 128 and len(f) > 10
    np.testing.assert_allclose(np.linalg.norm(f.desc, axis=1), 1.0, atol=1e-4)
    back = dequantize(quantize_desc(f.desc))
    assert np.abs(back - f.desc).max() < 1.0 / DESC_SCALE + 1e-3 or rootsift
    assert np.linalg.norm(back - f.desc, axis=1).mean() < 0.02


def test_upright_sets_angles_to_zero_and_float_input():
    gray = _texture(128, 128, seed=2)
    f = detect_and_describe(gray.astype(np.float32) * 10.0, None, merged_conf({"upright": True}))
    assert len(f) > 10 and np.all(f.angle == 0)
    # no duplicated keypoints (SIFT's one-per-orientation copies are collapsed)
    assert len(np.unique(f.xy, axis=0)) == len(f)


def test_mask_and_cap():
    gray = _texture(200, 200, seed=4)
    mask = np.zeros_like(gray, bool)
    mask[:, :100] = True
    f = detect_and_describe(gray, mask, CONF)
    assert len(f) > 0 and f.xy[:, 0].max() < 100
    capped = detect_and_describe(gray, None, merged_conf({"max_features_per_mpx": 2500}))
    assert 0 < len(capped) <= int(np.ceil(2500 * 200 * 200 / 1e6)) + 5


def test_rgb_to_gray_luminance_and_band_order():
    rgb = np.zeros((3, 4, 5), np.uint8)
    rgb[1] = 200
    g = rgb_to_gray(rgb)
    assert g.shape == (4, 5) and g.dtype == np.uint8 and abs(int(g[0, 0]) - 117) <= 1
    np.testing.assert_array_equal(rgb_to_gray(np.moveaxis(rgb, 0, -1)), g)


def test_save_load_tile_roundtrip(tmp_path):
    gray = _texture(96, 96, seed=6)
    tf = tile_features(gray, None, TRANSFORM, CONF)
    save_tile_features(tmp_path / "t", tf, {"n": len(tf)})
    back, meta = load_tile_features(tmp_path / "t")
    assert meta["n"] == len(tf)
    for name in ("xy", "z", "scale", "desc"):
        np.testing.assert_array_equal(np.asarray(getattr(back, name)), getattr(tf, name))
    assert back.xy.dtype == np.float64 and back.desc.dtype == np.uint8
