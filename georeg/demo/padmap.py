"""A real frames case padded into a large map of other real imagery (frames on county-sized maps).

The case's orthophoto and elevation (``../shared/data/frames_dev/<case>``) keep their pixels and
coordinates; around them the map grows to ``n`` x ``n`` blocks of ``BLOCK`` px with real aerial
imagery of other places (autzen tiles, the brighton orthophoto, the SRIF optical references,
packed into blocks; never the other frames case), chosen per block by a seeded draw. The DSM is
the case's elevation in its blocks and flat (its median) elsewhere.

Outputs under ``out``: ``blocks/*.tif`` (distinct 1024 px blocks), ``ortho.vrt`` and ``dsm.vrt``
(mosaics referencing the blocks, so a 1 Gpx map costs disk only for its distinct blocks),
``index/`` (a ``MapIndex`` in the workflow's format and default feature settings: one tile per
block, the features of a distinct block extracted once and placed wherever it is used, the
vocabulary trained on a uniform sample of all placed features) and ``padmap.json``.
Features of a repeated block are those of the block alone (no context across block borders);
otherwise the index is what ``tile_features`` / ``MapIndex.build`` write.

    python -m georeg.demo.padmap --case odm --blocks 6 --out /work/bigmaps/odm_6
"""

from __future__ import annotations

import argparse
import glob
import json
import logging
import time
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import rasterio
from affine import Affine
from rasterio.windows import Window

BLOCK = 1024
log = logging.getLogger(__name__)


def _tiles_of(img: np.ndarray, side: int = BLOCK) -> list[np.ndarray]:
    h, w = img.shape[:2]
    return [img[r : r + side, c : c + side] for r in range(0, h - side + 1, side)
            for c in range(0, w - side + 1, side)]  # fmt: skip


