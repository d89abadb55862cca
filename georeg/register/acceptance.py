"""Calibrated acceptance of a candidate homography: a-contrario NFA + geometric plausibility.

The paper accepts any homography with more than 5 inliers; on cross-spectral imagery that accepts
wrong registrations. See docs/ACCEPTANCE.md for the test and its derivation.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np
from scipy.special import gammaln

LN10 = math.log(10.0)
SAMPLE = 4  # minimal sample of a homography


def log10_binom(n: np.ndarray | int, k: np.ndarray | int) -> np.ndarray:
    """log10 of the binomial coefficient C(n, k), vectorised."""
    n = np.asarray(n, np.float64)
    k = np.asarray(k, np.float64)
    return (gammaln(n + 1) - gammaln(k + 1) - gammaln(n - k + 1)) / LN10


def log10_nfa(
    residual_px: np.ndarray,
    area_px: float,
    n_tests_extra: float = 1.0,
    min_residual_px: float = 0.5,
    min_k: int = SAMPLE + 1,
) -> tuple[float, int, float]:
    """Best (log10 NFA, k, e_k) over k of the ORSA bound for n matches with these residuals.

    NFA(k) = T * (n - 4) * C(n, k) * C(k, 4) * p_k^(k - 4),  p_k = pi e_k^2 / area,
    where e_k is the k-th smallest residual (map pixels), ``area`` the candidate region's area in
    map pixels (where a chance match could land) and T the number of candidate regions tried.
    Under the null hypothesis (matches uniformly at random in the region), the expected number of
    homographies that look at least this good by chance is below NFA.
    """
    r = np.sort(np.asarray(residual_px, np.float64))
    r = r[np.isfinite(r)]
    n = len(r)
    if n < min_k or area_px <= 0:
        return float("inf"), 0, float("nan")
    k = np.arange(min_k, n + 1)
    e = np.maximum(r[k - 1], min_residual_px)
    p = np.minimum(1.0, math.pi * e**2 / float(area_px))
    lnfa = (
        math.log10(max(n_tests_extra, 1.0))
        + math.log10(n - SAMPLE)
        + log10_binom(n, k)
        + log10_binom(k, SAMPLE)
        + (k - SAMPLE) * np.log10(p)
    )
    i = int(np.argmin(lnfa))
    return float(lnfa[i]), int(k[i]), float(e[i])


def log10_nfa_binomial(
    residual_px: np.ndarray,
    area_px: float,
    n_tests_extra: float = 1.0,
    sample: int = 2,
    min_residual_px: float = 0.5,
) -> tuple[float, int, float]:
    """Best (log10 NFA, k, e_k) over k of the binomial-tail a-contrario bound.

    NFA(k) = T * (n - s) * C(n, s) * P[Binomial(n - s, p_k) >= k - s],  p_k = pi e_k^2 / area,
    with s = ``sample`` the minimal sample of the model (2 for a similarity), e_k the k-th
    smallest residual and ``area`` where a chance match could land (map pixels). The same null
    as ``log10_nfa`` (matches uniform in the area); the binomial tail is the exact probability
    that k - s of the other n - s matches fall within e_k, where ORSA's C(n - s, k - s) p^(k - s)
    bounds it (loose when p is not small, e.g. a guided re-match whose area is a small disc).
    """
    from scipy.stats import binom

    r = np.sort(np.asarray(residual_px, np.float64))
    r = r[np.isfinite(r)]
    n = len(r)
    if n < sample + 2 or area_px <= 0:
        return float("inf"), 0, float("nan")
    k = np.arange(sample + 2, n + 1)
    e = np.maximum(r[k - 1], min_residual_px)
    p = np.minimum(1.0, math.pi * e**2 / float(area_px))
    tail = binom.logsf(k - sample - 1, n - sample, p) / LN10
    lnfa = (
        math.log10(max(n_tests_extra, 1.0))
        + math.log10(n - sample)
        + float(log10_binom(n, sample))
        + tail
    )
    i = int(np.argmin(lnfa))
    return float(lnfa[i]), int(k[i]), float(e[i])


def jacobian(H: np.ndarray, uv: np.ndarray) -> np.ndarray:
    """(n,2,2) Jacobians d(x,y)/d(col,row) of the homography at query points ``uv`` (n,2)."""
    uv = np.atleast_2d(np.asarray(uv, np.float64))
    p = uv @ H[:, :2].T + H[:, 2]
    w = p[:, 2]
    x, y = p[:, 0] / w, p[:, 1] / w
    J = np.empty((len(uv), 2, 2))
    J[:, 0, 0] = (H[0, 0] - x * H[2, 0]) / w
    J[:, 0, 1] = (H[0, 1] - x * H[2, 1]) / w
    J[:, 1, 0] = (H[1, 0] - y * H[2, 0]) / w
    J[:, 1, 1] = (H[1, 1] - y * H[2, 1]) / w
    return J


def plausibility(
    H: np.ndarray,
    width: int,
    height: int,
    gsd_m: float | None,
    conf: dict[str, Any],
    origin: tuple[float, float] = (0.0, 0.0),
) -> dict[str, Any]:
    """Is H a plausible nadir mapping of a ``width`` x ``height`` query footprint?

    Checks: no horizon inside the footprint (w > 0), handedness (det J < 0 everywhere for
    (col,row) -> (x, y north-up): rows go down, map y goes up, no mirror), scale near ``gsd_m``
    (or within ``gsd_range_m`` when unknown), anisotropy, shear of the mapped axes and the
    perspective change of scale across the footprint.
    """
    u0, v0 = origin
    corners = np.array(
        [[u0, v0], [u0 + width, v0], [u0 + width, v0 + height], [u0, v0 + height]], np.float64
    )
    centre = corners.mean(axis=0, keepdims=True)
    pts = np.vstack([centre, corners])
    w = pts @ H[2, :2] + H[2, 2]
    reasons: list[str] = []
    out: dict[str, Any] = {}
    if not np.all(np.isfinite(H)) or np.any(w <= 0):
        return {"ok": False, "reasons": ["footprint crosses the horizon line of the homography"]}
    J = jacobian(H, pts)
    det = np.linalg.det(J)
    sv = np.linalg.svd(J, compute_uv=False)  # (5,2) s1 >= s2, metres per query pixel
    scale = float(np.sqrt(abs(det[0])))
    aniso = float(sv[0, 0] / max(sv[0, 1], 1e-12))
    a, b = J[0][:, 0], J[0][:, 1]
    cosang = float(abs(a @ b) / max(np.linalg.norm(a) * np.linalg.norm(b), 1e-12))
    shear_deg = float(90.0 - math.degrees(math.acos(min(1.0, cosang))))
    persp = float(np.abs(det).max() / max(np.abs(det).min(), 1e-300))
    out.update(scale_m_per_px=scale, anisotropy=aniso, shear_deg=shear_deg, perspective=persp)
    out["det_sign"] = int(np.sign(det[0]))
    if not np.all(det < 0):
        reasons.append("mirrored mapping (det of the linear part must be < 0 for col,row -> x,y)")
    if gsd_m:
        tol = float(conf.get("scale_tolerance", 0.3))
        ratio = scale / float(gsd_m)
        out["scale_ratio"] = ratio
        if not (1.0 / (1.0 + tol) <= ratio <= 1.0 + tol):
            reasons.append(f"scale {scale:.3g} m/px is not within {tol:.0%} of the GSD {gsd_m:g} m")
    else:
        lo, hi = conf.get("gsd_range_m", [0.05, 100.0])
        if not (lo <= scale <= hi):
            reasons.append(f"scale {scale:.3g} m/px outside [{lo}, {hi}]")
    if aniso > float(conf.get("max_anisotropy", 1.5)):
        reasons.append(f"anisotropy {aniso:.2f} > {conf.get('max_anisotropy', 1.5)}")
    if shear_deg > float(conf.get("max_shear_deg", 20.0)):
        reasons.append(f"shear {shear_deg:.1f} deg > {conf.get('max_shear_deg', 20.0)}")
    if persp > float(conf.get("max_perspective", 1.5)):
        reasons.append(f"scale changes {persp:.2f}x across the footprint")
    out["ok"] = not reasons
    out["reasons"] = reasons
    return out


def inlier_spread(q_xy: np.ndarray, width: int, height: int) -> dict[str, float]:
    """How well inliers (query pixels) pin a 2-D transform: spread along their minor axis.

    Collinear inliers (a row of cars or houses matched to another row) leave a homography or an
    affine map free across the line, so any NFA computed from their residuals is meaningless.
    Returns the minor/major standard deviation ratio and the minor standard deviation as a
    fraction of the part's smaller side.
    """
    q = np.asarray(q_xy, np.float64).reshape(-1, 2)
    if len(q) < 3:
        return {"minor_major": 0.0, "minor_frac": 0.0}
    ev = np.linalg.eigvalsh(np.cov((q - q.mean(axis=0)).T))
    minor, major = math.sqrt(max(ev[0], 0.0)), math.sqrt(max(ev[1], 1e-12))
    return {"minor_major": minor / major, "minor_frac": minor / max(min(width, height), 1)}


def decide(
    H: np.ndarray | None,
    residual_px: np.ndarray,
    n_inliers: int,
    area_px: float,
    width: int,
    height: int,
    gsd_m: float | None,
    conf: dict[str, Any],
    n_candidates: int = 1,
    origin: tuple[float, float] = (0.0, 0.0),
    inlier_q_xy: np.ndarray | None = None,
    strip_log_nfa: float = -math.inf,
) -> dict[str, Any]:
    """Accept or reject one candidate; returns the decision and every number it used.

    ``conf`` is ``register.acceptance``: mode ``nfa`` (log10 NFA < log_nfa_max and plausible) or
    ``paper`` (inliers > paper_min_inliers, nothing else). Nearly collinear inliers
    (``inlier_q_xy``) are refused unless the log10 NFA is below ``strip_log_nfa`` (a model that a
    strip of inliers fixes, e.g. a rigid pose at a known GSD, when its evidence is strong).
    """
    mode = str(conf.get("mode", "nfa"))
    out: dict[str, Any] = {"mode": mode, "inliers": int(n_inliers)}
    if H is None:
        out.update(accepted=False, reason="no homography")
        return out
    lnfa, k, ek = log10_nfa(
        residual_px,
        area_px,
        n_tests_extra=n_candidates if conf.get("count_candidates", True) else 1,
        min_residual_px=float(conf.get("min_residual_px", 0.5)),
    )
    plaus = plausibility(H, width, height, gsd_m, conf, origin)
    out.update(log10_nfa=lnfa, nfa_k=k, nfa_eps_px=ek, plausibility=plaus)
    if mode == "paper":
        ok = n_inliers > int(conf.get("paper_min_inliers", 5))
        out.update(
            accepted=ok,
            reason="" if ok else f"{n_inliers} inliers <= {conf.get('paper_min_inliers', 5)}",
        )
        return out
    if mode != "nfa":
        raise ValueError(f"unknown acceptance mode {mode!r} (nfa | paper)")
    reasons = []
    if not lnfa < float(conf.get("log_nfa_max", 0.0)):
        reasons.append(f"log10 NFA {lnfa:.1f} >= {conf.get('log_nfa_max', 0.0)}")
    reasons += plaus.get("reasons", [])
    if inlier_q_xy is not None:
        spread = inlier_spread(inlier_q_xy, width, height)
        out["spread"] = spread
        lo_ratio = float(conf.get("min_spread_ratio", 0.2))
        lo_frac = float(conf.get("min_spread_frac", 0.05))
        strip = spread["minor_major"] < lo_ratio or spread["minor_frac"] < lo_frac
        if strip and lnfa < strip_log_nfa:
            out["strip_accepted"] = True
        elif strip:
            reasons.append(
                f"inliers nearly collinear (minor/major spread {spread['minor_major']:.2f} < "
                f"{lo_ratio} or minor spread {spread['minor_frac']:.1%} of the part < {lo_frac:.0%})"
            )
    out.update(accepted=not reasons, reason="; ".join(reasons))
    return out
