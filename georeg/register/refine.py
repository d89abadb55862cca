"""Sub-pixel local refinement of a global registration.

One homography cannot follow a pushbroom cube: attitude jitter moves every line by a fraction of a
pixel along and across track. This module corrects it with tie points measured against the map:

1. The orthophoto is rendered into query geometry through the current mapping (so every remaining
   misregistration is a small shift), and both images become CFOG-like structure channels
   (``cfog``: |oriented gradient| in ``orientations`` directions over 180 deg, Gaussian-smoothed,
   L2-normalised per pixel). The absolute value makes them insensitive to the contrast reversals
   of the SWIR-visible spectral gap.
2. At every point of a ``grid_step_px`` grid the query window (``window_px``) is matched over
   integer shifts up to ``search_px`` by normalised cross-correlation of the channels, computed
   for all points at once (one box filter per shift); the peak is refined by a 3 x 3 quadratic
   fit. The peak NCC is the point's reliability score. Points are rejected by score, invalid
   pixels, a peak on the search border, then by consistency with their neighbours.
3. A displacement model ``D(col, row)`` (query pixels) is fitted: the refined mapping is
   ``f(p) = H(p + D(p))`` where H is the global homography. Models: ``per_line`` (a penalised
   cubic B-spline in the line of an offset and an across-track slope, for both components: the
   pushbroom model: roll, pitch and yaw per line), ``polynomial`` (2-D, ``poly_degree``), ``tps``
   (thin-plate spline with smoothing) and ``homography`` (D = 0). ``auto`` picks the model with
   the lowest k-fold cross-validated tie-point residual (it must beat ``homography`` by
   ``auto_min_gain``). Fewer than ``min_tie_points`` accepted points: the homography is kept.
   Before step 3 (``global_fit``, georeg.register.densefit, issue 20) the global map itself is
   refitted to the tie points of the whole footprint and kept only if its blocked CV beats the
   feature homography; a local model then acts only where its own blocked CV beats the global
   fit (``cv_guard``) and tie points support it (``support_*``), and ``auto`` needs a gain of
   ``auto_min_gain_px`` too: the refinement never extrapolates a local model.
4. Window averaging attenuates fast jitter, so steps 1-3 are iterated (``iterations``): each pass
   measures the residual shift against the current refined mapping and refits the total.
   A last measurement pass against the final mapping gives the residuals "after".
"""

from __future__ import annotations

import logging
import time
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from georeg.register import tiepoints
from georeg.register.densefit import dense_fit
from georeg.register.geolocation import apply_h, ground_px
from georeg.register.tiepoints import (  # noqa: F401  (MapImage, read_map_gray: re-exported)
    MapImage,
    cfog,
    consistent,
    grid_points,
    measure_shifts,
    query_cfog,
    query_valid,
    read_map_gray,
    window_centroid,
)

log = logging.getLogger(__name__)

DEFAULTS: dict[str, Any] = {
    **tiepoints.DEFAULTS,
    "enabled": True,
    "min_tie_points": 30,
    "iterations": 3,
    "model": "auto",
    "line_knot_px": 16,
    "line_smoothing": 0.02,
    "line_terms": 3,
    "poly_degree": 3,
    "tps_smoothing": 1000.0,
    "tps_max_points": 1500,
    "cv_folds": 5,
    "auto_min_gain": 0.05,
    "auto_min_gain_px": 0.05,
    "auto_models": ["per_line", "polynomial"],
    "seed": 0,
    "support_full_steps": 1.5,
    "support_zero_steps": 4.0,
    "cv_guard": True,
    "cv_guard_sigma_steps": 3.0,
    "cv_guard_full_gain": 0.05,
    "pooled_bands": True,  # tie points from the CFOG of every pooled query band (else the primary)
    "global_fit": {},  # georeg.register.densefit settings (enabled by default)
}
MODELS = ("per_line", "polynomial", "tps", "homography")


