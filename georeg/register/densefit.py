"""Dense least-squares refit of the global homography over the whole footprint (issue 20).

The feature homography rests on its inliers: few or clustered inliers leave it off towards the
footprint's edges. Here the orthophoto is rendered through the current homography, CFOG channels
of query and render are correlated in windows on a grid (``georeg.register.refine``'s tie
points), and the homography is refitted to every accepted tie point by weighted least squares
with iterative outlier rejection; measure -> fit is iterated.

"Never hurts": the refit replaces the feature homography only when its tie points cover the
footprint (as far as windows can be measured there) and its spatially blocked cross-validated
residual (each block predicted by the homography fitted without it) is lower than the feature
homography's residual on the same points; otherwise the feature homography is kept (``accepted: false`` and why).
"""

from __future__ import annotations

import logging
import time
from typing import Any

import numpy as np

from georeg.register.geolocation import apply_h, ground_px
from georeg.register.matching import one_se_choice, similarity_lsq
from georeg.register.tiepoints import (
    cfog,
    consistent,
    grid_points,
    measure_shifts,
    query_cfog,
    query_measurable,
    window_centroid,
)
from georeg.register.tiepoints import merged as tiepoint_settings

log = logging.getLogger(__name__)

DEFAULTS: dict[str, Any] = {
    "enabled": True,
    "iterations": 4,  # measure -> fit passes
    "min_tie_points": 20,  # fewer accepted tie points: keep the feature homography
    "min_cover": 0.3,  # tie points' convex hull / that of the windows that could be measured
    # (``cover_fraction``; over the valid pixels before session 59, which refused most queries
    # of 100-130 px: their windows' margin is much of them)
    # the footprint of min_cover: overlap = where the map has data too (a map smaller than the
    # query holds tie points on its overlap only: session 57); footprint = the whole query
    "cover_of": "overlap",
    # ... but with ``overlap`` the tie points still cover this share of the whole footprint: an
    # affine refit of a patch of 3-4 % of it moved the reversed source's poses on a map a
    # sixteenth of the query 4-9 map px off; on a map a quarter of it they cover 15-18 % and the
    # refit brought three poses 8-15 -> 2-2.6 px (session 57)
    "min_footprint_cover": 0.05,
    "reject_sigma": 3.0,  # outlier bound: this many robust sigmas of the residuals ...
    "reject_floor_px": 0.75,  # ... but never below this (query px)
    "cv_folds": 5,  # spatially blocked folds of the guard
    "cv_block_windows": 1.0,  # side of a CV block, in tie-point windows (refine.window_px)
    "min_gain": 0.1,  # the refit's CV residual must be this fraction below the feature fit's
    # auto: gain (affine unless the homography's CV is min_gain lower) | one_se (the simplest of
    # similarity, affine, homography within one standard error of the lowest blocked CV)
    "auto_rule": "one_se",
    "converged_px": 0.05,  # stop when the footprint moves less than this (query px)
    "model": "auto",  # auto (auto_rule) | homography | affine | similarity
}


def merged(conf: dict[str, Any] | None) -> dict[str, Any]:
    c = dict(DEFAULTS)
    c.update({k: v for k, v in (conf or {}).items() if v is not None})
    return c


def fit_homography_lsq(src: np.ndarray, dst: np.ndarray, w: np.ndarray | None = None) -> np.ndarray:
    """Weighted normalised-DLT homography src (N, 2) -> dst (N, 2); N >= 4."""

    def norm(p: np.ndarray) -> np.ndarray:
        c = p.mean(0)
        s = np.sqrt(2) / max(float(np.mean(np.hypot(*(p - c).T))), 1e-12)
        return np.array([[s, 0, -s * c[0]], [0, s, -s * c[1]], [0, 0, 1.0]])

    Ts, Td = norm(src), norm(dst)
    a = src @ Ts[:2, :2].T + Ts[:2, 2]
    b = dst @ Td[:2, :2].T + Td[:2, 2]
    n = len(a)
    o, z = np.ones(n), np.zeros((n, 3))
    A1 = np.c_[a, o, z, -b[:, :1] * a, -b[:, :1]]
    A2 = np.c_[z, a, o, -b[:, 1:] * a, -b[:, 1:]]
    sw = np.sqrt(np.ones(n) if w is None else np.asarray(w, float))
    A = np.r_[A1 * sw[:, None], A2 * sw[:, None]]
    h = np.linalg.svd(A, full_matrices=False)[2][-1].reshape(3, 3)
    H = np.linalg.inv(Td) @ h @ Ts
    return H / H[2, 2]


