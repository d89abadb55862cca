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
