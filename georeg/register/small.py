"""Very small queries (< ~100 px a side): dense correlation in the candidate regions, then a
feature re-match with features dense on both sides, decided by the feature NFA.

A 48-100 px SWIR query keeps a few dozen features at the map index's density
(``features.max_features_per_mpx``), too few to survive the cross-spectral ratio test; in its
true candidate region the verification finds at most 4 inliers. Two things are cheap once the
search is restricted to a candidate region (docs/BENCHMARKS.md "Small queries"):

* the CFOG channels of query and orthophoto window correlated by FFT over rotations
  (``georeg.register.dense.dense_search``) put the query within 1-3 map px of its true place in
  most true regions -- a similarity hypothesis, not a decision;
* the orthophoto window is read and its features re-detected without the per-Mpx cap and with a
  lower contrast threshold (same for the query), so the guided re-match around that similarity
  has many more candidates.

The decision is the feature NFA of the guided re-match (``acceptance.decide``): matches can only
land within ``radius_px`` of the prediction (the disc is the area of the null), and the test count
is every rotation step x every disc-sized place of the window x every window searched.
"""

from __future__ import annotations

import logging
import math
import time
from typing import Any

import numpy as np

from georeg.index.features import detect_and_describe, merged_conf, resample
from georeg.register import acceptance, matching
from georeg.register.null_scan import null_conf
from georeg.register.search import MapSource, MapView, QueryFeatures, QueryInput, query_features

log = logging.getLogger(__name__)

SMALL_DEFAULTS: dict[str, Any] = {
    "enabled": True,
    "max_side_px": 160,
    "max_windows": 3,
    "step_deg": 10.0,
    "max_side": 96,
    "radii_px": [8.0, 4.0],
    "ratio": 0.8,
    "inlier_px": 3.0,
    "features": {"max_features_per_mpx": 0, "sift": {"contrast_threshold": 0.02}},
}


def small_conf(reg_conf: dict[str, Any] | None) -> dict[str, Any]:
    """``register.small`` with defaults."""
    return {**SMALL_DEFAULTS, **((reg_conf or {}).get("small") or {})}


def applies(width: int, height: int, reg_conf: dict[str, Any] | None) -> bool:
    """Whether the small-query fallback is on and the query is small enough for it."""
    sc = small_conf(reg_conf)
    return bool(sc["enabled"]) and max(width, height) <= float(sc["max_side_px"])


def dense_features_conf(features_conf: dict[str, Any] | None, sc: dict[str, Any]) -> dict:
    """The map's feature settings with ``register.small.features`` on top (no cap, lower
    contrast threshold): the same settings for the query and the re-detected window."""
    base = merged_conf(features_conf or {})
    extra = sc.get("features") or {}
    out = {**base, **{k: v for k, v in extra.items() if k != "sift"}}
    out["sift"] = {**base["sift"], **(extra.get("sift") or {})}
    return out


def window_features(
    win_u8: np.ndarray, win_to_map: np.ndarray, feature_gsd: float, fconf: dict[str, Any]
) -> MapSource:
    """Features of a map window (uint8, 0 = nodata; 3 x 3 window pixel centre -> map x, y)
    detected at the map's feature GSD, as a plain-array MapSource."""
    win_px = float(np.sqrt(abs(np.linalg.det(win_to_map[:2, :2]))))
    img, m, (sx, sy) = resample(win_u8, win_px / feature_gsd, win_u8 > 0)
    f = detect_and_describe(img, m, fconf)
    px = (f.xy.astype(np.float64) + 0.5) * np.array([sx, sy]) - 0.5
    xy = matching.apply_h(win_to_map, px) if len(px) else np.zeros((0, 2))
    return MapSource(xy, f.desc, feature_gsd, angle=f.angle.astype(np.float64),
                     scale=f.scale.astype(np.float64) * feature_gsd)  # fmt: skip


