"""The harder development set (issue 34): SRIF multimodal pairs and Landsat Pucallpa cross-date.

    . /work/main/.venv/bin/activate
    nice -n 5 python benchmarks/bench_devset.py --sets srif_wide,srif_pair,pucallpa \\
        --methods sift_plain,wf_default --out benchmarks/out/devset_baseline.json -v
    nice -n 5 python benchmarks/bench_devset.py --sets srif_wide,srif_pair,pucallpa \\
        --per-half 5 --puc-first 11 --puc-crops 1 -v --out benchmarks/out/devset_run3.json

Same protocol as benchmarks/bench_crossspectral.py (docs/BENCHMARKS.md "Cross-spectral matching /
Protocol"): a fixed tuning / checking split, both halves reported, plain SIFT beside every
figure (here, in the benchmark, never in the library); outcome per query: success = accepted
with median error within the tolerance, false accept = accepted with a larger error, or any
acceptance of a query whose true place is not in the map ("outside" / unrelated).

Sets (all from ../shared/data, made by nobody here):

- ``srif_wide``: SRIF (Li, Hu, Zhang, ISPRS J. 204 (2023) 77-88; ../shared/data/srif_dev)
  Optical-Optical (``oo``), Optical-Infrared (``oi``), Optical-Depth (``od``), 100 pairs each
  (pair indices 1, 3, ..., 199). **Split by pair index**: tuning = pairs 1-99, checking = pairs
  101-199 (50 each). Each half is cut into two blocks of 25 consecutive pairs; in each block the
  references of 20 pairs are laid side by side (shelf packing, 0 = nodata between them) into one
  mosaic geo-referenced at 1 m pixels in UTM 33N (origin 500000 E, 5000000 N; ``MOSAIC_ORIGIN``),
  and the references of the 5th, 10th, ..., 25th pair are LEFT OUT: their queries are searched
  in the block's mosaic and must end not found ("outside") -- unless another reference in the
  mosaic overlaps theirs (SRIF references are crops of larger scenes and neighbours overlap:
  ``overlaps``, plain SIFT between the optical references), then they are in the map.
  A query found on an overlapping copy of its place is right (``places``). Every query (``pair<i>_2``) is
  searched in all of its mosaic. The query's GSD is taken as known (the project's premise: the
  query sensor's GSD is known, its rotation is not): 1 m over the scale of the ground truth's
  linear part.
- ``srif_pair``: the same 300 pairs pair by pair (map = the query's own reference, 1 m pixels).
  This stands in for "pair by pair with a location prior" until the ``prior`` of issue 34 item 4
  (branch ``core``) lands: a prior that keeps the search to the reference's footprint is this.
- ``pucallpa``: ../shared/data/swir_dates/landsat_pucallpa, 8 dates 1985-2020. The SWIR1 band of
  one date against the red/green luminance of another, 5-35 years apart: all 28 date pairs,
  direction alternating; per pair one crop of half the scene's smaller side and one of 0.3-0.45
  of it, rotated by any angle, rescaled x0.75-1.3 (the protocol's Landsat style, seeded).
  **Split by date pair**: the 28 pairs sorted by (gap, earlier date), alternately tuning /
  checking (every gap in both halves). Unrelated: each query against its map with the true
  footprint (dilated by 10 px) blanked to nodata.

Truth: SRIF ``[gt; 0 0 1]`` maps reference px to query px, MATLAB 1-based (``p2 + 1 = A (p1 +
1)``), hand-picked, off by 3-5 query px in translation (data README; plain SIFT fits with 15-64
inliers differ from it by up to 8 query px): success = median error <= 8 query px (the README's
own scoring of plain SIFT) or 5 map px, whichever is larger; Pucallpa: one grid, exact; 5 map px.
**Optical-optical truth audited** (``audit_truth``, session 16): the query warped onto its
reference by the GT, the translation within +-24 reference px that maximises the normalised
cross-correlation of the two gradient magnitudes (same sensor type, so a direct measure), used
when it raises that correlation by >= ``AUDIT_MIN_GAIN``; method-independent, both halves, each
row records it (``truth_audit``). Pair 43: the GT is 17 reference px (9.8 query px) off: NCC
0.17 at the GT, 0.43 shifted; plain SIFT's 16-inlier affine is 9.1 query px from the GT too.

Methods: ``sift_plain`` (OpenCV SIFT, ratio 0.8, MAGSAC, > 5 inliers: the outside baseline),
``wf_default`` (the workflow's registration stages, georeg.register.fuse.register_query with
config/config.yaml's ``register`` section, as bench_crossspectral's ``wf_*`` methods). The
hypothesis sources of issue 34 item 3 (``src_*``: CFOG structure, XFeat; commit cd6ab47) were
measured here and not kept (docs/experiments/2026-11-26-devset.md). ``src_rift``: the RIFT-style
phase-congruency source alone (georeg.register.rift.register on the benchmark's arrays, the map's
features built once per map); ``src_rift12``: the same with 12 rotations of 30 deg (measured, not
kept); ``wf_rift``: the workflow with ``register.rift.enabled`` (docs/experiments/2026-11-26-rift.md);
``wf_rift_nogsd`` / ``wf_learned_nogsd``: ``wf_rift`` / ``wf_learned`` with the query's GSD withheld
(the ``unknown_gsd_factors`` guesses searched; session 31).
The record says which methods ran (``sources`` in the json).
"""

from __future__ import annotations

import argparse
import json
import math
import sys
import time
from pathlib import Path
from typing import Any

import cv2
import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
import bench_crossspectral as bx  # noqa: E402

from georeg.register import rift  # noqa: E402

ROOT = bx.ROOT
SHARED = bx.SHARED
SRIF = SHARED / "srif_dev"
PUCALLPA = SHARED / "swir_dates" / "landsat_pucallpa"
MODALITIES = {"oo": "Optical-Optical", "oi": "Optical-Infrared", "od": "Optical-Depth"}
MOSAIC_ORIGIN = (500000.0, 5000000.0)  # UTM 33N (EPSG:32633), 1 m pixels, north-up
MOSAIC_GSD = 1.0
BLOCK = 25  # consecutive pairs per mosaic; every 5th pair's reference is left out
LEFT_OUT_EVERY = 5
TOL_QUERY_PX = 8.0  # SRIF success: median error <= 8 query px (the data README's scoring)
AUDIT_RADIUS = 24  # optical-optical truth audit: translations searched (reference px)
AUDIT_MIN_GAIN = 0.1  # ... used when the gradient NCC rises by at least this
RAW_QUERY = False  # --raw-query: every pixel of a SRIF query valid, its black fill too (a user's JPEG)
PUC_DATES = (1985, 1990, 1995, 2000, 2005, 2010, 2015, 2020)


