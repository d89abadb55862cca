"""Whole-footprint direct alignment of a small query to the orthophoto (issue 20).

The tie-point refit (``georeg.register.densefit``) needs tie-point windows (32 px) spread over
the footprint and spatial CV blocks for its guard: a query under ~100 px has a handful of
windows, so its feature (or CFOG-peak) fit is kept as it is, 1-2 map px off at its edges.

Here every valid pixel takes part. The orthophoto is rendered through the current fit, CFOG
channels of the query and of the render are compared pixel by pixel, and a small similarity
(or affine) warp of the query frame is solved by Gauss-Newton on the channels' squared
difference (robust weights, a coarse-to-fine channel smoothing), composed into the fit; render
-> solve is iterated. Parameters are the warp's displacements at the footprint's edge, so the
normal equations are well conditioned whatever the query's size.

"Never hurts", without CV blocks: the pixels are dealt to two interleaved checkerboards of
``cell_px`` cells. The warp is fitted on each board alone; each board's fit must raise the
pooled CFOG correlation on the *other* board above the starting fit's, and the two fits must
agree over the footprint within ``max_disagree_px`` (their difference measures the fit's own
noise). Otherwise the starting fit is kept (``accepted: false`` and why).
"""

from __future__ import annotations

import logging
import time
from typing import Any

import cv2
import numpy as np

from georeg.register.geolocation import apply_h, ground_px

log = logging.getLogger(__name__)

DEFAULTS: dict[str, Any] = {
    "enabled": False,  # off by default: the checking half did not confirm the tuning half's gain
    "when": "always",  # always (after the tie-point refit) | no_refit (only when it was not accepted)
    "model": "similarity",  # similarity (4 parameters) | affine (6)
    "sigmas_px": [1.0],  # CFOG smoothing per stage, coarse to fine (query px)
    "iterations": 8,  # Gauss-Newton passes per stage
    "converged_px": 0.01,  # a pass that moves the footprint less than this ends the stage
    "robust_k": 2.0,  # Huber bound on a pixel's residual norm, in robust sigmas
    "cell_px": 8,  # checkerboard cells of the guard (query px)
    "max_disagree_px": 3.0,  # the two boards' fits must agree this well (query px, footprint max)
    "max_move_px": 3.0,  # a refinement, not a new registration: the fit moves at most this
    "min_pixels": 400,  # valid pixels (query and render) needed on each board
    "max_pixels": 160000,  # larger footprints are the tie-point refit's domain: not run
}


def merged(conf: dict[str, Any] | None) -> dict[str, Any]:
    c = dict(DEFAULTS)
    c.update({k: v for k, v in (conf or {}).items() if v is not None})
    return c


def _basis(w: int, h: int, model: str) -> tuple[np.ndarray, np.ndarray, float, tuple]:
    """Per-pixel displacement basis: (P, h, w) for dx and for dy; scale L; centre."""
    cx, cy = (w - 1) / 2.0, (h - 1) / 2.0
    L = max(0.5 * max(w, h), 1.0)
    u = ((np.arange(w, dtype=np.float32) - cx) / L)[None, :].repeat(h, 0)
    v = ((np.arange(h, dtype=np.float32) - cy) / L)[:, None].repeat(w, 1)
    o, z = np.ones((h, w), np.float32), np.zeros((h, w), np.float32)
    if model == "similarity":
        bx = np.stack([o, z, u, -v])
        by = np.stack([z, o, v, u])
    elif model == "rigid":  # rotation and shift: the scale (the known GSD) is kept
        bx = np.stack([o, z, -v])
        by = np.stack([z, o, u])
    elif model == "translation":
        bx = np.stack([o, z])
        by = np.stack([z, o])
    elif model == "affine":
        bx = np.stack([o, z, u, v, z, z])
        by = np.stack([z, o, z, z, u, v])
    else:
        raise ValueError(f"unknown direct_fit model {model!r} "
                         "(expected translation, rigid, similarity or affine)")
    return bx, by, L, (cx, cy)