def fit_similarity(
    q_xy: np.ndarray, m_xy: np.ndarray, feature_gsd: float, inlier_px: float, seed: int = 0
) -> matching.HomographyFit | None:
    """A similarity (rotation, scale, shift: a nadir view of a small footprint) query (col, row)
    -> map (x, y), by RANSAC then least squares on the inliers; residuals of every match in map
    feature px. None when it cannot be fitted."""
    import cv2

    if len(q_xy) < 3:
        return None
    g = float(feature_gsd)
    flip = np.diag([1.0, -1.0, 1.0])  # map y goes up, rows go down: fit in (x, -y)
    dst = (np.asarray(m_xy, np.float64) * [1.0, -1.0] / g).astype(np.float32)
    src = np.asarray(q_xy, np.float32)
    cv2.setRNGSeed(int(seed))
    M, inl = cv2.estimateAffinePartial2D(src, dst, method=cv2.RANSAC,
                                         ransacReprojThreshold=float(inlier_px), maxIters=4000,
                                         confidence=0.999, refineIters=10)  # fmt: skip
    if M is None or inl is None:
        return None
    H = flip @ np.diag([g, g, 1.0]) @ np.vstack([M, [0.0, 0.0, 1.0]])
    res = np.linalg.norm(matching.apply_h(H, q_xy) - m_xy, axis=1) / g
    inliers = res <= float(inlier_px)
    return matching.HomographyFit(H, inliers, res, float(inlier_px), 1, 0.0, {"model": "similarity"})


def decide_small(
    fit: matching.HomographyFit,
    disc_px: float,
    n_tests: int,
    width: int,
    height: int,
    q_gsd: float,
    q_xy: np.ndarray,
    reg_conf: dict[str, Any],
) -> dict[str, Any]:
    """Accept a guided similarity fit: binomial-tail NFA over the disc the matches could land in
    (``acceptance.log10_nfa_binomial``, sample 2) below ``register.acceptance.log_nfa_max``, a
    plausible mapping and inliers spread in 2-D (``acceptance.plausibility``, ``inlier_spread``)."""
    ac = reg_conf.get("acceptance", {}) or {}
    lnfa, k, ek = acceptance.log10_nfa_binomial(
        fit.residual_px, disc_px, n_tests, 2, float(ac.get("min_residual_px", 0.5))
    )
    out: dict[str, Any] = {"log10_nfa": lnfa, "nfa_k": k, "nfa_eps_px": ek}
    reasons = []
    if not lnfa < float(ac.get("log_nfa_max", 0.0)):
        reasons.append(f"log10 NFA {lnfa:.1f} >= {ac.get('log_nfa_max', 0.0)}")
    plaus = acceptance.plausibility(fit.H, width, height, q_gsd, ac)
    reasons += plaus.get("reasons", [])
    spread = acceptance.inlier_spread(q_xy[fit.inliers], width, height)
    if spread["minor_major"] < float(ac.get("min_spread_ratio", 0.2)) or spread[
        "minor_frac"
    ] < float(ac.get("min_spread_frac", 0.05)):
        reasons.append("inliers nearly collinear")
    out.update(accepted=not reasons, reason="; ".join(reasons), spread=spread)
    return out


def _guided_rematch(
    H: np.ndarray,
    q_xy: np.ndarray,
    q_desc: np.ndarray,
    mxy: np.ndarray,
    mdesc: np.ndarray,
    knn: Any,
    g: float,
    sc: dict[str, Any],
    win_area: float,
    n_rot: int,
    n_windows: int,
    qf: QueryFeatures,
    q_gsd: float,
    reg_conf: dict[str, Any],
    seed: int,
    tests_before: int = 0,
) -> tuple[Any, matching.HomographyFit, dict[str, Any], float] | None:
    """The guided re-match around the similarity ``H`` (query px -> map x, y) at the radii
    ``radii_px`` (a later radius only refines an accepted fit): (matches, fit, decision,
    radius) of the last fit kept, or None when nothing could be fitted. The NFA counts every
    rotation, disc and window, plus ``tests_before`` (the sources that ran before)."""
    best = None
    for k, radius_px in enumerate(float(v) for v in sc["radii_px"]):
        disc = math.pi * radius_px**2
        gm = matching.guided_matches(q_xy, q_desc, H, mxy, mdesc, radius_px * g,
                                          float(sc["ratio"]), knn)  # fmt: skip
        if len(gm) < 4:
            break
        fit = fit_similarity(gm.q_xy, gm.m_xy, g, float(sc["inlier_px"]), seed + k)
        if fit is None:
            break
        n_tests = n_rot * max(1, int(math.ceil(win_area / disc))) * max(1, int(n_windows))
        n_tests += int(tests_before)
        dec = decide_small(fit, disc, n_tests, qf.width, qf.height, q_gsd, gm.q_xy, reg_conf)
        if best is not None and (not dec["accepted"] or fit.n_inliers <= best[1].n_inliers):
            break  # a smaller radius only replaces an accepted fit by a better one
        best = (gm, fit, dec, radius_px)
        H = fit.H
        if not dec["accepted"]:
            break
    return best