# ----------------------------------------------------------------------------- SRIF


def coarsened(q: bx.Query, f: float) -> bx.Query:
    """``q`` seen by a sensor ``f`` x coarser: each band area-averaged (a query pixel is the mean
    of the f x f it covers; nodata where any of them was), the GSD x f, the truth grid's query px
    moved with it (its map px unchanged, so the tolerance in map px stays). ``--coarsen``: a
    real fine map under a coarse query (session 58)."""
    bands = {}
    for k, b in q.bands.items():
        h, w = b.shape
        size = (max(8, round(w / f)), max(8, round(h / f)))
        ok = (b > 0).astype(np.float32)
        img = cv2.resize(b.astype(np.float32) * ok, size, interpolation=cv2.INTER_AREA)
        val = cv2.resize(ok, size, interpolation=cv2.INTER_AREA)
        bands[k] = np.where(val > 0.99, np.clip(np.round(img / np.maximum(val, 1e-6)), 1, 255),
                            0).astype(np.uint8)  # fmt: skip
    h, w = next(iter(q.bands.values())).shape
    sh, sw = next(iter(bands.values())).shape
    q.bands = bands
    q.gsd *= w / sw
    if q.truth is not None:
        q.truth = (q.truth + 0.5) * np.array([sw / w, sh / h]) - 0.5
    q.name += f"_c{f:g}"
    return q


def srif_half(i: int) -> str:
    """The fixed split by pair index: 1-99 tuning, 101-199 checking."""
    return "tuning" if i < 100 else "checking"


def srif_pairs(mod: str) -> list[int]:
    d = SRIF / MODALITIES[mod]
    return sorted(int(p.stem[4:-2]) for p in d.glob("pair*_1.jpg"))


def _valid_mask(gray: np.ndarray) -> np.ndarray:
    """Valid pixels of a SRIF image: not the black fill of a rotated image (JPEG-noisy zeros)."""
    blur = cv2.blur(gray, (5, 5))
    m = (blur > 3).astype(np.uint8)
    return cv2.erode(m, np.ones((5, 5), np.uint8)) > 0


