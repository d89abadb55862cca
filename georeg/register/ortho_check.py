"""Check an accepted registration densely against the orthophoto it was matched to.

A feature fit rests on its inliers; with few of them (a small query, a cross-spectral pair) it
can pass the a-contrario and plausibility tests at the right place yet be distorted (an affine
fit through 6 inliers, 10-25 map px off towards the footprint's edges). Here the orthophoto is
rendered into the query geometry through H at about one map pixel per working pixel (the query
resampled by its ground pixel size, at most ``max_side`` pixels across), both images become
CFOG structure channels (:func:`georeg.register.tiepoints.cfog`, blind to contrast reversals) and
tie points are measured on a grid (:func:`georeg.register.tiepoints.measure_shifts`). A tie point
*supports* H when its peak NCC is at least ``min_score``, its peak is not on the search border
and its shift is within ``support_px`` working px of zero, i.e. where H puts it.

The same fraction is measured at four *moved hypotheses* (H moved by ``null_shift`` x
``search_px`` working px left, right, up and down): what this footprint's texture supports by
chance, in place of a significance of one correlation peak (which is not valid: the surface is
spatially correlated, docs/BENCHMARKS.md "Cross-spectral matching").

In the fuse step (:func:`apply`, fits with at most ``max_inliers`` inliers) the fit is first
refitted to these tie points (:func:`refit`: :func:`georeg.register.densefit.dense_fit`, affine,
taken when its blocked CV residual is lower); the refit is checked, and when it does not agree
the feature fit is checked too (:func:`verify`). The check is a term of the verifier's record:
it never changes the fit (a refit that replaced the feature fit was measured and not kept,
docs/BENCHMARKS.md "Dense check of accepted fits"); a fit it keeps is then turned by the fuse
step (``fuse.turn_weak_fit``, recorded here as ``turn``).

Outcome (``ortho_check.outcome`` in registration.json):

- ``agrees``: the supported fraction at H is at least ``min_support`` and ``min_gain`` times the
  best moved hypothesis's;
- ``disagrees``: not so, for the refit nor the feature fit (a wrong or distorted fit: its tie
  points sit away from where H puts them, or nowhere);
- ``skipped``: fewer than ``min_points`` measurable tie points (a footprint mostly off the
  orthophoto or nodata), or the check was not due (``max_inliers``).

``mode: reject`` turns ``disagrees`` into ``not_found``; ``record`` only writes the outcome.
"""

from __future__ import annotations

import logging
import time
from typing import Any

import numpy as np

from georeg.register.dense import _shrink
from georeg.register.geolocation import apply_h, ground_px
from georeg.register.tiepoints import MapImage, cfog, grid_points, measure_shifts

log = logging.getLogger(__name__)

DEFAULTS: dict[str, Any] = {
    "mode": "record",  # off | record (registration.json only) | reject (disagrees -> not_found)
    "max_inliers": 30,  # check fits with at most this many inliers; 0 = every accepted fit
    "map_px": 1.0,  # working pixel size in map pixels (the query resampled to it)
    "max_side": 400,  # ... but the query at most this many working px across
    "grid_step_px": 8,  # tie-point grid step (working px)
    "window_px": 16,  # tie-point window (working px)
    "search_px": 6,  # integer search radius (working px)
    "min_score": 0.2,  # tie-point peak NCC
    "support_px": 2.0,  # a tie point within this of zero shift supports H (working px)
    "null_shift": 2.0,  # moved hypotheses: H moved by this x search_px (working px)
    "min_points": 12,  # measurable tie points needed, else skipped
    "min_support": 0.2,  # agreement: supported fraction at H at least this ...
    "min_gain": 3.0,  # ... and this times the best moved hypothesis's
    "refit": True,  # refit the fit to dense tie points first (georeg.register.densefit)
    "refit_iterations": 6,  # measure -> affine fit passes of the refit
    "refit_min_gain": 0.1,  # the refit is taken when its blocked CV residual is this much lower
    # its tie points must cover this footprint (densefit ``cover_of``): the whole query where the
    # refit decides (a feature fit's check: on the map's overlap only, a wrong fit's refit passed
    # the veto, session 57); ``rift.polish`` of an accepted pose: the map's overlap
    "refit_cover_of": "footprint",
    "veto_gain": 2.0,  # any mode but off: a checked fit supported less than this times the best
    # moved hypothesis is not_found (0 = never); not applied to rift's poses (their polish is
    # this check with its own floor of 1)
}
MODES = ("off", "record", "reject")


