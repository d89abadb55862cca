"""Check a registration against the map's elevation, a modality that does not depend on the spectrum.

Building and terrain edges in a LiDAR DSM (or nDSM) show up in any band of the query. Given the
query band and a query -> map homography H, both images are shrunk so that the query is at most
``max_side`` pixels across, the elevation layer is rendered into that query geometry through H,
and both become CFOG structure channels (:func:`georeg.register.tiepoints.cfog`, which ignore
contrast reversals). Tie points are measured as in the refinement
(:func:`georeg.register.tiepoints.measure_shifts`: windows of ``window_px`` on a ``grid_step_px``
grid, integer shifts up to ``search_px``): a point is *coherent* when its peak score is at least
``min_score``, not on the search border, and its shift lies within ``coherent_px`` of the median
shift. The same measure is taken at four perturbed hypotheses (H moved by ``null_shift`` x
``search_px`` shrunk pixels left, right, up, down in the query): where the elevation does not
match, the coherent fraction is what chance gives, so the hypotheses around H say what the
elevation shows by chance over this very footprint.

Outcome (``lidar_check.outcome`` in registration.json):

- ``agrees``: the coherent fraction at H is at least ``min_coherent`` and ``min_gain`` times the
  best perturbed hypothesis, and the median shift is within ``max_offset_px`` map pixels;
- ``disagrees``: coherent, but the elevation puts the query ``offset_map_px`` away from H, or
  a perturbed hypothesis is coherent (``min_gain`` times H) instead (errors of a few to about
  ``null_shift`` x ``search_px`` shrunk px; larger ones leave no coherence: ``inconclusive``);
- ``inconclusive``: no coherence above chance (a wrong place, or flat / too coarse elevation);
- ``skipped``: no elevation over the footprint (a map without LiDAR or DEM: heights are nodata),
  or fewer than ``min_points`` measurable tie points.

A peak score of one correlation surface is not used as a significance: the surface is spatially
correlated (docs/BENCHMARKS.md "Cross-spectral matching"); the perturbed hypotheses stand in.
"""

from __future__ import annotations

import logging
import time
from pathlib import Path
from typing import Any

import numpy as np

from georeg.register.dense import _shrink
from georeg.register.geolocation import apply_h, ground_px
from georeg.register.tiepoints import MapImage, cfog, grid_points, measure_shifts

log = logging.getLogger(__name__)

DEFAULTS: dict[str, Any] = {
    "mode": "record",  # off | record (registration.json only) | reject (disagrees -> not_found)
    "layer": "dsm",  # dsm | ndsm: the elevation layer whose edges are matched
    "max_side": 400,  # query px across after shrinking (resolution of the check)
    "grid_step_px": 16,  # tie-point grid step (shrunk px)
    "window_px": 32,  # tie-point window (shrunk px)
    "search_px": 6,  # integer search radius (shrunk px)
    "min_score": 0.15,  # tie-point peak NCC
    "coherent_px": 1.5,  # shift within this of the median shift (shrunk px)
    "null_shift": 3.0,  # perturbed hypotheses: H moved by this x search_px (shrunk px)
    "min_points": 50,  # measurable tie points needed (valid windows)
    "min_coherent": 0.08,  # coherent fraction at H
    "min_gain": 3.0,  # ... and this times the best perturbed hypothesis's
    "max_offset_px": 3.0,  # agreement: median shift within this many map px
    "min_valid_frac": 0.5,  # elevation valid over at least this fraction of the footprint
}
MODES = ("off", "record", "reject")
LAYERS = ("dsm", "ndsm")


def lidar_conf(reg_conf: dict[str, Any] | None) -> dict[str, Any]:
    """``register.lidar_check`` with defaults; a bad mode or layer raises ValueError."""
    c = {**DEFAULTS, **((reg_conf or {}).get("lidar_check") or {})}
    if c["mode"] is False:  # YAML 1.1 reads an unquoted off as false
        c["mode"] = "off"
    if c["mode"] not in MODES:
        raise ValueError(f"register.lidar_check.mode must be one of {MODES}, got {c['mode']!r}")
    if c["layer"] not in LAYERS:
        raise ValueError(f"register.lidar_check.layer must be one of {LAYERS}, got {c['layer']!r}")
    return c


