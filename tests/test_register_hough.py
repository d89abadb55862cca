"""Wide-area retrieval by a Hough vote of nearest map features (georeg.register.hough)."""

from __future__ import annotations

import cv2
import numpy as np
import pytest
from rasterio.transform import Affine
from test_index import CONF, _texture, _tile_image

from georeg.index.map_index import MapIndex
from georeg.index.vocabulary import build_vocabulary
from georeg.register.hough import hough_regions, vote_centres
from georeg.register.search import MapSource, index_candidates, plain_nearest, query_features


@pytest.fixture(scope="module")
def wide_map(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("hough")
    gray = _texture(1024, 1536, seed=5)
    tr = Affine(0.5, 0.0, 600000.0, 0.0, -0.5, 5000000.0)
    dirs, ids, _cores = _tile_image(gray, tr, 256, 48, tmp / "features")
    build_vocabulary(dirs, tmp / "vocab", {"k": 200, "sample_size": 20000, "iterations": 8}, 3, 1)
    idx = MapIndex.build(dirs, ids, np.load(tmp / "vocab" / "centroids.npy"), tmp / "map")
    return gray, tr, idx


def _warped_query(gray, r0, c0, size, angle, scale):
    """A crop rotated by ``angle`` (cv2: counter-clockwise on screen) and zoomed by ``scale``;
    0 = nodata outside the rotated crop."""
    crop = gray[r0 : r0 + size, c0 : c0 + size]
    m = cv2.getRotationMatrix2D((size / 2 - 0.5, size / 2 - 0.5), angle, scale)
    q = cv2.warpAffine(crop, m, (size, size))
    valid = cv2.warpAffine(np.full_like(crop, 255), m, (size, size)) > 0
    return np.where(valid, np.maximum(q, 1), 0).astype(np.uint8)


def test_knn_words_with_every_word_probed_is_exact(wide_map):
    _g, _tr, idx = wide_map
    q = np.asarray(idx.desc[::997][:40])
    cq, cf, d = idx.knn_words(q, k=3, nprobe=idx.n_words)
    dist, fid = idx.knn(q, k=3)
    assert np.array_equal(cq, np.repeat(np.arange(len(q)), 3))
    np.testing.assert_allclose(d.reshape(-1, 3), dist, rtol=1e-4, atol=1e-3)
    assert (fid[:, 0] == cf.reshape(-1, 3)[:, 0]).mean() > 0.95  # ties aside, the same nearest
    # with few words probed, still mostly the exact nearest (the IVF approximation)
    cq2, cf2, _ = idx.knn_words(q, k=1, nprobe=4)
    assert (cf2 == fid[cq2, 0]).mean() > 0.7


@pytest.mark.parametrize("angle", [0.0, 35.0, -120.0, 200.0])
def test_vote_centres_geometry(angle):
    """Points of a rotated, zoomed query vote for its centre exactly (no descriptors involved)."""
    rng = np.random.default_rng(1)
    scale, gsd = 1.25, 0.5  # query zoomed x1.25: a query pixel is gsd / scale map units
    size = 200
    m = cv2.getRotationMatrix2D((size / 2 - 0.5, size / 2 - 0.5), angle, scale)
    minv = cv2.invertAffineTransform(m)
    q_xy = rng.uniform(20, 180, (50, 2))
    map_px = q_xy @ minv[:, :2].T + minv[:, 2]  # crop pixel of each query point
    tr = Affine(gsd, 0.0, 1000.0, 0.0, -gsd, 2000.0)
    m_xy = np.c_[tr @ (map_px[:, 0], map_px[:, 1])]
    # SIFT angles: a feature's angle grows by the on-screen rotation (+angle counter-clockwise)
    m_ang = rng.uniform(0, 360, 50)
    q_ang = (m_ang + angle) % 360
    x, y, rot = vote_centres(q_xy, q_ang, np.full(50, gsd / scale), (99.5, 99.5), m_xy, m_ang)
    cx, cy = tr @ (size / 2 - 0.5, size / 2 - 0.5)
    np.testing.assert_allclose(x, cx, atol=1e-6)
    np.testing.assert_allclose(y, cy, atol=1e-6)
    np.testing.assert_allclose(np.cos(np.deg2rad(rot + angle)), 1.0, atol=1e-9)


@pytest.mark.parametrize(("r0", "c0", "angle", "scale"), [(300, 420, 40.0, 1.0),
                                                          (620, 1100, -110.0, 1.3),
                                                          (90, 150, 170.0, 0.8)])  # fmt: skip
def test_hough_regions_find_rotated_query(wide_map, r0, c0, angle, scale):
    gray, tr, idx = wide_map
    size = 256
    q = _warped_query(gray, r0, c0, size, angle, scale)
    gsd = 0.5 / scale
    qf = query_features(q, (0, size), [gsd / 0.5], CONF)
    src = MapSource.from_index(idx.path)
    diag = float(np.hypot(size, size) * gsd)
    regions = hough_regions(qf, idx, src.bounds, src.gsd_m, diag, 5)
    cx, cy = tr @ (c0 + size / 2, r0 + size / 2)
    (x0, y0, x1, y1), votes = regions[0]
    assert x0 <= cx <= x1 and y0 <= cy <= y1
    for b, v in regions[1:]:  # elsewhere (farther than the footprint), far fewer votes
        if np.hypot(0.5 * (b[0] + b[2]) - cx, 0.5 * (b[1] + b[3]) - cy) > diag:
            assert v < 0.5 * votes
    # a region is the footprint diagonal (+ one cell) around the voted centre, not a whole tile
    assert x1 - x0 < 2 * diag
    # through the search's candidate list (register.index.rank: hough)
    cands = index_candidates(qf, src, diag, {"rank": "hough", "top_candidates": 4})
    assert len(cands) == 4
    b = cands[0][0]
    assert b[0] <= cx <= b[2] and b[1] <= cy <= b[3]


def test_hough_regions_nothing_to_vote(wide_map):
    _g, _tr, idx = wide_map
    blank = np.zeros((64, 64), np.uint8)
    qf = query_features(blank, (0, 64), [1.0], CONF)
    assert hough_regions(qf, idx, (0, 0, 1, 1), 0.5, 50.0, 5) == []


def test_hough_regions_peak_on_the_map_edge(wide_map):
    """A query at the map's corner: its votes pile up in the edge cells (no index error)."""
    gray, tr, idx = wide_map
    q = _warped_query(gray, 0, 1536 - 200, 200, 0.0, 1.0)
    qf = query_features(q, (0, 200), [1.0], CONF)
    src = MapSource.from_index(idx.path)
    diag = float(np.hypot(200, 200) * 0.5)
    (x0, y0, x1, y1), _v = hough_regions(
        qf, idx, src.bounds, src.gsd_m, diag, 3, {"cell_frac": 1.0}
    )[0]
    cx, cy = tr @ (1536 - 100, 100)
    assert x0 <= cx <= x1 and y0 <= cy <= y1


def test_hough_regions_unknown_gsd_votes_at_each_factor(wide_map):
    """GSD unknown: features at several resize factors each vote at their own scale; the right
    factor's votes find the place (zoom 1.25 -> true factor 0.8)."""
    gray, tr, idx = wide_map
    q = _warped_query(gray, 500, 700, 256, 60.0, 1.25)
    qf = query_features(q, (0, 256), [0.6, 0.8, 1.0, 1.25], CONF)
    assert set(np.unique(qf.factor)) == {0.6, 0.8, 1.0, 1.25}
    src = MapSource.from_index(idx.path)
    diag = float(np.hypot(256, 256) * 0.5 * 1.25)  # the largest assumed footprint
    (x0, y0, x1, y1), _v = hough_regions(qf, idx, src.bounds, src.gsd_m, diag, 3)[0]
    cx, cy = tr @ (700 + 128, 500 + 128)
    assert x0 <= cx <= x1 and y0 <= cy <= y1


def _plain(idx, src):
    """The indexed map's features as plain arrays (no index), with their keypoint geometry."""
    return MapSource(
        np.asarray(idx.xy), np.asarray(idx.desc), src.gsd_m, angle=np.asarray(idx.angle),
        scale=np.asarray(idx.scale),
    )  # fmt: skip


def test_plain_nearest_is_exact(wide_map):
    """On plain arrays knn_words compares every map feature: the index's exact knn."""
    _g, _tr, idx = wide_map
    plain = _plain(idx, MapSource.from_index(idx.path))
    nn = plain_nearest(plain)
    assert nn is plain_nearest(plain)  # built once per source
    q = np.asarray(idx.desc[::997][:40])
    cq, cf, d = nn.knn_words(q, k=3)
    dist, fid = idx.knn(q, k=3)
    assert np.array_equal(cq, np.repeat(np.arange(len(q)), 3))
    np.testing.assert_allclose(d.reshape(-1, 3), dist, rtol=1e-4, atol=1e-3)
    assert (fid[:, 0] == cf.reshape(-1, 3)[:, 0]).mean() > 0.95  # ties aside
    # no keypoint geometry: no Hough vote possible
    assert plain_nearest(MapSource(plain.xy, plain.desc, plain.gsd_m)) is None


@pytest.mark.parametrize(("r0", "c0", "angle", "scale"), [(300, 420, 40.0, 1.0),
                                                          (620, 1100, -110.0, 1.3)])  # fmt: skip
def test_plain_arrays_rank_by_hough(wide_map, r0, c0, angle, scale):
    """Plain map arrays (no index), rank hough: the true place is the first candidate region,
    a footprint-sized square; rank tiles there: the 1-NN cell vote (whole cells + footprint)."""
    gray, tr, idx = wide_map
    size = 256
    q = _warped_query(gray, r0, c0, size, angle, scale)
    gsd = 0.5 / scale
    qf = query_features(q, (0, size), [gsd / 0.5], CONF)
    plain = _plain(idx, MapSource.from_index(idx.path))
    diag = float(np.hypot(size, size) * gsd)
    cx, cy = tr @ (c0 + size / 2, r0 + size / 2)
    cands = index_candidates(qf, plain, diag, {"rank": "hough", "top_candidates": 4})
    assert len(cands) == 4
    (x0, y0, x1, y1), votes = cands[0]
    assert x0 <= cx <= x1 and y0 <= cy <= y1
    assert x1 - x0 < 2 * diag
    for b, v in cands[1:]:
        if np.hypot(0.5 * (b[0] + b[2]) - cx, 0.5 * (b[1] + b[3]) - cy) > diag:
            assert v < 0.5 * votes
    # the same regions as through the index with every word probed (exact neighbours both)
    via_index = index_candidates(
        qf,
        MapSource.from_index(idx.path),
        diag,
        {"rank": "hough", "top_candidates": 1, "hough": {"nprobe": idx.n_words}},
    )
    np.testing.assert_allclose(via_index[0][0], cands[0][0], atol=0.5 * diag)
    cell = index_candidates(qf, plain, diag, {"rank": "tiles", "top_candidates": 4})
    assert cell and all(b[2] - b[0] >= 3 * diag - 1e-6 for b, _ in cell)
