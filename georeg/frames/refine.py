"""Intensity refinement of a frame pose: mutual information + gradient correlation.

As in the seed paper's intensity-based 2-D/3-D step: the pose from PnP is polished by maximising
a similarity between the frame and the map, over the 6 pose parameters (SE(3) Lie-algebra
increments xi = (omega, v): T = exp(hat(xi)) T0, camera frame), with Nelder-Mead (derivative
free) across 3 pyramid octaves (coarse to fine, the simplex shrinking with the octave).

To keep a cost evaluation cheap (no re-render per evaluation), the map is rendered once per
octave at the starting pose; its visible pixels become 3-D points carrying the render's
intensity and gradient. Each evaluation projects them into the frame at the trial pose and
samples the frame's intensity and gradients there (visibility is frozen: fine for the small
moves of a refinement). Similarity = normalised mutual information (32 x 32 joint histogram,
NMI - 1 in [0, 1]) + gradient correlation (mean of the NCCs of d/dx and d/dy), both in [0, 1].
"""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass, field
from typing import Any

import cv2
import numpy as np
from scipy.linalg import expm
from scipy.optimize import minimize

from georeg.frames.render import PinholeCamera, PointCloud, render

log = logging.getLogger(__name__)

DEFAULTS: dict[str, Any] = {
    "octaves": 3,
    "base_gsd_factor": 0.5,  # finest octave renders at this x the map GSD (like the PnP matching)
    "map_gsd": 1.0,
    "max_points": 20000,
    "bins": 32,
    "rot_step_deg": 0.3,  # initial simplex at the finest octave (doubled per octave above)
    "trans_step_m": 0.5,
    "max_evals": 150,  # per octave
    "gc_weight": 1.0,
    "seed": 0,
}


@dataclass
class Refined:
    R: np.ndarray
    C: np.ndarray
    info: dict[str, Any] = field(default_factory=dict)


def _hat(xi: np.ndarray) -> np.ndarray:
    w, v = xi[:3], xi[3:]
    return np.array(
        [[0, -w[2], w[1], v[0]], [w[2], 0, -w[0], v[1]], [-w[1], w[0], 0, v[2]], [0, 0, 0, 0]]
    )