def warp_matrix(theta: np.ndarray, model: str, L: float, centre: tuple) -> np.ndarray:
    """The 3 x 3 affine of p -> p + displacement(theta) in query px."""
    cx, cy = centre
    if model == "similarity":
        t0, t1, a, b = theta
        A = np.array([[a, -b], [b, a]]) / L
    elif model == "rigid":  # first order in the angle, re-orthonormalised
        t0, t1, b = theta
        ang = b / L
        A = np.array([[np.cos(ang) - 1, -np.sin(ang)], [np.sin(ang), np.cos(ang) - 1]])
    elif model == "translation":
        t0, t1 = theta
        A = np.zeros((2, 2))
    else:
        t0, t1, a, b, c, d = theta
        A = np.array([[a, b], [c, d]]) / L
    M = np.eye(3)
    M[:2, :2] += A
    M[:2, 2] = np.array([t0, t1]) - A @ np.array([cx, cy])
    return M


def _render_cfog(H: np.ndarray, map_image: Any, w: int, h: int, orient: int,
                 sigma: float) -> tuple[np.ndarray, np.ndarray]:  # fmt: skip
    from georeg.register.refine import cfog

    cols = np.arange(w, dtype=np.float64)[None, :]
    rows = np.arange(h, dtype=np.float64)[:, None]
    x, y = apply_h(H, cols, rows)
    rendered = map_image.render(x, y)
    rvalid = np.isfinite(rendered)
    return cfog(np.nan_to_num(rendered), rvalid, orient, sigma), _good(rvalid)


def _good(valid: np.ndarray) -> np.ndarray:
    """Pixels whose CFOG channels and their gradients are free of nodata borders."""
    return cv2.erode(valid.astype(np.uint8), np.ones((7, 7), np.uint8)).astype(bool)


def pooled_ncc(qf: np.ndarray, rf: np.ndarray, mask: np.ndarray) -> float:
    """Correlation of the CFOG channels over ``mask``, pooled over channels (zero mean)."""
    if mask.sum() < 2:
        return float("nan")
    a = qf[:, mask].ravel().astype(np.float64)
    b = rf[:, mask].ravel().astype(np.float64)
    a -= a.mean()
    b -= b.mean()
    d = float(np.sqrt((a @ a) * (b @ b)))
    return float(a @ b) / d if d > 0 else float("nan")


def _solve(H0: np.ndarray, qfs: list[np.ndarray], qgood: np.ndarray, sel: np.ndarray,
           map_image: Any, c: dict[str, Any], orient: int) -> tuple[np.ndarray, dict[str, Any]]:  # fmt: skip
    """Gauss-Newton of the warp on the pixels ``sel`` (coarse to fine); (H, report)."""
    h, w = qgood.shape
    model = str(c["model"])
    bx, by, L, centre = _basis(w, h, model)
    H = H0.copy()
    passes = 0
    corners = np.array([[0, 0, 1], [w - 1, 0, 1], [0, h - 1, 1], [w - 1, h - 1, 1]], float).T
    for qf, sigma in zip(qfs, c["sigmas_px"], strict=True):
        for _ in range(max(1, int(c["iterations"]))):
            rf, rgood = _render_cfog(H, map_image, w, h, orient, float(sigma))
            m = sel & qgood & rgood
            if m.sum() < int(c["min_pixels"]):
                return H, {"passes": passes, "reason": f"{int(m.sum())} valid pixels"}
            gx = np.stack([cv2.Sobel(ch, cv2.CV_32F, 1, 0, ksize=3) / 8.0 for ch in rf])
            gy = np.stack([cv2.Sobel(ch, cv2.CV_32F, 0, 1, ksize=3) / 8.0 for ch in rf])
            e = (rf - qf)[:, m]  # (C, N)
            G = gx[:, m][:, None, :] * bx[:, m][None] + gy[:, m][:, None, :] * by[:, m][None]
            r = np.sqrt((e**2).sum(0))
            s = 1.4826 * float(np.median(r)) + 1e-9
            k = float(c["robust_k"]) * s
            wt = np.where(r <= k, 1.0, k / np.maximum(r, 1e-12)).astype(np.float32)
            Gw = G * wt[None, None, :]
            A = np.einsum("cpn,cqn->pq", Gw, G, optimize=True).astype(np.float64)
            b = np.einsum("cpn,cn->p", Gw, e, optimize=True).astype(np.float64)
            A += 1e-6 * np.trace(A) / len(A) * np.eye(len(A))
            try:
                theta = -np.linalg.solve(A, b)
            except np.linalg.LinAlgError:
                return H, {"passes": passes, "reason": "singular normal equations"}
            M = warp_matrix(theta, model, L, centre)
            H = H @ M
            passes += 1
            moved = np.abs((M @ corners)[:2] - corners[:2]).max()
            if moved < float(c["converged_px"]):
                break
    return H, {"passes": passes}