def merged(conf: dict[str, Any] | None) -> dict[str, Any]:
    c = dict(DEFAULTS)
    c.update({k: v for k, v in (conf or {}).items() if v is not None})
    return c


# ----------------------------------------------------------------------------- models


def _bspline_basis(t: np.ndarray, lo: float, hi: float, spacing: float) -> np.ndarray:
    """Cubic B-spline basis (len(t), m) with uniform knots every ``spacing`` over [lo, hi]."""
    from scipy.interpolate import BSpline

    nseg = max(1, int(np.ceil((hi - lo) / max(spacing, 1e-9))))
    step = (hi - lo) / nseg if hi > lo else 1.0
    knots = lo + step * np.arange(-3, nseg + 4)
    m = len(knots) - 4
    tt = np.clip(t, lo, hi)
    return BSpline.design_matrix(tt, knots, 3, extrapolate=True).toarray()[:, :m]


class Model:
    """A displacement field D(col, row) -> (dcol, drow) in query pixels."""

    name = "homography"

    def fit(self, pts: np.ndarray, d: np.ndarray, w: np.ndarray | None = None) -> Model:
        return self

    def __call__(self, col: np.ndarray, row: np.ndarray) -> np.ndarray:
        return np.zeros((*np.shape(col), 2))


class PerLine(Model):
    """Per-line pushbroom model: D(c, r) = a(r) + b(r) s, s = (c - w/2) / (w/2); a, b P-splines."""

    name = "per_line"

    def __init__(self, width: int, height: int, knot_px: float, smoothing: float, terms: int = 3):
        self.width, self.height, self.knot, self.lam = width, height, knot_px, smoothing
        self.terms = max(1, int(terms))

    def _s(self, col: np.ndarray) -> np.ndarray:
        return (np.asarray(col, float) - self.width / 2) / (self.width / 2)

    def _design(self, col: np.ndarray, row: np.ndarray) -> np.ndarray:
        B = _bspline_basis(np.ravel(row), 0.0, self.height - 1.0, self.knot)
        s = self._s(np.ravel(col))[:, None]
        return np.hstack([B * s**k for k in range(self.terms)])

    def fit(self, pts: np.ndarray, d: np.ndarray, w: np.ndarray | None = None) -> PerLine:
        A = self._design(pts[:, 0], pts[:, 1])
        n = A.shape[1]
        m = n // self.terms
        w = np.ones(len(pts)) if w is None else w
        D2 = np.diff(np.eye(m), 2, axis=0)
        P = np.kron(np.eye(self.terms), D2.T @ D2)
        Aw = A * w[:, None]
        lam = self.lam * float(w.sum()) / m  # per knot: independent of the tie-point density
        N = A.T @ Aw + lam * P + 1e-8 * np.eye(n)
        self.coef = np.linalg.solve(N, Aw.T @ d)
        return self

    def __call__(self, col: np.ndarray, row: np.ndarray) -> np.ndarray:
        col, row = np.broadcast_arrays(np.asarray(col, float), np.asarray(row, float))
        if col.ndim == 2 and np.all(row == row[:, :1]):  # full image: per line, cheap
            r = row[:, 0]
            B = _bspline_basis(r, 0.0, self.height - 1.0, self.knot)
            m = B.shape[1]
            s = self._s(col)[..., None]
            out = np.zeros((*col.shape, 2))
            for k in range(self.terms):
                out += (B @ self.coef[k * m : (k + 1) * m])[:, None, :] * s**k
            return out
        return (self._design(col, row) @ self.coef).reshape(*col.shape, 2)


