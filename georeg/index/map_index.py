"""The map index: every map feature with its 3-D position, its visual word and an inverted file.

On-disk format (``results/index/map/``, documented in docs/INDEX_FORMAT.md): plain ``.npy``
arrays, memory-mapped on load, and a ``meta.json``. ``MapIndex`` is the API the registration
stage uses: ``quantize`` (nearest visual words), ``rank_tiles`` / ``rank_regions`` (TF-IDF
retrieval), ``knn_words`` (approximate nearest map features over the whole map, through the
words' inverted file), ``features_in`` (features in a map rectangle) and ``knn`` (two nearest
map features).
"""

from __future__ import annotations

import json
import logging
import math
import os
import shutil
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np
from threadpoolctl import threadpool_limits

from georeg.index.features import DESC_DIM, DESC_SCALE, dequantize
from georeg.index.kdtree import kdtree, knn_search
from georeg.io.atomic import atomic_path
from georeg.io.errors import InputError

log = logging.getLogger(__name__)

FORMAT_VERSION = 1
#: every array of the index directory (``<name>.npy``); ``meta.json`` comes with them
INDEX_ARRAYS = (
    "xy",
    "z",
    "ndsm",
    "scale",
    "angle",
    "response",
    "desc",
    "tile",
    "word",
    "tile_offsets",
    "tile_bounds",
    "centroids",
    "ivf_offsets",
    "ivf_ids",
    "df",
    "idf",
    "wt_offsets",
    "wt_tile",
    "wt_count",
    "tile_norm",
)
_PER_FEATURE = ("xy", "z", "ndsm", "scale", "angle", "response", "desc")
#: the nearest-word structure saved beside the arrays (rule word_quantizer's file, copied)
QUANTIZER_FILE = "quantizer.faiss"
#: exact (flat) word assignment up to this many words; above, an HNSW graph (see BENCHMARKS.md)
FLAT_MAX_WORDS = 16384
#: knn: exact flat search while |query| * |ids| stays below this; FLANN kd-tree above
KNN_FLAT_MAX_PAIRS = 2_000_000_000
_CHUNK = 65536


