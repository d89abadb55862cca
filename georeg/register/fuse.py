"""Fuse the parts' winners: check agreement, re-match the whole query in the winning neighbourhood.

The paper's two halves came out slightly misaligned; here the full query is re-matched in the
neighbourhood the best part found and one homography is estimated from all inliers.
"""

from __future__ import annotations

import logging
import time
from itertools import combinations
from typing import Any

import numpy as np

from georeg.register import lidar_check, matching, ortho_check
from georeg.register.search import (
    MapSource,
    QueryFeatures,
    index_rank,
    query_features,
    search_count,
    search_one_part,
    search_part,
    verify,
)
from georeg.register.small import null_check, small_fallback

log = logging.getLogger(__name__)


def sample_grid(
    width: int, height: int, rows: tuple[int, int] | None = None, n: int = 16
) -> np.ndarray:
    """An n x n grid of query pixel positions over the footprint (or over ``rows``)."""
    r0, r1 = rows if rows is not None else (0, height)
    u = np.linspace(0, width - 1, n)
    v = np.linspace(r0, max(r0, r1 - 1), n)
    gu, gv = np.meshgrid(u, v)
    return np.c_[gu.ravel(), gv.ravel()]


def disagreement_m(Ha: np.ndarray, Hb: np.ndarray, pts: np.ndarray) -> dict[str, float]:
    """Distance in map units between two homographies' predictions at query points."""
    d = np.linalg.norm(matching.apply_h(Ha, pts) - matching.apply_h(Hb, pts), axis=1)
    d = np.where(np.isfinite(d), d, np.inf)
    return {"median": float(np.median(d)), "max": float(d.max())}


def footprint_bounds(
    H: np.ndarray, width: int, height: int, margin: float
) -> tuple[float, float, float, float]:
    """Map bounding box of the query footprint through H, grown by ``margin``."""
    p = matching.apply_h(H, sample_grid(width, height, n=8))
    return (
        float(p[:, 0].min() - margin),
        float(p[:, 1].min() - margin),
        float(p[:, 0].max() + margin),
        float(p[:, 1].max() + margin),
    )


def fuse(
    full: QueryFeatures,
    source: MapSource,
    parts: list[dict[str, Any]],
    conf: dict[str, Any],
    gsd_m: float | None,
    seed: int = 0,
) -> dict[str, Any]:
    """Combine part results into one registration of the whole query (``conf`` = ``register``)."""
    t0 = time.perf_counter()
    fc = conf.get("fuse", {})
    width, height = full.width, full.height
    acc = [p for p in parts if p.get("accepted")]
    out: dict[str, Any] = {"parts_accepted": [p["part"] for p in acc]}
    if not acc:
        reasons = "; ".join(
            f"{_part_name(p)}: {p['candidates_tried']} candidate(s) tried, none accepted"
            for p in parts
            if not p.get("skipped")
        )
        out.update(status="not_found", reason=reasons or "no part", homography=None)
        return out
    Hs = {p["part"]: np.array(p["homography"]) for p in acc}
    # before: the parts' own homographies compared over the whole footprint and at their seam
    grid = sample_grid(width, height)
    before: dict[str, Any] = {}
    for a, b in combinations(sorted(Hs), 2):
        seam_row = parts[b]["rows"][0] if b < len(parts) else height // 2
        seam = np.c_[np.linspace(0, width - 1, 32), np.full(32, float(seam_row))]
        before[f"{a}-{b}"] = {
            "footprint_m": disagreement_m(Hs[a], Hs[b], grid),
            "seam_m": disagreement_m(Hs[a], Hs[b], seam),
        }
    out["disagreement_before"] = before
    # the best part (lowest NFA, then most inliers) and the parts that agree with it
    best = min(acc, key=lambda p: (p.get("log10_nfa") or 0.0, -p["inliers"]))
    Hb = Hs[best["part"]]
    tol = float(fc.get("agree_m", 25.0))
    agree = [p["part"] for p in acc if disagreement_m(Hb, Hs[p["part"]], grid)["median"] <= tol]
    out["best_part"] = best["part"]
    out["agreeing_parts"] = agree
    if len(acc) > 1 and len(agree) < len(acc):
        log.warning(
            "parts %s disagree with part %s by more than %.0f m",
            sorted(set(Hs) - set(agree)),
            best["part"],
            tol,
        )
    # re-match the full query in the winning neighbourhood
    margin = float(fc.get("margin_m", 50.0))
    region = footprint_bounds(Hb, width, height, margin)
    rec, m, fit = verify(
        full,
        source,
        region,
        conf,
        gsd_m,
        n_candidates=1,
        seed=seed,
        max_matches=int(fc.get("max_matches", 0)),
        guide=(Hb, float(fc.get("guide_radius_m", 30.0))),
    )
    out["fused_candidate"] = {k: v for k, v in rec.items() if k != "homography"}
    if rec["accepted"] and fit is not None and m is not None:
        H = fit.H
        inl = fit.inliers
        out.update(
            status="registered",
            method="fused",
            homography=H.tolist(),  # type: ignore[union-attr]
            inliers=fit.n_inliers,
            matches=len(m),
            residual_px=fit.rms_px,
            log10_nfa=rec.get("log10_nfa"),
            region=list(region),
        )
        # after: each part's own area under the fused homography vs its own fit, and inlier residuals
        after = {}
        res_m = fit.residual_px * source.gsd_m
        for p in parts:
            if p.get("skipped"):
                continue
            r0, r1 = p["rows"]
            sel = inl & (m.q_xy[:, 1] >= r0) & (m.q_xy[:, 1] < r1)
            entry: dict[str, Any] = {
                "inliers": int(sel.sum()),
                "residual_rms_m": float(np.sqrt(np.mean(res_m[sel] ** 2))) if sel.any() else None,
            }
            if p["part"] in Hs:
                entry["vs_part_homography_m"] = disagreement_m(
                    H, Hs[p["part"]], sample_grid(width, height, (r0, r1))
                )
            after[str(p["part"])] = entry
        out["disagreement_after"] = after
    else:
        # the fused fit failed: keep the best part (its homography already passed acceptance)
        log.warning(
            "full-query re-match not accepted (%s): using part %s", rec.get("reason"), best["part"]
        )
        out.update(
            status="registered",
            method="best_part",
            homography=Hb.tolist(),
            inliers=best["inliers"],
            matches=best.get("matches"),
            residual_px=best.get("residual_px"),
            log10_nfa=best.get("log10_nfa"),
            region=best.get("region"),
        )
    out["seconds"] = time.perf_counter() - t0
    return out