def _coherence(
    qf: np.ndarray, qm: np.ndarray, rendered: np.ndarray, pts: np.ndarray, c: dict[str, Any]
) -> tuple[float, int, np.ndarray]:
    """(coherent fraction of the valid tie points, valid tie points, median shift (shrunk px))."""
    rv = np.isfinite(rendered)
    rf = cfog(np.where(rv, rendered, 0).astype(np.float32), rv)
    m = measure_shifts(qf, rf, qm, rv, pts, int(c["window_px"]), int(c["search_px"]))
    ok = (m["score"] >= float(c["min_score"])) & ~m["border"] & m["valid"]
    n = int(m["valid"].sum())
    if not ok.any():
        return 0.0, n, np.array([np.nan, np.nan])
    med = np.median(m["shift"][ok], 0)
    coh = int((np.hypot(*(m["shift"][ok] - med).T) <= float(c["coherent_px"])).sum())
    return coh / max(n, 1), n, med


def check(
    q_u8: np.ndarray,
    H: np.ndarray,
    elevation: MapImage,
    conf: dict[str, Any] | None = None,
) -> dict[str, Any]:
    """Compare the elevation's agreement with the query at H and at perturbed hypotheses.

    ``q_u8``: the query band (uint8, 0 = nodata); ``H``: 3 x 3, query pixel centre (col, row) ->
    map (x, y); ``elevation``: the elevation layer around the footprint (NaN = nodata);
    ``conf``: :data:`DEFAULTS` overrides. Returns the record written to registration.json.
    """
    t0 = time.perf_counter()
    c = {**DEFAULTS, **(conf or {})}
    H = np.asarray(H, np.float64)
    h, w = q_u8.shape
    rec: dict[str, Any] = {"layer": c["layer"], "outcome": "skipped"}
    s = min(1.0, float(c["max_side"]) / max(h, w))
    qs, qm = _shrink(q_u8.astype(np.float32), q_u8 > 0, s)
    hs, ws = qs.shape
    # shrunk pixel centres in query px: u = (u' + 0.5) / s - 0.5
    u = (np.arange(ws) + 0.5) / s - 0.5
    v = (np.arange(hs) + 0.5) / s - 0.5

    def render(dx: float, dy: float) -> np.ndarray:
        return elevation.render(*apply_h(H, u[None, :] + dx / s, v[:, None] + dy / s))

    at_h = render(0.0, 0.0)
    frac = float(np.isfinite(at_h[qm]).mean()) if qm.any() else 0.0
    rec["valid_frac"] = frac
    if frac < float(c["min_valid_frac"]):
        rec.update(reason="no elevation over the footprint", seconds=time.perf_counter() - t0)
        return rec
    qf = cfog(qs, qm)
    pts = grid_points(ws, hs, int(c["grid_step_px"]), int(c["window_px"]))
    coh, n, med = _coherence(qf, qm, at_h, pts, c)
    if n < int(c["min_points"]):
        rec.update(reason=f"{n} measurable tie points", seconds=time.perf_counter() - t0)
        return rec
    d = float(c["null_shift"]) * float(c["search_px"])
    moves = ((d, 0.0), (-d, 0.0), (0.0, d), (0.0, -d))
    null = [_coherence(qf, qm, render(dx, dy), pts, c) for dx, dy in moves]
    scale = ground_px(H, w, h) / abs(float(elevation.transform[0])) / s  # map px / shrunk px
    best = max(x[0] for x in null)
    rec.update(
        coherent=coh,
        coherent_null=[x[0] for x in null],
        gain=coh / max(best, 1.0 / n),
        tie_points=n,
        offset_map_px=float(np.hypot(*med)) * scale if np.isfinite(med).all() else None,
        resolution_map_px=scale,
    )
    min_coh, min_gain = float(c["min_coherent"]), float(c["min_gain"])
    if coh >= min_coh and rec["gain"] >= min_gain:
        near = rec["offset_map_px"] <= float(c["max_offset_px"])
        rec["outcome"] = "agrees" if near else "disagrees"
    else:
        rec["outcome"] = "inconclusive"
        k = int(np.argmax([x[0] for x in null]))
        if best >= min_coh and best >= min_gain * max(coh, 1.0 / n):
            # a perturbed hypothesis matches: the elevation puts the query there
            rec["outcome"] = "disagrees"
            tot = np.asarray(moves[k]) + null[k][2]
            rec["offset_map_px"] = float(np.hypot(*tot)) * scale
    rec["seconds"] = time.perf_counter() - t0
    return rec