def small_register(
    q_u8: np.ndarray,
    q_gsd: float,
    win: np.ndarray,
    win_to_map: np.ndarray,
    feature_gsd: float,
    reg_conf: dict[str, Any],
    features_conf: dict[str, Any] | None = None,
    seed: int = 0,
    n_windows: int = 1,
    qf: QueryFeatures | None = None,
    region: tuple[float, float, float, float] | None = None,
    tests_before: int = 0,
) -> dict[str, Any]:
    """Register a small query in one map window: CFOG peak, then the guided re-match with dense
    features at radii ``radii_px`` (feature px; a later radius only refines an accepted fit).

    ``q_u8``: query band(s) (0 = nodata; several pooled bands: all give features, the first
    the correlation); ``win``: window (uint8, 0 = nodata); ``q_gsd``: query GSD in map units.
    ``qf``: the query's dense features when already computed. ``region`` (map x0, y0, x1, y1):
    only places whose query centre lies in it are searched and counted (the window should hold
    the region grown by half the footprint diagonal); None = the whole window. Returns a record like a search
    part's (``accepted``, ``homography``, ``inliers``, ``log10_nfa``, ...).
    """
    from georeg.register.dense import dense_search

    t0 = time.perf_counter()
    sc = small_conf(reg_conf)
    rec: dict[str, Any] = {"method": "small", "accepted": False, "homography": None, "inliers": 0}
    win_px = float(np.sqrt(abs(np.linalg.det(win_to_map[:2, :2]))))
    q0 = q_u8 if q_u8.ndim == 2 else q_u8[0]
    box = None
    places_px = float(win.shape[0] * win.shape[1])
    if region is not None:
        inv = np.linalg.inv(win_to_map)
        cr = matching.apply_h(inv, np.array([[region[0], region[1]], [region[2], region[3]]]))
        box = (float(cr[:, 0].min()), float(cr[:, 1].min()), float(cr[:, 0].max()),
               float(cr[:, 1].max()))  # fmt: skip
        places_px = max(1.0, (box[2] - box[0]) * (box[3] - box[1]))
    r = dense_search(q0, q_gsd / win_px, win, float(sc["step_deg"]), int(sc["max_side"]),
                     centre_box=box)  # fmt: skip
    if r is None:
        rec.update(reason="no overlap", seconds=time.perf_counter() - t0)
        return rec
    rec.update(angle_deg=r.angle_deg, dense_score=r.score, dense_peak_ratio=r.second_ratio)
    g = float(feature_gsd)
    fconf = dense_features_conf(features_conf, sc)
    if qf is None:
        qf = query_features(q_u8, (0, q_u8.shape[-2]), [q_gsd / g], fconf)
    src = window_features(win, win_to_map, g, fconf)
    rec.update(query_features=len(qf), window_features=len(src.xy))
    if len(qf) < 4 or len(src.xy) < 8:
        rec.update(reason="too few features", seconds=time.perf_counter() - t0)
        return rec
    mxy, mdesc = np.asarray(src.xy, np.float64), np.asarray(src.desc, np.float32)
    knn = matching.knn2(mdesc)
    q_xy, q_desc, _ = matching.add_polarity(qf.xy, qf.desc, qf.response)
    win_area = places_px * (win_px / g) ** 2  # where the query centre may be, feature px
    n_rot = int(round(360.0 / float(sc["step_deg"])))
    hyps = [(r.S, r.angle_deg, r.score)] + list(r.others or [])
    best = None
    for j, (S, angle, score) in enumerate(hyps):
        got = _guided_rematch(win_to_map @ S, q_xy, q_desc, mxy, mdesc, knn, g, sc, win_area,
                              n_rot, n_windows, qf, q_gsd, reg_conf, seed, tests_before)  # fmt: skip
        if got is None:
            continue
        if best is None or got[2]["accepted"] or got[2]["log10_nfa"] < best[2]["log10_nfa"]:
            best = (*got, j, angle, score)
        if got[2]["accepted"]:
            break  # the first accepted peak, in the order of the correlation score
    if best is not None:
        gm, fit, dec, radius_px, j, angle, score = best
        inl = fit.inliers
        rec.update(
            accepted=bool(dec["accepted"]), homography=fit.H.tolist(), inliers=fit.n_inliers,
            matches=len(gm), residual_px=fit.rms_px, log10_nfa=dec.get("log10_nfa"),
            reason=dec.get("reason", ""), radius_px=radius_px, peak=j, angle_deg=angle,
            dense_score=score, peaks_tried=len(hyps),
            inlier_query_xy=gm.q_xy[inl].tolist(), inlier_map_xy=gm.m_xy[inl].tolist(),
        )  # fmt: skip
    rec["seconds"] = time.perf_counter() - t0
    return rec


