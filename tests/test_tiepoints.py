"""Tie-point primitives (georeg.register.tiepoints): sub-pixel peaks, neighbour consistency."""

import numpy as np

from georeg.register.tiepoints import consistent, quad_peaks


def test_quad_peaks_find_the_maximum_of_sampled_quadratics():
    rng = np.random.default_rng(3)
    yy, xx = np.mgrid[-1:2, -1:2]
    centre = rng.uniform(-0.45, 0.45, (200, 2))
    a = rng.uniform(0.5, 2.0, (200, 2))
    b = rng.uniform(-0.3, 0.3, 200)  # a tilted bowl, still a maximum
    dx, dy = xx[None] - centre[:, 0, None, None], yy[None] - centre[:, 1, None, None]
    s = 5.0 - a[:, 0, None, None] * dx**2 - a[:, 1, None, None] * dy**2 - b[:, None, None] * dx * dy
    np.testing.assert_allclose(quad_peaks(s), centre, atol=1e-9)


def test_quad_peaks_fall_back_to_parabolas_without_a_maximum():
    saddle = np.array([[0.0, 1.0, 0.0], [-1.0, 0.0, -1.0], [0.0, 1.0, 0.0]])  # max along y, min along x
    d = quad_peaks(saddle[None])[0]
    assert d[0] == 0.0  # no maximum across x: no shift
    assert d[1] == 0.0  # the y parabola opens upwards (lo + hi > 2 c): no maximum either
    ridge = np.array([[0.0, 0.5, 0.0], [0.0, 1.0, 0.0], [0.0, 0.9, 0.0]])
    d = quad_peaks(ridge[None])[0]
    assert 0.0 < d[1] <= 0.5  # the peak leans towards the higher neighbour below


def test_consistent_flags_the_vectors_that_disagree_with_their_neighbours():
    rng = np.random.default_rng(5)
    g = np.stack(np.meshgrid(np.arange(0, 480, 12.0), np.arange(0, 360, 12.0)), -1).reshape(-1, 2)
    vec = 0.002 * g + rng.normal(0, 0.05, g.shape)  # a smooth field
    bad = rng.choice(len(g), 40, replace=False)
    vec[bad] += rng.choice([-1, 1], (40, 2)) * 2.0
    ok = consistent(g, vec, 30.0, 0.6)
    assert not ok[bad].any()
    assert ok[np.setdiff1d(np.arange(len(g)), bad)].mean() > 0.98
    lone = consistent(np.array([[0.0, 0.0], [500.0, 0.0], [0.0, 500.0]]), np.eye(3)[:, :2] * 9, 30.0, 0.6)
    assert lone.all()  # no neighbours: nothing to disagree with


def test_a_coarse_sampling_renders_the_maps_area_mean():
    """A query pixel covering 4 x 4 map pixels sees their mean, not a bilinear pick of the
    central four (white noise: the pick's error is ~sigma/2, the area mean's spread sigma/4)."""
    from rasterio.transform import Affine

    from georeg.register.tiepoints import MapImage

    rng = np.random.default_rng(5)
    n, k = 256, 4
    gray = rng.normal(100.0, 20.0, (n, n)).astype(np.float32)
    truth = gray.reshape(n // k, k, n // k, k).mean(axis=(1, 3))
    mi = MapImage(gray, Affine(1.0, 0, 0.0, 0, -1.0, float(n)))
    centres = (np.arange(n // k) + 0.5) * k  # map x of each block's centre
    x, y = centres[None, :], float(n) - centres[:, None]
    x, y = np.broadcast_arrays(x, y)
    out = mi.render(x, y)
    inner = (slice(3, -3), slice(3, -3))
    err = np.sqrt(np.nanmean((out[inner] - truth[inner]) ** 2))
    picks = 0.25 * (gray[1::k, 1::k] + gray[1::k, 2::k] + gray[2::k, 1::k] + gray[2::k, 2::k])
    err_pick = np.sqrt(np.mean((picks[inner] - truth[inner]) ** 2))
    assert err < 0.6 * err_pick, (err, err_pick)
    # one map px per sample: plain bilinear, exactly the map at pixel centres
    xs, ys = np.meshgrid(np.arange(n) + 0.5, float(n) - (np.arange(n) + 0.5))
    assert np.allclose(mi.render(xs, ys), gray, atol=1e-3)


def test_the_low_pass_keeps_nodata_out_of_the_values():
    """Nodata next to valid pixels neither darkens them nor spreads: a constant map with a hole
    renders the constant right up to the hole, NaN inside it."""
    from rasterio.transform import Affine

    from georeg.register.tiepoints import MapImage

    n = 128
    gray = np.full((n, n), 50.0, np.float32)
    gray[40:80, 40:80] = np.nan
    mi = MapImage(gray, Affine(1.0, 0, 0.0, 0, -1.0, float(n)))
    c = np.arange(0, n, 4) + 2.0
    x, y = np.broadcast_arrays(c[None, :], float(n) - c[:, None])
    out = mi.render(x, y)
    ok = np.isfinite(out)
    assert np.allclose(out[ok], 50.0, atol=1e-3)
    hole = (c[:, None] > 42) & (c[:, None] < 78) & (c[None, :] > 42) & (c[None, :] < 78)
    assert not ok[hole].any()
    assert ok.mean() > 0.8