def elevation_path(dsm: str | None, layer: str) -> str | None:
    """The mosaic of ``layer`` next to the DSM mosaic (``results/map/mosaic/<layer>.vrt``)."""
    if not dsm:
        return None
    p = Path(dsm)
    q = p if layer == "dsm" else p.with_name(f"{layer}{p.suffix}")
    return str(q) if q.exists() else None


def read_elevation(
    path: str, shape: tuple[int, ...], H: np.ndarray, conf: dict[str, Any] | None = None
) -> MapImage | None:
    """The elevation raster around the footprint of a query of ``shape`` (rows, cols) at H,
    grown by what the perturbed hypotheses and the tie-point search reach; None when the
    footprint misses the raster."""
    from georeg.io.errors import InputError
    from georeg.register.tiepoints import read_map_gray

    c = {**DEFAULTS, **(conf or {})}
    h, w = shape[-2:]
    s = min(1.0, float(c["max_side"]) / max(h, w))
    reach = (float(c["null_shift"]) + 1.0) * float(c["search_px"]) + float(c["window_px"]) / 2
    m = reach / s + 2.0  # query px
    u, v = np.meshgrid(np.linspace(-m, w + m, 17), np.linspace(-m, h + m, 17))
    x, y = apply_h(np.asarray(H, float), u, v)
    try:
        return read_map_gray(path, x, y, pad=2.0)
    except InputError:
        return None


def run_check(
    q_u8: np.ndarray, H: np.ndarray | None, dsm: str | None, reg_conf: dict[str, Any] | None
) -> dict[str, Any] | None:
    """The check of a fused registration in the workflow; None when ``mode: off`` or no H."""
    c = lidar_conf(reg_conf)
    if c["mode"] == "off" or H is None:
        return None
    path = elevation_path(dsm, c["layer"])
    base = {"mode": c["mode"], "layer": c["layer"], "outcome": "skipped"}
    if path is None:
        return {**base, "reason": "no elevation layer"}
    elev = read_elevation(path, q_u8.shape, H, c)
    if elev is None:
        return {**base, "reason": "the footprint does not overlap the elevation"}
    rec = check(q_u8, np.asarray(H, float), elev, c)
    log.info("lidar check (%s): %s, coherent %.3f (x%.1f the perturbed), offset %.2f map px",
             c["layer"], rec["outcome"], rec.get("coherent", 0.0), rec.get("gain", 0.0),
             rec.get("offset_map_px") or 0.0)  # fmt: skip
    return {"mode": c["mode"], **rec}


def veto(fused: dict[str, Any], rec: dict[str, Any] | None) -> dict[str, Any]:
    """The fused result, turned ``not_found`` when ``mode: reject`` and the elevation disagrees."""
    if not rec or rec.get("mode") != "reject" or rec.get("outcome") != "disagrees":
        return fused
    why = "the elevation disagrees with the registration (lidar_check)"
    return {**fused, "status": "not_found", "homography": None, "reason": why}