def small_windows(
    qf: QueryFeatures,
    source: MapSource,
    conf: dict[str, Any],
    gsd_m: float,
) -> list[tuple[float, ...]]:
    """The first ``max_windows`` candidate regions, ranked again with the dense query features
    ``qf`` (the index's Hough vote, ``register.index``; more query features put the true place in
    the first three regions more often than the regions the searches tried: 30 vs 26 of the 48
    queries of the tuning cities' small subset)."""
    from georeg.register.search import footprint_diagonal_m, index_candidates

    sc = small_conf(conf)
    n = int(sc["max_windows"])
    ic = {**(conf.get("index") or {}), "top_candidates": n}
    diag = footprint_diagonal_m(qf, source.gsd_m, gsd_m)
    return [tuple(float(v) for v in b) for b, _ in index_candidates(qf, source, diag, ic)][:n]


def first_accepted_window(windows: list[tuple[float, ...]], read_window: Any, register: Any,
                          parts: list[dict[str, Any]], height: int, flag: str,
                          keys: tuple[str, ...] = (), grow: float = 0.0,
                          ) -> tuple[list[dict[str, Any]], dict[str, Any]]:  # fmt: skip
    """Each window (grown by ``grow`` map units) read by ``read_window``, then ``register(k, gray,
    A, bounds)``; the first accepted record becomes one more whole-query part, marked ``flag``.
    Returns the parts and the record of the windows tried (their bounds, acceptance, inliers,
    NFA, reason, seconds and ``keys``)."""
    tried = []
    for k, b in enumerate(windows):
        got = read_window((b[0] - grow, b[1] - grow, b[2] + grow, b[3] + grow))
        if got is None:
            continue
        rec = register(k, *got, b)
        rec["bounds"] = [float(v) for v in b]
        tried.append({k2: rec.get(k2) for k2 in ("bounds", "accepted", "inliers", "matches",
                      "log10_nfa", *keys, "reason", "seconds")})  # fmt: skip
        log.info("%s search in window %d: %s inliers, log10 NFA %s -> %s", flag, k,
                 rec.get("inliers"), rec.get("log10_nfa"),
                 "ACCEPT" if rec["accepted"] else rec.get("reason"))  # fmt: skip
        if rec["accepted"]:
            part = {**rec, "part": len(parts), "rows": [0, height], "whole_query": True,
                    flag: True, "candidates_tried": k + 1, "candidates": []}  # fmt: skip
            return [*parts, part], {"ran": True, "candidates": len(tried), "windows": tried,
                                    "accepted_window": k}  # fmt: skip
    return parts, {"ran": True, "candidates": len(tried), "windows": tried,
                   "accepted_window": None}  # fmt: skip


def _why_not(u8: np.ndarray, conf: dict[str, Any], gsd_m: float | None,
             read_window: Any) -> str | None:  # fmt: skip
    """Why the small-query sources do not apply to this query (None: they do)."""
    sc = small_conf(conf)
    h, w = u8.shape[-2:]
    if not applies(w, h, conf):
        return "disabled" if not sc["enabled"] else f"query side > {sc['max_side_px']} px"
    if not gsd_m or read_window is None:
        return "no query GSD or no orthophoto"
    return None


def window_source(
    q: QueryInput, view: MapView, parts: list[dict[str, Any]], conf: dict[str, Any]
) -> tuple[list[dict[str, Any]], dict[str, Any]]:
    """Source ``small_windows`` (``register.small``): ``small_register`` in the first
    ``max_windows`` candidate regions of the dense query features; the first accepted one
    becomes one more (whole-query) part. ``read_window(bounds)`` -> (float gray window, NaN =
    nodata; 3 x 3 window pixel centre -> map x, y) or None. Returns the parts and the record."""
    from georeg.register.dense import window_u8

    u8, gsd_m, seed, source, read_window = q.u8, q.gsd, q.seed, view.source, view.read_window
    why = _why_not(u8, conf, gsd_m, read_window)
    if why:
        return parts, {"ran": False, "reason": why}
    assert gsd_m is not None
    sc = small_conf(conf)
    h, w = u8.shape[-2:]
    fconf = dense_features_conf(source.features_conf, sc)
    qf = query_features(u8, (0, h), [gsd_m / source.gsd_m], fconf)
    windows = small_windows(qf, source, conf, gsd_m)
    grow = 0.5 * math.hypot(w, h) * float(gsd_m)  # a centre in the region, the footprint around

    def register(k: int, gray: np.ndarray, A: np.ndarray, b: tuple[float, ...]) -> dict[str, Any]:
        return small_register(u8, gsd_m, window_u8(gray), A, source.gsd_m, conf,
                              source.features_conf, seed + k, len(windows), qf, b,
                              q.tests_before)  # fmt: skip

    return first_accepted_window(windows, read_window, register, parts, h, "small",
                                 ("angle_deg", "dense_score", "peak"), grow)  # fmt: skip