def _fit(img: np.ndarray, side: int) -> np.ndarray:
    """Centre crop, then reflect padding, to ``side`` x ``side``."""
    h, w = img.shape[:2]
    r0, c0 = max(0, (h - side) // 2), max(0, (w - side) // 2)
    img = img[r0 : r0 + side, c0 : c0 + side]
    h, w = img.shape[:2]
    return cv2.copyMakeBorder(img, 0, side - h, 0, side - w, cv2.BORDER_REFLECT_101)


def pad_blocks(data: str | Path) -> list[np.ndarray]:
    """Distinct RGB blocks of real imagery from ``data`` (``../shared/data``), deterministic order."""
    data = Path(data)
    out: list[np.ndarray] = []
    rgb = cv2.cvtColor(cv2.imread(str(data / "autzen" / "autzen.jpg")), cv2.COLOR_BGR2RGB)
    out += _tiles_of(rgb)
    with rasterio.open(data / "brighton" / "map_ortho.tif") as s:
        out.append(_fit(np.moveaxis(s.read([1, 2, 3]), 0, -1), BLOCK))
    refs = sorted(glob.glob(str(data / "srif_dev" / "Optical-*" / "pair*_1.jpg")))
    cells = [_fit(cv2.cvtColor(cv2.imread(f), cv2.COLOR_BGR2RGB), BLOCK // 2) for f in refs]
    for i in range(0, len(cells) - 3, 4):
        a, b, c, d = cells[i : i + 4]
        out.append(np.vstack([np.hstack([a, b]), np.hstack([c, d])]))
    return [np.ascontiguousarray(b) for b in out]


def _write(path: Path, arr: np.ndarray, dtype: str) -> None:
    a = arr if arr.ndim == 3 else arr[..., None]
    prof = {"driver": "GTiff", "width": a.shape[1], "height": a.shape[0], "count": a.shape[2],
            "dtype": dtype, "tiled": True, "blockxsize": 256, "blockysize": 256, "compress": "deflate"}  # fmt: skip
    with rasterio.open(path, "w", **prof) as d:
        d.write(np.moveaxis(a, -1, 0).astype(dtype))


def case_layout(case_dir: Path, n: int, block: int = BLOCK) -> dict[str, Any]:
    """Where the case sits: its block rectangle (rows, cols) and the big map's geotransform."""
    with rasterio.open(case_dir / "map_ortho.tif") as s:
        tr, w, h = s.transform, s.width, s.height
    cb = (int(np.ceil(h / block)), int(np.ceil(w / block)))
    n = max(n, *cb)
    r0, c0 = (n - cb[0]) // 3, (n - cb[1]) // 3
    g = float(tr.a)
    big = Affine(g, 0, tr.c - c0 * block * g, 0, tr.e, tr.f - r0 * block * tr.e)
    return {"n": n, "case_blocks": cb, "case_origin_block": (r0, c0), "transform": big, "gsd": g,
            "block": block}  # fmt: skip


def case_blocks(case_dir: Path, lay: dict, pads: list[np.ndarray], pick: np.ndarray, crs: str):
    """The case's ortho and elevation cut into blocks on the big grid (invalid ortho pixels from
    the pad block drawn for that place; elevation NaN -> its median). Yields (r, c, rgb, z)."""
    from rasterio.warp import Resampling, reproject

    (nr, nc), (r0, c0), big = lay["case_blocks"], lay["case_origin_block"], lay["transform"]
    bs = lay["block"]
    with rasterio.open(case_dir / "map_ortho.tif") as s:
        rgb = np.moveaxis(s.read([1, 2, 3]), 0, -1)
        valid = s.dataset_mask() > 0
    H, W = nr * bs, nc * bs
    canvas = np.zeros((H, W, 3), np.uint8)
    for i in range(nr):
        for j in range(nc):
            canvas[i * bs : (i + 1) * bs, j * bs : (j + 1) * bs] = pads[pick[r0 + i, c0 + j]]
    h, w = valid.shape
    canvas[:h, :w][valid] = rgb[valid]
    tr = big @ Affine.translation(c0 * bs, r0 * bs)
    z = np.full((H, W), np.nan, np.float32)
    with rasterio.open(case_dir / "elevation.tif") as s:
        reproject(s.read(1), z, src_transform=s.transform, src_crs=crs, dst_transform=tr,
                  dst_crs=crs, src_nodata=s.nodata, dst_nodata=np.nan,
                  resampling=Resampling.bilinear)  # fmt: skip
    flat = float(np.nanmedian(z))
    z = np.where(np.isfinite(z), z, flat).astype(np.float32)
    for i in range(nr):
        for j in range(nc):
            sl = (slice(i * bs, (i + 1) * bs), slice(j * bs, (j + 1) * bs))
            yield r0 + i, c0 + j, canvas[sl], z[sl], flat


def build(case_dir: str | Path, data: str | Path | None, n: int, out: str | Path, seed: int = 0,
          feat_conf: dict | None = None, vocab_k: int = 1000, sample: int = 500_000,
          pads: list[np.ndarray] | None = None, block: int = BLOCK) -> dict:  # fmt: skip
    """Write the padded map (blocks, VRTs) and its index under ``out``; returns the manifest.
    ``pads``: the padding blocks (``block`` px RGB; default ``pad_blocks(data)``)."""
    from georeg.index.features import (
        TileFeatures,
        conf_hash,
        merged_conf,
        rgb_to_gray,
        save_tile_features,
        tile_features,
    )
    from georeg.index.map_index import MapIndex, WordQuantizer
    from georeg.index.vocabulary import train_kmeans
    from georeg.io.raster import write_vrt

    t0 = time.perf_counter()
    case_dir, out = Path(case_dir), Path(out)
    (out / "blocks").mkdir(parents=True, exist_ok=True)
    crs = json.loads((case_dir / "case.json").read_text())["crs_wkt"]
    conf = merged_conf(feat_conf or {})
    lay = case_layout(case_dir, n, block)
    n, g, big = lay["n"], lay["gsd"], lay["transform"]
    pads = pad_blocks(data) if pads is None else pads
    bs = block
    pick = np.random.default_rng(seed).integers(0, len(pads), (n, n))
    local = Affine(g, 0, 0, 0, -g, 0)
    feats: dict[str, TileFeatures] = {}
    place: dict[tuple[int, int], str] = {}
    flat = 0.0
    for r, c, rgb, z, fz in case_blocks(case_dir, lay, pads, pick, crs):
        flat, name = fz, f"case_r{r:03d}_c{c:03d}"
        _write(out / "blocks" / f"{name}.tif", rgb, "uint8")
        _write(out / "blocks" / f"{name}_dsm.tif", z, "float32")
        feats[name] = tile_features(rgb_to_gray(np.moveaxis(rgb, -1, 0)), None, local, conf, None,
                                    (z, local, None))  # fmt: skip
        place[(r, c)] = name
    _write(out / "blocks" / "flat_dsm.tif", np.full((bs, bs), flat, np.float32), "float32")
    for k in sorted({int(pick[r, c]) for r in range(n) for c in range(n) if (r, c) not in place}):
        name = f"pad_{k:03d}"
        _write(out / "blocks" / f"{name}.tif", pads[k], "uint8")
        tf = tile_features(rgb_to_gray(np.moveaxis(pads[k], -1, 0)), None, local, conf)
        tf.z[:] = flat
        feats[name] = tf
    for r in range(n):
        for c in range(n):
            place.setdefault((r, c), f"pad_{int(pick[r, c]):03d}")
    log.info("%d distinct blocks described (%.0f s)", len(feats), time.perf_counter() - t0)
    full = Window(0, 0, bs, bs)
    srcs = [(out / "blocks" / f"{nm}.tif", full, Window(c * bs, r * bs, bs, bs))
            for (r, c), nm in sorted(place.items())]  # fmt: skip
    dsrcs = [(out / "blocks" / (f"{nm}_dsm.tif" if nm.startswith("case") else "flat_dsm.tif"), full, d)
             for (_, _, d), nm in zip(srcs, [place[k] for k in sorted(place)], strict=True)]  # fmt: skip
    write_vrt(out / "ortho.vrt", srcs, crs, big, n * bs, n * bs, 3, "uint8")
    write_vrt(out / "dsm.vrt", dsrcs, crs, big, n * bs, n * bs, 1, "float32", nodata=-9999.0)
    # vocabulary: a uniform sample over all placed features (a repeated block weighs its count)
    names = [place[k] for k in sorted(place)]
    counts = np.array([len(feats[nm]) for nm in names])
    rng = np.random.default_rng(seed)
    rows = np.sort(rng.choice(counts.sum(), min(sample, counts.sum()), replace=False))
    starts = np.r_[0, np.cumsum(counts)]
    which = np.searchsorted(starts, rows, side="right") - 1
    x = np.concatenate([np.asarray(feats[names[t]].desc)[rows[which == t] - starts[t]]
                        for t in np.unique(which)]).astype(np.float32) / 512.0  # fmt: skip
    cent, _ = train_kmeans(x, vocab_k, seed)
    q = WordQuantizer(cent)
    words = {nm: q.words(np.asarray(tf.desc, np.float32) / 512.0) for nm, tf in feats.items()}
    dirs, wfiles, tids = [], [], []
    meta0 = {"crs_wkt": crs, "native_gsd": g, "gsd_m": conf.get("gsd_m") or g,
             "features_conf": conf, "features_conf_hash": conf_hash(conf), "desc_dtype": "uint8",
             "desc_scale": 512}  # fmt: skip
    for (r, c), nm in sorted(place.items()):
        tid = f"r{r:03d}_c{c:03d}"
        tf = feats[nm]
        x0, y0 = big @ (c * bs, r * bs)
        moved = TileFeatures(tf.xy + np.array([x0, y0]), tf.z, tf.ndsm, tf.scale, tf.angle,
                             tf.response, tf.desc)  # fmt: skip
        d = out / "features" / tid
        if not (d / "meta.json").exists():
            save_tile_features(d, moved, {**meta0, "n": len(tf), "tile": tid, "block": nm})
        wf = out / "words" / f"{tid}.npy"
        wf.parent.mkdir(exist_ok=True)
        np.save(wf, words[nm])
        dirs.append(d)
        wfiles.append(wf)
        tids.append(tid)
    np.save(out / "centroids.npy", cent)
    MapIndex.build(dirs, tids, cent, out / "index", crs_wkt=crs, words=wfiles)
    man = {"case": case_dir.name, "blocks_per_side": n, "mpx": n * n * bs * bs / 1e6,
           "gsd": g, "case_blocks": lay["case_blocks"], "case_origin_block": lay["case_origin_block"],
           "distinct_blocks": len(feats), "features": int(sum(len(feats[nm]) for nm in names)),
           "flat_z": flat, "seconds": time.perf_counter() - t0, "seed": seed}  # fmt: skip
    (out / "padmap.json").write_text(json.dumps(man, indent=1) + "\n")
    return man


def reindex(out: str | Path, vocab_k: int, sample: int = 500_000, seed: int = 0) -> Path:
    """Rebuild the index of a padded map under ``out`` with ``vocab_k`` words (the config's rule:
    k grows with the map, ~N / 1,000) into ``out/index_k<k>``: a new vocabulary on a uniform
    sample of the placed features, words assigned once per distinct block. Returns the index dir."""
    from georeg.index.features import load_tile_features
    from georeg.index.map_index import MapIndex, WordQuantizer
    from georeg.index.vocabulary import train_kmeans

    out = Path(out)
    dirs = sorted((out / "features").iterdir())
    metas = [json.loads((d / "meta.json").read_text()) for d in dirs]
    first: dict[str, Path] = {}
    for d, m in zip(dirs, metas, strict=True):
        first.setdefault(m["block"], d)
    desc = {b: np.asarray(load_tile_features(d)[0].desc) for b, d in first.items()}
    names = [m["block"] for m in metas]
    counts = np.array([len(desc[nm]) for nm in names])
    rng = np.random.default_rng(seed)
    rows = np.sort(rng.choice(counts.sum(), min(sample, counts.sum()), replace=False))
    starts = np.r_[0, np.cumsum(counts)]
    which = np.searchsorted(starts, rows, side="right") - 1
    x = np.concatenate([desc[names[t]][rows[which == t] - starts[t]]
                        for t in np.unique(which)]).astype(np.float32) / 512.0  # fmt: skip
    cent, _ = train_kmeans(x, vocab_k, seed)
    q = WordQuantizer(cent)
    words = {b: q.words(d.astype(np.float32) / 512.0) for b, d in desc.items()}
    wdir = out / f"words_k{vocab_k}"
    wdir.mkdir(exist_ok=True)
    wfiles = []
    for d, nm in zip(dirs, names, strict=True):
        np.save(wdir / f"{d.name}.npy", words[nm])
        wfiles.append(wdir / f"{d.name}.npy")
    dst = out / f"index_k{vocab_k}"
    MapIndex.build(dirs, [d.name for d in dirs], cent, dst, crs_wkt=metas[0]["crs_wkt"], words=wfiles)
    return dst


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--case", required=True, help="frames_dev case: odm | ngi")
    ap.add_argument("--blocks", type=int, required=True, help="blocks of 1024 px per side")
    ap.add_argument("--out", required=True)
    ap.add_argument("--data", default="../shared/data")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--vocab-k", type=int, default=1000, help="visual words (the config's default)")
    ap.add_argument("--sample", type=int, default=500_000, help="k-means sample")
    ap.add_argument("--reindex", action="store_true", help="only a new index_k<k> of a built map")
    a = ap.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(message)s")
    if a.reindex:
        print(reindex(a.out, a.vocab_k, a.sample, a.seed))
        return
    man = build(Path(a.data) / "frames_dev" / a.case, a.data, a.blocks, a.out, a.seed,
                vocab_k=a.vocab_k, sample=a.sample)  # fmt: skip
    print(json.dumps(man))


if __name__ == "__main__":
    main()