class Polynomial(Model):
    name = "polynomial"

    def __init__(self, width: int, height: int, degree: int):
        self.width, self.height, self.deg = width, height, degree

    def _design(self, col: np.ndarray, row: np.ndarray) -> np.ndarray:
        u = 2 * np.ravel(col) / max(self.width - 1, 1) - 1
        v = 2 * np.ravel(row) / max(self.height - 1, 1) - 1
        return np.column_stack(
            [u**i * v**j for i in range(self.deg + 1) for j in range(self.deg + 1 - i)]
        )

    def fit(self, pts: np.ndarray, d: np.ndarray, w: np.ndarray | None = None) -> Polynomial:
        A = self._design(pts[:, 0], pts[:, 1])
        sw = np.sqrt(np.ones(len(pts)) if w is None else w)
        self.coef = np.linalg.lstsq(A * sw[:, None], d * sw[:, None], rcond=None)[0]
        return self

    def __call__(self, col: np.ndarray, row: np.ndarray) -> np.ndarray:
        col, row = np.broadcast_arrays(np.asarray(col, float), np.asarray(row, float))
        return (self._design(col, row) @ self.coef).reshape(*col.shape, 2)


class ThinPlate(Model):
    name = "tps"

    def __init__(self, smoothing: float, max_points: int, seed: int):
        self.smoothing, self.max_points, self.seed = smoothing, max_points, seed

    def fit(self, pts: np.ndarray, d: np.ndarray, w: np.ndarray | None = None) -> ThinPlate:
        from scipy.interpolate import RBFInterpolator

        if len(pts) > self.max_points:
            idx = np.random.default_rng(self.seed).choice(len(pts), self.max_points, replace=False)
            pts, d = pts[idx], d[idx]
        self.rbf = RBFInterpolator(pts, d, kernel="thin_plate_spline", smoothing=self.smoothing,
                                   degree=1)  # fmt: skip
        return self

    def __call__(self, col: np.ndarray, row: np.ndarray) -> np.ndarray:
        col, row = np.broadcast_arrays(np.asarray(col, float), np.asarray(row, float))
        if col.ndim == 2 and col.size > 20000:  # full image: evaluate every 4 px, interpolate
            h, w = col.shape
            step = 4
            gc, gr = np.arange(0, w + step, step, float), np.arange(0, h + step, step, float)
            cc, rr = np.meshgrid(gc, gr)
            g = self.rbf(np.column_stack([cc.ravel(), rr.ravel()])).reshape(*cc.shape, 2)
            mx, my = (col / step).astype(np.float32), (row / step).astype(np.float32)
            out = np.empty((h, w, 2))
            for k in range(2):
                out[..., k] = cv2.remap(g[..., k].astype(np.float32), mx, my, cv2.INTER_LINEAR,
                                        borderMode=cv2.BORDER_REPLICATE)  # fmt: skip
            return out
        return self.rbf(np.column_stack([col.ravel(), row.ravel()])).reshape(*col.shape, 2)


def make_model(name: str, width: int, height: int, c: dict[str, Any]) -> Model:
    if name == "per_line":
        return PerLine(
            width,
            height,
            float(c["line_knot_px"]),
            float(c["line_smoothing"]),
            int(c["line_terms"]),
        )
    if name == "polynomial":
        return Polynomial(width, height, int(c["poly_degree"]))
    if name == "tps":
        return ThinPlate(float(c["tps_smoothing"]), int(c["tps_max_points"]), int(c["seed"]))
    if name == "homography":
        return Model()
    raise ValueError(f"unknown refine model {name!r} (expected auto or one of {MODELS})")


def cross_validate(name: str, pts: np.ndarray, d: np.ndarray, w: np.ndarray, width: int,
                   height: int, c: dict[str, Any]) -> float:  # fmt: skip
    """k-fold cross-validated RMS tie-point residual (query px) of a model."""
    err = held_out_errors(name, pts, d, w, width, height, c)
    return float(np.sqrt(np.mean(err**2)))