def null_source(
    q: QueryInput, view: MapView, parts: list[dict[str, Any]], conf: dict[str, Any]
) -> tuple[list[dict[str, Any]], dict[str, Any]]:
    """Source ``cfog_null`` (``register.small.null_test``): the small query's CFOG peak over the
    whole map (``null_register``); an accepted peak becomes one more (whole-query) part.
    Returns the parts and the record."""
    u8, gsd_m, source, read_window = q.u8, q.gsd, view.source, view.read_window
    why = _why_not(u8, conf, gsd_m, read_window)
    if why or not null_conf(small_conf(conf))["enabled"]:
        return parts, {"ran": False, "reason": why or "disabled"}
    assert gsd_m is not None
    h = u8.shape[-2]
    got = null_register(u8, gsd_m, source, conf, read_window)
    rec = {"ran": True, "candidates": 1, **{k: v for k, v in got.items() if k != "homography"}}
    if got["accepted"]:
        part = {**got, "part": len(parts), "rows": [0, h], "whole_query": True,
                "small": True, "candidates_tried": 1, "candidates": []}  # fmt: skip
        parts = [*parts, part]
    return parts, rec


def whole_map(u8: np.ndarray, q_gsd: float, source: MapSource, sc: dict[str, Any],
              nc: dict[str, Any], read_window: Any) -> tuple[tuple[float, ...], Any, float]:  # fmt: skip
    """The map's bounds grown by half the query, and the orthophoto over them read whole
    (gray, NaN = nodata; 3 x 3 pixel centre -> map) with the query's GSD over its pixel size,
    when the correlation (the query shrunk to ``max_side`` px) sees at most
    ``null_test.max_map_px`` px of it; else None (too large for one FFT) or "no orthophoto"."""
    h, w = u8.shape[-2:]
    b = source.bounds
    pad = 0.5 * math.hypot(w, h) * float(q_gsd)
    b = (b[0] - pad, b[1] - pad, b[2] + pad, b[3] + pad)
    # the map as the correlation sees it: the query shrunk to max_side px
    per_m = min(1.0 / source.gsd_m, float(sc["max_side"]) / (max(h, w) * float(q_gsd)))
    est = (b[2] - b[0]) * (b[3] - b[1]) * per_m**2
    if est > float(nc["max_map_px"]):
        return b, None, 0.0
    got = read_window(b)
    if got is None:
        return b, "no orthophoto", 0.0
    gray, A = got
    factor = float(q_gsd) / float(np.sqrt(abs(np.linalg.det(A[:2, :2]))))
    est = gray.size * min(1.0, float(sc["max_side"]) / (max(h, w) * factor)) ** 2
    if est > float(nc["max_map_px"]):  # the orthophoto is finer than the features
        return b, None, 0.0
    return b, got, factor