def _part_name(p: dict[str, Any]) -> str:
    return "whole query" if p.get("whole_query") else f"part {p['part']}"


def whole_query_fallback(
    full: QueryFeatures,
    source: MapSource,
    parts: list[dict[str, Any]],
    conf: dict[str, Any],
    gsd_m: float | None,
    seed: int = 0,
) -> tuple[list[dict[str, Any]], dict[str, Any]]:
    """When the query was split and every part failed, search the whole query as one more part.

    Returns the parts (with the whole-query search appended when it ran) and the split record
    for registration.json: the plan the parts followed and whether the whole query was searched.
    """
    plan = dict(next((p["split"] for p in parts if p.get("split")), None) or {})
    skipped = [p["part"] for p in parts if p.get("skipped")]
    if skipped:
        plan["idle_part_jobs"] = skipped
    if plan.get("parts", 1) == 1:
        plan["whole_query_searched"] = "first, in part 0" if plan else "not recorded"
        return parts, plan
    if any(p.get("accepted") for p in parts) or not plan.get("whole_if_parts_fail", True):
        plan["whole_query_searched"] = "no"
        return parts, plan
    log.info("every part failed: searching the whole query")
    whole = search_part(full, source, conf, gsd_m, seed + 1000 * len(parts), search_count(plan))
    whole.update(part=len(parts), whole_query=True)
    plan["whole_query_searched"] = "after every part failed"
    return [*parts, whole], plan


def first_accepted_window(windows: list[tuple[float, ...]], read_window: Any, register: Any,
                          parts: list[dict[str, Any]], height: int, flag: str,
                          keys: tuple[str, ...] = (), grow: float = 0.0,
                          ) -> tuple[list[dict[str, Any]], dict[str, Any]]:  # fmt: skip
    """A fallback's loop over candidate windows: each window (grown by ``grow`` map units) read
    by ``read_window``, then ``register(k, gray, A, bounds)``; the first accepted record becomes
    one more whole-query part, marked ``flag``. Returns the parts and the record of the windows
    tried (their bounds, acceptance, inliers, NFA, reason, seconds and ``keys``)."""
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
            return [*parts, part], {"ran": True, "windows": tried, "accepted_window": k}
    return parts, {"ran": True, "windows": tried, "accepted_window": None}