def srif_images(mod: str, i: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(reference u8, query u8 with 0 = nodata, A 3x3 reference px -> query px, 0-based)."""
    d = SRIF / MODALITIES[mod]
    ref = cv2.imread(str(d / f"pair{i}_1.jpg"), cv2.IMREAD_GRAYSCALE)
    qry = cv2.imread(str(d / f"pair{i}_2.jpg"), cv2.IMREAD_GRAYSCALE)
    if ref is None or qry is None:
        raise FileNotFoundError(f"SRIF pair {i} of {d} unreadable")
    A = np.vstack([np.loadtxt(d / f"gt_{i}.txt"), [0, 0, 1.0]])
    one = np.array([[1, 0, 1], [0, 1, 1], [0, 0, 1.0]])
    A0 = np.linalg.inv(one) @ A @ one  # 0-based: p2 = A0 p1
    q = bx._stretch(qry, np.ones(qry.shape, bool) if RAW_QUERY else _valid_mask(qry))
    return ref, q, A0


def _grad(im: np.ndarray) -> np.ndarray:
    g = cv2.GaussianBlur(im.astype(np.float32), (0, 0), 1.5)
    return cv2.magnitude(cv2.Sobel(g, cv2.CV_32F, 1, 0), cv2.Sobel(g, cv2.CV_32F, 0, 1))


def audit_truth(ref: np.ndarray, q: np.ndarray, A0: np.ndarray) -> tuple[np.ndarray, dict[str, Any]]:
    """The GT checked against the images (optical-optical): the query warped onto the reference
    by it, the shift d (reference px, within ``AUDIT_RADIUS``) maximising the masked NCC of the
    gradient magnitudes (cv2.matchTemplate). Returns the GT to use (``A0 @ T(-d)`` when the NCC
    rises by >= ``AUDIT_MIN_GAIN``, else ``A0``) and the record (shift, NCC at the GT and shifted,
    used)."""
    h, w = ref.shape
    R = AUDIT_RADIUS
    M = np.linalg.inv(A0)
    wq = cv2.warpPerspective(q.astype(np.float32), M, (w, h))
    v = cv2.warpPerspective((q > 0).astype(np.uint8), M, (w, h), flags=cv2.INTER_NEAREST)
    v = cv2.erode(v, np.ones((9, 9), np.uint8))
    ys, xs = np.nonzero(v)
    if len(ys) < 1000:
        return A0, {"used": False, "reason": "overlap too small"}
    y0, y1, x0, x1 = ys.min(), ys.max() + 1, xs.min(), xs.max() + 1
    img = np.pad(_grad(ref), R)[y0 : y1 + 2 * R, x0 : x1 + 2 * R]
    ncc = cv2.matchTemplate(img, _grad(wq)[y0:y1, x0:x1], cv2.TM_CCOEFF_NORMED,
                            mask=v[y0:y1, x0:x1].astype(np.float32))  # fmt: skip
    ncc = np.nan_to_num(ncc, nan=-1.0)
    iy, ix = np.unravel_index(int(np.argmax(ncc)), ncc.shape)
    d = (int(ix) - R, int(iy) - R)
    rec = {"shift_ref_px": list(d), "ncc_gt": round(float(ncc[R, R]), 3),
           "ncc_shifted": round(float(ncc[iy, ix]), 3)}  # fmt: skip
    rec["used"] = bool(rec["ncc_shifted"] - rec["ncc_gt"] >= AUDIT_MIN_GAIN)
    if not rec["used"]:
        return A0, rec
    return A0 @ np.array([[1, 0, -d[0]], [0, 1, -d[1]], [0, 0, 1.0]]), rec


def overlaps(refs: dict[int, np.ndarray], min_inliers: int = 30) -> dict[tuple[int, int], np.ndarray]:
    """SRIF references of one set overlap (crops of one scene): (i, j) -> 3 x 3 reference i px ->
    reference j px, from plain SIFT between the two optical references (same sensor: ratio 0.8,
    RANSAC similarity 3 px, >= ``min_inliers`` inliers). A query whose reference is left out is
    still in the map when another reference there overlaps its own (optical-depth pairs 105, 107
    and 109: 181-216 inliers), and a query may be found on either copy. All pairs of n references
    (O(n^2) matchings: ~20 min for 50 optical references) are cached in benchmarks/out/cache,
    keyed by the references' bytes."""
    import hashlib

    h = hashlib.sha256(str(min_inliers).encode())
    for i in sorted(refs):
        h.update(str(i).encode() + refs[i].tobytes())
    cache = ROOT / "benchmarks" / "out" / "cache" / f"srif_overlaps_{h.hexdigest()[:16]}.json"
    if cache.exists():
        return {tuple(int(v) for v in k.split(",")): np.array(T)  # type: ignore[misc]
                for k, T in json.loads(cache.read_text()).items()}  # fmt: skip
    out = _overlaps(refs, min_inliers)
    cache.parent.mkdir(parents=True, exist_ok=True)
    tmp = cache.with_suffix(".tmp")
    tmp.write_text(json.dumps({f"{i},{j}": T.tolist() for (i, j), T in out.items()}))
    tmp.replace(cache)
    return out


def _overlaps(refs: dict[int, np.ndarray], min_inliers: int) -> dict[tuple[int, int], np.ndarray]:
    sift = cv2.SIFT_create()
    feats = {i: sift.detectAndCompute(r, None) for i, r in refs.items()}
    bf = cv2.BFMatcher()
    out = {}
    for i in refs:
        for j in refs:
            (ki, di), (kj, dj) = feats[i], feats[j]
            if i >= j or di is None or dj is None or len(di) < 2 or len(dj) < 2:
                continue
            g = [a for a, b in bf.knnMatch(di, dj, k=2) if a.distance < 0.8 * b.distance]
            if len(g) < min_inliers:
                continue
            pi = np.float32([ki[a.queryIdx].pt for a in g])
            pj = np.float32([kj[a.trainIdx].pt for a in g])
            cv2.setRNGSeed(0)
            A, inl = cv2.estimateAffinePartial2D(pi, pj, method=cv2.RANSAC,
                                                 ransacReprojThreshold=3.0)  # fmt: skip
            if A is None or inl.sum() < min_inliers or abs(np.linalg.det(A[:, :2])) < 1e-3:
                continue
            T = np.vstack([A, [0, 0, 1.0]])
            out[(i, j)], out[(j, i)] = T, np.linalg.inv(T)
    return out


def pack(sizes: list[tuple[int, int]]) -> tuple[list[tuple[int, int]], tuple[int, int]]:
    """Shelf packing of (h, w) images into a near-square canvas: (row, col) offsets, (H, W)."""
    area = sum(h * w for h, w in sizes)
    width = max(max(w for _, w in sizes), int(math.sqrt(area) * 1.05))
    offs, r, c, shelf = [], 0, 0, 0
    for h, w in sizes:
        if c + w > width:
            r, c, shelf = r + shelf, 0, 0
        offs.append((r, c))
        c += w
        shelf = max(shelf, h)
    return offs, (r + shelf, width)


def truth_grid(q: np.ndarray) -> np.ndarray:
    """The truth's 12 x 12 grid of query px (x, y), its valid points only."""
    n_r, n_c = q.shape
    uu, vv = np.meshgrid(np.linspace(2, n_c - 3, 12), np.linspace(2, n_r - 3, 12))
    qp = np.c_[uu.ravel(), vv.ravel()]
    return qp[q[qp[:, 1].astype(int), qp[:, 0].astype(int)] > 0]


def srif_query(mod: str, i: int, q: np.ndarray, A0: np.ndarray, places: list[np.ndarray],
               map_scene: str, outside: bool = False, audit: dict[str, Any] | None = None) -> bx.Query:  # fmt: skip
    """A SRIF query with its truth grid (12 x 12 valid query px) and the map px of that grid at
    each of its ``places`` (3 x 3 reference px -> map px: its own reference, and any other
    reference in the map that overlaps it); no place = not in the map."""
    s = math.sqrt(abs(np.linalg.det(A0[:2, :2])))  # query px per reference px
    name = f"{mod}_{i}" + ("_leftout" if outside else "")
    truth = tmap = None
    alts: list[np.ndarray] = []
    if places:
        qp = truth_grid(q)
        rp = bx.matching.apply_h(np.linalg.inv(A0), qp)
        alts = [bx.matching.apply_h(P, rp) for P in places]
        truth, tmap = qp, alts[0]
    qq = bx.Query(name, map_scene, map_scene, {"band": q}, MOSAIC_GSD / s, truth, tmap)
    qq.alts = alts  # type: ignore[attr-defined]
    qq.tol_px = max(5.0, TOL_QUERY_PX / s)  # type: ignore[attr-defined]
    qq.half = srif_half(i)  # type: ignore[attr-defined]
    qq.truth_audit = audit  # type: ignore[attr-defined]
    return qq


def build_srif(mods: list[str], wide: bool, pair: bool, per_half: int = 0,
               block: int = BLOCK, pool: bool = False) -> tuple[list[bx.Scene], list[bx.Query]]:  # fmt: skip
    """SRIF queries and maps; ``per_half`` > 0: only the first ``per_half`` pairs of each half
    (one block, one mosaic: a run that fits a loaded machine); ``block``: consecutive pairs per
    mosaic (50: one mosaic of 40 references per half and modality); ``pool``: one wide-area
    mosaic per half holding the in-map references of every modality in ``mods`` (each
    modality's left-out pairs as without it), every query of the half searched in all of it."""
    scenes: list[bx.Scene] = []
    queries: list[bx.Query] = []
    pooled: dict[str, list[tuple[str, int, tuple[Any, ...], bool]]] = {}
    for mod in mods:
        idx = srif_pairs(mod)
        for half in ("tuning", "checking"):
            hi = [i for i in idx if srif_half(i) == half]
            hi = hi[:per_half] if per_half else hi
            step = per_half or block
            for b in range(0, len(hi), step):
                pairs = hi[b : b + step]
                data = {i: srif_images(mod, i) for i in pairs}
                audits: dict[int, dict[str, Any] | None] = dict.fromkeys(pairs)
                if mod == "oo":
                    for i in pairs:
                        ref, q, A0 = data[i]
                        A1, audits[i] = audit_truth(ref, q, A0)
                        data[i] = (ref, q, A1)
                if pair:
                    for i in pairs:
                        ref, q, A0 = data[i]
                        sc = bx.Scene(f"{mod}_{i}_ref", {}, MOSAIC_GSD, np.maximum(ref, 1),
                                      MOSAIC_GSD, lambda p: p, mod)  # fmt: skip
                        scenes.append(sc)
                        qq = srif_query(mod, i, q, A0, [np.eye(3)], sc.name, audit=audits[i])
                        qq.name = "pair_" + qq.name
                        qq.setting = "pair"  # type: ignore[attr-defined]
                        queries.append(qq)
                if wide:
                    items = [(mod, i, (*data[i], audits[i]), (k + 1) % LEFT_OUT_EVERY != 0)
                             for k, i in enumerate(pairs)]  # fmt: skip
                    if pool:
                        pooled.setdefault(half, []).extend(items)
                    else:
                        name = f"{mod}_mosaic_{pairs[0]}_{pairs[-1]}"
                        s, q = _wide_mosaic(name, items)
                        scenes += s
                        queries += q
    for half, items in pooled.items():
        s, q = _wide_mosaic(f"{'_'.join(mods)}_mosaic_{half}", items)
        scenes += s
        queries += q
    return scenes, queries


_MOD_KEY = {"oo": 0, "oi": 1000, "od": 2000}  # (modality, pair) -> one int key for overlaps


def _wide_mosaic(name: str, items: list[tuple[str, int, tuple[Any, ...], bool]]
                 ) -> tuple[list[bx.Scene], list[bx.Query]]:  # fmt: skip
    """One wide-area mosaic of the in-map references among ``items`` ((modality, pair,
    (reference, query, A0, audit), in map)) and every item's query searched in all of it."""
    mixed = len({m for m, _, _, _ in items}) > 1
    key = {(m, i): _MOD_KEY[m] * mixed + i for m, i, _, _ in items}
    refs = {key[(m, i)]: d[0] for m, i, d, _ in items}
    inside = [key[(m, i)] for m, i, _, keep in items if keep]
    offs, (H, W) = pack([refs[k].shape for k in inside])
    mosaic = np.zeros((H, W), np.uint8)
    for k, (r, c) in zip(inside, offs, strict=True):
        ref = refs[k]
        mosaic[r : r + ref.shape[0], c : c + ref.shape[1]] = np.maximum(ref, 1)
    mod0 = items[0][0]
    sc = bx.Scene(name, {}, MOSAIC_GSD, mosaic, MOSAIC_GSD, lambda p: p, mod0)
    where = dict(zip(inside, offs, strict=True))
    over = overlaps(refs)
    queries = []
    for m, i, (_, q, A0, audit), _ in items:
        k = key[(m, i)]
        places = []  # its own reference first, then any overlapping one
        for j in sorted(where, key=lambda j: j != k):
            r, c = where[j]
            T = np.eye(3) if j == k else over.get((k, j))
            if T is not None:
                places.append(np.array([[1, 0, c], [0, 1, r], [0, 0, 1.0]]) @ T)
        qq = srif_query(m, i, q, A0, places, name, k not in where, audit)
        qq.name = "wide_" + qq.name
        qq.setting = "wide"  # type: ignore[attr-defined]
        queries.append(qq)
    return [sc], queries


BIG_LEFT_OUT_EVERY = 10  # the stand-in: every 10th optical-infrared reference left out
BIG_FILLERS = 20  # ... and the first 20 optical-depth references of each half as filler


def build_srif_big() -> tuple[list[bx.Scene], list[bx.Query]]:
    """Issue 34's unseen case's stand-in (``srif_big``, session 34; session 33 ran it through
    ``snakemake`` from /tmp): one mosaic of the 100 SRIF optical-infrared references, every
    ``BIG_LEFT_OUT_EVERY``-th left out, and ``BIG_FILLERS`` optical-depth optical references of
    each half as filler (130 references, ~13 Mpx), every optical-infrared query searched in all
    of it. Overlapping references (SRIF's are crops of a few scenes) are found only where a pose
    lands (``judge``: ``lazy_places``), not for all ~8,000 pairs up front."""
    items = []
    for k, i in enumerate(srif_pairs("oi")):
        ref, q, A0 = srif_images("oi", i)
        items.append(("oi", i, ref, q, A0, (k + 1) % BIG_LEFT_OUT_EVERY != 0))
    for half in ("tuning", "checking"):
        for i in [i for i in srif_pairs("od") if srif_half(i) == half][:BIG_FILLERS]:
            items.append(("od", i, srif_images("od", i)[0], None, None, True))
    inside = [(m, i) for m, i, *_, keep in items if keep]
    refs = {(m, i): ref for m, i, ref, *_ in items}
    offs, (H, W) = pack([refs[k].shape for k in inside])
    mosaic = np.zeros((H, W), np.uint8)
    boxes = {}
    for k, (r, c) in zip(inside, offs, strict=True):
        h, w = refs[k].shape
        mosaic[r : r + h, c : c + w] = np.maximum(refs[k], 1)
        boxes[k] = (r, c, h, w)
    name = "oi_big_mosaic"
    sc = bx.Scene(name, {}, MOSAIC_GSD, mosaic, MOSAIC_GSD, lambda p: p, "oi")
    queries = []
    for m, i, _, q, A0, keep in items:
        if m != "oi":
            continue
        r, c = boxes.get((m, i), (0, 0, 0, 0))[:2]
        place = [np.array([[1, 0, c], [0, 1, r], [0, 0, 1.0]])] if keep else []
        qq = srif_query(m, i, q, A0, place, name, not keep)
        qq.name = "big_" + qq.name
        qq.setting = "big"  # type: ignore[attr-defined]
        qq.lazy_places = (refs, boxes, (m, i), A0)  # type: ignore[attr-defined]
        queries.append(qq)
    return [sc], queries


def _lazy_place(q: bx.Query, res: dict[str, Any]) -> bool:
    """A big-mosaic query's pose that lands on another reference: that reference made one more
    place of the query when it overlaps the query's own (``_overlaps``, plain SIFT between the
    two optical references); True when a place was added."""
    refs, boxes, own, A0 = q.lazy_places  # type: ignore[attr-defined]
    n_r, n_c = q.bands["band"].shape
    centre = bx.matching.apply_h(res["H"], np.array([[n_c / 2, n_r / 2]]))[0] / MOSAIC_GSD
    col, row = centre[0], -centre[1]
    for k, (r, c, h, w) in boxes.items():
        if k == own or not (r <= row < r + h and c <= col < c + w):
            continue
        T = _overlaps({0: refs[own], 1: refs[k]}, 30).get((0, 1))
        if T is None:
            continue
        P = np.array([[1, 0, c], [0, 1, r], [0, 0, 1.0]]) @ T
        qp = truth_grid(q.bands["band"])
        alt = bx.matching.apply_h(P, bx.matching.apply_h(np.linalg.inv(A0), qp))
        if q.truth is None:
            q.truth, q.truth_map = qp, alt
        q.alts = [*(getattr(q, "alts", None) or [q.truth_map]), alt]  # type: ignore[attr-defined]
        return True
    return False


def mosaic_geotransform(sc: bx.Scene) -> list[float]:
    """GDAL geotransform of a mosaic (UTM 33N, 1 m px): the map frame this benchmark gives it."""
    return [MOSAIC_ORIGIN[0], MOSAIC_GSD, 0.0, MOSAIC_ORIGIN[1], 0.0, -MOSAIC_GSD]


# ----------------------------------------------------------------------------- Pucallpa


def pucallpa_date_pairs() -> list[tuple[int, int, str]]:
    """(query date, map date, half): all 28 pairs, sorted by (gap, earlier), halves alternate;
    the query is the earlier date on even positions, the later on odd ones."""
    pairs = sorted(
        ((a, b) for a in PUC_DATES for b in PUC_DATES if a < b), key=lambda p: (p[1] - p[0], p[0])
    )
    out = []
    for k, (a, b) in enumerate(pairs):
        q, m = (a, b) if (k // 2) % 2 == 0 else (b, a)
        out.append((q, m, "tuning" if k % 2 == 0 else "checking"))
    return out


def _read_puc(year: int) -> np.ndarray:
    import rasterio

    with rasterio.open(PUCALLPA / f"{year}.tif") as s:
        return s.read().astype(np.float32)  # SWIR1, NIR, red, green; 0 = nodata


def build_pucallpa(seed: int, unrelated: bool = True, first: int = 0, crops: int = 2,
                   query: str = "swir") -> tuple[list[bx.Scene], list[bx.Query]]:  # fmt: skip
    """Pucallpa queries; ``first``: skip the first date pairs (their queries are drawn all the
    same, so a query keeps its content whatever is skipped); ``crops`` 1: the half-side crop
    only; ``query`` "visible": the query date's red/green instead of its SWIR1 (a control: the
    same crops and dates, cross-date only, not cross-spectral)."""
    scenes, queries = [], []
    cube = {y: _read_puc(y) for y in PUC_DATES}
    rng = np.random.default_rng(seed)
    for kp, (qd, md, half) in enumerate(pucallpa_date_pairs()):
        qband = cube[qd][0] if query == "swir" else 0.5 * (cube[qd][2] + cube[qd][3])
        qimg = np.where(qband > 0, qband, np.nan)
        valid = (cube[md][2] > 0) & (cube[md][3] > 0)
        gray = bx._stretch(0.5 * (cube[md][2] + cube[md][3]), valid)
        bands = {"1.6um" if query == "swir" else "rg": qimg}
        sc = bx.Scene(f"puc_{qd}_on_{md}", bands, 90.0, gray, 90.0, lambda p: p, "pucallpa")
        scenes.append(sc)
        for k, frac in enumerate((0.5, float(rng.uniform(0.3, 0.45)))):
            q = bx.make_query(sc, rng, k, frac)
            if kp < first or k >= crops:
                continue
            q.half = half  # type: ignore[attr-defined]
            q.tol_px = bx.SUCCESS_PX  # type: ignore[attr-defined]
            q.setting = "pucallpa"  # type: ignore[attr-defined]
            queries.append(q)
            if not unrelated:
                continue
            # the same map with the query's true footprint (dilated 10 px) blanked
            hole = np.zeros(gray.shape, np.uint8)
            n = next(iter(q.bands.values())).shape[0]
            box = np.array([[0, 0], [n - 1, 0], [n - 1, n - 1], [0, n - 1]], np.float64)
            A = np.linalg.lstsq(np.c_[q.truth, np.ones(len(q.truth))], q.truth_map, rcond=None)[0]
            corners = np.c_[box, np.ones(4)] @ A
            cv2.fillPoly(hole, [corners.round().astype(np.int32)], 1)
            hole = cv2.dilate(hole, np.ones((21, 21), np.uint8)) > 0
            other = bx.Scene(f"{sc.name}_without_{q.name}", {}, 90.0, np.where(hole, 0, gray),
                             90.0, lambda p: p, "pucallpa")  # fmt: skip
            scenes.append(other)
            neg = bx.Query(q.name + "_blanked", sc.name, other.name, q.bands, q.gsd, None, None)
            neg.half, neg.tol_px, neg.setting = half, bx.SUCCESS_PX, "pucallpa"  # type: ignore
            queries.append(neg)
    return scenes, queries


# ----------------------------------------------------------------------------- methods

METHODS: dict[str, dict[str, Any]] = {
    "sift_plain": bx.METHODS["sift_plain"],
    "wf_default": {"pipeline": {}, "bands": 1},
    # hypothesis sources of issue 34 item 3 were measured here and not kept (CFOG structure:
    # georeg/register/structure.py, XFeat with mutual nearest neighbours and its own verifier:
    # georeg/register/learned.py; verified by georeg/register/candidate.verify): commit cd6ab47
    # has them, the figures are in docs/experiments/2026-11-26-devset.md; XFeat came back in
    # session 27 inside rift's search and acceptance (src_learned, wf_learned; ALIKED since session 62)
    # RIFT-style phase-congruency features (georeg/register/rift.py), verified by the acceptance
    "src_rift": {"rift": {}},
    "src_rift12": {"rift": {"rotations": 12, "max_angle_deg": 20.0}},  # v3: 30 deg steps
    "src_rift_novote": {"rift": {"vote_regions": 0}},  # without the vote regions (session 34)
    "src_rift_kp5k": {"rift": {"max_kp": 5000}},  # the map windows' density before session 35
    "wf_rift_kp5k": {"pipeline": {"rift": {"enabled": True, "max_kp": 5000}, "learned": {"enabled": False}},
                     "bands": 1},  # the map windows' density before session 35
    # the workflow with the rift source enabled (fuse.SOURCES: runs when nothing else accepted)
    "wf_rift": {"pipeline": {"rift": {"enabled": True}, "learned": {"enabled": False}}, "bands": 1},
    "wf_rift_reangle": {"pipeline": {"rift": {"enabled": True, "reangle": True}, "learned": {"enabled": False}},
                        "bands": 1},  # session 38: rift's accepted poses sharpened at their own angle
    "wf_rift_noturn": {"pipeline": {"rift": {"enabled": True, "turn_deg": 0}, "learned": {"enabled": False}},
                       "bands": 1},  # before session 39: accepted poses not turned (``rift.turned``)
    "wf_rift_refined_noturn": {"pipeline": {"rift": {"enabled": True, "turn_deg": 0}}, "bands": 1,
                               "refine": {}},  # the same, then the refinement stage  # fmt: skip
    "wf_rift_novote": {"pipeline": {"rift": {"enabled": True, "vote_regions": 0}, "learned": {"enabled": False}},
                       "bands": 1},  # without the vote regions (session 34)
    "wf_rift_nogsd_novote": {"pipeline": {"rift": {"enabled": True, "vote_regions": 0},
                                          "learned": {"enabled": False}}, "bands": 1, "no_gsd": True},
    "wf_rift_nogsd": {"pipeline": {"rift": {"enabled": True}, "learned": {"enabled": False}}, "bands": 1,
                      "no_gsd": True},
    # with a location prior (issue 34 item 4, queries.<name>.prior): a square of half side 2
    # query sides around the true centre moved by a seeded offset of up to half of that (an
    # outside query: at a seeded place of its map; bench_crossspectral.location_prior)
    "wf_rift_prior2": {"pipeline": {"rift": {"enabled": True}, "learned": {"enabled": False}}, "bands": 1,
                       "prior": 2.0},
    "wf_rift_prior2_refined": {"pipeline": {"rift": {"enabled": True}, "learned": {"enabled": False}},
                               "bands": 1, "prior": 2.0, "refine": {}},  # + the refinement stage
    # + the learned source (rift.LEARNED in rift's search, fuse.SOURCES after rift; session 27
    # with XFeat, ALIKED since session 62)
    "wf_learned": {"pipeline": {"rift": {"enabled": True}, "learned": {"enabled": True}}, "bands": 1},
    "wf_learned_nogsd": {"pipeline": {"rift": {"enabled": True}, "learned": {"enabled": True}}, "bands": 1,
                         "no_gsd": True},
    # the learned source alone over the map (``rift.LEARNED``: ALIKED since session 62; XFeat's
    # figures, ``src_xfeat`` of sessions 27-61, stay in docs/BENCHMARKS.md and the logs)
    "src_learned": {"rift": dict(rift.LEARNED)},
    "wf_rift_64m": {"pipeline": {"rift": {"enabled": True, "max_map_px": 64_000_000}}, "bands": 1},
    "wf_rift_refined": {"pipeline": {"rift": {"enabled": True}}, "bands": 1,
                        "refine": {}},  # + the workflow's refinement stage (its product)  # fmt: skip
    "wf_rift_k1": {"pipeline": {"rift": {"enabled": True, "candidates": 1}}, "bands": 1},  # mutual nearest
    "src_rift_k1": {"rift": {"candidates": 1}},
    "wf_rift_k1_refined": {"pipeline": {"rift": {"enabled": True, "candidates": 1}}, "bands": 1,
                           "refine": {}},  # + the workflow's refinement stage  # fmt: skip
}
_RIFT_MAPS: dict[tuple[str, str], Any] = {}  # (scene, conf) -> map features (built once)


def run_rift(q: bx.Query, sc: bx.Scene, spec: dict[str, Any], seed: int) -> dict[str, Any]:
    """georeg.register.rift.register of the query against the whole map (features of the map
    built once per scene and conf: their CPU seconds are recorded as ``map_cpu_seconds`` on the
    first query of that map, inside its ``cpu_seconds``)."""
    t0 = time.perf_counter()
    conf = rift.rift_conf(spec["rift"])
    key = (sc.name, json.dumps(conf, sort_keys=True))
    map_s = 0.0
    if key not in _RIFT_MAPS:
        c0 = time.process_time()
        _RIFT_MAPS.clear()
        _RIFT_MAPS[key] = rift.map_features(sc.map_gray, conf)
        map_s = time.process_time() - c0
    reg = bx.workflow_register_conf()
    u8 = next(iter(q.bands.values()))
    r = rift.register(u8, sc.map_gray, q.gsd / sc.map_gsd, reg["acceptance"], conf,
                      _RIFT_MAPS[key], q.gsd, sc.map_gsd)  # fmt: skip
    g = sc.map_gsd
    H = None if r["H"] is None else np.diag([g, -g, 1.0]) @ r["H"]  # judged only if accepted
    pol = None
    if r["accepted"] and conf["polish"]:  # as rift.source does with the orthophoto's window
        H, pol = rift.polish(u8, H, bx.plain_window_reader(sc), reg)
        r["accepted"] = not (pol and pol["moved_better"])
    st = None
    if r["accepted"] and float(conf["structure_z_min"]) > 0:  # as rift.source does
        st = rift.structure_check(u8, H, bx.plain_window_reader(sc), q.gsd, conf, seed,
                                  z_enough=2 * float(conf["structure_z_min"]))  # fmt: skip
        r["accepted"] = st is None or st["z"] >= float(conf["structure_z_min"])
    if r["accepted"] and float(conf["turn_deg"]) > 0:  # as rift.source does
        H, _ = rift.turned(u8, H, bx.plain_window_reader(sc), reg, float(conf["turn_deg"]))
    return {"matches": r["matches"], "inliers": r["inliers"], "accepted": r["accepted"], "H": H,
            "log10_nfa": r["log10_nfa"], "tests": r["tests"], "candidates": r["tests"],
            "angle_deg": r["angle_deg"], "map_cpu_seconds": map_s,
            "null_log10_nfa": r["null_log10_nfa"], "polish": pol, "structure": st,
            "per_rotation": r["per_rotation"], "seconds": time.perf_counter() - t0,
            "confirm": r.get("confirm"), "rescue": r.get("rescue"),
            **{k: (r["decision"] or {}).get(k) for k in ("nfa_k", "nfa_eps_px", "reason")}}  # fmt: skip


def _rift_fields(res: dict[str, Any]) -> dict[str, Any]:
    """The rift source's null, polish, per-rotation NFAs, NFA's k and e_k, confirmation, rescue
    and reason (source alone, or the workflow's registration record)."""
    r = res if "per_rotation" in res else (res.get("rift") or {})
    keys = ("null_log10_nfa", "polish", "structure", "per_rotation", "nfa_k", "nfa_eps_px", "confirm",
            "rescue", "reason")  # fmt: skip
    return {k: r.get(k) for k in keys}


def _peaks_fields(r: dict[str, Any] | None) -> dict[str, Any] | None:
    """The cfog_peaks source's record in short: accepted peak, each peak's dense log10 NFA."""
    if not r:
        return None
    return {"accepted": r.get("accepted"), "peak": r.get("peak"), "tests": r.get("tests"),
            "log10_nfa": [p["log10_nfa"] for p in r.get("peaks") or []],
            "supported": [p["supported"] for p in r.get("peaks") or []]}  # fmt: skip


def run(q: bx.Query, sc: bx.Scene, name: str, seed: int) -> dict[str, Any]:
    spec = METHODS[name]
    if "rift" in spec:
        return run_rift(q, sc, spec, seed)
    return bx.run_method(q, sc, spec, seed)


def judge(q: bx.Query, sc: bx.Scene, res: dict[str, Any]) -> dict[str, Any]:
    """bench_crossspectral.judge with the query's own tolerance (SRIF: >= 5 query px)."""
    j = bx.judge(q, sc, res)
    if j["outcome"] in ("success", "false_accept") and getattr(q, "lazy_places", None):
        ok = q.truth is not None and j["error_px"] is not None and j["error_px"] <= q.tol_px  # type: ignore[attr-defined]
        if not ok and _lazy_place(q, res):
            j = bx.judge(q, sc, res)
    alts = getattr(q, "alts", None) or []
    for alt in alts[1:]:  # the nearest place of the query counts
        q2 = bx.Query(q.name, q.scene, q.map_scene, q.bands, q.gsd, q.truth, alt)
        j2 = bx.judge(q2, sc, res)
        if j2["error_px"] is not None and (j["error_px"] is None or j2["error_px"] < j["error_px"]):
            j = j2
    if j["outcome"] in ("success", "false_accept") and q.truth is not None:
        ok = j["error_px"] is not None and j["error_px"] <= q.tol_px  # type: ignore[attr-defined]
        j["outcome"] = "success" if ok else "false_accept"
    return j


def summarise(r: list[dict[str, Any]]) -> dict[str, Any]:
    pos = [x for x in r if x["positive"]]
    ok = [x for x in pos if x["outcome"] == "success"]
    return {
        "success": len(ok),
        "positives": len(pos),
        "false_accept": sum(x["outcome"] == "false_accept" for x in pos),
        "unrelated_accepted": sum(x["outcome"] == "false_accept" for x in r if not x["positive"]),
        "negatives": len(r) - len(pos),
        "median_error_px": float(np.median([x["error_px"] for x in ok])) if ok else float("nan"),
        "seconds_per_query": float(np.mean([x["seconds"] for x in r])) if r else float("nan"),
        "cpu_seconds_per_query": float(np.mean([x["cpu_seconds"] for x in r]))
        if r
        else float("nan"),
    }


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawTextHelpFormatter)
    ap.add_argument("--sets", default="srif_wide,srif_pair,pucallpa")
    ap.add_argument("--modalities", default="oo,oi,od")
    ap.add_argument("--methods", default="sift_plain,wf_default")
    ap.add_argument("--half", choices=("tuning", "checking", "both"), default="both")
    ap.add_argument("--seed", type=int, default=11)
    ap.add_argument("--limit", type=int, default=0, help="first N queries per set (smoke runs)")
    ap.add_argument("--only", default="",
                    help="only the queries whose names start with one of these (comma-separated, "
                    "e.g. wide_oi_,wide_od_: a pooled mosaic's oi and od queries); the maps stay whole")
    ap.add_argument("--exact", action="store_true", help="--only names whole query names, not prefixes")
    ap.add_argument("--out", default=str(ROOT / "benchmarks" / "out" / "devset.json"))
    ap.add_argument("-v", action="store_true")
    ap.add_argument("--per-half", type=int, default=0,
                    help="SRIF: the first N pairs of each half per modality (0 = all 50)")
    ap.add_argument("--block", type=int, default=BLOCK,
                    help="SRIF wide: consecutive pairs per mosaic (every 5th left out)")
    ap.add_argument("--coarsen", type=float, default=1.0,
                    help="every query area-averaged by this factor (a real fine map under a "
                    "coarse query: the map keeps its GSD); 1 = as the set has it")
    ap.add_argument("--raw-query", action="store_true",
                    help="SRIF queries as a user's JPEG arrives: the black fill of a rotated image valid too")
    ap.add_argument("--pool", action="store_true",
                    help="srif_wide: one mosaic per half of every chosen modality's references")
    ap.add_argument("--puc-first", type=int, default=0, help="Pucallpa: skip the first date pairs")
    ap.add_argument("--puc-crops", type=int, default=2, help="Pucallpa: crops per date pair")
    ap.add_argument("--puc-query", choices=("swir", "visible"), default="swir",
                    help="Pucallpa: the query date's SWIR1 (the set) or its red/green (a control)")
    ap.add_argument("--reuse", default="",
                    help="a .jsonl of an earlier run (same set): its records of the methods "
                    "asked are taken, not run again (a run cut by the machine's load)")
    ap.add_argument("--reuse-methods", default="sift_plain,wf_default",
                    help="which methods' records --reuse may take")
    ap.add_argument("--rerun-rift", action="store_true",
                    help="with --reuse: run again the queries on which the rift source ran (a "
                    "change to rift alone cannot change the others: it runs only when nothing "
                    "else was accepted)")
    ap.add_argument("--table", help="print the table of a .jsonl record file and stop")
    a = ap.parse_args(argv)
    if a.table:
        table_from_jsonl(a.table)
        return 0
    if not SRIF.is_dir() or not PUCALLPA.is_dir():
        print(f"no development data at {SRIF} / {PUCALLPA}", file=sys.stderr)
        return 1
    cv2.setNumThreads(1)
    global RAW_QUERY
    RAW_QUERY = a.raw_query
    sets = a.sets.split(",")
    scenes: list[bx.Scene] = []
    queries: list[bx.Query] = []
    mods = a.modalities.split(",")
    if "srif_wide" in sets or "srif_pair" in sets:
        s, q = build_srif(mods, "srif_wide" in sets, "srif_pair" in sets, a.per_half, a.block,
                          a.pool)
        scenes += s
        queries += q
    if "srif_big" in sets:
        s, q = build_srif_big()
        scenes += s
        queries += q
    if "pucallpa" in sets:
        s, q = build_pucallpa(a.seed, True, a.puc_first, a.puc_crops, a.puc_query)
        scenes += s
        queries += q
    if a.coarsen != 1.0:
        queries = [coarsened(q, a.coarsen) for q in queries]
    order = {"wide": 0, "big": 0, "pucallpa": 1, "pair": 2}  # a cut run keeps the targets first
    queries.sort(key=lambda q: order[q.setting])  # type: ignore[attr-defined]
    if a.half != "both":
        queries = [q for q in queries if q.half == a.half]  # type: ignore[attr-defined]
    if a.only:
        only = tuple(a.only.split(","))
        queries = [q for q in queries if (q.name in only if a.exact else q.name.startswith(only))]
    if a.limit:
        keep: dict[str, int] = {}
        sel = []
        for q in queries:
            k = q.setting  # type: ignore[attr-defined]
            if keep.get(k, 0) < a.limit:
                keep[k] = keep.get(k, 0) + 1
                sel.append(q)
        queries = sel
    by = {s.name: s for s in scenes}
    methods = a.methods.split(",")
    rows: dict[str, list[dict[str, Any]]] = {m: [] for m in methods}
    Path(a.out).parent.mkdir(parents=True, exist_ok=True)
    partial = Path(a.out).with_suffix(".jsonl")  # one line per record as it is made
    partial.write_text("")
    done: dict[tuple[str, str], dict[str, Any]] = {}
    if a.reuse:
        for r in read_records(a.reuse):
            # wide-area records are judged against every place of the query since the overlap
            # check: never reused from a run before it
            if a.rerun_rift and r.get("per_rotation"):
                continue
            if r["method"] in a.reuse_methods.split(",") and "places" in r or (
                r["method"] in a.reuse_methods.split(",") and not r["group"].startswith("wide")
            ):
                done[(r.pop("method"), r["query"])] = r
    qby = {q.name: q for q in queries}
    for r in done.values():  # reused rows judged again (the truth may have been audited since)
        if r["query"] in qby and r.get("H") is not None and r["outcome"] in ("success", "false_accept"):
            q = qby[r["query"]]
            r.update(judge(q, by[q.map_scene], {"H": np.array(r["H"]), "accepted": True}))
            r["truth_audit"] = getattr(q, "truth_audit", None)
    for q in queries:
        setting = q.setting  # type: ignore[attr-defined]
        group = setting if setting == "pucallpa" else f"{setting}_{q.name.split('_')[1]}"
        for name in methods:
            if (name, q.name) in done:
                rows[name].append(done[(name, q.name)])
                append_record(partial, name, done[(name, q.name)])
                continue
            c0 = time.process_time()
            res = run(q, by[q.map_scene], name, bx.query_seed(a.seed, q.name))
            cpu = time.process_time() - c0
            j = judge(q, by[q.map_scene], res)
            rec = {"query": q.name, "group": group, "half": q.half,  # type: ignore[attr-defined]
                   "positive": q.truth is not None, **j, "inliers": res["inliers"],
                   "matches": res["matches"], "log10_nfa": res.get("log10_nfa"),
                   "seconds": res["seconds"], "cpu_seconds": cpu,
                   "candidates": res.get("candidates"), "tests": res.get("tests"),
                   "places": len(getattr(q, "alts", []) or []),
                   "truth_audit": getattr(q, "truth_audit", None),
                   **_rift_fields(res), "ortho_gain": res.get("ortho_gain"),
                   "context_refit": res.get("context_refit"),
                   "second_pass": res.get("second_pass"),
                   "cfog_peaks": _peaks_fields(res.get("cfog_peaks")),
                   "sources": res.get("sources"), "pose_source": res.get("pose_source"),
                   "learned": {k: (res.get("learned") or {}).get(k) for k in
                               ("ran", "accepted", "log10_nfa", "null_log10_nfa", "inliers",
                                "matches", "angle_deg", "confirm", "rescue", "reason", "seconds")},
                   "H": None if res.get("H") is None else np.asarray(res["H"]).tolist()}  # fmt: skip
            rows[name].append(rec)
            append_record(partial, name, rec)
            if a.v:
                e = "-" if j["error_px"] is None else f"{j['error_px']:.2f}"
                print(f"{rec['half'][:5]} {q.name:34s} {name:14s} {j['outcome']:12s} err {e:>8s} "
                      f"inl {res['inliers']:3d}/{res['matches']:4d} {res['seconds']:.2f}s "
                      f"cpu {cpu:.2f}s", flush=True)  # fmt: skip
    print(f"\n{len(queries)} queries, seed {a.seed}; machine shared (2 cores, ~8 engineers)")
    summary = table(rows, methods)
    sources = {m: METHODS[m].get("source", "bench") for m in methods}
    Path(a.out).write_text(json.dumps({"summary": summary, "sources": sources, "rows": rows},
                                      indent=1, default=float))  # fmt: skip
    return 0


def table(rows: dict[str, list[dict[str, Any]]], methods: list[str]) -> dict[str, Any]:
    """Print the markdown table (set x method x half) and return the summary."""
    print("| set | method | half | registered | false accepts | unrelated accepted "
          "| median err px | s/query | cpu s/query |")
    print("|---|---|---|---:|---:|---:|---:|---:|---:|")
    summary: dict[str, Any] = {}
    groups = sorted({r["group"] for rr in rows.values() for r in rr})
    for g in groups:
        for name in methods:
            for half in ("tuning", "checking"):
                sm = summarise([x for x in rows[name] if x["group"] == g and x["half"] == half])
                summary.setdefault(g, {}).setdefault(name, {})[half] = sm
                if not sm["positives"] and not sm["negatives"]:
                    continue
                print(f"| {g} | {name} | {half} | {sm['success']}/{sm['positives']} "
                      f"| {sm['false_accept']} | {sm['unrelated_accepted']}/{sm['negatives']} "
                      f"| {sm['median_error_px']:.2f} | {sm['seconds_per_query']:.2f} "
                      f"| {sm['cpu_seconds_per_query']:.2f} |")  # fmt: skip
    return summary


def read_records(path: str | Path) -> list[dict[str, Any]]:
    """The records of a run's .jsonl file (one per query and method, ``method`` included)."""
    return [json.loads(line) for line in Path(path).read_text().splitlines()]


def append_record(path: Path, method: str, rec: dict[str, Any]) -> None:
    """One record more in a run's .jsonl file (written as it is made: a cut run keeps it)."""
    with path.open("a") as f:
        f.write(json.dumps({"method": method, **rec}, default=float) + "\n")


def table_from_jsonl(path: str) -> None:
    """The table of a (possibly unfinished) run from its .jsonl records."""
    rows: dict[str, list[dict[str, Any]]] = {}
    for r in read_records(path):
        rows.setdefault(r.pop("method"), []).append(r)
    table(rows, list(rows))


if __name__ == "__main__":
    sys.exit(main())
