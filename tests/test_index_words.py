"""Per-tile word assignment (rule tile_words) gives the same index as in-process assignment."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import pytest
from rasterio.transform import Affine
from test_index import _texture, _tile_image

from georeg.index.map_index import (
    INDEX_ARRAYS,
    MapIndex,
    WordQuantizer,
    assign_tile_words,
    build_from_grid,
    save_word_quantizer,
)
from georeg.index.vocabulary import build_vocabulary
from georeg.io.errors import InputError


@pytest.fixture(scope="module")
def tiles(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("words")
    gray = _texture(512, 768, seed=5)
    tr = Affine(0.5, 0.0, 600000.0, 0.0, -0.5, 5000000.0)
    dirs, ids, _ = _tile_image(gray, tr, 256, 48, tmp / "features")
    # an empty tile (no feature), as a map edge or a featureless tile gives
    empty = tmp / "features" / "r009_c009"
    shutil.copytree(dirs[0], empty)
    for f in empty.glob("*.npy"):
        a = np.load(f)
        np.save(f, a[:0])
    dirs.append(empty)
    ids.append(empty.name)
    build_vocabulary(dirs, tmp / "vocab", {"k": 200, "sample_size": 20000, "iterations": 8}, 3, 1)
    (tmp / "grid.json").write_text(json.dumps({"crs": None, "tiles": ids}))
    return {"tmp": tmp, "dirs": dirs, "ids": ids, "cent": tmp / "vocab" / "centroids.npy"}


def _assert_same_index(a: Path, b: Path) -> None:
    for name in INDEX_ARRAYS:
        x, y = np.load(a / f"{name}.npy"), np.load(b / f"{name}.npy")
        assert x.dtype == y.dtype and x.shape == y.shape, name
        np.testing.assert_array_equal(x, y, err_msg=name)
    ma, mb = (json.loads((p / "meta.json").read_text()) for p in (a, b))
    ma.pop("build_seconds")
    mb.pop("build_seconds")
    assert ma == mb


@pytest.mark.parametrize("method", ["flat", "hnsw"])
def test_per_tile_words_give_identical_index(tiles, tmp_path, method):
    dirs, ids, cent = tiles["dirs"], tiles["ids"], np.load(tiles["cent"])
    # old path: the library assigns the words in process
    MapIndex.build(dirs, ids, cent, tmp_path / "inprocess", quantizer=method)
    # new path: the quantizer saved once, words per tile, then the merge
    qpath = tmp_path / "quantizer.faiss"
    assert save_word_quantizer(tiles["cent"], qpath, method) == method
    words = []
    for d in dirs:
        out = tmp_path / "words" / f"{d.name}.npy"
        w = assign_tile_words(d, tiles["cent"], out, qpath)
        assert w.dtype == np.int32 and np.load(out).shape == (len(np.load(d / "desc.npy")),)
        words.append(out)
    idx = MapIndex.build(dirs, ids, cent, tmp_path / "pertile", quantizer=method, words=words)
    _assert_same_index(tmp_path / "inprocess", tmp_path / "pertile")
    assert idx.meta["word_assignment"] == method
    # the saved quantizer answers like a freshly built one (MapIndex.quantize)
    d = np.load(dirs[1] / "desc.npy")
    np.testing.assert_array_equal(
        WordQuantizer.load(qpath, cent).search(d, 2)[1], idx.quantize(d, 2)[1]
    )


def test_build_from_grid_with_word_files(tiles, tmp_path):
    dirs, cent = tiles["dirs"], tiles["cent"]
    grid = tiles["tmp"] / "grid.json"
    words = [assign_tile_words(d, cent, tmp_path / "w" / f"{d.name}.npy") for d in dirs]
    assert sum(map(len, words)) > 1000
    files = sorted((tmp_path / "w").glob("*.npy"))
    build_from_grid(grid, dirs[::-1], cent, tmp_path / "a")  # in process (old path)
    build_from_grid(grid, dirs, cent, tmp_path / "b", word_files=files[::-1])
    _assert_same_index(tmp_path / "a", tmp_path / "b")
    with pytest.raises(InputError, match="do not match"):
        build_from_grid(grid, dirs, cent, tmp_path / "c", word_files=files[1:])
    np.save(files[0], np.load(files[0])[:-1])  # a stale word file (tile re-extracted)
    with pytest.raises(InputError, match="expected int32"):
        build_from_grid(grid, dirs, cent, tmp_path / "c", word_files=files)
    assert not (tmp_path / "c").exists()


def test_quantizer_file_must_match_vocabulary(tiles, tmp_path):
    save_word_quantizer(tiles["cent"], tmp_path / "q.faiss")
    cent = np.load(tiles["cent"])
    with pytest.raises(InputError, match="words of dim"):
        WordQuantizer.load(tmp_path / "q.faiss", cent[:-1])


def test_index_carries_the_saved_quantizer(tiles, tmp_path):
    """build_index copies rule word_quantizer's structure; queries load it (not rebuild it), with
    the efSearch it was saved with."""
    dirs, cent = tiles["dirs"], tiles["cent"]
    qpath = tmp_path / "quantizer.faiss"
    save_word_quantizer(cent, qpath, "hnsw", ef_search=24)
    words = [assign_tile_words(d, cent, tmp_path / "w" / f"{d.name}.npy", qpath) for d in dirs]
    assert sum(map(len, words)) > 1000
    files = sorted((tmp_path / "w").glob("*.npy"))
    build_from_grid(
        tiles["tmp"] / "grid.json", dirs, cent, tmp_path / "map", files, quantizer_file=qpath
    )
    assert (tmp_path / "map" / "quantizer.faiss").exists()
    q = MapIndex.load(tmp_path / "map").quantizer
    assert q.method == "hnsw" and q._index.hnsw.efSearch == 24  # 200 words: flat if rebuilt
    d = np.load(dirs[1] / "desc.npy")
    np.testing.assert_array_equal(q.words(d), np.load(tmp_path / "w" / f"{dirs[1].name}.npy"))
    # an index without the file still answers (the structure is built from its centroids)
    (tmp_path / "map" / "quantizer.faiss").unlink()
    assert MapIndex.load(tmp_path / "map").quantizer.method == "flat"