#: the sources whose own poses this check polishes with a floor of 1 (``rift.polish``: rift's,
#: the learned source's and the elevation source's, the last against the DSM): rift's search
#: with its record (``split.<name>``), which the report reads too
POLISHED_SOURCES = ("rift", "reversed", "learned", "elevation")


def ortho_conf(reg_conf: dict[str, Any] | None) -> dict[str, Any]:
    """``register.ortho_check`` with defaults; a bad mode raises ValueError."""
    c = {**DEFAULTS, **((reg_conf or {}).get("ortho_check") or {})}
    if c["mode"] is False:  # YAML 1.1 reads an unquoted off as false
        c["mode"] = "off"
    if c["mode"] not in MODES:
        raise ValueError(f"register.ortho_check.mode must be one of {MODES}, got {c['mode']!r}")
    return c


def _support(qf: np.ndarray, qm: np.ndarray, rendered: np.ndarray, pts: np.ndarray,
             c: dict[str, Any]) -> dict[str, Any]:  # fmt: skip
    """Tie points of the query against one rendering: the supported fraction of the measurable
    ones, their count, and the median shift of the good ones (working px)."""
    rv = np.isfinite(rendered)
    rf = cfog(np.where(rv, rendered, 0).astype(np.float32), rv)
    m = measure_shifts(qf, rf, qm, rv, pts, int(c["window_px"]), int(c["search_px"]))
    n = int(m["valid"].sum())
    good = m["valid"] & ~m["border"] & (m["score"] >= float(c["min_score"]))
    near = good & (np.hypot(*m["shift"].T) <= float(c["support_px"]))
    med = np.median(m["shift"][good], 0) if good.any() else np.array([np.nan, np.nan])
    return {"support": int(near.sum()) / max(n, 1), "n": n, "good": int(good.sum()),
            "median_shift": med}  # fmt: skip


def check(
    q_u8: np.ndarray,
    H: np.ndarray,
    ortho: MapImage,
    conf: dict[str, Any] | None = None,
    moved: bool = True,
) -> dict[str, Any]:
    """Tie points of the query against the orthophoto at H and at moved hypotheses.

    ``q_u8``: the query band (uint8, 0 = nodata); ``H``: 3 x 3, query pixel centre (col, row) ->
    map (x, y); ``ortho``: the orthophoto (gray, NaN = nodata) around the footprint;
    ``conf``: :data:`DEFAULTS` overrides; ``moved`` False: the supported fraction at H only
    (outcome ``unmoved``, a screen: the moved hypotheses cost four times as much). Returns the
    record written to registration.json.
    """
    t0 = time.perf_counter()
    c = {**DEFAULTS, **(conf or {})}
    H = np.asarray(H, np.float64)
    h, w = q_u8.shape
    rec: dict[str, Any] = {"outcome": "skipped"}
    map_px = abs(float(ortho.transform[0]))
    ground = ground_px(H, w, h) / map_px  # map px per query px
    s = working_scale(q_u8.shape, H, map_px, c)
    qs, qm = _shrink(q_u8.astype(np.float32), q_u8 > 0, s)
    hs, ws = qs.shape
    u = (np.arange(ws) + 0.5) / s - 0.5  # working pixel centres in query px
    v = (np.arange(hs) + 0.5) / s - 0.5

    def render(dx: float, dy: float) -> np.ndarray:
        return ortho.render(*apply_h(H, u[None, :] + dx / s, v[:, None] + dy / s))

    qf = cfog(qs, qm)
    pts = grid_points(ws, hs, int(c["grid_step_px"]), int(c["window_px"]))
    at_h = _support(qf, qm, render(0.0, 0.0), pts, c)
    scale = ground / s  # map px per working px
    rec.update(tie_points=at_h["n"], resolution_map_px=scale)
    if at_h["n"] < int(c["min_points"]):
        rec.update(reason=f"{at_h['n']} measurable tie points < min_points {c['min_points']}",
                   seconds=time.perf_counter() - t0)  # fmt: skip
        return rec
    if not moved:
        rec.update(outcome="unmoved", supported=at_h["support"], seconds=time.perf_counter() - t0)
        return rec
    d = float(c["null_shift"]) * float(c["search_px"])
    null = [_support(qf, qm, render(dx, dy), pts, c)["support"]
            for dx, dy in ((d, 0.0), (-d, 0.0), (0.0, d), (0.0, -d))]  # fmt: skip
    best = max(null)
    med = at_h["median_shift"]
    rec.update(
        supported=at_h["support"],
        supported_moved=null,
        gain=at_h["support"] / max(best, 1.0 / at_h["n"]),
        good=at_h["good"],
        offset_map_px=float(np.hypot(*med)) * scale if np.isfinite(med).all() else None,
    )
    ok = at_h["support"] >= float(c["min_support"]) and rec["gain"] >= float(c["min_gain"])
    rec["outcome"] = "agrees" if ok else "disagrees"
    rec["seconds"] = time.perf_counter() - t0
    return rec