def fit_affine_lsq(src: np.ndarray, dst: np.ndarray, w: np.ndarray | None = None) -> np.ndarray:
    """Weighted least-squares affine map src (N, 2) -> dst (N, 2) as a 3 x 3 matrix; N >= 3."""
    c = src.mean(0)
    A = np.c_[src - c, np.ones(len(src))]
    sw = np.sqrt(np.ones(len(src)) if w is None else np.asarray(w, float))[:, None]
    coef = np.linalg.lstsq(A * sw, dst * sw, rcond=None)[0]
    H = np.eye(3)
    H[:2, :2] = coef[:2].T
    H[:2, 2] = coef[2] - coef[:2].T @ c
    return H


def fit_similarity_lsq(src: np.ndarray, dst: np.ndarray, w: np.ndarray | None = None) -> np.ndarray:
    """Weighted least-squares similarity (rotation, scale, shift) query px src (N, 2) -> map
    x, y dst (N, 2, y up: proper in (x, -y)) as a 3 x 3 matrix; N >= 2."""
    c = src.mean(0)
    S = similarity_lsq(src - c, dst * [1.0, -1.0], w)
    return np.diag([1.0, -1.0, 1.0]) @ S @ np.array([[1.0, 0, -c[0]], [0, 1.0, -c[1]], [0, 0, 1]])


def _fit(src: np.ndarray, dst: np.ndarray, w: np.ndarray, model: str) -> np.ndarray:
    if model == "similarity":
        return fit_similarity_lsq(src, dst, w)
    if model == "affine":
        return fit_affine_lsq(src, dst, w)
    if model == "homography":
        return fit_homography_lsq(src, dst, w)
    raise ValueError(f"unknown global_fit model {model!r} (expected homography, affine or auto)")


def residuals_px(H: np.ndarray, src: np.ndarray, dst: np.ndarray, px: float) -> np.ndarray:
    """|H(src) - dst| in query pixels (``px`` map units per query pixel)."""
    x, y = apply_h(H, src[:, 0], src[:, 1])
    r = np.hypot(x - dst[:, 0], y - dst[:, 1]) / px
    return np.where(np.isfinite(r), r, np.inf)


def robust_fit(src: np.ndarray, dst: np.ndarray, w: np.ndarray, px: float,
               c: dict[str, Any]) -> tuple[np.ndarray, np.ndarray]:  # fmt: skip
    """Weighted homography with iterative rejection (robust sigma, floor); (H, inlier mask)."""
    keep = np.ones(len(src), bool)
    model = str(c["model"])
    H = _fit(src, dst, w, model)
    for _ in range(5):
        r = residuals_px(H, src, dst, px)
        sig = 1.4826 * float(np.median(r[keep]))
        new = r <= max(float(c["reject_sigma"]) * sig, float(c["reject_floor_px"]))
        if new.sum() < 4 or np.array_equal(new, keep):
            break
        keep = new
        H = _fit(src[keep], dst[keep], w[keep], model)
    return H, keep