def null_register(
    u8: np.ndarray,
    q_gsd: float,
    source: MapSource,
    conf: dict[str, Any],
    read_window: Any,
) -> dict[str, Any]:
    """The small query's CFOG peak over the whole map, decided by the calibrated block-maxima
    null (``georeg.register.null_scan``, ``register.small.null_test``); an accepted peak becomes a
    similarity at the known GSD refined by ``null_scan.fine_pose`` and checked for
    plausibility. A record like a search part's (``accepted``, ``homography``, ``log10_nfa``
    = the CFOG peak's, ``inliers`` 0) with the evidence (statistic, p-value, null size).

    The map is read and correlated at once up to ``max_map_px`` correlation px (``scan:
    whole``), tile by tile above it (``null_scan.tiled_scan``, ``tile_px``; ``scan:
    tiled``, ``tiles``) up to ``max_tiled_map_px``, and not at all beyond (``reason``)."""
    from georeg.register.dense import window_u8
    from georeg.register.null_scan import fine_pose, scan, tiled_scan

    t0 = time.perf_counter()
    sc = small_conf(conf)
    nc = null_conf(sc)
    h, w = u8.shape[-2:]
    rec: dict[str, Any] = {"method": "small_cfog_null", "accepted": False, "homography": None,
                           "inliers": 0, "matches": 0, "statistic": "CFOG peak score, top spacing",
                           "block_px": int(nc["block_px"])}  # fmt: skip
    b, got, factor = whole_map(u8, q_gsd, source, sc, nc, read_window)
    q0 = u8 if u8.ndim == 2 else u8[0]
    if got == "no orthophoto":
        rec.update(reason="no orthophoto", seconds=time.perf_counter() - t0)
        return rec
    if got is None:  # larger than one FFT: tile by tile (null_scan.tiled_scan), up to max_tiled_map_px
        try:
            r = tiled_scan(q0, float(q_gsd), b, read_window, source.gsd_m, float(sc["step_deg"]),
                           int(sc["max_side"]), int(nc["block_px"]), float(nc["exclude_px"]),
                           int(nc["tail_k"]), int(nc["tile_px"]), float(nc["max_tiled_map_px"]))  # fmt: skip
        except ValueError as exc:  # an orthophoto grid the tiles cannot share (not north-up)
            r = {"reason": str(exc)}
        rec["scan"] = "tiled"
        if "S" not in r:
            rec.update({k: v for k, v in r.items() if k in ("tiles", "map_px")})
            rec.update(reason=r["reason"], seconds=time.perf_counter() - t0)
            return rec
        A, m_u8, factor = r.pop("A"), r.pop("m_u8"), r.pop("factor")
    else:
        rec["scan"] = "whole"
        gray, A = got
        m_u8 = window_u8(gray)
        r = scan(q0, factor, m_u8, float(sc["step_deg"]), int(sc["max_side"]),
                 int(nc["block_px"]), float(nc["exclude_px"]), int(nc["tail_k"]))  # fmt: skip
        if r is None:
            rec.update(reason="no overlap or too few null blocks",
                       seconds=time.perf_counter() - t0)  # fmt: skip
            return rec
    rec.update({k: v for k, v in r.items() if k != "S"})
    rec["map_px_m"] = float(q_gsd) / float(factor)  # map units per map pixel
    reasons = []
    if not r["log10_nfa"] < float(nc["log_nfa_max"]):
        reasons.append(f"CFOG peak log10 NFA {r['log10_nfa']:.1f} >= {nc['log_nfa_max']}")
    else:
        S, ang, score = fine_pose(q0, factor, m_u8, r["S"], r["angle_deg"],
                                  float(nc["fine_step_deg"]), float(nc["fine_range_deg"]))  # fmt: skip
        H = A @ S
        rec.update(homography=H.tolist(), fine_angle_deg=ang, fine_score=score)
        ac = conf.get("acceptance", {}) or {}
        plaus = acceptance.plausibility(H, w, h, q_gsd, ac)
        reasons += plaus.get("reasons", [])
    rec.update(accepted=not reasons, reason="; ".join(reasons), seconds=time.perf_counter() - t0)
    return rec


