"""Feature index benchmark (issue 4): build throughput vs bare SIFT, k-means backends, quantizers.

    source /work/venv/bin/activate
    python benchmarks/bench_index.py throughput      # index build vs bare cv2 SIFT, 1 core
    python benchmarks/bench_index.py backends        # faiss vs MiniBatchKMeans: time, mse, retrieval
    python benchmarks/bench_index.py kmeans --k 10000 --n 1000000 --iterations 20
    python benchmarks/bench_index.py quantizer       # flat vs HNSW vs FLANN kd-tree, k = 100,000
    python benchmarks/bench_index.py words --k 1000  # build_index: in-process words vs tile_words

Data: ../shared/data/autzen/autzen.jpg (real RGB orthophoto, 3248 x 4385 px). Results are
printed as JSON lines and appended to benchmarks/out/bench_index.jsonl.
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import statistics
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
AUTZEN = ROOT.parent / "shared" / "data" / "autzen" / "autzen.jpg"
OUT = ROOT / "benchmarks" / "out" / "bench_index.jsonl"


def peak_rss_mb() -> float:
    """Peak resident memory of this process (VmHWM), MB."""
    for line in Path("/proc/self/status").read_text().splitlines():
        if line.startswith("VmHWM:"):
            return int(line.split()[1]) / 1024
    return float("nan")


def emit(rec: dict) -> None:
    rec = {"time": time.strftime("%Y-%m-%dT%H:%M:%S"), **rec}
    print(json.dumps(rec), flush=True)
    OUT.parent.mkdir(parents=True, exist_ok=True)
    with OUT.open("a") as f:
        f.write(json.dumps(rec) + "\n")


def autzen_gray() -> tuple[np.ndarray, object]:
    import rasterio

    from georeg.index.features import rgb_to_gray

    with rasterio.open(AUTZEN) as ds:
        return rgb_to_gray(ds.read()), ds.transform


def write_tiles(tmp: Path, size: int = 1024, overlap: int = 64) -> tuple[Path, list[str]]:
    """Cut autzen into map-stage-like tiles: ortho.tif (RGB), dsm.tif, ndsm.tif + grid.json."""
    import rasterio
    from rasterio.transform import Affine

    with rasterio.open(AUTZEN) as ds:
        rgb, tr, crs = ds.read(), ds.transform, ds.crs
    h, w = rgb.shape[1:]
    tiles = {}
    stride = size - overlap
    starts = lambda n: list(range(0, max(n - overlap, 1), stride))  # noqa: E731
    rs, cs = starts(h), starts(w)
    for r, r0 in enumerate(rs):
        for c, c0 in enumerate(cs):
            tid = f"r{r:03d}_c{c:03d}"
            ww, hh = min(size, w - c0), min(size, h - r0)
            clo = 0 if c == 0 else c0 + overlap // 2
            chi = w if c == len(cs) - 1 else cs[c + 1] + overlap // 2
            rlo = 0 if r == 0 else r0 + overlap // 2
            rhi = h if r == len(rs) - 1 else rs[r + 1] + overlap // 2
            tiles[tid] = {
                "row": r,
                "col": c,
                "window": [c0, r0, ww, hh],
                "core": [clo, rlo, chi - clo, rhi - rlo],
            }
            d = tmp / "tiles" / tid
            d.mkdir(parents=True, exist_ok=True)
            ttr = tr @ Affine.translation(c0, r0)
            prof = dict(
                driver="GTiff",
                width=ww,
                height=hh,
                crs=crs,
                transform=ttr,
                tiled=True,
                blockxsize=256,
                blockysize=256,
                compress="deflate",
            )
            with rasterio.open(d / "ortho.tif", "w", count=3, dtype="uint8", **prof) as o:
                o.write(rgb[:, r0 : r0 + hh, c0 : c0 + ww])
            z = (100 + rgb[0, r0 : r0 + hh, c0 : c0 + ww] / 25.0).astype(np.float32)
            for name in ("dsm", "ndsm"):
                with rasterio.open(
                    d / f"{name}.tif", "w", count=1, dtype="float32", nodata=-9999, **prof
                ) as o:
                    o.write(z, 1)
    grid = {"crs": crs.to_wkt(), "transform": list(tr)[:6], "width": w, "height": h, "tiles": tiles}
    (tmp / "grid.json").write_text(json.dumps(grid))
    return tmp / "grid.json", sorted(tiles)


def bench_throughput(args: argparse.Namespace) -> None:
    """Whole index build (tile features from disk + vocabulary + index) vs bare SIFT, 1 core."""
    import cv2
    import faiss

    from georeg.index.features import extract_tile_from_grid, merged_conf, read_ortho_gray
    from georeg.index.map_index import build_from_grid
    from georeg.index.vocabulary import build_vocabulary

    cv2.setNumThreads(1)
    faiss.omp_set_num_threads(1)
    conf = merged_conf({})
    vconf = {"k": args.k, "sample_size": 500_000, "iterations": args.iterations}
    tmp = Path(tempfile.mkdtemp(prefix="bench_index_"))
    try:
        grid, tids = write_tiles(tmp)
        grays = [read_ortho_gray(tmp / "tiles" / t / "ortho.tif")[0] for t in tids]
        mpx_tiles = sum(g.size for g in grays) / 1e6
        g = json.loads(grid.read_text())
        mpx_map = g["width"] * g["height"] / 1e6
        s = conf["sift"]
        floor_t, feat_t, vocab_t, build_t = [], [], [], []
        for _ in range(args.runs):
            sift = cv2.SIFT_create(
                nfeatures=0,
                nOctaveLayers=s["n_octave_layers"],
                contrastThreshold=s["contrast_threshold"],
                edgeThreshold=s["edge_threshold"],
                sigma=s["sigma"],
                enable_precise_upscale=True,
            )
            t0 = time.perf_counter()
            for gr in grays:
                sift.detectAndCompute(gr, None)
            floor_t.append(time.perf_counter() - t0)
            out = tmp / "index"
            shutil.rmtree(out, ignore_errors=True)
            t0 = time.perf_counter()
            dirs = []
            for t in tids:
                d = tmp / "tiles" / t
                extract_tile_from_grid(
                    grid,
                    t,
                    d / "ortho.tif",
                    d / "dsm.tif",
                    d / "ndsm.tif",
                    conf,
                    out / "features" / t,
                )
                dirs.append(out / "features" / t)
            t1 = time.perf_counter()
            build_vocabulary(dirs, out / "vocabulary", vconf, 42, 1)
            t2 = time.perf_counter()
            build_from_grid(grid, dirs, out / "vocabulary" / "centroids.npy", out / "map")
            t3 = time.perf_counter()
            feat_t.append(t1 - t0)
            vocab_t.append(t2 - t1)
            build_t.append(t3 - t2)
        med = statistics.median
        total = [a + b + c for a, b, c in zip(feat_t, vocab_t, build_t, strict=True)]
        meta = json.loads((out / "map" / "meta.json").read_text())
        size_idx = sum(f.stat().st_size for f in (out / "map").iterdir())
        size_feat = sum(f.stat().st_size for f in (out / "features").rglob("*") if f.is_file())
        emit(
            {
                "bench": "throughput",
                "tiles": len(tids),
                "mpx_tile_pixels": round(mpx_tiles, 3),
                "mpx_map": round(mpx_map, 3),
                "n_features": meta["n_features"],
                "k": args.k,
                "vocab_iterations": args.iterations,
                "runs": args.runs,
                "floor_s": round(med(floor_t), 3),
                "features_s": round(med(feat_t), 3),
                "vocabulary_s": round(med(vocab_t), 3),
                "build_s": round(med(build_t), 3),
                "total_s": round(med(total), 3),
                "floor_mpx_s_core": round(mpx_tiles / med(floor_t), 3),
                "index_mpx_s_core": round(mpx_tiles / med(total), 3),
                "ratio_total": round(med(total) / med(floor_t), 3),
                "ratio_features_only": round(med(feat_t) / med(floor_t), 3),
                "ratio_without_vocabulary": round((med(feat_t) + med(build_t)) / med(floor_t), 3),
                "index_mb_per_mpx": round(size_idx / 1e6 / mpx_map, 4),
                "features_mb_per_mpx": round(size_feat / 1e6 / mpx_map, 4),
                "peak_rss_mb": round(peak_rss_mb(), 1),
            }
        )
    finally:
        shutil.rmtree(tmp, ignore_errors=True)


def descriptor_pool(n: int, seed: int = 0) -> np.ndarray:
    """n RootSIFT descriptors: real ones from autzen and rotated/rescaled copies of it
    (new keypoints, real descriptors); beyond those, noisy copies (Gaussian noise sigma 0.02 on
    each component, clipped at 0 and renormalised). Cached in benchmarks/out/."""
    cache = ROOT / "benchmarks" / "out" / f"desc_pool_{n}_{seed}.npy"
    if cache.exists():
        return np.load(cache)
    import cv2

    from georeg.index.features import detect_and_describe, merged_conf

    gray, _ = autzen_gray()
    conf = merged_conf({"max_features_per_mpx": None, "sift": {"contrast_threshold": 0.02}})
    real, count = [], 0
    h, w = gray.shape
    for angle, scale in [(0, 1.0), (33, 0.8), (-71, 0.6), (120, 1.25), (200, 0.7), (290, 0.9)]:
        m = cv2.getRotationMatrix2D((w / 2, h / 2), angle, scale)
        img = cv2.warpAffine(gray, m, (w, h))
        msk = cv2.warpAffine(np.full_like(gray, 255), m, (w, h)) > 0
        d = detect_and_describe(img, msk, conf).desc
        real.append(d)
        count += len(d)
        if count >= n:
            break
    x = np.concatenate(real)
    n_real = len(x)
    rng = np.random.default_rng(seed)
    parts = [x]
    while sum(len(p) for p in parts) < n:
        y = np.maximum(x + rng.normal(0, 0.02, x.shape).astype(np.float32), 0)
        y /= np.linalg.norm(y, axis=1, keepdims=True)
        parts.append(y)
    pool = np.concatenate(parts)[:n]
    pool = pool[rng.permutation(len(pool))]
    cache.parent.mkdir(parents=True, exist_ok=True)
    np.save(cache, pool)
    print(f"descriptor pool: {n_real} real, {n - min(n, n_real)} noisy copies", file=sys.stderr)
    return pool


def heldout_descriptors() -> np.ndarray:
    """RootSIFT descriptors of autzen rotated by 47 deg and scaled by 1.1: keypoints not in the
    training pool (different resampling), for a held-out quantisation error."""
    cache = ROOT / "benchmarks" / "out" / "desc_heldout.npy"
    if cache.exists():
        return np.load(cache)
    import cv2

    from georeg.index.features import detect_and_describe, merged_conf

    gray, _ = autzen_gray()
    h, w = gray.shape
    m = cv2.getRotationMatrix2D((w / 2, h / 2), 47, 1.1)
    img = cv2.warpAffine(gray, m, (w, h))
    msk = cv2.warpAffine(np.full_like(gray, 255), m, (w, h)) > 0
    d = detect_and_describe(img, msk, merged_conf({"max_features_per_mpx": None})).desc[:20000]
    np.save(cache, d)
    return d


def bench_kmeans(args: argparse.Namespace) -> None:
    """One k-means run (meant to be run in its own process so that peak memory is its own)."""
    from georeg.index.vocabulary import quantization_error, train_kmeans

    x = descriptor_pool(args.n)
    rss0 = peak_rss_mb()
    t0 = time.perf_counter()
    cent, stats = train_kmeans(x, args.k, 42, args.backend, args.iterations, args.threads)
    dt = time.perf_counter() - t0
    held = heldout_descriptors()
    emit(
        {
            "bench": "kmeans",
            "backend": args.backend,
            "k": args.k,
            "n": args.n,
            "iterations": args.iterations,
            "threads": args.threads,
            "seconds": round(dt, 2),
            "seconds_per_iteration": round(dt / args.iterations, 2),
            "mse_train_subset": round(quantization_error(x[:50000], cent), 5),
            "mse_heldout": round(quantization_error(held, cent), 5),
            "peak_rss_mb": round(peak_rss_mb(), 1),
            "rss_before_mb": round(rss0, 1),
        }
    )


def bench_backends(args: argparse.Namespace) -> None:
    """faiss vs MiniBatchKMeans on the same sample: time, quantisation error, tile retrieval."""
    import cv2
    from rasterio.transform import Affine

    from georeg.index.features import (
        detect_and_describe,
        merged_conf,
        save_tile_features,
        tile_features,
    )
    from georeg.index.map_index import MapIndex
    from georeg.index.vocabulary import quantization_error, sample_descriptors, train_kmeans

    gray, tr = autzen_gray()
    conf = merged_conf({})
    tmp = Path(tempfile.mkdtemp(prefix="bench_backends_"))
    try:
        size, ov = 512, 64
        h, w = gray.shape
        dirs, ids, cores = [], [], []
        for r0 in range(0, h, size):
            for c0 in range(0, w, size):
                wr0, wc0 = max(r0 - ov // 2, 0), max(c0 - ov // 2, 0)
                wr1, wc1 = min(r0 + size + ov // 2, h), min(c0 + size + ov // 2, w)
                core = (c0 - wc0, r0 - wr0, min(size, w - c0), min(size, h - r0))
                tf = tile_features(
                    gray[wr0:wr1, wc0:wc1], None, tr @ Affine.translation(wc0, wr0), conf, core
                )
                tid = f"r{r0 // size:03d}_c{c0 // size:03d}"
                save_tile_features(tmp / tid, tf, {"features_conf_hash": "b"})
                dirs.append(tmp / tid)
                ids.append(tid)
                cores.append((r0, c0))
        x = sample_descriptors(dirs, 10**9, 0)
        rng = np.random.default_rng(3)
        queries = []
        for t in rng.choice(len(ids), size=min(40, len(ids)), replace=False):
            r0, c0 = cores[t]
            crop = gray[r0 : r0 + size, c0 : c0 + size]
            if crop.shape != (size, size):
                continue
            m = cv2.getRotationMatrix2D(
                (size / 2, size / 2), float(rng.uniform(0, 360)), float(rng.uniform(0.7, 1.3))
            )
            q = cv2.warpAffine(crop, m, (size, size))
            qm = cv2.warpAffine(np.full_like(crop, 255), m, (size, size)) > 0
            # photometric change too: gamma and noise, like a different sensor/date
            q = np.clip(255 * (q / 255.0) ** 0.7 + rng.normal(0, 6, q.shape), 0, 255).astype(
                np.uint8
            )
            queries.append((int(t), detect_and_describe(q, qm, conf).desc))
        for k in args.ks:
            for backend in ("faiss", "minibatch"):
                t0 = time.perf_counter()
                cent, _ = train_kmeans(x, k, 42, backend, args.iterations, args.threads)
                dt = time.perf_counter() - t0
                idx = MapIndex.build(dirs, ids, cent, tmp / f"map_{backend}_{k}")
                top1 = np.mean([idx.rank_tiles(d, top=1)[0][0] == t for t, d in queries])
                top3 = np.mean([t in [r[0] for r in idx.rank_tiles(d, top=3)] for t, d in queries])
                emit(
                    {
                        "bench": "backends",
                        "backend": backend,
                        "k": k,
                        "n": len(x),
                        "iterations": args.iterations,
                        "threads": args.threads,
                        "seconds": round(dt, 2),
                        "mse": round(quantization_error(x, cent), 5),
                        "retrieval_top1": round(float(top1), 3),
                        "retrieval_top3": round(float(top3), 3),
                        "queries": len(queries),
                        "tiles": len(ids),
                    }
                )
    finally:
        shutil.rmtree(tmp, ignore_errors=True)


def bench_quantizer(args: argparse.Namespace) -> None:
    """Nearest-word search over k centroids: exact flat vs HNSW vs FLANN kd-tree."""
    import faiss

    from georeg.index.map_index import WordQuantizer

    faiss.omp_set_num_threads(args.threads)
    pool = descriptor_pool(args.n)
    rng = np.random.default_rng(0)
    cent = pool[
        rng.choice(len(pool), args.k, replace=False)
    ]  # stand-in centroids (real descriptors)
    q = heldout_descriptors()[: args.queries]
    ref = None
    for method in ("flat", "hnsw", "kdtree"):
        t0 = time.perf_counter()
        wq = WordQuantizer(cent, method)
        t_build = time.perf_counter() - t0
        t0 = time.perf_counter()
        _, w = wq.search(q, 2)
        t_q = time.perf_counter() - t0
        if ref is None:
            ref = w
        emit(
            {
                "bench": "quantizer",
                "method": method,
                "k": args.k,
                "queries": len(q),
                "threads": args.threads,
                "build_s": round(t_build, 2),
                "search_s": round(t_q, 3),
                "us_per_query": round(1e6 * t_q / len(q), 1),
                "recall_at_1": round(float((w[:, 0] == ref[:, 0]).mean()), 4),
            }
        )


_CHILD = r"""
import json, os, sys, time
import faiss
faiss.omp_set_num_threads(1)
sys.path.insert(0, {root!r})
from georeg.index import map_index as I
t0, c0 = time.perf_counter(), os.times()
{body}
c1 = os.times()
hwm = [l for l in open("/proc/self/status") if l.startswith("VmHWM:")][0].split()[1]
print(json.dumps({{"s": time.perf_counter() - t0, "cpu_s": c1.user + c1.system - c0.user - c0.system,
                   "peak_rss_mb": int(hwm) / 1024}}))