def apply_increment(R: np.ndarray, C: np.ndarray, xi: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """T' = exp(hat(xi)) T with T = [R | -R C] (world -> camera); returns (R', C')."""
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = R, -R @ C
    T2 = expm(_hat(np.asarray(xi, float))) @ T
    R2 = T2[:3, :3]
    return R2, -R2.T @ T2[:3, 3]


def _entropy(p: np.ndarray) -> np.ndarray:
    """Shannon entropy (nats) of each distribution along the last axis (zeros skipped)."""
    with np.errstate(divide="ignore", invalid="ignore"):
        return -np.where(p > 0, p * np.log(p), 0.0).sum(-1)


def nmi(a: np.ndarray, b: np.ndarray, bins: int = 32, segments: np.ndarray | None = None) -> np.ndarray:
    """Normalised mutual information (H(A) + H(B)) / H(A, B) - 1 of uint8-range samples, one
    value per segment (``segments``: each sample's segment 0..k-1, sorted; None: one segment)."""
    ia = np.clip((a * (bins / 256.0)).astype(np.int64), 0, bins - 1)
    ib = np.clip((b * (bins / 256.0)).astype(np.int64), 0, bins - 1)
    k = int(segments[-1]) + 1 if segments is not None and len(segments) else 1
    key = ia * bins + ib if segments is None else (segments * bins + ia) * bins + ib
    j = np.bincount(key, minlength=k * bins * bins).astype(np.float64)
    j = j.reshape(k, bins, bins)
    j /= np.maximum(j.sum((1, 2)), 1.0)[:, None, None]
    hj = _entropy(j.reshape(k, -1))
    with np.errstate(divide="ignore", invalid="ignore"):
        return np.where(hj > 0, (_entropy(j.sum(2)) + _entropy(j.sum(1))) / hj - 1.0, 0.0)


def _ncc(a: np.ndarray, b: np.ndarray, starts: np.ndarray, n: np.ndarray) -> np.ndarray:
    """Normalised cross-correlation of ``a`` and ``b`` over each segment (``starts``, sizes ``n``)."""
    a, b = a.astype(np.float64), b.astype(np.float64)
    sa, sb = np.add.reduceat(a, starts), np.add.reduceat(b, starts)
    cov = np.add.reduceat(a * b, starts) - sa * sb / n
    var = (np.add.reduceat(a * a, starts) - sa**2 / n) * (np.add.reduceat(b * b, starts) - sb**2 / n)
    with np.errstate(divide="ignore", invalid="ignore"):
        return np.where(var > 0, cov / np.sqrt(np.maximum(var, 0.0)), 0.0)


def _grad(img: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    return (
        cv2.Sobel(img, cv2.CV_32F, 1, 0, ksize=3) / 8.0,
        cv2.Sobel(img, cv2.CV_32F, 0, 1, ksize=3) / 8.0,
    )


def frame_channels(frame: np.ndarray) -> np.ndarray:
    """The frame's intensity and gradients (H, W, 3) float32: what ``similarity`` samples."""
    f = frame.astype(np.float32)
    return np.dstack([f, *_grad(f)])


#: ``similarity``'s poses x points projected at once (bounded memory)
BATCH_POINTS = 1_000_000


def _sample(img: np.ndarray, u: np.ndarray, v: np.ndarray, cols: int = 4096) -> np.ndarray:
    """Bilinear samples (n, channels) of ``img`` at (u, v): one ``cv2.remap``, its maps laid out
    ``cols`` wide (remap takes fewer than 32,767 rows)."""
    n = len(u)
    rows = -(-n // cols)
    mx, my = np.zeros(rows * cols, np.float32), np.zeros(rows * cols, np.float32)
    mx[:n], my[:n] = u, v
    out = cv2.remap(img, mx.reshape(rows, cols), my.reshape(rows, cols), cv2.INTER_LINEAR)
    return out.reshape(rows * cols, -1)[:n]


def similarity(img3: np.ndarray, cam: PinholeCamera, R: np.ndarray, C: np.ndarray, X: np.ndarray,
               ref3: np.ndarray, bins: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:  # fmt: skip
    """(NMI - 1, gradient correlation, fraction of points inside the frame) of the points ``X``
    (N, 3) carrying ``ref3`` (N, 3: the render's intensity and gradients) seen from each pose
    (one rotation ``R`` (3, 3), centres ``C`` (P, 3)) of ``cam``'s intrinsics in the frame
    ``img3`` (``frame_channels``); arrays (P,). A pose with fewer than 100 points inside scores 0."""
    R, C = np.asarray(R, float), np.asarray(C, float).reshape(-1, 3)
    P, N = len(C), len(X)
    mi, gc, frac = np.zeros(P), np.zeros(P), np.zeros(P)
    step = max(1, BATCH_POINTS // max(N, 1))
    A, T = (X - C[0]) @ R.T, (C - C[0]) @ R.T  # (X - C_p) R^T = (X - C_0) R^T - (C_p - C_0) R^T
    for p0 in range(0, P if N else 0, step):
        Xc = [A[None, :, k] - T[p0 : p0 + step, k, None] for k in range(3)]
        z = Xc[2]
        with np.errstate(divide="ignore", invalid="ignore"):
            u = cam.fx * Xc[0] / z + cam.cx
            v = cam.fy * Xc[1] / z + cam.cy
        ok = (z > 0) & (u >= 0) & (u <= cam.width - 1) & (v >= 0) & (v <= cam.height - 1)
        n = ok.sum(1)
        frac[p0 : p0 + len(ok)] = n / N
        ok &= (n >= 100)[:, None]
        pi, ni = np.nonzero(ok)
        if not pi.size:
            continue
        f = _sample(img3, u[pi, ni], v[pi, ni])
        has = np.flatnonzero(n >= 100)
        seg = np.searchsorted(has, pi) if len(has) > 1 else None  # each sample's rank among the scored poses
        cnt = n[has].astype(np.float64)
        starts = np.r_[0, np.cumsum(n[has])[:-1]]
        r = ref3[ni]
        mi[p0 + has] = nmi(r[:, 0], f[:, 0], bins, seg)
        gc[p0 + has] = 0.5 * (_ncc(r[:, 1], f[:, 1], starts, cnt) + _ncc(r[:, 2], f[:, 2], starts, cnt))
    return mi, gc, frac


def refine_pose(
    gray: np.ndarray, cam: PinholeCamera, cloud: PointCloud, conf: dict | None = None
) -> Refined:
    """Nelder-Mead over SE(3) increments maximising NMI + GC, 3 octaves coarse to fine."""
    c = {**DEFAULTS, **(conf or {})}
    t0 = time.perf_counter()
    rng = np.random.default_rng(int(c["seed"]))
    R, C = np.asarray(cam.R, float), np.asarray(cam.C, float)
    r0 = render(cloud, cam.scaled(min(1.0, 160 / cam.width)))
    d = r0.depth[np.isfinite(r0.depth)]
    dist = float(np.median(d)) if d.size else 100.0
    s_fine = float(
        np.clip(dist / cam.fx / (float(c["base_gsd_factor"]) * float(c["map_gsd"])), 0.05, 1.0)
    )
    info: dict[str, Any] = {"octaves": []}
    bins, w = int(c["bins"]), float(c["gc_weight"])
    for o in reversed(range(int(c["octaves"]))):
        s = s_fine / 2**o
        cs = cam.with_pose(R, C).scaled(s)
        img3 = frame_channels(cv2.resize(gray, (cs.width, cs.height), interpolation=cv2.INTER_AREA))
        rr = render(cloud, cs)
        rg = rr.gray().astype(np.float32)
        rgx, rgy = _grad(rg)
        valid = rr.mask & (cv2.erode(rr.mask.astype(np.uint8), np.ones((3, 3), np.uint8)) > 0)
        rows, cols = np.nonzero(valid)
        if rows.size > int(c["max_points"]):
            k = rng.choice(rows.size, int(c["max_points"]), replace=False)
            rows, cols = rows[k], cols[k]
        if rows.size < 200:
            break
        X = cs.backproject(np.c_[cols, rows].astype(float), rr.depth[rows, cols])
        ref3 = np.c_[rg[rows, cols], rgx[rows, cols], rgy[rows, cols]]
        R0, C0 = R, C

        def cost(xi, R0=R0, C0=C0, cs=cs, img3=img3, X=X, ref3=ref3):
            mi, gc, frac = similarity(img3, cs, *apply_increment(R0, C0, xi), X, ref3, bins)
            return float(-(mi[0] + w * gc[0]) * min(1.0, frac[0] / 0.8))

        f0 = cost(np.zeros(6))
        step_r = np.radians(float(c["rot_step_deg"])) * 2**o
        step_t = float(c["trans_step_m"]) * 2**o
        simplex = np.zeros((7, 6))
        for i in range(6):
            simplex[i + 1, i] = step_r if i < 3 else step_t
        res = minimize(cost, np.zeros(6), method="Nelder-Mead",
                       options={"initial_simplex": simplex, "maxfev": int(c["max_evals"]),
                                "xatol": 1e-4, "fatol": 1e-5})  # fmt: skip
        if res.fun < f0:
            R, C = apply_increment(R0, C0, res.x)
        info["octaves"].append({"octave": o, "scale": s, "points": int(rows.size), "cost_start": float(f0),
                                "cost_end": float(min(res.fun, f0)), "evals": int(res.nfev),
                                "moved_m": float(np.linalg.norm(C - C0))})  # fmt: skip
        log.info("refine octave %d (scale %.2f): cost %.4f -> %.4f in %d evals, moved %.2f m", o, s, f0,
                 min(res.fun, f0), res.nfev, np.linalg.norm(C - C0))  # fmt: skip
    info["seconds"] = time.perf_counter() - t0
    info["moved_m"] = float(np.linalg.norm(C - np.asarray(cam.C, float)))
    return Refined(R, C, info)