def blocked_cv(src: np.ndarray, dst: np.ndarray, w: np.ndarray, H0: np.ndarray, px: float,
               block: float, c: dict[str, Any], seed: int = 0,
               models: tuple[str, ...] = ()) -> dict[str, float]:  # fmt: skip
    """Held-out residual RMS (query px) of the refit (each of ``models``, default ``c["model"]``)
    and of ``H0`` (key ``feature``) on the same points.

    Tie points are grouped in square blocks of ``block`` px that go to ``cv_folds`` folds at
    random; each fold is predicted by the model fitted (robustly) without it. Points that the
    first model's fit of the other folds rejects as outliers are left out of every figure."""
    models = models or (str(c["model"]),)
    k = max(2, int(c["cv_folds"]))
    bid = (src[:, 0] // block).astype(int) * 100003 + (src[:, 1] // block).astype(int)
    ub, inv = np.unique(bid, return_inverse=True)
    fold = (np.random.default_rng(seed).permutation(len(ub)) % k)[inv]
    errs: dict[str, list[np.ndarray]] = {m: [] for m in (*models, "feature")}
    blocks: list[np.ndarray] = []
    for f in range(k):
        test = fold == f
        if test.sum() == 0 or (~test).sum() < 8:
            continue
        r = {}
        for m in models:
            H, _ = robust_fit(src[~test], dst[~test], w[~test], px, {**c, "model": m})
            r[m] = residuals_px(H, src[test], dst[test], px)
        r["feature"] = residuals_px(H0, src[test], dst[test], px)
        r1 = r[models[0]]
        bound = max(float(c["reject_sigma"]) * 1.4826 * float(np.median(r1)),
                    float(c["reject_floor_px"]))  # fmt: skip
        ok = r1 <= bound
        for m, v in r.items():
            errs[m].append(v[ok])
        blocks.append(inv[test][ok])
    out: dict[str, float] = {}
    for m, v in errs.items():
        a = np.concatenate(v) if v else np.zeros(0)
        out[m] = float(np.sqrt(np.mean(a**2))) if a.size else float("inf")
    out["refit"] = out[models[0]]
    if blocks:  # each model's blocks' mean held-out squared residual, and its standard error
        b = np.concatenate(blocks)
        n = np.bincount(b)
        has = n > 0
        for m in models:
            v = np.bincount(b, np.concatenate(errs[m]) ** 2)[has] / n[has]
            out[f"block_mse_{m}"] = float(v.mean())
            out[f"block_se_{m}"] = float(v.std() / np.sqrt(len(v))) if len(v) > 1 else 0.0
    return out


def hull_area(pts: np.ndarray) -> float:
    """Area of the convex hull of ``pts`` (N, 2); 0 for fewer than 3 points."""
    import cv2

    if len(pts) < 3:
        return 0.0
    return float(cv2.contourArea(cv2.convexHull(pts.astype(np.float32))))


def cover_fraction(pts: np.ndarray, measurable: np.ndarray) -> float:
    """Convex hull area of the tie points ``pts`` over that of the grid points where a tie point
    could be measured (``measurable``: their windows valid enough). Not over the valid pixels:
    a window's centre keeps off the edge of the valid area, a margin that is most of a small
    query (a 100 px query's 32 px windows span at most ~0.6 of it)."""
    reach = hull_area(measurable)
    return min(1.0, hull_area(pts) / reach) if reach > 0 else 0.0


def dense_fit(
    band: np.ndarray,
    H: np.ndarray,
    map_image: Any,
    conf: dict[str, Any] | None = None,
    refine_conf: dict[str, Any] | None = None,
) -> tuple[np.ndarray, dict[str, Any]]:
    """Refit the global homography ``H`` (query px -> map x, y) to CFOG tie points over the
    whole footprint. ``conf``: this module's settings (``refine.global_fit``); ``refine_conf``:
    the tie-point settings (grid, window, search, scores: ``georeg.register.refine``).

    Returns the homography to use (the refit, or ``H`` when the guard keeps it) and a report."""
    t0 = time.perf_counter()
    c = merged(conf)
    requested = str(c["model"])
    if requested not in ("homography", "affine", "similarity", "auto"):
        raise ValueError(f"unknown global_fit model {requested!r}")
    if str(c["cover_of"]) not in ("overlap", "footprint"):
        raise ValueError(f"unknown global_fit cover_of {c['cover_of']!r} (overlap | footprint)")
    if str(c["auto_rule"]) not in ("gain", "one_se"):
        raise ValueError(f"unknown global_fit auto_rule {c['auto_rule']!r} (gain | one_se)")
    if requested == "auto":  # iterate with the affine map, then choose by blocked CV
        c["model"] = "affine"
    rc = tiepoint_settings(refine_conf)
    H0 = np.asarray(H, np.float64)
    h, w = band.shape[-2:]
    qf, qvalid = query_cfog(band, int(rc["orientations"]), float(rc["cfog_sigma_px"]))
    win, step, search = int(rc["window_px"]), int(rc["grid_step_px"]), int(rc["search_px"])
    centres = grid_points(w, h, step, win)
    pts = window_centroid(centres, w, h, win)
    cols = np.arange(w, dtype=np.float64)[None, :]
    rows = np.arange(h, dtype=np.float64)[:, None]
    px = ground_px(H0, w, h)
    corners = np.array([[0, 0], [w - 1, 0], [0, h - 1], [w - 1, h - 1]], float)
    info: dict[str, Any] = {"enabled": True, "accepted": False, "grid_points": int(len(pts))}
    Hc = H0.copy()
    first: dict[str, Any] | None = None
    last: tuple | None = None
    history = []
    for it in range(max(1, int(c["iterations"]))):
        x, y = apply_h(Hc, cols, rows)
        rendered = map_image.render(x, y)
        rvalid = np.isfinite(rendered)
        rf = cfog(np.nan_to_num(rendered), rvalid, int(rc["orientations"]),
                  float(rc["cfog_sigma_px"]))  # fmt: skip
        m = measure_shifts(qf, rf, qvalid, rvalid, centres, win, search,
                           float(rc["min_valid_fraction"]))  # fmt: skip
        ok = m["valid"] & ~m["border"] & (m["score"] >= float(rc["min_score"]))
        if ok.sum() >= 3:
            ok[ok] &= consistent(pts[ok], m["shift"][ok], 2.5 * step, float(rc["consistency_px"]))
        src, measured = pts[ok], m["valid"]
        dx, dy = apply_h(Hc, src[:, 0] + m["shift"][ok, 0], src[:, 1] + m["shift"][ok, 1])
        dst = np.c_[dx, dy]
        wts = np.clip(m["score"][ok], 0.05, 1.0)
        if first is None:
            first = {"src": src, "dst": dst, "w": wts}
        entry: dict[str, Any] = {"iteration": it, "tie_points": int(ok.sum())}
        history.append(entry)
        if ok.sum() < max(8, int(c["min_tie_points"])):
            info["reason"] = f"{int(ok.sum())} tie points < min_tie_points {c['min_tie_points']}"
            break
        Hn, keep = robust_fit(src, dst, wts, px, c)
        entry["inliers"] = int(keep.sum())
        entry["residual_px"] = float(np.median(residuals_px(Hn, src[keep], dst[keep], px)))
        move = residuals_px(Hn, corners, np.c_[apply_h(Hc, corners[:, 0], corners[:, 1])], px)
        entry["moved_px"] = float(move.max())
        last = (src, dst, wts, keep, measured)
        Hc = Hn
        if move.max() < float(c["converged_px"]):
            break
    info["iterations"] = history
    if last is None:
        info["seconds"] = time.perf_counter() - t0
        return H0, info
    src, dst, wts, keep, measured = last
    # of where tie points could be measured: in the query (footprint) or in both (overlap)
    qmeas = query_measurable(qvalid, centres, win, float(rc["min_valid_fraction"]))
    cover_all = cover_fraction(src[keep], pts[qmeas])
    cover = cover_fraction(src[keep], pts[measured]) if c["cover_of"] == "overlap" else cover_all
    seed = int(rc.get("seed", 0))
    block = float(c["cv_block_windows"]) * win
    if requested == "auto" and c.get("auto_rule") == "one_se":
        models = ("similarity", "affine", "homography")
        cv = blocked_cv(src, dst, wts, H0, px, block, c, seed, models)
        c["model"] = one_se_choice({m: cv.get(f"block_mse_{m}", float("inf")) for m in models},
                                   {m: cv.get(f"block_se_{m}", 0.0) for m in models})  # fmt: skip
        if c["model"] != "affine":  # the iterations' fit is already the affine one
            Hc, keep = robust_fit(src, dst, wts, px, c)
        cv["refit"] = cv[c["model"]]
    elif requested == "auto":
        cv = blocked_cv(src, dst, wts, H0, px, block, c, seed, ("affine", "homography"))
        if cv["homography"] < (1 - float(c["min_gain"])) * cv["affine"]:
            c["model"] = "homography"
            Hc, keep = robust_fit(src, dst, wts, px, c)
            cv["refit"] = cv["homography"]
    else:
        cv = blocked_cv(src, dst, wts, H0, px, block, c, seed)
    info["model"] = str(c["model"])
    moved = residuals_px(Hc, corners, np.c_[apply_h(H0, corners[:, 0], corners[:, 1])], px)
    info.update(
        tie_points=int(len(src)),
        inliers=int(keep.sum()),
        cover=cover,
        cover_footprint=cover_all,
        cv_rms_px=cv,
        moved_corners_px=[round(float(v), 3) for v in moved],
    )
    if cover < float(c["min_cover"]):
        info["reason"] = (
            f"tie points cover {cover:.2f} of the footprint < min_cover {c['min_cover']}"
        )
    elif c["cover_of"] == "overlap" and cover_all < float(c["min_footprint_cover"]):
        info["reason"] = (f"tie points cover {cover_all:.3f} of the whole footprint < "
                          f"min_footprint_cover {c['min_footprint_cover']}")  # fmt: skip
    elif not cv["refit"] < (1 - float(c["min_gain"])) * cv["feature"]:
        info["reason"] = (
            f"cross-validated residual {cv['refit']:.3f} px not below the feature homography's "
            f"{cv['feature']:.3f} px"
        )
    else:
        info["accepted"] = True
    info["homography"] = Hc.tolist()
    info["seconds"] = time.perf_counter() - t0
    log.info("global dense fit: %d tie points, cover %.2f (%.3f of the footprint), CV %.3f vs "
             "%.3f px -> %s", len(src), cover, cover_all, cv["refit"], cv["feature"],
             "refit" if info["accepted"] else info.get("reason"))  # fmt: skip
    return (Hc if info["accepted"] else H0), info