"""


def _child(body: str) -> dict:
    """Run ``body`` in a fresh Python (like a Snakemake script job): its time, CPU, peak RSS."""
    import subprocess

    t0 = time.perf_counter()
    res = subprocess.run(
        [sys.executable, "-c", _CHILD.format(root=str(ROOT), body=body)],
        capture_output=True,
        text=True,
        check=True,
    )
    rec = json.loads(res.stdout.strip().splitlines()[-1])
    rec["process_s"] = time.perf_counter() - t0
    return rec


def bench_words(args: argparse.Namespace) -> None:
    """build_index before (words assigned in process) vs after (tile_words jobs + a merge).

    Each step runs in its own Python process, as the rules do: time inside, CPU, peak RSS
    (VmHWM), and the process wall time including start-up. The two indexes must be identical.
    K <= the number of autzen features: a real faiss vocabulary; above (the HNSW range), a
    synthetic one (descriptors + noise, renormalised): the cost does not depend on the words.
    """
    import cv2

    from georeg.index.features import dequantize, extract_tile_from_grid, merged_conf
    from georeg.index.map_index import INDEX_ARRAYS
    from georeg.index.vocabulary import build_vocabulary

    cv2.setNumThreads(1)
    tmp = Path(tempfile.mkdtemp(prefix="bench_words_"))
    try:
        grid, tids = write_tiles(tmp)
        conf = merged_conf({})
        dirs = []
        for t in tids:
            d = tmp / "tiles" / t
            out = tmp / "features" / t
            extract_tile_from_grid(
                grid, t, d / "ortho.tif", d / "dsm.tif", d / "ndsm.tif", conf, out
            )
            dirs.append(out)
        desc = np.concatenate([np.load(d / "desc.npy") for d in dirs])
        cent = tmp / "vocabulary" / "centroids.npy"
        if args.k <= len(desc):
            build_vocabulary(dirs, cent.parent, {"k": args.k, "iterations": 20}, 42, 1)
        else:
            rng = np.random.default_rng(0)
            c = dequantize(desc[rng.integers(0, len(desc), args.k)])
            c += rng.normal(0, 0.02, c.shape).astype(np.float32)
            c /= np.linalg.norm(c, axis=1, keepdims=True)
            cent.parent.mkdir(parents=True)
            np.save(cent, c.astype(np.float32))
        dl = [str(d) for d in dirs]
        before = _child(
            f"I.build_from_grid({str(grid)!r}, {dl!r}, {str(cent)!r}, {str(tmp / 'before')!r})"
        )
        qpath = tmp / "vocabulary" / "quantizer.faiss"
        quant = _child(f"I.save_word_quantizer({str(cent)!r}, {str(qpath)!r})")
        words, per_tile = [], []
        for d in dirs:
            w = tmp / "words" / f"{d.name}.npy"
            per_tile.append(
                _child(
                    f"I.assign_tile_words({str(d)!r}, {str(cent)!r}, {str(w)!r}, {str(qpath)!r})"
                )
            )
            words.append(str(w))
        after = _child(
            f"I.build_from_grid({str(grid)!r}, {dl!r}, {str(cent)!r}, {str(tmp / 'after')!r}, {words!r})"
        )
        identical = all(
            np.array_equal(
                np.load(tmp / "before" / f"{n}.npy"), np.load(tmp / "after" / f"{n}.npy")
            )
            for n in INDEX_ARRAYS
        )
        r = lambda x: round(x, 3)  # noqa: E731
        emit(
            {
                "bench": "words",
                "k": args.k,
                "features": int(len(desc)),
                "tiles": len(dirs),
                "before_build_index": {k: r(v) for k, v in before.items()},
                "word_quantizer": {k: r(v) for k, v in quant.items()},
                "tile_words_sum": {
                    k: r(sum(p[k] for p in per_tile)) for k in ("s", "cpu_s", "process_s")
                },
                "tile_words_max": {k: r(max(p[k] for p in per_tile)) for k in per_tile[0]},
                "after_build_index": {k: r(v) for k, v in after.items()},
                "identical": identical,
                "loadavg": os.getloadavg()[0],
            }
        )
    finally:
        shutil.rmtree(tmp, ignore_errors=True)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawTextHelpFormatter)
    ap.add_argument("stage", choices=["throughput", "kmeans", "backends", "quantizer", "words"])
    ap.add_argument("--k", type=int, default=2000)
    ap.add_argument("--ks", type=int, nargs="+", default=[1000, 4000])
    ap.add_argument("--n", type=int, default=1_000_000)
    ap.add_argument("--iterations", type=int, default=20)
    ap.add_argument("--threads", type=int, default=os.cpu_count() or 1)
    ap.add_argument("--backend", default="faiss")
    ap.add_argument("--runs", type=int, default=3)
    ap.add_argument("--queries", type=int, default=20000)
    args = ap.parse_args()
    if not AUTZEN.exists():
        sys.exit(f"benchmark data missing: {AUTZEN}")
    {
        "throughput": bench_throughput,
        "kmeans": bench_kmeans,
        "backends": bench_backends,
        "quantizer": bench_quantizer,
        "words": bench_words,
    }[args.stage](args)


if __name__ == "__main__":
    main()