def working_scale(q_shape: tuple[int, ...], H: np.ndarray, map_px: float,
                  c: dict[str, Any]) -> float:  # fmt: skip
    """Query px -> working px factor: ``map_px`` map pixels per working pixel, the query at most
    ``max_side`` working px across."""
    h, w = q_shape[-2:]
    ground = ground_px(np.asarray(H, float), w, h) / map_px
    return min(ground / float(c["map_px"]), float(c["max_side"]) / max(h, w))


def refit(q_u8: np.ndarray, H: np.ndarray, ortho: MapImage,
          c: dict[str, Any]) -> tuple[np.ndarray, dict[str, Any]]:  # fmt: skip
    """The dense affine refit of H (:func:`georeg.register.densefit.dense_fit`) at the working
    resolution, with the check's tie-point settings. Returns the refit homography (query px ->
    map) when its blocked CV residual beats H's by ``refit_min_gain``, else H, and a record with
    the footprint corners' move in map px."""
    from georeg.register.dense import _scale
    from georeg.register.densefit import dense_fit

    map_px = abs(float(ortho.transform[0]))
    s = working_scale(q_u8.shape, H, map_px, c)
    qs, qm = _shrink(q_u8.astype(np.float32), q_u8 > 0, s)
    qs8 = np.where(qm, np.clip(np.round(qs), 1, 255), 0).astype(np.uint8)
    S = _scale(s)
    Hs = np.asarray(H, float) @ np.linalg.inv(S)
    gconf = {"model": "affine", "iterations": int(c["refit_iterations"]),
             "min_tie_points": int(c["min_points"]), "min_gain": float(c["refit_min_gain"]),
             "cover_of": str(c["refit_cover_of"])}  # fmt: skip
    rconf = {k: int(c[k]) for k in ("window_px", "grid_step_px", "search_px")}
    Hn, info = dense_fit(qs8, Hs, ortho, gconf, rconf)
    Hr = Hn @ S
    h, w = q_u8.shape
    corners = np.array([[0, 0], [w - 1, 0], [0, h - 1], [w - 1, h - 1]], float)
    Hc = np.asarray(info.get("homography", Hs)) @ S
    a = np.c_[apply_h(np.asarray(H, float), corners[:, 0], corners[:, 1])]
    b = np.c_[apply_h(Hc, corners[:, 0], corners[:, 1])]
    moved = float(np.hypot(*(a - b).T).max()) / map_px
    cv = info.get("cv_rms_px") or {}
    rec = {"accepted": bool(info["accepted"]), "moved_corners_map_px": moved,
           "tie_points": info.get("tie_points"), "cover": info.get("cover"),
           "cv_rms_map_px": {k: cv[k] for k in ("refit", "feature") if k in cv},
           "reason": info.get("reason"), "seconds": info.get("seconds")}  # fmt: skip
    return Hr, rec


def verify(q_u8: np.ndarray, H: np.ndarray, ortho: MapImage,
           conf: dict[str, Any] | None = None) -> tuple[np.ndarray, dict[str, Any]]:  # fmt: skip
    """Refit H densely (``refit``), then :func:`check` the fit to use: the refit when its CV
    says it is better, else H. When the refit was taken but does not agree, H is checked too
    and kept if it agrees. Returns (homography to use, record)."""
    t0 = time.perf_counter()
    c = {**DEFAULTS, **(conf or {})}
    H = np.asarray(H, float)
    rf: dict[str, Any] | None = None
    Hr = H
    if c["refit"]:
        Hr, rf = refit(q_u8, H, ortho, c)
    rec = check(q_u8, Hr, ortho, c)
    use = Hr
    if rf is not None and rf["accepted"] and rec["outcome"] != "agrees":
        at_h = check(q_u8, H, ortho, c)
        if at_h["outcome"] == "agrees":
            rec, use = at_h, H
    if rf is not None:
        rf["kept"] = bool(rf["accepted"] and use is Hr)
        rec["refit"] = rf
    rec["seconds"] = time.perf_counter() - t0
    return use, rec


