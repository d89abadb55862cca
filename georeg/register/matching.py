"""Verification of one candidate: 2-NN ratio matching (stop at Nt), time-bounded RANSAC homography,
and the model of an accepted fit (similarity, affine or homography, by leave-one-out CV).

Query side in query pixels (col, row at the original query resolution); map side in map x, y.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import cv2
import numpy as np

from georeg.index.kdtree import kdtree, knn_search

# knn(query_desc) -> (dist (n,2) L2 (not squared), idx (n,2) positions in the candidate's arrays)
KnnFn = Callable[[np.ndarray], tuple[np.ndarray, np.ndarray]]

FLAT_MAX = 60_000  # exact faiss search up to this many map descriptors, FLANN kd-tree beyond


def knn2(map_desc: np.ndarray, threads: int = 1) -> KnnFn:
    """A 2-NN searcher over ``map_desc``: exact (faiss flat) when small, FLANN kd-tree when large."""
    md = np.ascontiguousarray(map_desc, dtype=np.float32)
    n = len(md)
    if n == 0:
        return lambda q: (np.full((len(q), 2), np.inf, np.float32), np.full((len(q), 2), -1))
    if n <= FLAT_MAX:
        import faiss

        faiss.omp_set_num_threads(max(1, int(threads)))
        index = faiss.IndexFlatL2(md.shape[1])
        index.add(md)

        def search(q: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
            d2, ii = index.search(np.ascontiguousarray(q, dtype=np.float32), min(2, n))
            d = np.sqrt(np.maximum(d2, 0.0))
            if n == 1:  # a single map feature: no second neighbour, the ratio test cannot pass
                d = np.c_[d, np.full(len(d), np.inf, np.float32)]
                ii = np.c_[ii, np.full(len(ii), -1)]
            return d, ii

        return search
    flann = kdtree(md)

    def search_flann(q: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        ii, d2 = knn_search(flann, q, 2)
        return np.sqrt(np.maximum(d2, 0.0)), ii

    return search_flann


@dataclass
class Matches:
    """Ratio-test correspondences, one per map keypoint, strongest query features first."""

    q_idx: np.ndarray  # index into the query features
    m_idx: np.ndarray  # index into the candidate's map arrays
    q_xy: np.ndarray  # (n,2) query col,row (original query pixels)
    m_xy: np.ndarray  # (n,2) map x,y
    dist: np.ndarray  # descriptor distance of the best neighbour
    n_examined: int = 0  # query features looked at before stopping

    def __len__(self) -> int:
        return len(self.q_idx)


def ratio_matches(
    q_xy: np.ndarray,
    q_desc: np.ndarray,
    q_response: np.ndarray | None,
    m_xy: np.ndarray,
    knn: KnnFn,
    ratio: float = 0.7,
    max_matches: int | None = 100,
    chunk: int = 1024,
) -> Matches:
    """The paper's linear search: query features in order of response, 2-NN ratio test, stop at Nt.

    If several query features match one map keypoint only the closest is kept. ``max_matches``
    None or 0 uses every query feature.
    """
    n = len(q_desc)
    order = np.argsort(-q_response, kind="stable") if q_response is not None else np.arange(n)
    limit = int(max_matches) if max_matches else None
    qi_all: list[np.ndarray] = []
    mi_all: list[np.ndarray] = []
    d_all: list[np.ndarray] = []
    best: dict[int, float] = {}
    examined = 0
    for start in range(0, n, chunk):
        sel = order[start : start + chunk]
        d, ii = knn(q_desc[sel])
        examined = start + len(sel)
        ok = (ii[:, 0] >= 0) & (d[:, 0] < ratio * d[:, 1])
        qi_all.append(sel[ok])
        mi_all.append(ii[ok, 0])
        d_all.append(d[ok, 0])
        best.update(dict.fromkeys(ii[ok, 0].tolist(), 0.0))
        if limit is not None and len(best) >= limit:
            break
    qi = np.concatenate(qi_all) if qi_all else np.zeros(0, np.int64)
    mi = np.concatenate(mi_all).astype(np.int64) if mi_all else np.zeros(0, np.int64)
    dd = np.concatenate(d_all) if d_all else np.zeros(0, np.float32)
    # one match per map keypoint: the smallest descriptor distance wins
    keep = _closest_per_key(mi, dd)
    # back to the search order (strongest query features first), then cut at Nt
    rank = np.empty(n, np.int64)
    rank[order] = np.arange(n)
    keep = keep[np.argsort(rank[qi[keep]], kind="stable")]
    if limit is not None:
        if len(keep) > limit:
            # examined counts the query features up to (and including) the Nt-th kept match
            examined = int(rank[qi[keep[limit - 1]]]) + 1
        keep = keep[:limit]
    qi, mi, dd = qi[keep], mi[keep], dd[keep]
    return Matches(qi, mi, q_xy[qi].astype(np.float64), m_xy[mi].astype(np.float64), dd, examined)


def _closest_per_key(keys: np.ndarray, dist: np.ndarray) -> np.ndarray:
    """Positions of the smallest ``dist`` for every distinct key."""
    if len(keys) == 0:
        return np.zeros(0, np.int64)
    o = np.lexsort((dist, keys))
    first = np.r_[True, keys[o][1:] != keys[o][:-1]]
    return o[first]


@dataclass
class HomographyFit:
    """A homography query (col,row) -> map (x,y) with its inliers and residuals in map pixels."""

    H: np.ndarray | None
    inliers: np.ndarray  # bool (n,)
    residual_px: np.ndarray  # (n,) reprojection distance in map feature pixels
    threshold_px: float
    rounds: int = 0
    seconds: float = 0.0
    info: dict[str, Any] = field(default_factory=dict)

    @property
    def n_inliers(self) -> int:
        return int(self.inliers.sum())

    @property
    def rms_px(self) -> float:
        """RMS residual of the inliers (map feature pixels)."""
        r = self.residual_px[self.inliers]
        return float(np.sqrt(np.mean(r**2))) if len(r) else float("nan")


def apply_h(H: np.ndarray, xy: np.ndarray) -> np.ndarray:
    """Apply a 3x3 homography to (n,2) points (float64)."""
    xy = np.asarray(xy, np.float64)
    p = xy @ H[:, :2].T + H[:, 2]
    with np.errstate(divide="ignore", invalid="ignore"):
        return p[:, :2] / p[:, 2:3]


_METHODS = {
    "magsac": "usac",
    "usac_magsac": "usac",
    "usac_accurate": "usac",
    "usac_default": "usac",
    "ransac": "ransac",
    "rho": "rho",
}


def usac_params(method: str, thr: float, conf: float, iters: int, seed: int) -> cv2.UsacParams:
    """Seeded, single-threaded OpenCV USAC parameters: MAGSAC++ (``magsac``) or, otherwise, an
    USAC_ACCURATE-like MSAC score with graph-cut local optimisation."""
    p = cv2.UsacParams()
    p.threshold = float(thr)
    p.confidence = float(conf)
    p.maxIterations = int(iters)
    p.randomGeneratorState = int(seed) & 0x7FFFFFFF
    p.isParallel = False
    p.sampler = cv2.SAMPLING_UNIFORM
    p.loIterations = 10
    p.loSampleSize = 14
    if method in ("magsac", "usac_magsac"):
        p.score = cv2.SCORE_METHOD_MAGSAC
        p.loMethod = cv2.LOCAL_OPTIM_SIGMA
        p.final_polisher = cv2.MAGSAC
        p.final_polisher_iterations = 10
    else:
        p.score = cv2.SCORE_METHOD_MSAC
        p.loMethod = cv2.LOCAL_OPTIM_GC
        p.final_polisher = cv2.LSQ_POLISHER
        p.final_polisher_iterations = 3
    return p


def fit_homography(
    q_xy: np.ndarray,
    m_xy: np.ndarray,
    map_px_m: float,
    conf: dict[str, Any],
    seed: int = 0,
) -> HomographyFit:
    """Time-bounded robust homography, then least squares on all inliers.

    ``conf`` keys: method (magsac | usac_accurate | ransac | rho), reproj_px (inlier threshold in
    map feature pixels), max_seconds (time bound over rounds), max_iters (per round), confidence,
    rounds (most rounds; stops early when two rounds agree), affine_below (with fewer inliers the
    least-squares re-estimation fits an affine map: 8 degrees of freedom from a handful of
    clustered points extrapolate badly over the footprint). Map coordinates are centred and scaled
    to map feature pixels for the solver, so thresholds are in pixels and numerics stay sane.
    """
    n = len(q_xy)
    thr = float(conf.get("reproj_px", 3.0))
    empty = HomographyFit(None, np.zeros(n, bool), np.full(n, np.inf), thr)
    if n < 4:
        return empty
    t0 = time.perf_counter()
    c = m_xy.mean(axis=0)
    s = float(map_px_m)
    # map y is flipped (north-up -> row-down) so that a proper nadir mapping preserves orientation:
    # USAC rejects orientation-reversing minimal samples, and (col,row) -> (x,y) is one otherwise
    T = np.array([[1 / s, 0, -c[0] / s], [0, -1 / s, c[1] / s], [0, 0, 1.0]])
    src = np.ascontiguousarray(q_xy, np.float32)
    dst = np.ascontiguousarray(apply_h(T, m_xy), np.float32)
    method = str(conf.get("method", "magsac")).lower()
    kind = _METHODS.get(method)
    if kind is None:
        raise ValueError(f"unknown RANSAC method {method!r}; expected one of {sorted(_METHODS)}")
    max_s = float(conf.get("max_seconds", 2.0))
    iters = int(conf.get("max_iters", 10000))
    confidence = float(conf.get("confidence", 0.999))
    max_rounds = int(conf.get("rounds", 3))
    best_H, best_count, last_count, rounds = None, -1, -2, 0
    while rounds < max_rounds and (rounds == 0 or time.perf_counter() - t0 < max_s):
        rs = seed * 7919 + rounds
        try:
            if kind == "usac":
                Hn, mask = cv2.findHomography(
                    src, dst, usac_params(method, thr, confidence, iters, rs)
                )
            else:
                cv2.setRNGSeed(rs)
                flag = cv2.RANSAC if kind == "ransac" else cv2.RHO
                Hn, mask = cv2.findHomography(
                    src, dst, flag, thr, maxIters=iters, confidence=confidence
                )
        except cv2.error:
            Hn, mask = None, None
        rounds += 1
        if Hn is None or mask is None or Hn.shape != (3, 3):
            continue
        cnt = int(mask.sum())
        if cnt > best_count:
            best_H, best_count = Hn, cnt
        if cnt == last_count:  # two rounds found the same support: converged
            break
        last_count = cnt
    if best_H is None:
        empty.rounds, empty.seconds = rounds, time.perf_counter() - t0
        return empty
    Hn = best_H
    inl = _residuals(Hn, src, dst) < thr
    affine_below = int(conf.get("affine_below", 12))
    model = "homography"
    for _ in range(3):  # least squares on all inliers, re-evaluate the support
        if inl.sum() < 4:
            break
        if inl.sum() < affine_below:
            # too few inliers to pin 8 degrees of freedom: perspective terms would extrapolate wildly
            Hls, cand, keep = affine_lsq(src[inl], dst[inl]), "affine", 0.8
        else:
            Hls, _m = cv2.findHomography(src[inl], dst[inl], 0)
            cand, keep = "homography", 1.0
        if Hls is None:
            break
        new = _residuals(Hls, src, dst) < thr
        if new.sum() < keep * inl.sum() or new.sum() < 4:
            break
        Hn, model, stable = Hls, cand, bool(np.array_equal(new, inl))
        inl = new
        if stable:
            break
    res = _residuals(Hn, src, dst)
    H = np.linalg.inv(T) @ Hn
    H = H / H[2, 2]
    return HomographyFit(
        H, res < thr, res, thr, rounds, time.perf_counter() - t0, {"method": method, "model": model}
    )


def affine_lsq(src: np.ndarray, dst: np.ndarray) -> np.ndarray:
    """Least-squares affine map src -> dst as a 3x3 matrix."""
    A = np.c_[src.astype(np.float64), np.ones(len(src))]
    sol, *_ = np.linalg.lstsq(A, dst.astype(np.float64), rcond=None)
    return np.vstack([sol.T, [0.0, 0.0, 1.0]])


def similarity_lsq(src: np.ndarray, dst: np.ndarray, w: np.ndarray | None = None) -> np.ndarray:
    """(Weighted) least-squares similarity (rotation, scale, shift; no mirror) src -> dst as a
    3x3 matrix: x' = a x - b y + tx, y' = b x + a y + ty."""
    x, y = src[:, 0].astype(np.float64), src[:, 1].astype(np.float64)
    one, zero = np.ones(len(src)), np.zeros(len(src))
    sw = np.sqrt(one if w is None else np.asarray(w, np.float64))
    A = np.r_[np.c_[x, -y, one, zero] * sw[:, None], np.c_[y, x, zero, one] * sw[:, None]]
    b = np.r_[dst[:, 0] * sw, dst[:, 1] * sw].astype(np.float64)
    (a, bb, tx, ty), *_ = np.linalg.lstsq(A, b, rcond=None)
    return np.array([[a, -bb, tx], [bb, a, ty], [0.0, 0.0, 1.0]])


def _residuals(Hn: np.ndarray, src: np.ndarray, dst: np.ndarray) -> np.ndarray:
    p = apply_h(Hn, src)
    r = np.linalg.norm(p - dst, axis=1)
    return np.where(np.isfinite(r), r, np.inf)


# ----------------------------------------------------------------------------- cross-spectral
# Cross-spectral matching front-end: features that survive SWIR vs visible and years.
#
# Measured on the cross-date SWIR -> RGB development set (benchmarks/bench_crossspectral.py,
# docs/BENCHMARKS.md "Cross-spectral matching"). The pieces:
#
# * ``flip_polarity``: the SIFT descriptor of the contrast-inverted image at the same keypoint,
#   computed by permuting the descriptor (no second extraction). Inverting an image negates every
#   gradient: the dominant orientation turns by 180 degrees, the orientation bins relative to it are
#   unchanged, and the 4 x 4 spatial cells are visited in the opposite order. So the inverted
#   descriptor is the original with its cell grid rotated by 180 degrees (exact; checked in
#   tests/test_crossspectral.py). Querying with both polarities is the same as putting both
#   polarities of the map in the vocabulary, at no cost on the map side: a roof bright in the
#   visible and dark at 2.2 um (or vegetation, dark in the visible, bright at 1.6 um) still matches.
# * ``rotation_hypotheses``: a loose ratio test, keypoint-size agreement and a vote on the
#   rotation (the ``vote`` matcher, the default: ``register.matcher``).

# descriptor layout of OpenCV SIFT: index = (row_cell * 4 + col_cell) * 8 + orientation_bin
_FLIP = np.arange(128).reshape(4, 4, 8)[::-1, ::-1, :].ravel()


def flip_polarity(desc: np.ndarray) -> np.ndarray:
    """SIFT/RootSIFT descriptors of the contrast-inverted image at the same keypoints."""
    d = np.asarray(desc)
    if d.shape[-1] != 128:
        raise ValueError(f"expected 128-D SIFT descriptors, got {d.shape}")
    return d[..., _FLIP]


def matcher_conf(reg_conf: dict[str, Any] | None) -> dict[str, Any]:
    """``register.matcher`` with the defaults of config/config.yaml: method vote (polarity both)
    | paper (polarity one unless asked)."""
    m = dict((reg_conf or {}).get("matcher") or {})
    m.setdefault("method", "vote")
    m.setdefault("polarity", "both" if m["method"] == "vote" else "one")
    return m


def add_polarity(xy: np.ndarray, desc: np.ndarray, response: np.ndarray):
    """Append the inverted-polarity copy of every feature (same position and response)."""
    return (
        np.concatenate([xy, xy]),
        np.concatenate([desc, flip_polarity(desc)]).astype(np.float32),
        np.concatenate([response, response]),
    )


def _circ_diff(a: np.ndarray, b: float) -> np.ndarray:
    return np.abs((a - b + 180.0) % 360.0 - 180.0)


def rotation_hypotheses(
    q_xy: np.ndarray,
    q_desc: np.ndarray,
    q_angle: np.ndarray,
    q_size: np.ndarray,
    m_xy: np.ndarray,
    m_angle: np.ndarray,
    m_size: np.ndarray,
    knn: Any,
    conf: dict[str, Any],
) -> list[tuple[Any, int]]:
    """Loose ratio matches, filtered by keypoint scale and grouped by rotation (Lowe's Hough vote).

    Cross-spectral descriptors are far apart, so the paper's 2-NN ratio 0.7 keeps almost nothing
    on real SWIR vs visible pairs. A loose ratio (``ratio``, 0.9) keeps many, mostly wrong; two
    properties of right matches that do not depend on the spectrum separate them: the keypoint
    sizes agree (both images are at the feature GSD: |log2 size ratio| <= ``max_octaves``) and the
    orientation differences of all right matches equal the query's rotation. The strongest
    ``hypotheses`` peaks of a ``bin_deg`` histogram of orientation differences (weighted by
    distinctiveness 1 - d1/d2) are returned, each with the matches within ``bin_deg`` of it, and
    the number of rotation bins (a multiple-test count for the NFA). Sizes in feature pixels;
    angles in degrees (OpenCV keypoint convention, both images row-down).
    """

    ratio = float(conf.get("ratio", 0.9))
    d, ii = knn(q_desc)
    ok = (ii[:, 0] >= 0) & (d[:, 0] < ratio * d[:, 1])
    qi = np.flatnonzero(ok)
    mi = ii[ok, 0].astype(np.int64)
    dist = d[ok, 0]
    w = 1.0 - d[ok, 0] / np.maximum(d[ok, 1], 1e-9)
    oct_max = float(conf.get("max_octaves", 1.0))
    if oct_max > 0:
        lr = np.abs(np.log2(np.maximum(m_size[mi], 1e-6) / np.maximum(q_size[qi], 1e-6)))
        keep = lr <= oct_max
        qi, mi, dist, w = qi[keep], mi[keep], dist[keep], w[keep]
    bin_deg = float(conf.get("bin_deg", 15.0))
    nb = max(1, int(round(360.0 / bin_deg)))
    if len(qi) == 0:
        return []
    delta = (m_angle[mi] - q_angle[qi]) % 360.0
    hist = np.bincount((delta / (360.0 / nb)).astype(int) % nb, weights=w, minlength=nb)
    sm = hist + 0.5 * (np.roll(hist, 1) + np.roll(hist, -1))
    peaks = [
        b
        for b in np.argsort(-sm, kind="stable")
        if sm[b] >= sm[(b - 1) % nb] and sm[b] >= sm[(b + 1) % nb]
    ]
    out = []
    for b in peaks[: int(conf.get("hypotheses", 2))]:
        centre = (b + 0.5) * 360.0 / nb
        sel = np.flatnonzero(_circ_diff(delta, centre) <= bin_deg)
        # one match per map feature and one per query position (a keypoint's polarity copy and
        # its extra orientations sit at one place: several matches there are not independent)
        sel = sel[_closest_per_key(mi[sel], dist[sel])]
        qkey = np.unique(np.round(q_xy[qi[sel]], 1), axis=0, return_inverse=True)[1].ravel()
        sel = sel[_closest_per_key(qkey, dist[sel])]
        order = np.argsort(dist[sel], kind="stable")
        sel = sel[order]
        m = Matches(
            qi[sel],
            mi[sel],
            q_xy[qi[sel]].astype(np.float64),
            m_xy[mi[sel]].astype(np.float64),
            dist[sel],
            len(q_desc),
        )
        out.append((m, nb))
    return out


def guided_matches(
    q_xy: np.ndarray,
    q_desc: np.ndarray,
    H: np.ndarray,
    m_xy: np.ndarray,
    m_desc: np.ndarray,
    radius: float,
    ratio: float = 0.95,
    knn: Any = None,
) -> Any:
    """Matches of every query feature among the map features within ``radius`` (map units) of
    H's prediction: nearest descriptor there, 2-NN ratio among those local candidates only
    (a second neighbour elsewhere on the map says nothing about this place). A feature with a
    single local candidate is compared with its nearest other descriptor over the whole region
    instead (``knn``, a georeg.register.matching.knn2 searcher over ``m_desc``), else it would pass
    unchecked. One match per map feature (the closest descriptor). Returns Matches."""
    from scipy.spatial import cKDTree


    z = np.zeros(0, np.int64)
    empty = Matches(z, z, np.zeros((0, 2)), np.zeros((0, 2)), np.zeros(0), len(q_desc))
    if len(q_xy) == 0 or len(m_xy) < 2:
        return empty
    pred = apply_h(H, q_xy)
    ok = np.isfinite(pred).all(axis=1)
    tree = cKDTree(np.asarray(m_xy, np.float64))
    lists = tree.query_ball_point(pred[ok], float(radius))
    qi_ok = np.flatnonzero(ok)
    lens = np.fromiter((len(x) for x in lists), np.int64, len(lists))
    if lens.sum() == 0:
        return empty
    qi = np.repeat(qi_ok, lens)
    mi = np.fromiter((j for x in lists for j in x), np.int64, int(lens.sum()))
    d = np.linalg.norm(q_desc[qi].astype(np.float32) - m_desc[mi].astype(np.float32), axis=1)
    # best and second best per query feature
    o = np.lexsort((d, qi))
    qi, mi, d = qi[o], mi[o], d[o]
    first = np.r_[True, qi[1:] != qi[:-1]]
    pos = np.flatnonzero(first)
    second = pos + 1
    has2 = (second < len(qi)) & (np.r_[qi, -1][np.minimum(second, len(qi))] == qi[pos])
    d2 = np.where(has2, d[np.minimum(second, len(qi) - 1)], np.inf)
    if knn is not None and (~has2).any():
        lone = np.flatnonzero(~has2)
        gd, gi = knn(q_desc[qi[pos[lone]]])
        other = np.where(gi[:, 0] == mi[pos[lone]], gd[:, 1], gd[:, 0])
        d2[lone] = np.maximum(other, d[pos[lone]])
    good = d[pos] < ratio * d2
    sel = pos[good]
    keep = sel[_closest_per_key(mi[sel], d[sel])]
    keep = keep[np.argsort(d[keep], kind="stable")]
    return Matches(qi[keep], mi[keep], q_xy[qi[keep]].astype(np.float64),
                   m_xy[mi[keep]].astype(np.float64), d[keep], len(q_desc))  # fmt: skip


# ---------------------------------------------------------------- the model of an accepted fit
# The model of an accepted feature fit, chosen by leave-one-out cross-validation on its inliers.
#
# RANSAC and the acceptance test work with a homography (8 degrees of freedom); once a fit is
# accepted, its inliers are refitted with the simplest model that predicts them as well as any:
# a similarity (rotation, scale, shift: 4), an affine map (6) or a homography (8). Each model's
# leave-one-out squared residuals are computed on the inliers; the simplest model whose mean is
# within one standard error of the lowest mean wins (the "one-standard-error rule", Hastie,
# Tibshirani and Friedman, *The Elements of Statistical Learning*, 7.10). No threshold to tune:
# a handful of inliers pins a similarity, and a more flexible model is kept only when its held-out
# residuals say the data need it (issue 20: 5-10 inlier homographies extrapolated 2-5 map px off
# over small footprints; docs/BENCHMARKS.md "The model of an accepted fit").

MODELS = ("similarity", "affine", "homography")
MIN_POINTS = {"similarity": 2, "affine": 3, "homography": 4}


def fit_model(name: str, src: np.ndarray, dst: np.ndarray) -> np.ndarray | None:
    """Least-squares ``name`` mapping src -> dst (both (n, 2), proper orientation) as 3 x 3."""
    if name == "similarity":
        return similarity_lsq(src, dst)
    if name == "affine":
        return affine_lsq(src, dst)
    if name == "homography":
        H, _ = cv2.findHomography(src.astype(np.float64), dst.astype(np.float64), 0)
        return None if H is None or not np.all(np.isfinite(H)) else H
    raise ValueError(f"unknown model {name!r} (expected one of {MODELS})")


def one_se_choice(mse: dict[str, float], se: dict[str, float]) -> str:
    """The first model of ``mse`` (simplest first) whose mean held-out squared residual is within
    one standard error ``se`` of the lowest (the one-standard-error rule)."""
    best = min(mse, key=lambda n: mse[n])
    return next(n for n in mse if mse[n] <= mse[best] + se[best])


def loo_squared_errors(name: str, src: np.ndarray, dst: np.ndarray) -> np.ndarray | None:
    """Squared residual of each point predicted by ``name`` fitted to all the others, or None
    when the model cannot be cross-validated (too few points, a degenerate fit)."""
    n = len(src)
    if n - 1 <= MIN_POINTS[name]:  # a held-out prediction needs an over-determined fit
        return None
    err = np.empty(n)
    keep = np.ones(n, bool)
    for i in range(n):
        keep[i] = False
        H = fit_model(name, src[keep], dst[keep])
        keep[i] = True
        if H is None:
            return None
        p = apply_h(H, src[i : i + 1])[0]
        err[i] = float(np.sum((p - dst[i]) ** 2))
    return err if np.all(np.isfinite(err)) else None


def choose_model(
    q_xy: np.ndarray, m_xy: np.ndarray, map_px_m: float
) -> tuple[np.ndarray | None, dict[str, Any]]:
    """The mapping query (col, row) -> map (x, y) refitted to the inlier pairs ``q_xy``,
    ``m_xy`` with the model chosen by leave-one-out CV (one-standard-error rule), and a report:
    ``model`` and each model's held-out RMS (map px, None when not computable). Returns
    (None, report) when no model can be cross-validated (fewer than 4 inliers)."""
    q = np.asarray(q_xy, np.float64)
    m = np.asarray(m_xy, np.float64)
    # centred, in map pixels, map y flipped (north-up -> row-down): a nadir mapping keeps its
    # orientation, so the similarity is proper, and the numbers are of order one
    qc, mc = q.mean(axis=0), m.mean(axis=0)
    s = float(map_px_m)
    dst = (m - mc) * [1.0 / s, -1.0 / s]
    src = q - qc
    errs = {n: loo_squared_errors(n, src, dst) for n in MODELS}
    cv = {n: None if e is None else float(np.sqrt(e.mean())) for n, e in errs.items()}
    ok = {n: e for n, e in errs.items() if e is not None}
    info: dict[str, Any] = {"model": None, "loo_rms_px": cv, "inliers": len(q)}
    if not ok:
        return None, info
    chosen = one_se_choice({n: float(e.mean()) for n, e in ok.items()},
                           {n: float(e.std() / np.sqrt(len(e))) for n, e in ok.items()})  # fmt: skip
    Hn = fit_model(chosen, src, dst)
    if Hn is None:
        return None, info
    # back to query px -> map x, y: undo the centring of the query and the map's scaling
    Tq = np.array([[1.0, 0.0, -qc[0]], [0.0, 1.0, -qc[1]], [0.0, 0.0, 1.0]])
    Tm = np.array([[s, 0.0, mc[0]], [0.0, -s, mc[1]], [0.0, 0.0, 1.0]])
    H = Tm @ Hn @ Tq
    info["model"] = chosen
    return H / H[2, 2], info
