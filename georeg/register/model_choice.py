"""The model of an accepted feature fit, chosen by leave-one-out cross-validation on its inliers.

RANSAC and the acceptance test work with a homography (8 degrees of freedom); once a fit is
accepted, its inliers are refitted with the simplest model that predicts them as well as any:
a similarity (rotation, scale, shift: 4), an affine map (6) or a homography (8). Each model's
leave-one-out squared residuals are computed on the inliers; the simplest model whose mean is
within one standard error of the lowest mean wins (the "one-standard-error rule", Hastie,
Tibshirani and Friedman, *The Elements of Statistical Learning*, 7.10). No threshold to tune:
a handful of inliers pins a similarity, and a more flexible model is kept only when its held-out
residuals say the data need it (issue 20: 5-10 inlier homographies extrapolated 2-5 map px off
over small footprints; docs/BENCHMARKS.md "The model of an accepted fit").
"""

from __future__ import annotations

from typing import Any

import cv2
import numpy as np

from georeg.register.matching import affine_lsq, apply_h, similarity_lsq

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