def window_image(read_window: Any, H: np.ndarray, shape: tuple[int, ...],
                 c: dict[str, Any]) -> MapImage | None:  # fmt: skip
    """The orthophoto around the footprint of a query of ``shape`` at H through the fuse step's
    window reader (``read_window(bounds)`` -> (gray, NaN = nodata; 3 x 3 pixel centre -> map) or
    None, :func:`georeg.register.fuse.ortho_window_reader`), grown by what the moved hypotheses
    and the tie-point search reach; None when the footprint misses the orthophoto."""
    from rasterio.transform import Affine

    h, w = shape[-2:]
    u, v = np.meshgrid(np.linspace(0, w - 1, 9), np.linspace(0, h - 1, 9))
    x, y = apply_h(np.asarray(H, float), u, v)
    if not (np.isfinite(x).all() and np.isfinite(y).all()):
        return None
    box = (float(x.min()), float(y.min()), float(x.max()), float(y.max()))
    got = read_window(box)
    if got is None:
        return None
    px = float(np.hypot(got[1][0, 0], got[1][1, 0]))  # map units per orthophoto pixel
    reach = (float(c["null_shift"]) + 1.0) * float(c["search_px"]) + float(c["window_px"]) / 2
    m = (reach * max(1.0, float(c["map_px"])) + 2.0) * px
    got = read_window((box[0] - m, box[1] - m, box[2] + m, box[3] + m))
    if got is None:
        return None
    gray, A = got
    T = np.asarray(A, float) @ np.array([[1, 0, -0.5], [0, 1, -0.5], [0, 0, 1.0]])
    return MapImage(np.asarray(gray, np.float32), Affine(*T[:2].ravel()))


def due(fused: dict[str, Any], c: dict[str, Any]) -> bool:
    """Whether the check runs on this fused result (registered, few enough inliers)."""
    if c["mode"] == "off" or fused.get("homography") is None:
        return False
    cap = int(c["max_inliers"])
    return cap <= 0 or int(fused.get("inliers") or 0) <= cap


def apply(q_u8: np.ndarray, fused: dict[str, Any], read_window: Any,
          reg_conf: dict[str, Any] | None) -> tuple[dict[str, Any], dict[str, Any] | None]:  # fmt: skip
    """The fuse step's check of a registered result: refit and verify and, with ``mode: reject``, turn a fit that disagrees into ``not_found``. ``q_u8``: the query
    band(s), the primary first; ``read_window``: the orthophoto window reader (None: skipped).
    Returns the (possibly changed) fused result and the record (None when ``mode: off`` or
    nothing was registered)."""
    c = ortho_conf(reg_conf)
    if c["mode"] == "off" or fused.get("homography") is None:
        return fused, None
    rec: dict[str, Any] = {"mode": c["mode"], "max_inliers": int(c["max_inliers"]),
                           "outcome": "skipped"}  # fmt: skip
    if not due(fused, c):
        rec["reason"] = f"{fused.get('inliers')} inliers > max_inliers"
        return fused, rec
    band = q_u8[0] if q_u8.ndim == 3 else q_u8
    H = np.asarray(fused["homography"], float)
    img = None if read_window is None else window_image(read_window, H, band.shape, c)
    if img is None:
        rec["reason"] = "no orthophoto over the footprint"
        return fused, rec
    _, got = verify(band, H, img, c)
    rec.update(got)
    # a feature re-match guided by a rift-family pose is a feature fit and meets the floor of
    # feature fits
    polished = fused.get("pose_source") in POLISHED_SOURCES
    rec["veto_gain"] = 0.0 if polished else float(c["veto_gain"])
    log.info("ortho check: %s, supported %.3f (x%.1f the moved hypotheses)",
             rec["outcome"], rec.get("supported", 0.0), rec.get("gain", 0.0))  # fmt: skip
    return veto(fused, rec), rec


def veto(fused: dict[str, Any], rec: dict[str, Any] | None) -> dict[str, Any]:
    """The fused result, turned ``not_found`` when the check's gain is below its ``veto_gain``
    (the tie points support a pose moved by a few pixels nearly as well: a weak fit at the wrong
    place, or a GT-level near miss), or with ``mode: reject`` when the check disagrees."""
    if not rec:
        return fused
    g, floor = rec.get("gain"), float(rec.get("veto_gain") or 0.0)
    if g is not None and floor > 0 and g < floor:
        why = (f"the orthophoto's tie points support moved poses nearly as well as the "
               f"registration (gain {g:.2f} < ortho_check.veto_gain {floor:g})")  # fmt: skip
    elif rec.get("mode") == "reject" and rec.get("outcome") == "disagrees":
        why = "the orthophoto's tie points do not support the registration (ortho_check)"
    else:
        return fused
    return {**fused, "status": "not_found", "homography": None, "reason": why}