def peaks_source(
    q: QueryInput, view: MapView, parts: list[dict[str, Any]], conf: dict[str, Any]
) -> tuple[list[dict[str, Any]], dict[str, Any]]:
    """Source ``cfog_peaks`` (``register.small.null_test.peaks``), when no other source was
    accepted, on a query of any size: the ``peaks`` best places of the query's CFOG correlation
    over the whole map (``null_scan.peaks``), each refined (``null_scan.fine_pose``) and checked
    densely against the orthophoto (``ortho_check.check``: the supported fraction of the tie
    points at the pose; for the ``MOVED_PEAKS`` best supported, at four moved poses too). A pose
    is judged by the a-contrario count of its
    supported tie points (``dense_nfa``) over every test of the search (``q.tests_before``) and
    these peaks; the lowest below ``log_nfa_max`` that is plausible becomes one more (whole-query)
    part. The rifts' features do not match across decades of land change where the structure
    of the whole footprint still does (Landsat Pucallpa, session 45). Returns the parts and the
    record."""
    from rasterio.transform import Affine

    from georeg.register.dense import window_u8
    from georeg.register.null_scan import fine_pose, peaks
    from georeg.register.ortho_check import check, ortho_conf
    from georeg.register.tiepoints import MapImage

    sc = small_conf(conf)
    nc = null_conf(sc)
    n = int(nc["peaks"])
    if not n or not nc["enabled"] or not sc["enabled"]:
        return parts, {"ran": False, "reason": "disabled"}
    if not q.gsd or view.read_window is None:
        return parts, {"ran": False, "reason": "no query GSD or no orthophoto"}
    t0 = time.perf_counter()
    u8 = q.primary
    h, w = u8.shape
    _, got, factor = whole_map(u8, q.gsd, view.source, sc, nc, view.read_window)
    if not isinstance(got, tuple):
        return parts, {"ran": False, "reason": got or "map too large for one FFT (null_test.max_map_px)"}
    gray, A = got
    # a query larger than PEAKS_SIDE_PX at the map's pixel size: the map read coarser (the
    # cost of the refinement and the tie points grows with the query's area; the fuse step's
    # checks and turn work at full resolution after)
    r = min(1.0, PEAKS_SIDE_PX / (max(h, w) * factor))
    if r < 1.0:
        o = 0.5 / r - 0.5  # new pixel centre c -> old (c + 0.5) / r - 0.5
        A = np.asarray(A, float) @ np.array([[1 / r, 0, o], [0, 1 / r, o], [0, 0, 1.0]])
        gray, factor = _coarser(gray, r), factor * r
    m_u8 = window_u8(gray)
    T = np.asarray(A, float) @ np.array([[1, 0, -0.5], [0, 1, -0.5], [0, 0, 1.0]])
    ortho = MapImage(np.asarray(gray, np.float32), Affine(*T[:2].ravel()))
    oc = ortho_conf(conf)
    tests = int(q.tests_before) + n
    cands = []
    for S0, ang0, score in peaks(u8, factor, m_u8, n, float(sc["step_deg"]), int(sc["max_side"])):
        S, ang, fine = fine_pose(u8, factor, m_u8, S0, ang0, float(nc["fine_step_deg"]),
                                 float(nc["fine_range_deg"]), box_px=6.0)  # fmt: skip
        H = A @ S
        ck = check(u8, H, ortho, oc, moved=False)
        cands.append({"H": H, "angle_deg": ang, "score": score, "fine_score": fine,
                      "supported": ck.get("supported"), "log10_nfa": None})  # fmt: skip
    # the moved poses of the best supported only: the count stays every peak
    for c in sorted(cands, key=lambda c: -(c["supported"] or 0.0))[:MOVED_PEAKS]:
        ck = check(u8, c["H"], ortho, oc)
        c.update(gain=ck.get("gain"), tie_points=ck.get("tie_points"), log10_nfa=dense_nfa(ck, tests))
    rec: dict[str, Any] = {"ran": True, "candidates": n, "tests": tests,
                           "peaks": [{k: v for k, v in c.items() if k != "H"} for c in cands]}  # fmt: skip
    good = [i for i, c in enumerate(cands)
            if c["log10_nfa"] is not None and c["log10_nfa"] < float(nc["log_nfa_max"])
            and acceptance.plausibility(c["H"], w, h, q.gsd, conf.get("acceptance") or {})["ok"]]  # fmt: skip
    i = min(good, key=lambda j: cands[j]["log10_nfa"]) if good else -1
    rec.update(accepted=i >= 0, seconds=round(time.perf_counter() - t0, 3))
    if i < 0:
        rec["reason"] = (f"no peak's dense log10 NFA < {nc['log_nfa_max']} (lowest "
                         f"{min((c['log10_nfa'] for c in cands if c['log10_nfa'] is not None), default=math.nan):.1f})")  # fmt: skip
        return parts, rec
    best = cands[i]
    log.info("cfog peaks: peak %d accepted, supported %.2f, log10 NFA %.1f", i,
             best["supported"], best["log10_nfa"])  # fmt: skip
    rec["peak"] = i
    part = {"accepted": True, "method": "cfog_peaks", "homography": best["H"].tolist(),
            "log10_nfa": best["log10_nfa"], "inliers": 0, "matches": 0, "part": len(parts),
            "rows": [0, h], "whole_query": True, "candidates_tried": n, "candidates": []}  # fmt: skip
    return [*parts, part], rec


#: ``peaks_source`` works with the query at most this many map pixels across (coarser maps)
PEAKS_SIDE_PX = 256


def _coarser(gray: np.ndarray, r: float) -> np.ndarray:
    """``gray`` (NaN = nodata) resampled by ``r`` < 1 (area average; a pixel with any nodata
    under it is nodata). Pixel centres: new (c + 0.5) / r - 0.5 = old c."""
    import cv2

    h, w = gray.shape
    size = (max(1, round(w * r)), max(1, round(h * r)))
    ok = np.isfinite(gray)
    img = cv2.resize(np.where(ok, gray, 0).astype(np.float32), size, interpolation=cv2.INTER_AREA)
    val = cv2.resize(ok.astype(np.float32), size, interpolation=cv2.INTER_AREA)
    return np.where(val > 0.99, img / np.maximum(val, 1e-6), np.nan).astype(np.float32)