def _footprint_diff_px(Ha: np.ndarray, Hb: np.ndarray, w: int, h: int, px: float) -> float:
    """Largest distance (query px) between two fits over a grid of the footprint."""
    cols, rows = np.meshgrid(np.linspace(0, w - 1, 9), np.linspace(0, h - 1, 9))
    xa, ya = apply_h(Ha, cols, rows)
    xb, yb = apply_h(Hb, cols, rows)
    return float(np.hypot(xa - xb, ya - yb).max() / px)


def direct_fit(
    band: np.ndarray,
    H: np.ndarray,
    map_image: Any,
    conf: dict[str, Any] | None = None,
    refine_conf: dict[str, Any] | None = None,
) -> tuple[np.ndarray, dict[str, Any]]:
    """Align the whole footprint of ``band`` to the map by a small warp composed into ``H``
    (query px -> map x, y). ``conf``: this module's settings (``refine.direct_fit``);
    ``refine_conf``: the CFOG settings (``georeg.register.refine``).

    Returns the homography to use (the fit, or ``H`` when the guard keeps it) and a report."""
    from georeg.register.refine import merged as refine_merged
    from georeg.register.refine import query_cfog, query_valid

    t0 = time.perf_counter()
    c = merged(conf)
    rc = refine_merged(refine_conf)
    orient = int(rc["orientations"])
    H0 = np.asarray(H, np.float64)
    h, w = band.shape[-2:]
    qvalid = query_valid(band)
    qgood = _good(qvalid)
    px = ground_px(H0, w, h)
    info: dict[str, Any] = {"enabled": True, "accepted": False, "model": str(c["model"])}
    if qvalid.sum() > int(c["max_pixels"]):
        info.update(reason=f"{int(qvalid.sum())} valid pixels > max_pixels {c['max_pixels']}",
                    seconds=time.perf_counter() - t0)  # fmt: skip
        return H0, info
    qfs = [query_cfog(band, orient, float(s))[0] for s in c["sigmas_px"]]
    cell = max(1, int(c["cell_px"]))
    rr, cc = np.mgrid[:h, :w]
    board = ((rr // cell + cc // cell) % 2).astype(bool)
    ends = {}
    for name, sel in (("a", ~board), ("b", board), ("all", np.ones((h, w), bool))):
        Hs, rep = _solve(H0, qfs, qgood, sel, map_image, c, orient)
        if "reason" in rep:
            info.update(reason=f"board {name}: {rep['reason']}", seconds=time.perf_counter() - t0)
            log.info("direct fit: %s -> kept", info["reason"])
            return H0, info
        ends[name] = Hs
    # the whole footprint's correlation must rise; the boards' fits bound the fit's noise
    sig = float(c["sigmas_px"][-1])
    rf0, g0 = _render_cfog(H0, map_image, w, h, orient, sig)
    rf1, g1 = _render_cfog(ends["all"], map_image, w, h, orient, sig)
    m = qgood & g0 & g1
    ncc0, ncc1 = pooled_ncc(qfs[-1], rf0, m), pooled_ncc(qfs[-1], rf1, m)
    disagree = _footprint_diff_px(ends["a"], ends["b"], w, h, px)
    moved = _footprint_diff_px(ends["all"], H0, w, h, px)
    info.update(ncc=[round(ncc0, 4), round(ncc1, 4)], disagree_px=round(disagree, 3),
                precision_px=round(disagree / 2, 3), moved_px=round(moved, 3))  # fmt: skip
    reasons = []
    if not ncc1 > ncc0:
        reasons.append(f"the correlation does not rise ({ncc0:.3f} -> {ncc1:.3f})")
    if not disagree <= float(c["max_disagree_px"]):
        reasons.append(f"the boards' fits differ by {disagree:.2f} px > {c['max_disagree_px']}")
    if not moved <= float(c["max_move_px"]):
        reasons.append(f"the fit moved {moved:.2f} px > {c['max_move_px']}")
    info["accepted"] = not reasons
    if reasons:
        info["reason"] = "; ".join(reasons)
    info["homography"] = ends["all"].tolist()
    info["seconds"] = time.perf_counter() - t0
    log.info("direct fit: moved %.2f px, boards differ %.2f px -> %s", moved, disagree,
             "accepted" if info["accepted"] else info["reason"])  # fmt: skip
    return (ends["all"] if info["accepted"] else H0), info