def _ranges(offsets: np.ndarray, rows: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Concatenated positions of CSR rows ``rows`` and, per position, which of ``rows`` it is."""
    starts = np.asarray(offsets[rows], np.int64)
    lens = np.asarray(offsets[rows + 1], np.int64) - starts
    total = int(lens.sum())
    which = np.repeat(np.arange(len(rows)), lens)
    if total == 0:
        return np.zeros(0, np.int64), which
    first = np.cumsum(lens) - lens
    pos = np.arange(total, dtype=np.int64) - np.repeat(first, lens) + np.repeat(starts, lens)
    return pos, which


def quantizer_method(n_words: int, method: str = "auto") -> str:
    """``method``, or for ``"auto"``: ``"flat"`` up to ``FLAT_MAX_WORDS`` words, ``"hnsw"`` above."""
    if method == "auto":
        return "flat" if n_words <= FLAT_MAX_WORDS else "hnsw"
    if method not in ("flat", "hnsw", "kdtree"):
        raise ValueError(f"unknown quantizer method {method!r}")
    return method


#: HNSW search breadth: recall@1 0.988 / 0.996 / 0.998 / 0.9998 at 16 / 32 / 64 / 128, the cost
#: doubling with each step (k = 100,000; docs/BENCHMARKS.md "Nearest-word structure")
EF_SEARCH = 64


class WordQuantizer:
    """Nearest visual words of descriptors: exact faiss ``IndexFlatL2`` for small vocabularies,
    faiss ``IndexHNSWFlat`` (M = 32, efSearch ``ef_search``) above ``FLAT_MAX_WORDS``, or an
    OpenCV FLANN kd-tree (the paper's choice; ``georeg.index.kdtree``) when asked for
    ``method="kdtree"``."""

    def __init__(
        self,
        centroids: np.ndarray,
        method: str = "auto",
        _index: Any = None,
        ef_search: int = EF_SEARCH,
    ) -> None:
        self.centroids = np.ascontiguousarray(centroids, np.float32)
        self.method = quantizer_method(self.centroids.shape[0], method)
        if _index is not None:  # from ``load``: the saved faiss structure
            self._index = _index
        elif self.method == "flat":
            import faiss

            self._index = faiss.IndexFlatL2(self.centroids.shape[1])
            self._index.add(self.centroids)
        elif self.method == "hnsw":
            import faiss

            self._index = faiss.IndexHNSWFlat(self.centroids.shape[1], 32)
            self._index.hnsw.efConstruction = 80
            # single-threaded insertion: the graph (so every word assignment) is reproducible
            nthreads = faiss.omp_get_max_threads()
            faiss.omp_set_num_threads(1)
            try:
                self._index.add(self.centroids)
            finally:
                faiss.omp_set_num_threads(nthreads)
            self._index.hnsw.efSearch = int(ef_search)  # saved with the graph
        else:  # kdtree
            self._index = kdtree(self.centroids)

    def save(self, path: str | os.PathLike) -> None:
        """Write the faiss structure (flat or HNSW: the built graph, so every reader assigns the
        same words without rebuilding it; 52 s at K = 100,000) atomically to ``path``."""
        if self.method == "kdtree":
            raise ValueError("the kd-tree quantizer is not saved (OpenCV FLANN is not portable)")
        import faiss

        with atomic_path(path) as tmp:
            faiss.write_index(self._index, str(tmp))

    @classmethod
    def load(
        cls, path: str | os.PathLike, centroids: np.ndarray, ef_search: int | None = None
    ) -> WordQuantizer:
        """A quantizer saved by ``save`` for ``centroids`` (checked: same number of words and
        dimension). An HNSW graph keeps the efSearch it was saved with unless ``ef_search``."""
        import faiss

        try:
            index = faiss.read_index(str(path))
        except RuntimeError as exc:
            raise InputError(path, f"cannot read: {exc}", "rerun rule word_quantizer") from exc
        cent = np.ascontiguousarray(centroids, np.float32)
        if index.ntotal != cent.shape[0] or index.d != cent.shape[1]:
            raise InputError(
                path,
                f"{index.ntotal} words of dim {index.d}, the vocabulary has {cent.shape}",
                "rerun rule word_quantizer",
            )
        if isinstance(index, faiss.IndexHNSWFlat):
            method = "hnsw"
            if ef_search is not None:
                index.hnsw.efSearch = int(ef_search)
        elif isinstance(index, faiss.IndexFlatL2):
            method = "flat"
        else:
            raise InputError(path, f"unexpected faiss index {type(index).__name__}")
        return cls(cent, method, _index=index)

    def words(self, desc: np.ndarray) -> np.ndarray:
        """The nearest word of each descriptor, int32 (n,): what ``MapIndex.build`` stores."""
        return self.search(desc, 1)[1][:, 0].astype(np.int32)

    def search(self, desc: np.ndarray, k: int = 1) -> tuple[np.ndarray, np.ndarray]:
        """(dist, word) arrays (n, k): Euclidean (not squared) distances, int64 word ids."""
        x = np.ascontiguousarray(dequantize(desc), np.float32).reshape(-1, self.centroids.shape[1])
        n = x.shape[0]
        k = int(k)
        dist = np.empty((n, k), np.float32)
        word = np.empty((n, k), np.int64)
        for i in range(0, n, _CHUNK):
            xb = x[i : i + _CHUNK]
            if self.method == "kdtree":
                idx, d2 = knn_search(self._index, xb, k)
            else:
                d2, idx = self._index.search(xb, k)
            dist[i : i + len(xb)] = np.sqrt(np.maximum(d2, 0))
            word[i : i + len(xb)] = idx
        return dist, word


class MapIndex:
    """A built map index (see the module docstring and docs/INDEX_FORMAT.md).

    Attributes (numpy arrays, memory-mapped when loaded): ``xy`` (N, 2) float64 map x, y;
    ``z``, ``ndsm`` (N,) float32; ``scale`` (N,) float32 map units; ``angle``, ``response``;
    ``desc`` (N, 128) uint8 (``desc / DESC_SCALE`` = unit descriptor); ``tile`` (N,) int32 into
    ``tile_ids``; ``word`` (N,) int32; ``tile_offsets`` (T+1,): features of tile t are the rows
    ``tile_offsets[t]:tile_offsets[t+1]``; ``tile_bounds`` (T, 4) bounds of each tile's features;
    ``centroids`` (K, 128) float32; inverted file ``ivf_offsets`` (K+1,) / ``ivf_ids`` (N,):
    features of word w; ``df`` (K,) number of tiles containing w, ``idf`` = log(T / df) (0 if
    df = 0); the word x tile count matrix in CSR ``wt_offsets`` (K+1,), ``wt_tile``,
    ``wt_count``; ``tile_norm`` (T,) L2 norm of each tile's TF-IDF vector (sqrt-tf).
    """

    def __init__(self, path: Path | None, arrays: dict[str, np.ndarray], meta: dict[str, Any]):
        self.path = path
        self.meta = meta
        for name, arr in arrays.items():
            setattr(self, name, arr)
        self._quantizer: WordQuantizer | None = None
        self._region_cache: dict[tuple[float, ...], Any] = {}

    # ---------------------------------------------------------------- properties
    @property
    def tile_ids(self) -> list[str]:
        return list(self.meta["tile_ids"])

    @property
    def n_features(self) -> int:
        return int(self.meta["n_features"])

    @property
    def n_words(self) -> int:
        return int(self.centroids.shape[0])

    @property
    def crs_wkt(self) -> str | None:
        return self.meta.get("crs_wkt")

    @property
    def gsd_m(self) -> float | None:
        return self.meta.get("gsd_m")

    def __len__(self) -> int:
        return self.n_features

    # ---------------------------------------------------------------- load / build
    @classmethod
    def load(cls, path: str | os.PathLike, mmap: bool = True) -> MapIndex:
        """Open an index directory (or its ``meta.json``); arrays are memory-mapped by default."""
        p = Path(path)
        if p.name == "meta.json":
            p = p.parent
        try:
            meta = json.loads((p / "meta.json").read_text())
        except (OSError, ValueError) as exc:
            raise InputError(p, f"not a map index: {exc}", "rerun rule build_index") from exc
        if meta.get("format_version") != FORMAT_VERSION:
            raise InputError(
                p,
                f"index format {meta.get('format_version')} != {FORMAT_VERSION}",
                "rerun rule build_index",
            )
        arrays = {}
        for name in INDEX_ARRAYS:
            try:
                arrays[name] = np.load(p / f"{name}.npy", mmap_mode="r" if mmap else None)
            except (OSError, ValueError) as exc:
                raise InputError(
                    p / f"{name}.npy", f"cannot read: {exc}", "rerun rule build_index"
                ) from exc
        arrays["centroids"] = np.ascontiguousarray(arrays["centroids"], np.float32)
        return cls(p, arrays, meta)

    @classmethod
    def build(
        cls,
        feature_dirs: Sequence[str | os.PathLike],
        tile_ids: Sequence[str],
        centroids: np.ndarray,
        out_dir: str | os.PathLike,
        crs_wkt: str | None = None,
        quantizer: str | WordQuantizer = "auto",
        extra_meta: dict[str, Any] | None = None,
        words: Sequence[str | os.PathLike] | None = None,
        quantizer_file: str | os.PathLike | None = None,
    ) -> MapIndex:
        """Concatenate per-tile features, assign words, build the inverted files; write
        ``out_dir`` atomically (a temporary sibling renamed at the end) and return it loaded.

        ``words``: one word file per tile (rule ``tile_words``, ``tile_word_file``), same order
        as ``feature_dirs``; they replace the in-process assignment (``WordQuantizer.words``,
        the same function, so the index is identical). ``quantizer`` then only names the method
        recorded in ``meta.json``. ``quantizer_file`` (rule word_quantizer's saved structure) is
        copied in as ``quantizer.faiss``: queries then load it instead of rebuilding it.

        Memory: O(K + T) plus one tile (or one chunk) at a time: the per-feature arrays, the
        (word, tile) pairs and the word x tile matrix all go through memory maps.
        """
        t0 = time.perf_counter()
        if len(feature_dirs) != len(tile_ids):
            raise ValueError("feature_dirs and tile_ids differ in length")
        if words is not None and len(words) != len(feature_dirs):
            raise ValueError("words and feature_dirs differ in length")
        out = Path(out_dir)
        out.parent.mkdir(parents=True, exist_ok=True)
        tmp = out.with_name(f".{out.name}.tmp-{os.getpid()}")
        if tmp.exists():
            shutil.rmtree(tmp)
        tmp.mkdir()
        try:
            metas, counts = [], []
            for d in feature_dirs:
                m = json.loads((Path(d) / "meta.json").read_text())
                metas.append(m)
                counts.append(int(np.load(Path(d) / "desc.npy", mmap_mode="r").shape[0]))
            hashes = {m.get("features_conf_hash") for m in metas}
            if len(hashes) > 1:
                raise InputError(
                    None,
                    "tiles were extracted with different feature settings",
                    "rerun rule tile_features for all tiles",
                )
            n = int(sum(counts))
            nt = len(tile_ids)
            cent = np.ascontiguousarray(centroids, np.float32)
            k = cent.shape[0]
            if words is not None:
                q = None
                method = (
                    quantizer.method
                    if isinstance(quantizer, WordQuantizer)
                    else quantizer_method(k, quantizer)
                )
            else:
                q = (
                    quantizer
                    if isinstance(quantizer, WordQuantizer)
                    else WordQuantizer(cent, quantizer)
                )
                method = q.method

            def mm(name: str, dtype: Any, shape: tuple[int, ...]) -> np.ndarray:
                return np.lib.format.open_memmap(tmp / f"{name}.npy", "w+", dtype, shape)

            arr = {
                "xy": mm("xy", np.float64, (n, 2)),
                "z": mm("z", np.float32, (n,)),
                "ndsm": mm("ndsm", np.float32, (n,)),
                "scale": mm("scale", np.float32, (n,)),
                "angle": mm("angle", np.float32, (n,)),
                "response": mm("response", np.float32, (n,)),
                "desc": mm("desc", np.uint8, (n, DESC_DIM)),
                "tile": mm("tile", np.int32, (n,)),
                "word": mm("word", np.int32, (n,)),
            }
            tile_offsets = np.zeros(nt + 1, np.int64)
            tile_offsets[1:] = np.cumsum(counts)
            tile_bounds = np.full((nt, 4), np.nan, np.float64)
            word_count = np.zeros(k, np.int64)
            df = np.zeros(k, np.int64)
            # (word, tile, count) pairs in tile order, through memory maps (M <= N pairs)
            pairs = {
                name: np.lib.format.open_memmap(
                    tmp / f"_pairs_{name}.npy", "w+", np.int32, (max(n, 1),)
                )
                for name in ("word", "tile", "count")
            }
            n_pairs = 0
            for t, d in enumerate(feature_dirs):
                lo, hi = int(tile_offsets[t]), int(tile_offsets[t + 1])
                if words is not None:
                    w = load_tile_words(words[t], hi - lo, k)
                if hi == lo:
                    continue
                for name in _PER_FEATURE:
                    src = np.load(Path(d) / f"{name}.npy", mmap_mode="r")
                    if name == "desc" and src.dtype != np.uint8:
                        src = np.clip(np.rint(np.asarray(src) * DESC_SCALE), 0, 255)
                    arr[name][lo:hi] = src
                arr["tile"][lo:hi] = t
                if words is None:
                    w = q.words(arr["desc"][lo:hi])
                arr["word"][lo:hi] = w
                xy = arr["xy"][lo:hi]
                tile_bounds[t] = [xy[:, 0].min(), xy[:, 1].min(), xy[:, 0].max(), xy[:, 1].max()]
                uw, uc = np.unique(w, return_counts=True)
                word_count[uw] += uc
                df[uw] += 1
                pairs["word"][n_pairs : n_pairs + len(uw)] = uw
                pairs["tile"][n_pairs : n_pairs + len(uw)] = t
                pairs["count"][n_pairs : n_pairs + len(uw)] = uc
                n_pairs += len(uw)
            # inverted file word -> feature ids (counting sort, chunked, bounded memory)
            ivf_offsets = np.zeros(k + 1, np.int64)
            ivf_offsets[1:] = np.cumsum(word_count)
            ivf_ids = mm("ivf_ids", np.int64, (n,))
            cursor = ivf_offsets[:-1].copy()
            for i in range(0, n, 4 * _CHUNK):
                w = np.asarray(arr["word"][i : i + 4 * _CHUNK], np.int64)
                order = np.argsort(w, kind="stable")
                ws = w[order]
                cnt = np.bincount(ws, minlength=k)
                first = np.cumsum(cnt) - cnt
                rank = np.arange(len(ws)) - first[ws]
                ivf_ids[cursor[ws] + rank] = i + order
                cursor += cnt
            # word x tile counts (CSR by word: a stable counting sort of the tile-ordered pairs,
            # chunked), document frequency, idf, tile norms
            df = df.astype(np.int32)
            wt_offsets = np.zeros(k + 1, np.int64)
            wt_offsets[1:] = np.cumsum(df)
            idf = np.where(df > 0, np.log(max(nt, 1) / np.maximum(df, 1)), 0.0).astype(np.float32)
            wt_tile = mm("wt_tile", np.int32, (n_pairs,))
            wt_count = mm("wt_count", np.int32, (n_pairs,))
            cursor = wt_offsets[:-1].copy()
            for i in range(0, n_pairs, 4 * _CHUNK):
                w = np.asarray(pairs["word"][i : min(i + 4 * _CHUNK, n_pairs)], np.int64)
                order = np.argsort(w, kind="stable")
                ws = w[order]
                cnt = np.bincount(ws, minlength=k)
                first = np.cumsum(cnt) - cnt
                dst = cursor[ws] + np.arange(len(ws)) - first[ws]
                wt_tile[dst] = pairs["tile"][i : i + len(w)][order]
                wt_count[dst] = pairs["count"][i : i + len(w)][order]
                cursor += cnt
            del pairs
            for name in ("word", "tile", "count"):
                (tmp / f"_pairs_{name}.npy").unlink()
            # sqrt-tf: |d|^2 = sum_w (sqrt(n_tw) idf_w)^2 = sum_w n_tw idf_w^2, summed in CSR
            # order one term at a time (np.add.at), as one bincount over the whole matrix would
            norm2 = np.zeros(nt, np.float64)
            for i in range(0, n_pairs, 4 * _CHUNK):
                j = min(i + 4 * _CHUNK, n_pairs)
                ww = np.searchsorted(wt_offsets, np.arange(i, j), side="right") - 1
                cc = np.asarray(wt_count[i:j])
                np.add.at(norm2, np.asarray(wt_tile[i:j]), cc * idf[ww].astype(np.float64) ** 2)
            tile_norm = np.sqrt(norm2).astype(np.float32)
            small = {
                "tile_offsets": tile_offsets,
                "tile_bounds": tile_bounds,
                "centroids": cent,
                "ivf_offsets": ivf_offsets,
                "df": df,
                "idf": idf,
                "wt_offsets": wt_offsets,
                "tile_norm": tile_norm,
            }
            for name, a in small.items():
                np.save(tmp / f"{name}.npy", a)
            for a in (*arr.values(), ivf_ids, wt_tile, wt_count):
                a.flush()
            del arr, ivf_ids, wt_tile, wt_count
            first_meta = metas[0] if metas else {}
            meta = {
                "format_version": FORMAT_VERSION,
                "n_features": n,
                "n_tiles": nt,
                "n_words": k,
                "tile_ids": list(tile_ids),
                "crs_wkt": crs_wkt if crs_wkt is not None else first_meta.get("crs_wkt"),
                "gsd_m": first_meta.get("gsd_m"),
                "features_conf": first_meta.get("features_conf"),
                "features_conf_hash": first_meta.get("features_conf_hash"),
                "desc_dtype": "uint8",
                "desc_scale": DESC_SCALE,
                "word_assignment": method,
                "tf": "sqrt",
                "xy_convention": "map CRS x, y of the keypoint (pixel-centre convention)",
                "build_seconds": round(time.perf_counter() - t0, 3),
                **(extra_meta or {}),
            }
            if quantizer_file is not None:
                shutil.copyfile(quantizer_file, tmp / QUANTIZER_FILE)
            (tmp / "meta.json").write_text(json.dumps(meta, indent=2) + "\n")
            if out.exists():
                shutil.rmtree(out)
            os.replace(tmp, out)
        except BaseException:
            shutil.rmtree(tmp, ignore_errors=True)
            raise
        log.info(
            "index: %d features, %d tiles, %d words in %.1f s", n, nt, k, time.perf_counter() - t0
        )
        return cls.load(out)

    # ---------------------------------------------------------------- queries
    @property
    def quantizer(self) -> WordQuantizer:
        """The nearest-word structure: the saved ``quantizer.faiss`` of the index directory when
        there is one (the same graph as the words were assigned with), else built lazily."""
        if self._quantizer is None:
            saved = None if self.path is None else Path(self.path) / QUANTIZER_FILE
            if saved is not None and saved.exists():  # the graph of rule word_quantizer
                self._quantizer = WordQuantizer.load(saved, self.centroids)
            else:  # built here (an HNSW graph of 100,000 words: ~1 min)
                self._quantizer = WordQuantizer(
                    self.centroids, self.meta.get("word_assignment", "auto")
                )
        return self._quantizer

    def quantize(self, desc: np.ndarray, k: int = 1) -> tuple[np.ndarray, np.ndarray]:
        """The ``k`` nearest visual words of each descriptor: (dist (n, k) float32 Euclidean,
        word_idx (n, k) int64), nearest first. ``k=2`` gives the paper's two nearest words for
        the 0.7 ratio test (``dist[:, 0] < 0.7 * dist[:, 1]``)."""
        return self.quantizer.search(desc, k)

    def _query_words(self, query_desc: np.ndarray) -> tuple[np.ndarray, np.ndarray, float]:
        """Unique query words, their TF-IDF weights, and the query vector's L2 norm."""
        if len(query_desc) == 0:
            return np.zeros(0, np.int64), np.zeros(0), 0.0
        _, w = self.quantize(query_desc, 1)
        uw, tf = np.unique(w[:, 0], return_counts=True)
        idf = np.asarray(self.idf, np.float64)[uw]
        qw = np.sqrt(tf) * idf
        return uw, qw, float(np.sqrt((qw**2).sum()))

    def rank_tiles(self, query_desc: np.ndarray, top: int | None = None) -> list[tuple[int, float]]:
        """Tiles ranked by TF-IDF cosine similarity with the query's bag of words.

        Query vector q_w = sqrt(n_q(w)) idf(w), tile vector d_w = sqrt(n(t, w)) idf(w), with
        idf(w) = log(T / df(w)) and n the word counts; score = q . d / (|q| |d|) in [0, 1].
        The square root damps burstiness (a word repeated many times in the query and in one
        tile, e.g. noise blobs or a repetitive roof pattern, dominating the cosine): measured on
        autzen with a 500-word faiss vocabulary, raw counts ranked the true tile first for 55%
        of rotated/rescaled/gamma-changed queries, sqrt counts for 100% (BENCHMARKS.md). Returns ``[(tile_index, score), ...]`` best first
        (index into ``tile_ids``), only tiles sharing a word, at most ``top``.
        """
        uw, qw, qn = self._query_words(query_desc)
        nt = len(self.tile_ids)
        if qn == 0 or nt == 0:
            return []
        pos, which = _ranges(self.wt_offsets, uw)
        if len(pos) == 0:
            return []
        idf = np.asarray(self.idf, np.float64)
        contrib = (qw * idf[uw])[which] * np.sqrt(np.asarray(self.wt_count[pos], np.float64))
        tiles = np.asarray(self.wt_tile[pos], np.int64)
        scores = np.bincount(tiles, weights=contrib, minlength=nt)
        norm = np.asarray(self.tile_norm, np.float64) * qn
        scores = np.divide(scores, norm, out=np.zeros(nt), where=norm > 0)
        hit = np.unique(tiles)
        order = hit[np.lexsort((hit, -scores[hit]))]
        if top is not None:
            order = order[: int(top)]
        return [(int(t), float(scores[t])) for t in order]

    def _region_grid(self, stride: float) -> tuple[float, float, int, int, np.ndarray]:
        """Per cell of a ``stride`` grid over all features: sum of idf(word)^2 (cached)."""
        key = (float(stride),)
        if key not in self._region_cache:
            b = np.asarray(self.tile_bounds)
            ok = np.isfinite(b).all(axis=1)
            x0, y0 = float(b[ok, 0].min()), float(b[ok, 1].min())
            nx = int(math.floor((b[ok, 2].max() - x0) / stride)) + 1
            ny = int(math.floor((b[ok, 3].max() - y0) / stride)) + 1
            acc = np.zeros(nx * ny, np.float64)
            idf2 = np.asarray(self.idf, np.float64) ** 2
            for i in range(0, self.n_features, 1 << 20):
                xy = np.asarray(self.xy[i : i + (1 << 20)])
                w = np.asarray(self.word[i : i + (1 << 20)])
                cx = np.minimum(((xy[:, 0] - x0) / stride).astype(np.int64), nx - 1)
                cy = np.minimum(((xy[:, 1] - y0) / stride).astype(np.int64), ny - 1)
                acc += np.bincount(cy * nx + cx, weights=idf2[w], minlength=nx * ny)
            self._region_cache[key] = (x0, y0, nx, ny, acc.reshape(ny, nx))
        return self._region_cache[key]

    def rank_regions(
        self,
        query_desc: np.ndarray,
        window_m: float,
        stride_m: float,
        top: int | None = 20,
    ) -> list[tuple[tuple[float, float, float, float], float]]:
        """Map windows of ``window_m`` (map units) every ``stride_m`` ranked by TF-IDF votes.

        Like ``rank_tiles`` but over sliding map windows, independent of the tile cut (good for
        queries straddling tiles). The window norm is approximated by sqrt(sum over its features
        of idf(word)^2) (exact when no word repeats inside a window). Returns
        ``[((xmin, ymin, xmax, ymax), score), ...]`` best first. Cost: the postings of the
        query's words, plus one pass over all features per new ``stride_m`` (cached).
        """
        if stride_m <= 0 or window_m <= 0:
            raise ValueError("window_m and stride_m must be > 0")
        uw, qw, qn = self._query_words(query_desc)
        if qn == 0 or self.n_features == 0:
            return []
        x0, y0, nx, ny, norm_cells = self._region_grid(stride_m)
        pos, which = _ranges(self.ivf_offsets, uw)
        fid = np.sort(np.asarray(self.ivf_ids[pos], np.int64))
        wq = np.zeros(self.n_words)
        wq[uw] = qw * np.asarray(self.idf, np.float64)[uw]
        xy = np.asarray(self.xy[fid])
        vw = wq[np.asarray(self.word[fid])]
        cx = np.minimum(((xy[:, 0] - x0) / stride_m).astype(np.int64), nx - 1)
        cy = np.minimum(((xy[:, 1] - y0) / stride_m).astype(np.int64), ny - 1)
        votes = np.bincount(cy * nx + cx, weights=vw, minlength=nx * ny).reshape(ny, nx)
        m = max(1, int(round(window_m / stride_m)))

        def box(a: np.ndarray) -> np.ndarray:
            s = np.zeros((ny + 1, nx + 1))
            s[1:, 1:] = a.cumsum(0).cumsum(1)
            mh, mw = min(m, ny), min(m, nx)
            return s[mh:, mw:] - s[:-mh, mw:] - s[mh:, :-mw] + s[:-mh, :-mw]

        # box sums by cumsum differences can be -1e-16 where a window is empty
        v, nrm = box(votes), np.sqrt(np.maximum(box(norm_cells), 0.0))
        score = np.divide(v, nrm * qn, out=np.zeros_like(v), where=nrm > 0)
        flat = np.flatnonzero(score > 0)
        order = flat[np.argsort(-score.ravel()[flat], kind="stable")]
        if top is not None:
            order = order[: int(top)]
        out = []
        for o in order:
            r, c = divmod(int(o), score.shape[1])
            xmin, ymin = x0 + c * stride_m, y0 + r * stride_m
            out.append(
                ((xmin, ymin, xmin + m * stride_m, ymin + m * stride_m), float(score.ravel()[o]))
            )
        return out

    def features_in(self, bounds: tuple[float, float, float, float]) -> np.ndarray:
        """Ids (int64, ascending) of the features with xmin <= x <= xmax and ymin <= y <= ymax."""
        xmin, ymin, xmax, ymax = (float(v) for v in bounds)
        tb = np.asarray(self.tile_bounds)
        with np.errstate(invalid="ignore"):
            cand = np.flatnonzero(
                (tb[:, 0] <= xmax) & (tb[:, 2] >= xmin) & (tb[:, 1] <= ymax) & (tb[:, 3] >= ymin)
            )
        out = []
        for t in cand:
            lo, hi = int(self.tile_offsets[t]), int(self.tile_offsets[t + 1])
            xy = np.asarray(self.xy[lo:hi])
            inside = (
                (xy[:, 0] >= xmin) & (xy[:, 0] <= xmax) & (xy[:, 1] >= ymin) & (xy[:, 1] <= ymax)
            )
            out.append(lo + np.flatnonzero(inside))
        return np.concatenate(out) if out else np.zeros(0, np.int64)

    def knn(
        self, query_desc: np.ndarray, ids: np.ndarray | None = None, k: int = 2
    ) -> tuple[np.ndarray, np.ndarray]:
        """The ``k`` nearest map features of each query descriptor among feature ids ``ids``
        (all features when None). Returns (dist (n, k) float32 Euclidean, fid (n, k) int64 global
        feature ids), nearest first; missing neighbours (fewer than k candidates) are
        (inf, -1). Exact faiss flat search while |query| * |ids| <= ``KNN_FLAT_MAX_PAIRS``,
        a seeded FLANN kd-tree (approximate, ``georeg.index.kdtree``) above; never OpenCV BFMatcher.
        """
        q = np.ascontiguousarray(dequantize(query_desc), np.float32).reshape(-1, DESC_DIM)
        ids = np.arange(self.n_features) if ids is None else np.unique(np.asarray(ids, np.int64))
        n, kk = q.shape[0], int(k)
        dist = np.full((n, kk), np.inf, np.float32)
        fid = np.full((n, kk), -1, np.int64)
        if n == 0 or len(ids) == 0:
            return dist, fid
        base = dequantize(np.asarray(self.desc[ids]))
        kr = min(kk, len(ids))
        if n * len(ids) <= KNN_FLAT_MAX_PAIRS or len(ids) < 64:
            import faiss

            index = faiss.IndexFlatL2(DESC_DIM)
            index.add(base)
            for i in range(0, n, _CHUNK):
                d2, j = index.search(q[i : i + _CHUNK], kr)
                dist[i : i + len(d2), :kr] = np.sqrt(np.maximum(d2, 0))
                fid[i : i + len(d2), :kr] = np.where(j >= 0, ids[np.maximum(j, 0)], -1)
        else:
            j, d2 = knn_search(kdtree(base), q, kr)
            dist[:, :kr] = np.sqrt(np.maximum(d2, 0))
            fid[:, :kr] = ids[j]  # knn_search's ids are int64
        return dist, fid

    def knn_words(
        self, query_desc: np.ndarray, k: int = 10, nprobe: int = 8
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Approximate ``k`` nearest map features of each query descriptor over the WHOLE map.

        The vocabulary is the coarse quantizer of an inverted file: each descriptor is compared
        (exact L2) with the features of its ``nprobe`` nearest words only (IVF search; the cost
        is |query| x nprobe x the mean word size, read word by word, so the memory stays that of
        one word's descriptors). Returns flat arrays (query index, global feature id, distance),
        at most ``k`` per query, nearest first within each query.
        """
        q = np.ascontiguousarray(dequantize(query_desc), np.float32).reshape(-1, DESC_DIM)
        n, k, nprobe = len(q), max(1, int(k)), max(1, min(int(nprobe), self.n_words))
        empty = (np.zeros(0, np.int64), np.zeros(0, np.int64), np.zeros(0, np.float32))
        if n == 0 or self.n_features == 0:
            return empty
        _, words = self.quantize(q, nprobe)
        qq = np.repeat(np.arange(n), nprobe)
        ww = words.ravel()
        ok = ww >= 0
        qq, ww = qq[ok], ww[ok]
        o = np.argsort(ww, kind="stable")
        qq, ww = qq[o], ww[o]
        uw, first = np.unique(ww, return_index=True)
        last = np.r_[first[1:], len(ww)]
        offs = np.asarray(self.ivf_offsets)
        qn = (q**2).sum(axis=1)
        # many small products (a word's queries x its features): BLAS threads only spin there
        # (measured on 2 loaded cores: 11-18 s with 2 threads, 1.5-2.2 s with 1)
        with threadpool_limits(1, "blas"):
            rows = [
                self._knn_word(q, qn, qq[a:b], int(offs[w]), int(offs[w + 1]), k)
                for w, a, b in zip(uw.tolist(), first.tolist(), last.tolist(), strict=True)
                if offs[w + 1] > offs[w]
            ]
        if not rows:
            return empty
        cq, cf, cd = (np.concatenate(c) for c in zip(*rows, strict=True))
        o = np.lexsort((cd, cq))
        cq, cf, cd = cq[o], cf[o], cd[o]
        # every feature is in one word's list: no duplicates; keep the k nearest per query
        start = np.r_[0, np.flatnonzero(np.diff(cq)) + 1]
        rank = np.arange(len(cq)) - np.repeat(start, np.diff(np.r_[start, len(cq)]))
        keep = rank < k
        return cq[keep], cf[keep], np.sqrt(np.maximum(cd[keep], 0.0)).astype(np.float32)

    def _knn_word(
        self, q: np.ndarray, qn: np.ndarray, qs: np.ndarray, lo: int, hi: int, k: int
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """The ``k`` nearest of the word's features ``ivf_ids[lo:hi]`` for the queries ``qs``:
        (query index, feature id, squared distance), flat."""
        fid = np.sort(np.asarray(self.ivf_ids[lo:hi], np.int64))  # ascending: local reads
        m = dequantize(np.asarray(self.desc[fid]))
        d2 = qn[qs, None] - 2.0 * (q[qs] @ m.T) + (m**2).sum(axis=1)[None, :]
        kk = min(k, len(fid))
        if kk < len(fid):
            part = np.argpartition(d2, kk - 1, axis=1)[:, :kk]
        else:
            part = np.broadcast_to(np.arange(len(fid)), (len(qs), len(fid)))
        return np.repeat(qs, kk), fid[part].ravel(), np.take_along_axis(d2, part, axis=1).ravel()

    def features(self, ids: np.ndarray) -> dict[str, np.ndarray]:
        """The per-feature arrays (xy, z, ndsm, scale, angle, response, tile, word) of ``ids``."""
        ids = np.asarray(ids, np.int64)
        names = ("xy", "z", "ndsm", "scale", "angle", "response", "tile", "word")
        return {name: np.asarray(getattr(self, name)[ids]) for name in names}


def load_tile_words(path: str | os.PathLike, n: int, n_words: int) -> np.ndarray:
    """A tile's word file (rule ``tile_words``), checked: int32, ``n`` entries in [0, n_words)."""
    try:
        w = np.load(path)
    except (OSError, ValueError) as exc:
        raise InputError(path, f"cannot read: {exc}", "rerun rule tile_words") from exc
    if w.dtype != np.int32 or w.shape != (n,):
        raise InputError(
            path,
            f"{w.dtype} {w.shape}, expected int32 ({n},) for the tile's features",
            "rerun rule tile_words",
        )
    if n and (int(w.min()) < 0 or int(w.max()) >= n_words):
        raise InputError(path, f"word ids outside [0, {n_words})", "rerun rule tile_words")
    return w


def save_word_quantizer(
    centroids_path: str | os.PathLike,
    out_path: str | os.PathLike,
    method: str = "auto",
    ef_search: int = EF_SEARCH,
) -> str:
    """Rule ``word_quantizer``: build the nearest-word structure of the vocabulary once (the
    HNSW graph at K > 16,384 takes ~1 min) and save it for every ``tile_words`` job."""
    try:
        cent = np.load(centroids_path)
    except (OSError, ValueError) as exc:
        raise InputError(centroids_path, f"cannot read: {exc}", "rerun rule vocabulary") from exc
    t0 = time.perf_counter()
    q = WordQuantizer(cent, method, ef_search=ef_search)
    q.save(out_path)
    log.info(
        "word quantizer: %s over %d words in %.1f s", q.method, len(cent), time.perf_counter() - t0
    )
    return q.method


def assign_tile_words(
    feature_dir: str | os.PathLike,
    centroids_path: str | os.PathLike,
    out_path: str | os.PathLike,
    quantizer_path: str | os.PathLike | None = None,
) -> np.ndarray:
    """Rule ``tile_words``: the nearest visual word (int32) of every feature of one tile,
    written atomically as ``out_path`` (.npy). Uses the saved quantizer when given (else builds
    it from the centroids): the same ``WordQuantizer.words`` as ``MapIndex.build``."""
    d = Path(feature_dir)
    try:
        cent = np.load(centroids_path)
        desc = np.load(d / "desc.npy", mmap_mode="r")
    except (OSError, ValueError) as exc:
        raise InputError(d, f"cannot read: {exc}", "rerun rule tile_features") from exc
    if desc.dtype != np.uint8:  # as MapIndex.build stores it
        desc = np.clip(np.rint(np.asarray(desc) * DESC_SCALE), 0, 255).astype(np.uint8)
    t0 = time.perf_counter()
    q = (
        WordQuantizer.load(quantizer_path, cent)
        if quantizer_path is not None
        else WordQuantizer(cent)
    )
    t1 = time.perf_counter()
    w = q.words(desc) if len(desc) else np.zeros(0, np.int32)
    with atomic_path(out_path) as tmp:
        np.save(tmp, w)
    log.info(
        "%s: %d features -> words (%s, %d words): quantizer %.2f s, assignment %.2f s",
        d.name, len(w), q.method, len(cent), t1 - t0, time.perf_counter() - t1,
    )  # fmt: skip
    return w


def build_from_grid(
    grid_path: str | os.PathLike,
    feature_dirs: Sequence[str | os.PathLike],
    centroids_path: str | os.PathLike,
    out_dir: str | os.PathLike,
    word_files: Sequence[str | os.PathLike] | None = None,
    quantizer_file: str | os.PathLike | None = None,
) -> MapIndex:
    """Rule ``build_index``: tile ids from the feature dirs' names, CRS from grid.json; words
    from ``word_files`` (``<tile>.npy``, matched to the feature dirs by name) when given; the
    saved nearest-word structure ``quantizer_file`` copied in for the queries."""
    try:
        grid = json.loads(Path(grid_path).read_text())
        cent = np.load(centroids_path)
    except (OSError, ValueError) as exc:
        raise InputError(grid_path, f"cannot read build inputs: {exc}") from exc
    dirs = sorted((Path(d) for d in feature_dirs), key=lambda p: p.name)
    words = None
    if word_files is not None:
        by_tile = {Path(f).stem: Path(f) for f in word_files}
        missing = [d.name for d in dirs if d.name not in by_tile]
        if missing or len(by_tile) != len(dirs):
            raise InputError(
                None,
                f"word files do not match the feature tiles (missing: {missing[:5]})",
                "rerun rule tile_words",
            )
        words = [by_tile[d.name] for d in dirs]
    vocab_meta = Path(centroids_path).with_name("meta.json")
    extra = {"vocabulary": json.loads(vocab_meta.read_text()) if vocab_meta.exists() else None}
    return MapIndex.build(
        dirs,
        [d.name for d in dirs],
        cent,
        out_dir,
        crs_wkt=grid.get("crs"),
        extra_meta=extra,
        words=words,
        quantizer_file=quantizer_file,
    )