#: the peaks whose moved poses are measured (the best supported at their own pose)
MOVED_PEAKS = 3

#: tie-point windows (``ortho_check.window_px``) overlap their neighbours on a grid of half
#: their side, so about this many tie points share one window's pixels: the count of
#: independent tie points is the measured one over it
TIE_OVERLAP = 4.0


#: the lowest log10 tail ``dense_nfa`` reports (float underflow below)
NFA_FLOOR = -300.0


def dense_nfa(ck: dict[str, Any], tests: int) -> float | None:
    """log10 NFA of a pose's dense check (``ortho_check.check``): ``tests`` x the binomial tail
    of its supported tie points, counted as independent over ``TIE_OVERLAP``, at the rate the
    best moved pose reaches (at least one tie point); None when the check was skipped."""
    from scipy.stats import binom

    n = int(ck.get("tie_points") or 0)
    if ck.get("supported_moved") is None or n == 0:
        return None
    p0 = max(max(ck.get("supported_moved") or [0.0]), 1.0 / n)
    k = int(math.floor(float(ck["supported"]) * n / TIE_OVERLAP))
    ne = int(n // TIE_OVERLAP)
    tail = float(binom.logsf(k - 1, ne, min(p0, 1.0))) / math.log(10) if k > 0 else 0.0
    # the tail underflows to -inf on a near-perfect match; registration.json keeps a number
    return math.log10(max(int(tests), 1)) + max(tail, NFA_FLOOR)


def null_check(
    u8: np.ndarray,
    fused: dict[str, Any],
    source: MapSource,
    conf: dict[str, Any],
    gsd_m: float | None,
    read_window: Any,
    split_small: dict[str, Any] | None = None,
) -> tuple[dict[str, Any], dict[str, Any] | None]:
    """A small query registered by its features, checked by the calibrated CFOG null scan
    (``register.small.null_test.check``): when the scan alone would accept a place more than
    ``conflict_px`` correlation px from the fit's (its peak is located to about one), the two
    detectors disagree and the calibrated one wins: the fused homography becomes the scan's.
    Returns the (possibly changed) fused result and the record (None when not run)."""
    sc = small_conf(conf)
    nc = null_conf(sc)
    h, w = u8.shape[-2:]
    if (not nc["enabled"] or not nc.get("check", True) or fused.get("homography") is None
            or not applies(w, h, conf) or not gsd_m or read_window is None):  # fmt: skip
        return fused, None
    if (split_small or {}).get("cfog_null") is not None:
        return fused, None  # the fallback already scanned: its peak registered this, or was not significant
    # the whole-map scan only: a tiled scan per registered query would cost minutes on a
    # county-scale map, and the test's power falls as the map grows (docs/BENCHMARKS.md)
    whole_only = {**conf, "small": {**sc, "null_test": {**nc, "max_tiled_map_px": 0}}}
    got = null_register(u8, gsd_m, source, whole_only, read_window)
    rec: dict[str, Any] = {k: v for k, v in got.items() if k != "homography"}
    rec["replaced"] = False
    if not got["accepted"]:
        rec["outcome"] = "no significant peak"
        return fused, rec
    c = np.array([(w - 1) / 2.0, (h - 1) / 2.0, 1.0])
    a = np.asarray(fused["homography"], float) @ c
    b = np.asarray(got["homography"], float) @ c
    d_map = float(np.hypot(*(a[:2] / a[2] - b[:2] / b[2])))
    d_corr = d_map / float(got["map_px_m"]) * float(got["shrink"])
    rec.update(distance_corr_px=round(d_corr, 2), conflict_px=float(nc["conflict_px"]))
    if d_corr <= float(nc["conflict_px"]):
        rec["outcome"] = "agrees"
        return fused, rec
    rec.update(outcome="conflict", replaced=True)
    log.info("CFOG null check: the scan's peak (log10 p %.1f) is %.1f correlation px from the "
             "feature fit: the fit is replaced", got["log10_p"], d_corr)  # fmt: skip
    out = {**fused, "homography": got["homography"], "feature_homography": fused["homography"],
           "method": "small_cfog_null"}  # fmt: skip
    return out, rec
