"""Visual words: k-means over a seeded sample of the map's descriptors.

Backends (chosen by measurement, see docs/BENCHMARKS.md "Feature index"):

* ``faiss``: ``faiss.Kmeans`` (Lloyd iterations, exact assignment with a flat L2 index,
  multi-threaded BLAS). The default: fast up to k = 100,000 and the best quantisation error.
* ``minibatch``: scikit-learn ``MiniBatchKMeans`` (kept for comparison and for machines
  without faiss; much slower for large k because of its k-means++ initialisation).

Both are deterministic for a given seed (faiss with a fixed thread count: the assignment is
exact and each centroid is reduced by one thread).
"""

from __future__ import annotations

import json
import logging
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

from georeg.index.features import dequantize
from georeg.io.errors import ConfigError, InputError

log = logging.getLogger(__name__)

DEFAULT_CONF: dict[str, Any] = {
    "k": 1000,
    "sample_size": 500_000,
    "seed": None,
    "backend": "faiss",
    "iterations": 20,
}


def sample_descriptors(
    feature_dirs: Sequence[str | Path], sample_size: int, seed: int
) -> np.ndarray:
    """A uniform sample without replacement of all tiles' descriptors, float32 (n, 128).

    Deterministic for a seed and an ordered list of tiles; memory is O(sample_size): the per-tile
    arrays are memory-mapped and only the sampled rows are read.
    """
    descs = []
    for d in feature_dirs:
        p = Path(d) / "desc.npy"
        try:
            descs.append(np.load(p, mmap_mode="r"))
        except (OSError, ValueError) as exc:
            raise InputError(
                p, f"cannot read descriptors: {exc}", "rerun rule tile_features"
            ) from exc
    counts = np.array([a.shape[0] for a in descs], np.int64)
    total = int(counts.sum())
    if total == 0:
        raise InputError(None, "no features in any map tile", "check the orthophoto and features:")
    rng = np.random.default_rng(seed)
    n = min(int(sample_size), total)
    pick = np.sort(rng.choice(total, size=n, replace=False)) if n < total else np.arange(total)
    starts = np.concatenate([[0], np.cumsum(counts)])
    out = np.empty((n, descs[0].shape[1] if descs[0].ndim == 2 else 128), np.float32)
    bounds = np.searchsorted(pick, starts)
    for i, a in enumerate(descs):
        lo, hi = bounds[i], bounds[i + 1]
        if hi > lo:
            out[lo:hi] = dequantize(np.asarray(a[pick[lo:hi] - starts[i]]))
    return out


def train_kmeans(
    x: np.ndarray,
    k: int,
    seed: int,
    backend: str = "faiss",
    iterations: int = 20,
    threads: int | None = None,
) -> tuple[np.ndarray, dict[str, Any]]:
    """k-means centroids (k, d) float32 of ``x`` (n, d); returns them and training stats."""
    x = np.ascontiguousarray(x, dtype=np.float32)
    n, d = x.shape
    if k < 1:
        raise ConfigError(f"vocabulary.k must be >= 1, got {k}")
    if n < k:
        raise ConfigError(
            f"vocabulary: only {n} descriptors sampled for k = {k} words",
        )
    t0 = time.perf_counter()
    if backend == "faiss":
        import faiss

        if threads:
            faiss.omp_set_num_threads(int(threads))
        km = faiss.Kmeans(
            d,
            int(k),
            niter=int(iterations),
            seed=int(seed) % (2**31),
            max_points_per_centroid=max(256, n // k + 1),  # use the whole sample
            min_points_per_centroid=1,
            verbose=False,
        )
        km.train(x)
        cent = np.ascontiguousarray(km.centroids, dtype=np.float32)
        obj = [float(v) for v in km.obj] if len(km.obj) else []
    elif backend == "minibatch":
        from sklearn.cluster import MiniBatchKMeans

        km = MiniBatchKMeans(
            n_clusters=int(k),
            random_state=int(seed),
            max_iter=int(iterations),
            batch_size=max(4096, 3 * int(k)),
            n_init=1,
            init_size=min(n, max(3 * int(k), 10_000)),
            reassignment_ratio=0.01,
        )
        km.fit(x)
        cent = np.ascontiguousarray(km.cluster_centers_, dtype=np.float32)
        obj = []
    else:
        raise ConfigError(f"vocabulary.backend must be 'faiss' or 'minibatch', got {backend!r}")
    stats = {"backend": backend, "k": int(k), "n": int(n), "seconds": time.perf_counter() - t0}
    if obj:
        stats["objective"] = obj[-1]
    return cent, stats


def quantization_error(x: np.ndarray, centroids: np.ndarray, chunk: int = 65536) -> float:
    """Mean squared distance from each row of ``x`` to its nearest centroid (exact)."""
    import faiss

    idx = faiss.IndexFlatL2(centroids.shape[1])
    idx.add(np.ascontiguousarray(centroids, np.float32))
    tot = 0.0
    for i in range(0, len(x), chunk):
        dist, _ = idx.search(np.ascontiguousarray(x[i : i + chunk], np.float32), 1)
        tot += float(dist.sum())
    return tot / max(len(x), 1)


def build_vocabulary(
    feature_dirs: Sequence[str | Path],
    out_dir: str | Path,
    conf: dict[str, Any],
    seed: int,
    threads: int | None = None,
) -> dict[str, Any]:
    """Sample, cluster, and write ``centroids.npy`` + ``meta.json`` into ``out_dir``."""
    from georeg.io.atomic import atomic_path, write_json

    c = {**DEFAULT_CONF, **(conf or {})}
    x = sample_descriptors(feature_dirs, int(c["sample_size"]), seed)
    k = int(c["k"])
    if len(x) < k:
        log.warning("vocabulary: %d descriptors for k = %d: using k = %d", len(x), k, len(x))
        k = len(x)
    log.info("vocabulary: k-means k=%d on %d descriptors (%s)", k, len(x), c["backend"])
    cent, stats = train_kmeans(x, k, seed, c["backend"], int(c["iterations"]), threads)
    stats["mse"] = quantization_error(x, cent)
    # the features conf of the first tile: the vocabulary is only valid for that descriptor type
    first_meta = json.loads((Path(feature_dirs[0]) / "meta.json").read_text())
    meta = {
        **stats,
        "seed": int(seed),
        "iterations": int(c["iterations"]),
        "sample_size": int(len(x)),
        "n_tiles": len(feature_dirs),
        "features_conf_hash": first_meta.get("features_conf_hash"),
    }
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    with atomic_path(out / "centroids.npy") as tmp:
        np.save(tmp, cent)
    write_json(out / "meta.json", meta)
    log.info("vocabulary: %d words in %.1f s, mse %.4f", k, stats["seconds"], stats["mse"])
    return meta