def held_out_errors(name: str, pts: np.ndarray, d: np.ndarray, w: np.ndarray, width: int,
                    height: int, c: dict[str, Any]) -> np.ndarray:  # fmt: skip
    """Per tie point: |residual| (query px) when predicted by the model fitted without its
    spatially blocked fold."""
    k = max(2, int(c["cv_folds"]))
    # spatial blocks (2 windows square) go to folds at random: neighbouring tie points share
    # pixels, so leaving single points out would favour interpolating models
    side = 2.0 * float(c["window_px"])
    bc, br = (pts[:, 0] // side).astype(int), (pts[:, 1] // side).astype(int)
    block = bc * 100003 + br
    ub, inv = np.unique(block, return_inverse=True)
    fold = (np.random.default_rng(int(c["seed"])).permutation(len(ub)) % k)[inv]
    err = np.empty(len(pts))
    for f in range(k):
        test = fold == f
        m = make_model(name, width, height, c).fit(pts[~test], d[~test], w[~test])
        err[test] = np.hypot(*(d[test] - m(pts[test, 0], pts[test, 1])).T)
    return err


def cv_guard_weight(pts: np.ndarray, err_model: np.ndarray, err_global: np.ndarray, width: int,
                    height: int, sigma: float, full_gain: float) -> np.ndarray:  # fmt: skip
    """Weight (height, width) of the local correction by its own cross-validation ("never
    hurts", issue 20): the held-out squared residuals of the local model and of the global fit
    (D = 0), each Gaussian-averaged (``sigma`` px) around every pixel; the weight is 1 where the
    local model's average is at least ``full_gain`` (a fraction) below the global fit's, falls
    linearly to 0 where it is no lower, and is 0 where it is higher."""
    if len(pts) == 0:
        return np.zeros((height, width), np.float32)
    step = max(1.0, sigma / 3.0)
    gc = np.arange(0.0, width + step, step)
    gr = np.arange(0.0, height + step, step)
    kc = np.exp(-0.5 * ((gc[:, None] - pts[None, :, 0]) / sigma) ** 2)  # (ngc, n)
    kr = np.exp(-0.5 * ((gr[:, None] - pts[None, :, 1]) / sigma) ** 2)  # (ngr, n)
    sm = (kr * err_model**2) @ kc.T  # (ngr, ngc): sum_i k(p - p_i) e_i^2
    sg = (kr * err_global**2) @ kc.T
    with np.errstate(invalid="ignore", divide="ignore"):
        gain = np.where(sg > 1e-12, 1.0 - sm / sg, 0.0)
    g = np.clip(gain / max(full_gain, 1e-6), 0.0, 1.0).astype(np.float32)
    mx = (np.arange(width, dtype=np.float32) / step)[None, :].repeat(height, 0)
    my = (np.arange(height, dtype=np.float32) / step)[:, None].repeat(width, 1)
    return cv2.remap(g, mx, my, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)


# ----------------------------------------------------------------------------- the loop


def support_weight(
    pts: np.ndarray, width: int, height: int, full: float, zero: float
) -> np.ndarray:
    """Weight (height, width) of the local correction: 1 within ``full`` px of a tie point,
    falling smoothly (cosine) to 0 at ``zero`` px, 0 beyond; all ones when ``zero`` <= 0."""
    if zero <= 0:
        return np.ones((height, width), np.float32)
    seeds = np.full((height, width), 255, np.uint8)
    if len(pts):
        c = np.clip(np.round(pts[:, 0]).astype(int), 0, width - 1)
        r = np.clip(np.round(pts[:, 1]).astype(int), 0, height - 1)
        seeds[r, c] = 0
    else:
        return np.zeros((height, width), np.float32)
    d = cv2.distanceTransform(seeds, cv2.DIST_L2, 5)
    t = np.clip((d - full) / max(zero - full, 1e-6), 0.0, 1.0)
    return (0.5 + 0.5 * np.cos(np.pi * t)).astype(np.float32)


def _stats(v: np.ndarray) -> dict[str, float | None]:
    n = np.hypot(*v.T) if len(v) else np.zeros(0)
    if n.size == 0:
        return {"median": None, "p90": None, "max": None, "rms": None}
    return {
        "median": float(np.median(n)),
        "p90": float(np.percentile(n, 90)),
        "max": float(n.max()),
        "rms": float(np.sqrt(np.mean(n**2))),
    }


def refine(
    band: np.ndarray,
    H: np.ndarray,
    map_image: MapImage,
    conf: dict[str, Any] | None = None,
) -> tuple[np.ndarray, np.ndarray, dict[str, Any]]:
    """Refine the mapping query pixel (col, row) -> map (x, y) of ``band`` beyond the homography H.

    ``band``: the query band (uint8, 0 = nodata, or float with NaN). Returns the refined x, y of
    every pixel centre and a report (tie points, residuals before/after, model chosen, timings).
    """
    t0 = time.perf_counter()
    c = merged(conf)
    h, w = band.shape[-2:]
    H = np.asarray(H, np.float64)
    global_fit: dict[str, Any] | None = None
    gconf = dict(c.get("global_fit") or {})
    if gconf.get("enabled", True):
        # the global homography refitted to dense tie points over the whole footprint first:
        # the local model then corrects only what no homography can, relative to that fit
        H, global_fit = dense_fit(band, H, map_image, gconf, c)
    qf, qvalid = query_cfog(band, int(c["orientations"]), float(c["cfog_sigma_px"]))
    win, step, search = int(c["window_px"]), int(c["grid_step_px"]), int(c["search_px"])
    centres = grid_points(w, h, step, win)  # window centres: where the shifts are measured
    pts = window_centroid(centres, w, h, win)  # where they apply (clipped windows at the edge)
    cols = np.arange(w, dtype=np.float64)[None, :]
    rows = np.arange(h, dtype=np.float64)[:, None]
    requested = str(c["model"])
    if requested != "auto" and requested not in MODELS:
        raise ValueError(f"unknown refine model {requested!r} (expected auto or one of {MODELS})")
    model: Model = Model()
    D = np.zeros((h, w, 2))
    info: dict[str, Any] = {"requested_model": requested, "grid_points": int(len(pts)),
                            "global_fit": global_fit or {"enabled": False}}  # fmt: skip
    history: list[dict[str, Any]] = []
    before = None
    final = None
    chosen = "homography"
    cv: dict[str, float] = {}
    support = np.ones((h, w), np.float32)
    n_iter = max(1, int(c["iterations"]))
    for it in range(n_iter + 1):
        x, y = apply_h(H, cols + D[..., 0], rows + D[..., 1])
        rendered = map_image.render(x, y)
        rvalid = np.isfinite(rendered)
        rf = cfog(
            np.nan_to_num(rendered), rvalid, int(c["orientations"]), float(c["cfog_sigma_px"])
        )
        m = measure_shifts(
            qf, rf, qvalid, rvalid, centres, win, search, float(c["min_valid_fraction"])
        )
        ok = m["valid"] & ~m["border"] & (m["score"] >= float(c["min_score"]))
        Dp = model(pts[:, 0], pts[:, 1]) if len(pts) else np.zeros((0, 2))
        target = Dp + m["shift"]
        if ok.sum() >= 3:
            ok[ok] &= consistent(pts[ok], target[ok], 2.5 * step, float(c["consistency_px"]))
        entry = {
            "iteration": it,
            "measured": int(m["valid"].sum()),
            "accepted": int(ok.sum()),
            "residual_px": _stats(m["shift"][ok]),
        }
        history.append(entry)
        log.info("refine pass %d: %d/%d tie points accepted, residual median %s px", it,
                 ok.sum(), len(pts), entry["residual_px"]["median"])  # fmt: skip
        if it == 0:
            before = {"m": m, "ok": ok}
        if it == n_iter or (it > 0 and chosen == "homography"):
            final = {"m": m, "ok": ok}
            break
        if ok.sum() < int(c["min_tie_points"]):
            info["fallback"] = (
                f"{int(ok.sum())} tie points accepted < min_tie_points {c['min_tie_points']}"
            )
            chosen, model, D = "homography", Model(), np.zeros((h, w, 2))
            final = {"m": m, "ok": ok} if it == 0 else None
            if final is None:  # re-measure against the homography for the "after" residuals
                continue
            break
        wts = np.clip(m["score"][ok], 0.05, 1.0)
        if it == 0:
            if requested == "auto":
                cands = [n for n in MODELS[:-1] if n in c["auto_models"]]
                for name in [*cands, "homography"]:
                    cv[name] = cross_validate(name, pts[ok], target[ok], wts, w, h, c)
                if "per_line" in cands:  # the smoothing too, by the same blocked CV
                    lam0 = float(c["line_smoothing"])
                    for f in (10.0, 100.0):
                        cf = {**c, "line_smoothing": lam0 * f}
                        e = cross_validate("per_line", pts[ok], target[ok], wts, w, h, cf)
                        if e < cv["per_line"]:
                            cv["per_line"], c = e, cf
                    info["line_smoothing"] = float(c["line_smoothing"])
                # simplest first (MODELS order: per_line, the pushbroom model, then polynomial,
                # tps, homography): a later model must beat the current choice by auto_min_gain
                # "never hurts": the gain must also exceed auto_min_gain_px (query px) -- at the
                # tie points' noise level a lower CV residual is no evidence of a local signal
                gain = 1 - float(c["auto_min_gain"])
                gain_px = float(c["auto_min_gain_px"])
                chosen = "homography"
                for name in cands:
                    if cv[name] < min(gain * cv[chosen], cv[chosen] - gain_px):
                        chosen = name
            else:
                chosen = requested
        model = make_model(chosen, w, h, c).fit(pts[ok], target[ok], wts)
        D = model(np.broadcast_to(cols, (h, w)), np.broadcast_to(rows, (h, w)))
        if it == 0:  # the tie points of the global fit decide where a local model may act
            support = support_weight(pts[ok], w, h, float(c["support_full_steps"]) * step,
                                     float(c["support_zero_steps"]) * step)  # fmt: skip
            info["support"] = {
                "full_fraction": float((support >= 0.999).mean()),
                "none_fraction": float((support <= 0.001).mean()),
            }
            if c["cv_guard"] and chosen != "homography":
                em = held_out_errors(chosen, pts[ok], target[ok], wts, w, h, c)
                eg = held_out_errors("homography", pts[ok], target[ok], wts, w, h, c)
                guard = cv_guard_weight(pts[ok], em, eg, w, h,
                                        float(c["cv_guard_sigma_steps"]) * step,
                                        float(c["cv_guard_full_gain"]))  # fmt: skip
                support = support * guard
                info["cv_guard"] = {
                    "full_fraction": float((guard >= 0.999).mean()),
                    "none_fraction": float((guard <= 0.001).mean()),
                }
        D = D * support[..., None]
    assert before is not None and final is not None
    x, y = apply_h(H, cols + D[..., 0], rows + D[..., 1])
    info["homography"] = H.tolist()  # the global model under the local correction
    bm, bok = before["m"], before["ok"]
    fm, fok = final["m"], final["ok"]
    info.update(
        {
            "model": chosen,
            "cv_rms_px": cv or None,
            "tie_points": int(bok.sum()),
            "tie_points_after": int(fok.sum()),
            "residual_before_px": _stats(bm["shift"][bok]),
            "residual_after_px": _stats(fm["shift"][fok]),
            "iterations": history,
            "correction_px": _stats(D.reshape(-1, 2)[:: max(1, D.size // 2 // 200000)]),
            "seconds": time.perf_counter() - t0,
            "points": {
                "col": pts[:, 0].tolist(),
                "row": pts[:, 1].tolist(),
                "score": [None if not np.isfinite(s) else round(float(s), 3) for s in bm["score"]],
                "accepted": bok.tolist(),
                "before": np.round(bm["shift"], 3).tolist(),
                "after": np.round(fm["shift"], 3).tolist(),
                "accepted_after": fok.tolist(),
            },
        }
    )
    return x, y, info


# ----------------------------------------------------------------------------- the rule


def run_refine(
    band_tif: str,
    reg_json: str,
    geoloc_tif: str,
    ortho: str,
    dsm: str | None,
    truth: str | None,
    conf: dict[str, Any],
    out_json: str,
    out_geoloc: str,
) -> dict[str, Any]:
    """Rule refine_registration: global registration -> refined registration.json + geolocation.tif.

    Disabled, not registered, or too few tie points: the global geometry is written unchanged
    (``refine.model`` says ``homography`` and why).
    """
    import json
    import shutil

    from georeg.io.atomic import atomic_path, write_json
    from georeg.register.band import read_query_band, read_query_bands
    from georeg.register.geolocation import evaluate, write_geolocation

    t0 = time.perf_counter()
    c = merged(conf)
    reg = json.loads(Path(reg_json).read_text())
    reg["refine"] = {"enabled": bool(c["enabled"]), "model": "homography"}
    timings = reg.setdefault("timings_s", {})
    if reg.get("evaluation") is not None:
        reg["evaluation_global"] = reg["evaluation"]
    H = reg.get("homography")
    if not c["enabled"] or reg.get("status") != "registered" or H is None:
        reason = "disabled" if not c["enabled"] else "query not registered"
        reg["refine"]["reason"] = reason
        with atomic_path(out_geoloc) as tmp:
            shutil.copyfile(geoloc_tif, tmp)
        reg.setdefault("geolocation", {})["path"] = str(out_geoloc)
        timings["refine"] = time.perf_counter() - t0
        write_json(out_json, reg)
        log.info("refinement skipped: %s", reason)
        return reg
    H = np.asarray(H, np.float64)
    # every pooled band (the primary first): their CFOG channels averaged, one band's noise is
    # not the others' (issue 20: p90 <= 2 px, checking half 23 -> 24/28, none worse)
    band = read_query_bands(band_tif) if c["pooled_bands"] else read_query_band(band_tif)
    if band.ndim == 3 and len(band) == 1:
        band = band[0]
    h, w = band.shape[-2:]
    x0, y0 = apply_h(H, np.arange(w, dtype=float)[None, :], np.arange(h, dtype=float)[:, None])
    map_image = read_map_gray(ortho, x0, y0, pad=4.0 * float(c["search_px"]) + 8.0)
    x, y, info = refine(band, H, map_image, c)
    qpx = ground_px(H, w, h)
    info["query_px_m"] = qpx
    info["enabled"] = True
    t1 = time.perf_counter()
    geo = write_geolocation(out_geoloc, H, w, h, dsm, reg.get("crs"), xy=(x, y))
    timings["refine_geolocation"] = time.perf_counter() - t1
    reg["geolocation"] = {"path": str(out_geoloc), **geo, "model": info["model"]}
    reg["refine"] = info
    if truth:
        map_px = float(reg.get("map_px_m") or 1.0)
        reg["evaluation"] = evaluate(None, truth, map_px, xy=(x, y))
        info["evaluation"] = {
            "before_px": (reg.get("evaluation_global") or {}).get("px"),
            "after_px": reg["evaluation"].get("px"),
        }
        if (info.get("global_fit") or {}).get("accepted"):
            info["evaluation"]["global_fit_px"] = evaluate(
                np.array(info["homography"]), truth, map_px
            ).get("px")
    timings["refine"] = time.perf_counter() - t0
    write_json(out_json, reg)
    log.info("refinement: model %s, %d tie points, residual median %.3f -> %.3f query px",
             info["model"], info["tie_points"], info["residual_before_px"]["median"] or float("nan"),
             info["residual_after_px"]["median"] or float("nan"))  # fmt: skip
    return reg
