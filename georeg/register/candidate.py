"""A hypothesis of a query's place in the map, as every hypothesis source returns it.

A source is a function ``candidates(query_img, map_img, conf) -> list[Candidate]`` (query and
map uint8, 0 = nodata; ``conf`` holds at least ``query_gsd_m`` and ``map_gsd_m``). Each
candidate carries the evidence it used (its matched point pairs, all of them, not only the
inliers) so that one verifier (georeg.register.acceptance.decide) can score every candidate of
every source the same way, counting ``tests`` hypotheses in the a-contrario number.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import cv2
import numpy as np


@dataclass
class Candidate:
    """``H`` maps query px (col, row) to map px (col, row); ``q_xy`` / ``m_xy`` the matched
    pairs (query px, map px); ``tests`` the hypotheses the source tried for this list;
    ``area_px`` the map area (px) a pair's map point could fall in by chance (None = the whole
    map; a guided search's window otherwise)."""

    H: np.ndarray
    q_xy: np.ndarray
    m_xy: np.ndarray
    score: float
    tests: int = 1
    area_px: float | None = None
    source: str = ""


def similarity_ransac(
    q_xy: np.ndarray, m_xy: np.ndarray, reproj_px: float, seed: int, iters: int = 2000
) -> tuple[np.ndarray | None, np.ndarray]:
    """RANSAC similarity (4 dof) query px -> map px: (3 x 3 or None, inlier mask)."""
    if len(q_xy) < 3:
        return None, np.zeros(len(q_xy), bool)
    cv2.setRNGSeed(int(seed))
    A, inl = cv2.estimateAffinePartial2D(
        q_xy.astype(np.float32), m_xy.astype(np.float32), method=cv2.RANSAC,
        ransacReprojThreshold=float(reproj_px), maxIters=int(iters), confidence=0.999,
    )  # fmt: skip
    if A is None:
        return None, np.zeros(len(q_xy), bool)
    return np.vstack([A, [0.0, 0.0, 1.0]]), inl.ravel().astype(bool)


def rotation_canvas(img: np.ndarray, angle_deg: float) -> tuple[np.ndarray, np.ndarray]:
    """``img`` (uint8, 0 = nodata) rotated by ``angle_deg`` on a canvas that holds it whole, and
    the 3 x 3 map img px -> canvas px."""
    h, w = img.shape
    D = int(np.ceil(np.hypot(h, w))) + 2
    R = cv2.getRotationMatrix2D(((w - 1) / 2, (h - 1) / 2), float(angle_deg), 1.0)
    R[:, 2] += ((D - 1) / 2 - (w - 1) / 2, (D - 1) / 2 - (h - 1) / 2)
    out = cv2.warpAffine(img, R, (D, D), flags=cv2.INTER_LINEAR, borderValue=0)
    return out, np.vstack([R, [0.0, 0.0, 1.0]])


def scale_matrix(f: float) -> np.ndarray:
    """Pixel-centre scaling by f: u' = (u + 0.5) f - 0.5."""
    return np.array([[f, 0, 0.5 * f - 0.5], [0, f, 0.5 * f - 0.5], [0, 0, 1.0]])


def resample(img: np.ndarray, f: float) -> np.ndarray:
    """``img`` (uint8, 0 = nodata) scaled by f (nodata stays 0: nearest for the mask)."""
    if abs(f - 1.0) < 1e-6:
        return img
    h, w = img.shape
    size = (max(1, int(round(w * f))), max(1, int(round(h * f))))
    out = cv2.resize(img, size, interpolation=cv2.INTER_AREA if f < 1 else cv2.INTER_LINEAR)
    valid = cv2.resize((img > 0).astype(np.uint8), size, interpolation=cv2.INTER_NEAREST)
    return np.where(valid > 0, np.maximum(out, 1), 0).astype(np.uint8)


def apply(H: np.ndarray, xy: np.ndarray) -> np.ndarray:
    """(n, 2) points through a 3 x 3 homography."""
    p = np.c_[xy, np.ones(len(xy))] @ H.T
    return p[:, :2] / p[:, 2:3]


def verify(
    cands: list[Candidate],
    width: int,
    height: int,
    gsd_m: float | None,
    map_gsd_m: float,
    map_area_px: float,
    acc_conf: dict[str, Any],
    reproj_px: float = 3.0,
) -> tuple[Candidate | None, dict[str, Any]]:
    """Every candidate through the project's acceptance (georeg.register.acceptance.decide):
    residuals of all its pairs in map px, the a-contrario count = the hypotheses the sources
    tested (the largest ``tests`` of the list: a source's candidates share one budget), the
    area = the candidate's ``area_px`` or the map's valid area. Returns the accepted candidate
    of lowest NFA (else the best rejected one, or None) and its decision."""
    from georeg.register import acceptance

    n_tests = max([int(c.tests) for c in cands] or [1])
    to_m = np.diag([map_gsd_m, -map_gsd_m, 1.0])  # map px -> map x, y (north-up)
    best: tuple[tuple[bool, float], Candidate, dict[str, Any]] | None = None
    for c in cands:
        if c.H is None or len(c.q_xy) < 4:
            continue
        res = np.linalg.norm(apply(c.H, c.q_xy) - c.m_xy, axis=1)
        inl = res <= reproj_px
        area = float(c.area_px) if c.area_px is not None else float(map_area_px)
        dec = acceptance.decide(to_m @ c.H, res, int(inl.sum()), area, width, height, gsd_m,
                                acc_conf, n_candidates=n_tests, inlier_q_xy=c.q_xy[inl])  # fmt: skip
        dec["source"], dec["tests"] = c.source, n_tests
        key = (bool(dec["accepted"]), -float(dec.get("log10_nfa", np.inf)))
        if best is None or key > best[0]:
            best = (key, c, dec)
    if best is None:
        return None, {"accepted": False, "reason": "no candidate", "tests": n_tests}
    return best[1], best[2]