def register_query(
    u8: np.ndarray,
    source: MapSource,
    conf: dict[str, Any],
    gsd_m: float | None,
    factors: list[float],
    seed: int = 0,
    read_window: Any = None,
) -> dict[str, Any]:
    """The workflow's search_part jobs and fuse_parts in one process: split plan, every part,
    the whole-query fallback, the small-query and dense fallbacks (when ``read_window`` is
    given, see ``georeg.register.small.small_fallback`` and ``dense_fallback``), fusion. Returns the fused result with ``split`` and ``parts``."""
    h = u8.shape[-2]
    full = query_features(u8, (0, h), factors, source.features_conf)
    n = int(conf.get("parts", 2))
    parts = [search_one_part(u8, k, source, conf, gsd_m, factors, seed, full) for k in range(n)]
    parts, split = whole_query_fallback(full, source, parts, conf, gsd_m, seed)
    if read_window is not None:
        parts, split["small"] = small_fallback(u8, full, source, parts, conf, gsd_m, read_window,
                                               seed)  # fmt: skip
    fused = fuse(full, source, parts, conf, gsd_m, seed)
    fused, nrec = null_check(u8, fused, source, conf, gsd_m, read_window, split.get("small"))
    fused, orec = ortho_check.apply(u8, fused, read_window, conf)
    return {**fused, "split": split, "parts": parts, "null_check": nrec, "ortho_check": orec}


