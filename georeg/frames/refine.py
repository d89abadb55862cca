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


def nmi(a: np.ndarray, b: np.ndarray, bins: int = 32) -> float:
    """Normalised mutual information (H(A) + H(B)) / H(A, B) - 1 of two uint8-range samples."""
    ia = np.clip((a * (bins / 256.0)).astype(np.int64), 0, bins - 1)
    ib = np.clip((b * (bins / 256.0)).astype(np.int64), 0, bins - 1)
    j = np.bincount(ia * bins + ib, minlength=bins * bins).astype(np.float64)
    j /= max(j.sum(), 1.0)
    pa, pb = j.reshape(bins, bins).sum(1), j.reshape(bins, bins).sum(0)

    def ent(p):
        p = p[p > 0]
        return float(-(p * np.log(p)).sum())

    hj = ent(j)
    return (ent(pa) + ent(pb)) / hj - 1.0 if hj > 0 else 0.0


def _ncc(a: np.ndarray, b: np.ndarray) -> float:
    a = a - a.mean()
    b = b - b.mean()
    d = np.sqrt((a * a).sum() * (b * b).sum())
    return float((a * b).sum() / d) if d > 0 else 0.0


def _grad(img: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    return (
        cv2.Sobel(img, cv2.CV_32F, 1, 0, ksize=3) / 8.0,
        cv2.Sobel(img, cv2.CV_32F, 0, 1, ksize=3) / 8.0,
    )


def similarity_terms(frame: np.ndarray, gx: np.ndarray, gy: np.ndarray, cam: PinholeCamera,
                     X: np.ndarray, ir: np.ndarray, rgx: np.ndarray, rgy: np.ndarray,
                     bins: int) -> tuple[float, float, float]:  # fmt: skip
    """(NMI - 1, gradient correlation, fraction of points inside the frame) at ``cam``."""
    uv, z = cam.project(X)
    ok = (
        (z > 0)
        & (uv[:, 0] >= 0)
        & (uv[:, 0] <= cam.width - 1)
        & (uv[:, 1] >= 0)
        & (uv[:, 1] <= cam.height - 1)
    )
    frac = float(ok.mean()) if len(ok) else 0.0
    if ok.sum() < 100:
        return 0.0, 0.0, frac
    mx = uv[ok, 0].astype(np.float32).reshape(-1, 1)
    my = uv[ok, 1].astype(np.float32).reshape(-1, 1)
    f = cv2.remap(frame, mx, my, cv2.INTER_LINEAR).ravel()
    fx = cv2.remap(gx, mx, my, cv2.INTER_LINEAR).ravel()
    fy = cv2.remap(gy, mx, my, cv2.INTER_LINEAR).ravel()
    mi = nmi(ir[ok], f, bins)
    gc = 0.5 * (_ncc(rgx[ok], fx) + _ncc(rgy[ok], fy))
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
        frame = cv2.resize(gray, (cs.width, cs.height), interpolation=cv2.INTER_AREA).astype(
            np.float32
        )
        gx, gy = _grad(frame)
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
        ir, pgx, pgy = rg[rows, cols], rgx[rows, cols], rgy[rows, cols]
        R0, C0 = R, C

        def cost(xi, R0=R0, C0=C0, cs=cs, frame=frame, gx=gx, gy=gy, X=X, ir=ir, pgx=pgx, pgy=pgy):
            Rt, Ct = apply_increment(R0, C0, xi)
            mi, gc, frac = similarity_terms(
                frame, gx, gy, cs.with_pose(Rt, Ct), X, ir, pgx, pgy, bins
            )
            return -(mi + w * gc) * min(1.0, frac / 0.8)

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
