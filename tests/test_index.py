"""Vocabulary and map index: determinism, TF-IDF retrieval, save/load, inverted-file integrity."""

from __future__ import annotations

import re
import shutil
from pathlib import Path

import cv2
import numpy as np
import pytest
from rasterio.transform import Affine

from georeg.index.features import (
    dequantize,
    detect_and_describe,
    merged_conf,
    rgb_to_gray,
    save_tile_features,
    tile_features,
)
from georeg.index.map_index import INDEX_ARRAYS, MapIndex
from georeg.index.vocabulary import build_vocabulary, sample_descriptors, train_kmeans

ROOT = Path(__file__).resolve().parents[1]
SHARED = Path(__file__).resolve().parents[2] / "shared" / "data"
AUTZEN = SHARED / "autzen" / "autzen.jpg"
CONF = merged_conf({})


def _texture(h: int, w: int, seed: int) -> np.ndarray:
    rng = np.random.default_rng(seed)
    img = np.full((h, w), 110, np.uint8)
    for _ in range(h * w // 700):
        x, y = int(rng.integers(0, w)), int(rng.integers(0, h))
        c = int(rng.integers(0, 256))
        if rng.random() < 0.5:
            dx, dy = (int(v) for v in rng.integers(4, 40, 2))
            cv2.rectangle(img, (x, y), (x + dx, y + dy), c, -1)
        else:
            cv2.circle(img, (x, y), int(rng.integers(3, 16)), c, -1)
    return cv2.GaussianBlur(img, (0, 0), 1.0)


def _tile_image(gray: np.ndarray, tr: Affine, size: int, overlap: int, out: Path):
    """Cut ``gray`` into overlapping tiles with half/half cores, like the map grid; save features."""
    h, w = gray.shape
    dirs, ids, cores = [], [], []
    for r, r0 in enumerate(range(0, h, size)):
        for c, c0 in enumerate(range(0, w, size)):
            wr0, wc0 = max(r0 - overlap // 2, 0), max(c0 - overlap // 2, 0)
            wr1, wc1 = min(r0 + size + overlap // 2, h), min(c0 + size + overlap // 2, w)
            core = (c0 - wc0, r0 - wr0, min(size, w - c0), min(size, h - r0))
            tf = tile_features(
                gray[wr0:wr1, wc0:wc1], None, tr @ Affine.translation(wc0, wr0), CONF, core
            )
            tid = f"r{r:03d}_c{c:03d}"
            meta = {"features_conf_hash": "test", "gsd_m": abs(tr.a), "crs_wkt": None}
            save_tile_features(out / tid, tf, meta)
            dirs.append(out / tid)
            ids.append(tid)
            cores.append((r0, c0))
    return dirs, ids, cores


def _query(gray: np.ndarray, r0: int, c0: int, size: int, angle: float, scale: float):
    crop = gray[r0 : r0 + size, c0 : c0 + size]
    m = cv2.getRotationMatrix2D((size / 2, size / 2), angle, scale)
    q = cv2.warpAffine(crop, m, (size, size))
    qm = cv2.warpAffine(np.full_like(crop, 255), m, (size, size)) > 0
    return detect_and_describe(q, qm, CONF)


@pytest.fixture(scope="module")
def synthetic_index(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("idx")
    gray = _texture(768, 1024, seed=11)
    tr = Affine(0.5, 0.0, 600000.0, 0.0, -0.5, 5000000.0)
    dirs, ids, cores = _tile_image(gray, tr, 256, 48, tmp / "features")
    build_vocabulary(dirs, tmp / "vocab", {"k": 300, "sample_size": 20000, "iterations": 10}, 42, 1)
    cent = np.load(tmp / "vocab" / "centroids.npy")
    idx = MapIndex.build(dirs, ids, cent, tmp / "map")
    return {
        "idx": idx,
        "gray": gray,
        "tr": tr,
        "ids": ids,
        "cores": cores,
        "dirs": dirs,
        "tmp": tmp,
    }


def test_vocabulary_deterministic_by_seed(synthetic_index, tmp_path):
    dirs = synthetic_index["dirs"]
    conf = {"k": 64, "sample_size": 5000, "iterations": 5}
    c1 = build_vocabulary(dirs, tmp_path / "a", conf, 7, 2)
    build_vocabulary(dirs, tmp_path / "b", conf, 7, 2)
    build_vocabulary(dirs, tmp_path / "c", conf, 8, 2)
    a, b, c = (np.load(tmp_path / n / "centroids.npy") for n in "abc")
    assert a.shape == (64, 128) and c1["k"] == 64
    np.testing.assert_array_equal(a, b)
    assert not np.array_equal(a, c)
    s1, s2 = sample_descriptors(dirs, 3000, 5), sample_descriptors(dirs, 3000, 5)
    np.testing.assert_array_equal(s1, s2)


def test_minibatch_backend_deterministic():
    x = np.random.default_rng(0).random((3000, 128), np.float32)
    a, _ = train_kmeans(x, 20, 3, "minibatch", 5)
    b, _ = train_kmeans(x, 20, 3, "minibatch", 5)
    np.testing.assert_array_equal(a, b)


def test_true_tile_ranks_first_synthetic(synthetic_index):
    s = synthetic_index
    idx, gray = s["idx"], s["gray"]
    hits = 0
    for t, (angle, scale) in zip([0, 5, 10], [(30, 0.8), (-75, 1.2), (160, 0.9)], strict=True):
        r0, c0 = s["cores"][t]
        q = _query(gray, r0, c0, 256, angle, scale)
        ranked = idx.rank_tiles(q.desc, top=3)
        hits += ranked[0][0] == t
        assert 0 < ranked[0][1] <= 1.0 + 1e-6
    assert hits == 3


def test_rank_regions_finds_query_window(synthetic_index):
    s = synthetic_index
    idx, gray, tr = s["idx"], s["gray"], s["tr"]
    r0, c0 = 300, 420  # straddles four tiles
    q = _query(gray, r0, c0, 256, 40, 1.0)
    (xmin, ymin, xmax, ymax), score = idx.rank_regions(q.desc, window_m=128, stride_m=32, top=1)[0]
    cx, cy = tr @ (c0 + 128, r0 + 128)
    assert xmin - 32 <= cx <= xmax + 32 and ymin - 32 <= cy <= ymax + 32
    assert score > 0


def test_index_integrity_and_tfidf_against_dense(synthetic_index):
    idx = synthetic_index["idx"]
    n, k, nt = idx.n_features, idx.n_words, len(idx.tile_ids)
    word, tile = np.asarray(idx.word), np.asarray(idx.tile)
    # the inverted file lists every feature exactly once, under its own word
    assert np.array_equal(np.sort(np.asarray(idx.ivf_ids)), np.arange(n))
    for w in range(0, k, 37):
        ids = idx.ivf_ids[idx.ivf_offsets[w] : idx.ivf_offsets[w + 1]]
        assert np.all(word[ids] == w)
    # words are the exact nearest centroids of the stored descriptors
    d = dequantize(np.asarray(idx.desc[:500]))
    d2 = ((d[:, None, :] - idx.centroids[None]) ** 2).sum(-1)
    assert (d2.argmin(1) == word[:500]).mean() > 0.99
    # dense TF-IDF cosine agrees with rank_tiles
    counts = np.zeros((nt, k))
    np.add.at(counts, (tile, word), 1)
    df = (counts > 0).sum(0)
    np.testing.assert_array_equal(df, idx.df)
    idf = np.where(df > 0, np.log(nt / np.maximum(df, 1)), 0)
    q = _query(synthetic_index["gray"], 256, 512, 256, 10, 1.0)
    _, qw = idx.quantize(q.desc)
    qv = np.sqrt(np.bincount(qw[:, 0], minlength=k)) * idf  # sqrt-tf (burstiness)
    dv = np.sqrt(counts) * idf
    dense = dv @ qv / (np.linalg.norm(dv, axis=1) * np.linalg.norm(qv) + 1e-30)
    got = dict(idx.rank_tiles(q.desc))
    for t in range(nt):
        assert got.get(t, 0.0) == pytest.approx(dense[t], abs=1e-6)


def test_features_in_and_knn_match_brute_force(synthetic_index):
    idx = synthetic_index["idx"]
    xy = np.asarray(idx.xy)
    b = (600100.0, 4999800.0, 600260.0, 4999900.0)
    ids = idx.features_in(b)
    ref = np.flatnonzero(
        (xy[:, 0] >= b[0]) & (xy[:, 0] <= b[2]) & (xy[:, 1] >= b[1]) & (xy[:, 1] <= b[3])
    )
    np.testing.assert_array_equal(np.sort(ids), ref)
    q = _query(synthetic_index["gray"], 200, 200, 256, 0, 1.0)
    dist, fid = idx.knn(q.desc, ids, k=2)
    base = dequantize(np.asarray(idx.desc[ids]))
    dd = np.sqrt(((q.desc[:, None, :] - base[None]) ** 2).sum(-1))
    order = np.argsort(dd, axis=1)[:, :2]
    np.testing.assert_allclose(dist, np.take_along_axis(dd, order, 1), rtol=1e-4, atol=1e-5)
    assert (fid[:, 0] == ids[order[:, 0]]).mean() > 0.99
    d1, f1 = idx.knn(q.desc[:5], ids[:1], k=2)  # fewer candidates than k
    assert np.all(f1[:, 1] == -1) and np.all(np.isinf(d1[:, 1]))


def test_knn_kdtree_path_is_near_exact_and_seeded(synthetic_index, monkeypatch):
    """Above ``KNN_FLAT_MAX_PAIRS`` the candidate search is a FLANN kd-tree: nearly the exact
    neighbours, and the same whatever OpenCV's process-wide generator was left at (a library
    user's earlier queries)."""
    import cv2

    import georeg.index.map_index as mi

    idx = synthetic_index["idx"]
    ids = np.arange(idx.n_features)
    q = _query(synthetic_index["gray"], 200, 200, 256, 0, 1.0)
    exact = idx.knn(q.desc, ids, k=2)
    monkeypatch.setattr(mi, "KNN_FLAT_MAX_PAIRS", 0)
    got = []
    for s in (1, 2):
        cv2.setRNGSeed(s)
        cv2.randu(np.zeros((10, 10), np.float32), 0, 1)
        got.append(idx.knn(q.desc, ids, k=2))
    np.testing.assert_array_equal(got[0][1], got[1][1])
    assert (got[0][1][:, 0] == exact[1][:, 0]).mean() > 0.95


def test_kdtree_search_of_no_query_rows_is_empty():
    """A query part without descriptors searched in a large map's kd-tree (SRIF optical-depth 177
    in an 80-reference mosaic crashed: FLANN returns None for no rows)."""
    from georeg.register import matching

    rng = np.random.default_rng(0)
    md = rng.random((matching.FLAT_MAX + 10, 8)).astype(np.float32)
    d, ii = matching.knn2(md)(np.empty((0, 8), np.float32))
    assert d.shape == (0, 2) and ii.shape == (0, 2) and ii.dtype == np.int64


def test_saved_index_loaded_memory_mapped_answers_the_same(synthetic_index, tmp_path):
    idx = synthetic_index["idx"]
    shutil.copytree(idx.path, tmp_path / "copy")
    loaded = MapIndex.load(tmp_path / "copy" / "meta.json")
    assert isinstance(loaded.desc, np.memmap) and isinstance(loaded.xy, np.memmap)
    inmem = MapIndex.load(tmp_path / "copy", mmap=False)
    q = _query(synthetic_index["gray"], 512, 256, 256, 20, 1.1)
    for other in (loaded, inmem):
        assert other.rank_tiles(q.desc) == idx.rank_tiles(q.desc)
        for a, b in zip(other.quantize(q.desc, 2), idx.quantize(q.desc, 2), strict=True):
            np.testing.assert_array_equal(a, b)
        ids = other.features_in(other.tile_bounds[4])
        np.testing.assert_array_equal(ids, idx.features_in(idx.tile_bounds[4]))
        for a, b in zip(other.knn(q.desc, ids), idx.knn(q.desc, ids), strict=True):
            np.testing.assert_array_equal(a, b)
    assert loaded.tile_ids == synthetic_index["ids"]


def test_smk_index_arrays_match_module():
    text = (ROOT / "workflow" / "rules" / "index.smk").read_text()
    block = text.split("INDEX_ARRAYS = [", 1)[1].split("]", 1)[0]
    assert tuple(re.findall(r'"(\w+)"', block)) == INDEX_ARRAYS


@pytest.mark.shared
@pytest.mark.skipif(not AUTZEN.exists(), reason="../shared/data is absent")
def test_true_tile_ranks_first_autzen(tmp_path):
    import rasterio

    with rasterio.open(AUTZEN) as ds:
        rgb = ds.read(window=((0, 1536), (0, 2048)))
        tr = ds.transform
    gray = rgb_to_gray(rgb)
    dirs, ids, cores = _tile_image(gray, tr, 512, 64, tmp_path / "features")
    build_vocabulary(
        dirs, tmp_path / "vocab", {"k": 500, "sample_size": 50000, "iterations": 10}, 1, 2
    )
    idx = MapIndex.build(dirs, ids, np.load(tmp_path / "vocab" / "centroids.npy"), tmp_path / "map")
    for t, (angle, scale) in zip([1, 6, 10], [(25, 0.85), (-60, 1.0), (120, 0.75)], strict=True):
        r0, c0 = cores[t]
        q = _query(gray, r0, c0, 512, angle, scale)
        assert idx.rank_tiles(q.desc, top=1)[0][0] == t


@pytest.mark.parametrize("method", ["hnsw", "kdtree"])
def test_approximate_word_quantizers_agree_with_flat(method):
    from georeg.index.map_index import WordQuantizer

    rng = np.random.default_rng(0)
    cent = rng.random((3000, 128), np.float32)
    q = cent[rng.choice(3000, 500)] + rng.normal(0, 0.05, (500, 128)).astype(np.float32)
    d_ref, w_ref = WordQuantizer(cent, "flat").search(q, 2)
    d, w = WordQuantizer(cent, method).search(q, 2)
    assert (w[:, 0] == w_ref[:, 0]).mean() > 0.9
    assert np.all(d[:, 0] <= d[:, 1] + 1e-6)
    if method == "hnsw":  # single-threaded insertion: reproducible
        np.testing.assert_array_equal(WordQuantizer(cent, method).search(q, 2)[1], w)