def run_fuse_parts(
    band_tif: str,
    band_json: str,
    part_jsons: list[str],
    index_path: str,
    grid_path: str | None,
    dsm: str | None,
    truth: str | None,
    reg_conf: dict[str, Any],
    seed: int,
    out_json: str,
    out_geoloc: str,
    ortho: str | None = None,
) -> dict[str, Any]:
    """Rule fuse_parts: fuse, write geolocation.tif (all NaN when not found) and registration.json.

    ``ortho``: the orthophoto mosaic, read for the small-query and dense fallbacks when no search
    was accepted and for the check of an accepted fit (``georeg.register.ortho_check``)."""
    import json
    from pathlib import Path

    from georeg.io.atomic import write_json
    from georeg.register.band import feature_scales, read_query_bands
    from georeg.register.geolocation import evaluate, write_geolocation
    from georeg.register.search import gsd_in_map_units, load_source

    t0 = time.perf_counter()
    meta = json.loads(Path(band_json).read_text())
    parts = sorted((json.loads(Path(p).read_text()) for p in part_jsons), key=lambda p: p["part"])
    source = load_source(index_path, grid_path)
    u8 = read_query_bands(band_tif)  # every pooled band, the primary first
    h, w = u8.shape[-2:]
    gsd = gsd_in_map_units(meta.get("gsd_m"), source.crs_wkt)
    timings: dict[str, Any] = {
        "query_band": meta.get("seconds"),
        "search_parts": {str(p["part"]): p.get("seconds") for p in parts},
    }
    fused: dict[str, Any]
    t1 = time.perf_counter()
    factors = feature_scales(gsd, source.gsd_m, reg_conf.get("unknown_gsd_factors", [1.0]))
    full = query_features(u8, (0, h), factors, source.features_conf)
    timings["fuse_features"] = time.perf_counter() - t1
    t1 = time.perf_counter()
    parts, split = whole_query_fallback(full, source, parts, reg_conf, gsd, seed)
    if split.get("whole_query_searched") == "after every part failed":
        timings["whole_query_search"] = time.perf_counter() - t1
    t1 = time.perf_counter()
    reader = None if not ortho else ortho_window_reader(ortho)
    parts, split["small"] = small_fallback(u8, full, source, parts, reg_conf, gsd, reader, seed)
    if split["small"].get("ran"):
        timings["small_search"] = time.perf_counter() - t1
    t1 = time.perf_counter()
    fused = fuse(full, source, parts, reg_conf, gsd, seed)
    timings["fuse_match"] = time.perf_counter() - t1
    t1 = time.perf_counter()
    fused, nrec = null_check(u8, fused, source, reg_conf, gsd, reader, split.get("small"))
    if nrec is not None:
        timings["null_check"] = time.perf_counter() - t1
    t1 = time.perf_counter()
    fused, orec = ortho_check.apply(u8, fused, reader, reg_conf)
    if orec is not None and orec.get("seconds") is not None:
        timings["ortho_check"] = time.perf_counter() - t1
    H = None if fused.get("homography") is None else np.array(fused["homography"])
    t1 = time.perf_counter()
    lidar = lidar_check.run_check(u8[0], H, dsm, reg_conf)
    if lidar is not None:
        timings["lidar_check"] = time.perf_counter() - t1
        fused = lidar_check.veto(fused, lidar)
        H = None if fused.get("homography") is None else H
    t1 = time.perf_counter()
    geo = write_geolocation(out_geoloc, H, w, h, dsm, source.crs_wkt)
    timings["geolocation"] = time.perf_counter() - t1
    map_px = _map_px(grid_path) or source.gsd_m
    reg: dict[str, Any] = {
        "status": fused["status"],
        "query": meta.get("image"),
        "band": meta.get("band"),
        "pooled_bands": [
            {k: b.get(k) for k in ("index", "wavelength_nm")}
            for b in meta.get("pooled_bands") or [meta.get("band") or {}]
        ],
        "width": w,
        "height": h,
        "crs": source.crs_wkt,
        "homography": fused.get("homography"),
        "homography_convention": "query pixel centre (col, row) -> map (x, y), [x y w] = H [col row 1]",
        "inliers": fused.get("inliers", 0),
        "matches": fused.get("matches"),
        "residual_px": fused.get("residual_px"),
        "log10_nfa": fused.get("log10_nfa"),
        "strategy": reg_conf.get("strategy"),
        "rank": index_rank(reg_conf),
        "acceptance": (reg_conf.get("acceptance") or {}).get("mode", "nfa"),
        "map_px_m": map_px,
        "feature_gsd_m": source.gsd_m,
        "candidates_tried": int(sum(p.get("candidates_tried", 0) for p in parts)),
        "split": split,
        "parts": [
            {
                "part": p["part"],
                "rows": p["rows"],
                "whole_query": p["rows"] == [0, h],
                "small": bool(p.get("small")),
                "skipped": bool(p.get("skipped")),
                "accepted": p["accepted"],
                "candidates_tried": p["candidates_tried"],
                "inliers": p["inliers"],
                "log10_nfa": p.get("log10_nfa"),
                "homography": p.get("homography"),
                "seconds": p.get("seconds"),
            }
            for p in parts
            if not p.get("skipped")
        ],
        "fuse": {k: v for k, v in fused.items() if k not in ("homography", "status", "reason")},
        "geolocation": {"path": str(out_geoloc), **geo},
    }
    if fused["status"] != "registered":
        reg["reason"] = fused.get("reason")
    if nrec is not None:
        reg["null_check"] = nrec
    if orec is not None:
        reg["ortho_check"] = orec
    if lidar is not None:
        reg["lidar_check"] = lidar
    if truth:
        t1 = time.perf_counter()
        reg["evaluation"] = evaluate(H, truth, map_px)
        timings["evaluation"] = time.perf_counter() - t1
    timings["fuse_total"] = time.perf_counter() - t0
    reg["timings_s"] = timings
    write_json(out_json, reg)
    return reg


def ortho_window_reader(ortho: str) -> Any:
    """bounds -> (gray window, NaN = nodata; 3 x 3 window pixel centre -> map x, y) or None."""
    from georeg.io.errors import InputError
    from georeg.register.tiepoints import read_map_gray

    def read(b: tuple[float, ...]) -> tuple[np.ndarray, np.ndarray] | None:
        try:
            mi = read_map_gray(ortho, np.array([b[0], b[2]]), np.array([b[1], b[3]]), pad=0.0)
        except InputError:
            return None
        a, bb, c, d, e, f = (float(v) for v in tuple(mi.transform)[:6])
        A = np.array([[a, bb, c], [d, e, f], [0, 0, 1.0]]) @ np.array(
            [[1, 0, 0.5], [0, 1, 0.5], [0, 0, 1.0]]
        )
        return mi.gray, A

    return read


def _map_px(grid_path: str | None) -> float | None:
    """Orthophoto pixel size from grid.json (map pixels for error reports)."""
    import json
    from pathlib import Path

    if not grid_path or not Path(grid_path).exists():
        return None
    return abs(float(json.loads(Path(grid_path).read_text())["transform"][0]))
