"""The fuse_parts step: the sources of candidates, the verifier's terms, the fusion.

The search_part jobs ran the first source (the features of each along-track part against the
index's candidate regions, ``georeg.register.search``). Here the remaining sources run in
``SOURCES`` order, each only while no candidate is accepted; each gets the same
``(QueryInput, MapView, parts, conf)`` and returns the parts with its accepted candidate added
and a record. The accepted candidates are fused (the full query re-matched in the neighbourhood
the best one found, one homography from all inliers: the paper's two halves came out slightly
misaligned), then checked by the verifier's dense terms (CFOG null scan, orthophoto, LiDAR).
``registration.json`` says which sources ran and which one was accepted (``sources``).
"""

from __future__ import annotations

import logging
import time
from collections.abc import Callable
from dataclasses import replace
from itertools import combinations
from typing import Any

import numpy as np

from georeg.io.prior import prior_bounds, prior_record
from georeg.register import acceptance, level, lidar_check, matching, ortho_check, rift, small
from georeg.register.search import (
    MapSource,
    MapView,
    QueryFeatures,
    QueryInput,
    index_rank,
    map_for_query,
    query_features,
    search_count,
    search_one_part,
    search_part,
    verify,
)

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

    def set_best(p: dict[str, Any]) -> list[int]:
        """Record ``p`` as the best part; the parts that agree with it."""
        agreeing = [q["part"] for q in acc
                    if disagreement_m(Hs[p["part"]], Hs[q["part"]], grid)["median"] <= tol]  # fmt: skip
        out.update(best_part=p["part"], best_source=p.get("method") or "features",
                   agreeing_parts=agreeing)  # fmt: skip
        return agreeing

    agree = set_best(best)
    if len(acc) > 1 and len(agree) < len(acc):
        log.warning(
            "parts %s disagree with part %s by more than %.0f m",
            sorted(set(Hs) - set(agree)),
            best["part"],
            tol,
        )
    # re-match the full query around the best part and around each accepted part that disagrees
    # with it (two parts at different places: at most one is right, and a part's fit may hold
    # on its own rows only; SRIF oo pair 129: a 13-inlier upper part 49 m from a 9-inlier lower
    # one, the re-match around the upper one 34 px off). The whole query's re-match decides:
    # the lowest NFA, each counted as one of the re-matches tried
    margin, radius = float(fc.get("margin_m", 50.0)), float(fc.get("guide_radius_m", 30.0))
    guides = [best] + [p for p in acc if p["part"] not in agree]
    tries = []
    for g in guides:
        Hg = Hs[g["part"]]
        reg = footprint_bounds(Hg, width, height, margin)
        # a part found at a guessed GSD (rift without the query's) is judged at the GSD its pose
        # found: the similarity fit takes scales up to rift.GUESS_SCALE from the guess, so judged
        # at the guess a true pose at 1.31x was refused (Landsat Pucallpa, session 41)
        got = verify(full, source, reg, conf, gsd_m or g.get("found_gsd"), n_candidates=len(guides), seed=seed,
                     max_matches=int(fc.get("max_matches", 0)), guide=(Hg, radius))  # fmt: skip
        tries.append((g, reg, *got))
    ok = [t for t in tries if t[2]["accepted"]]
    g, region, rec, m, fit = min(ok, key=lambda t: (t[2]["log10_nfa"], -t[2]["inliers"])) if ok else tries[0]
    if len(tries) > 1:
        out["rematches"] = [{"part": t[0]["part"], "accepted": t[2]["accepted"],
                             "inliers": t[2].get("inliers"), "log10_nfa": t[2].get("log10_nfa")}
                            for t in tries]  # fmt: skip
    if g is not best:  # the whole query sides with a part the best one disagreed with
        best, Hb = g, Hs[g["part"]]
        set_best(best)
    out["fused_candidate"] = {k: v for k, v in rec.items() if k != "homography"}
    # one model choice: the re-match is one more candidate. Its NFA is conditional on the guide,
    # so when it explains fewer matches or is less significant than the best part it may only
    # refine that pose (median move <= the inlier threshold), not move it: SIFT re-matches of 4
    # and 6 inliers had moved rift poses of 15 and 8 by 16 map px (SRIF wide oi 57, 77)
    best_nfa, best_inl = best.get("log10_nfa"), int(best.get("inliers") or 0)
    why = []
    if rec["accepted"] and int(rec.get("inliers") or 0) < best_inl:
        why.append(f"{rec.get('inliers')} inliers < the best part's {best_inl}")
    if (rec["accepted"] and best_nfa is not None and rec.get("log10_nfa") is not None
            and float(rec["log10_nfa"]) > float(best_nfa)):  # fmt: skip
        why.append(f"log10 NFA {rec['log10_nfa']:.1f} > the best part's {best_nfa:.1f}")
    weaker = False
    if why and fit is not None and fit.H is not None:
        move = disagreement_m(fit.H, Hb, grid)["median"]
        limit = float((conf.get("ransac") or {}).get("reproj_px", 3.0)) * source.gsd_m
        out["fused_candidate"]["moved_m"] = move
        weaker = move > limit
        why.append(f"it moves the pose by {move:.3g} > {limit:.3g} map units")
    if weaker:
        rec = {**rec, "reason": "; ".join(why)}
        out["fused_candidate"]["kept"] = False
    if rec["accepted"] and not weaker and fit is not None and m is not None:
        H = fit.H
        inl = fit.inliers
        out.update(
            status="registered",
            method="fused",
            pose_source="features",  # the re-match is a feature fit whatever guided it
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
        # the fused fit failed: keep the best part (its homography passed acceptance over the
        # part), if it is a plausible mapping of the whole query too: a part's homography may
        # hold on its own rows only (SRIF oo 77 in a 120-reference mosaic: a 14-inlier part whose
        # scale changes 1.8x across the whole query, 18.6 px off; no true accept of the records
        # was implausible so: docs/experiments/benchmark-history.md "Session 20")
        # judged on the ground: a pose found on pixels of another aspect (``MapView.aspect``)
        # maps the query's square pixels to map units that are not square on the ground
        a = float(best.get("aspect") or 1.0)
        whole = acceptance.plausibility(np.diag([a**-0.5, a**0.5, 1.0]) @ Hb, width, height,
                                        gsd_m or best.get("found_gsd"), conf.get("acceptance") or {})  # fmt: skip
        if not whole["ok"]:
            why = "; ".join(whole["reasons"])
            log.warning("full-query re-match not accepted (%s) and part %s's pose is not a "
                        "plausible mapping of the whole query (%s): not registered",
                        rec.get("reason"), best["part"], why)  # fmt: skip
            out.update(status="not_found", homography=None,
                       reason=f"part {best['part']}'s pose does not hold over the whole query: {why}")  # fmt: skip
        else:
            log.warning("full-query re-match not accepted (%s): using part %s",
                        rec.get("reason"), best["part"])  # fmt: skip
            out.update(
                status="registered",
                method="best_part",
                pose_source=out["best_source"],
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


def whole_query_source(
    q: QueryInput, view: MapView, parts: list[dict[str, Any]], conf: dict[str, Any]
) -> tuple[list[dict[str, Any]], dict[str, Any]]:
    """Source ``whole_query``: ``whole_query_fallback``; its record holds the split ``plan``."""
    n0 = len(parts)
    parts, plan = whole_query_fallback(q.features, view.source, parts, conf, q.gsd, q.seed)
    ran = plan.get("whole_query_searched") == "after every part failed"
    tried = sum(p.get("candidates_tried", 0) for p in parts[n0:])
    return parts, {"ran": ran, "candidates": tried, "plan": plan}


Source = Callable[
    [QueryInput, MapView, list[dict[str, Any]], dict[str, Any]],
    tuple[list[dict[str, Any]], dict[str, Any]],
]

#: the sources of candidates after the parts' feature search, in order; each runs only while no
#: candidate is accepted (and none on a query without structure: ``structureless``). A source is
#: one function with this signature: it returns the parts with its accepted candidate appended
#: (a part record) and its own record (``ran``, and ``candidates`` tried when it ran). Adding a
#: source is one entry here.
SOURCES: tuple[tuple[str, Source], ...] = (
    ("whole_query", whole_query_source),
    ("small_windows", small.window_source),
    ("cfog_null", small.null_source),
    ("rift", rift.source),
    ("reversed", rift.reversed_source),
    ("learned", rift.learned_source),
    ("elevation", rift.elevation_source),
    ("cfog_peaks", small.peaks_source),
)


#: a source's record when a candidate was accepted before it (``decide`` runs it in a second
#: pass when the verifier refuses that candidate)
SKIPPED = "a search was accepted"


def structureless(u8: np.ndarray) -> str | None:
    """Why the query (uint8, 0 = nodata; one band or a pooled stack) has nothing to match, or
    None: no valid pixel, or every band one value where it is valid. No source can accept
    such a query, so they are not run (a constant band went through all of them: 25 CPU s)."""
    bands = u8.reshape(-1, *u8.shape[-2:])
    valid = [b[b > 0] for b in bands]
    if not any(v.size for v in valid):
        return "the query has no valid pixel: nothing to match"
    if all(v.size == 0 or v.min() == v.max() for v in valid):
        return "the query is one value wherever it is valid: no structure to match"
    return None


#: a second-pass candidate whose footprint centre lies farther than this fraction of its
#: footprint's side from every refused candidate's is at another place: two candidates that each
#: passed their own a-contrario test disagree about where the query is, and neither is kept
ELSEWHERE_SIDE = 0.5


def elsewhere(refused: list[dict[str, Any]], new: list[dict[str, Any]],
              shape: tuple[int, int]) -> dict[str, Any] | None:  # fmt: skip
    """None when a candidate of ``new`` (the second pass's accepted parts) lies at the place of
    a ``refused`` one (the first pass's, refused by the verifier), or when either has no pose;
    else the nearest distance (map units), the new footprint's side and the reason."""
    h, w = shape
    centre = np.array([[w / 2, h / 2]])
    box = np.array([[0, 0], [w, 0], [w, h], [0, h]], float)
    best: dict[str, Any] | None = None
    for n in new:
        if n.get("homography") is None:
            return None
        Hn = np.array(n["homography"], float)
        c = matching.apply_h(Hn, box)
        side = float(np.sqrt(0.5 * abs(np.cross(c[2] - c[0], c[3] - c[1]))))
        for r in refused:
            if r.get("homography") is None:
                return None
            d = disagreement_m(np.array(r["homography"], float), Hn, centre)["median"]
            if d <= ELSEWHERE_SIDE * side:
                return None
            if best is None or d < best["distance_m"]:
                best = {"distance_m": round(d, 2), "side_m": round(side, 2)}
    if best is None:
        return None
    best["reason"] = (f"the second pass's candidate lies {best['distance_m']:.0f} map units from the "
                      f"refused one (footprint side {best['side_m']:.0f}): two candidates at "
                      "different places, the query's place is ambiguous")  # fmt: skip
    return best


def run_sources(
    q: QueryInput,
    view: MapView,
    parts: list[dict[str, Any]],
    conf: dict[str, Any],
    earlier: tuple[dict[str, Any], list[dict[str, Any]]] | None = None,
    blank: str | None = None,
) -> tuple[list[dict[str, Any]], dict[str, Any], list[dict[str, Any]], dict[str, float]]:
    """After the parts' feature search, every source of ``SOURCES`` in turn while nothing is
    accepted (the whole-query search also records the split plan). Each source sees, as
    ``q.tests_before``, the candidates tried by the feature search and the sources before it:
    its NFA counts them with its own (one a-contrario count for the whole search, so a source
    added at the end cannot add false accepts by testing on its own budget). ``earlier``: an
    earlier pass's source records and ``sources`` (``decide``'s second pass): only the sources it
    skipped run, after every test it made. ``blank``: why the query has nothing to match
    (``structureless``): no source but the whole-query search runs.

    Returns the parts (one more per accepted source), the split record of registration.json
    (the plan; ``small``: the small-query sources' records; ``sources_by_name``: every source's
    record, which ``decide`` takes out), the ``sources`` record (name, candidates tried,
    accepted, seconds of each source that ran) and their timings."""
    if earlier is None:
        recs: dict[str, dict[str, Any]] = {}
        ran = [{"name": "features", "accepted": any(p.get("accepted") for p in parts),
                "candidates": int(sum(p.get("candidates_tried", 0) for p in parts))}]  # fmt: skip
    else:
        recs, ran = dict(earlier[0]), list(earlier[1])
    timings: dict[str, float] = {}
    for name, fn in SOURCES:
        if name in recs and recs[name].get("reason") != SKIPPED:
            continue  # run in the earlier pass
        if any(p.get("accepted") for p in parts) and name != "whole_query":
            recs[name] = {"ran": False, "reason": SKIPPED}
            continue
        if blank and name != "whole_query":
            recs[name] = {"ran": False, "reason": blank}
            continue
        t0 = time.perf_counter()
        n0 = len(parts)
        q = replace(q, tests_before=int(sum(r["candidates"] for r in ran)))
        parts, recs[name] = fn(q, view, parts, conf)
        if recs[name].get("ran"):
            timings[name] = time.perf_counter() - t0
            ran.append({"name": name, "accepted": any(p.get("accepted") for p in parts[n0:]),
                        "candidates": int(recs[name].get("candidates", 0)),
                        "seconds": round(timings[name], 3)})  # fmt: skip
    split = dict(recs["whole_query"]["plan"])
    split["small"] = dict(recs.get("small_windows") or {})
    if (recs.get("cfog_null") or {}).get("ran"):
        split["small"]["cfog_null"] = recs["cfog_null"]
    if (recs.get("rift") or {}).get("ran"):
        split["rift"] = recs["rift"]
    if (recs.get("reversed") or {}).get("ran"):
        split["reversed"] = recs["reversed"]
    if recs.get("learned"):  # whether it ran or why not (not installed): results may differ
        split["learned"] = recs["learned"]
    if (recs.get("elevation") or {}).get("ran"):
        split["elevation"] = recs["elevation"]
    if (recs.get("cfog_peaks") or {}).get("ran"):
        split["cfog_peaks"] = recs["cfog_peaks"]
    split["sources_by_name"] = recs
    return parts, split, ran, timings


def decide(
    q: QueryInput,
    view: MapView,
    parts: list[dict[str, Any]],
    conf: dict[str, Any],
    dsm: str | None = None,
) -> tuple[dict[str, Any], dict[str, Any]]:
    """Sources (``run_sources``), then ``check_fused``: fusion and the verifier's terms. When the
    verifier refuses the accepted candidates and sources were skipped because of them, those
    candidates are marked refused (``refused``: the reason) and the skipped sources run in a
    second pass, counting every test of the first, and their candidate is verified the same way
    (SRIF optical-optical 7 on a 40-reference mosaic: part 0's pose did not hold over the whole
    query, and rift had not run). A second-pass candidate at another place than every refused
    one (``elsewhere``) is refused too: the refused candidate passed its own a-contrario test
    (Landsat Pucallpa, red/green 2015 on 2005: the feature pose 8 px from the truth, vetoed by the
    orthophoto check; rift then found a look-alike meander 186 px away). Returns the fused result and the record: ``split``, ``parts``,
    ``sources``, the terms' records (None when not run), ``timings_s`` and ``second_pass``."""
    blank = structureless(q.u8)
    parts, split, ran, timings = run_sources(q, view, parts, conf, blank=blank)
    recs = split.pop("sources_by_name")
    fused, rec = check_fused(q, view, parts, conf, split, dsm, timings)
    if blank and fused.get("status") != "registered":
        fused = {**fused, "reason": blank}
    skipped = [n for n, r in recs.items() if r.get("reason") == SKIPPED]
    if fused.get("status") == "registered" or not skipped:
        return fused, {**rec, "sources": ran, "second_pass": None}
    why = str(fused.get("reason") or "not registered")
    parts = [{**p, "accepted": False, "refused": why} if p.get("accepted") else p for p in parts]
    log.info("the verifier refused the accepted candidates (%s): %s run", why, ", ".join(skipped))
    parts, split, ran, t2 = run_sources(q, view, parts, conf, (recs, ran), blank=blank)
    split.pop("sources_by_name")
    timings.update(t2)
    second: dict[str, Any] = {"refused": why, "sources": skipped}
    far = elsewhere([p for p in parts if p.get("refused")], [p for p in parts if p.get("accepted")],
                    q.u8.shape[-2:])  # fmt: skip
    if far is not None:
        log.info("not registered: %s", far["reason"])
        second["elsewhere"] = far
        parts = [{**p, "accepted": False, "refused": far["reason"]} if p.get("accepted") else p for p in parts]
        fused = {**fused, "reason": far["reason"]}
    if not any(p.get("accepted") for p in parts):
        return fused, {**rec, "split": split, "parts": parts, "sources": ran, "second_pass": second}
    fused, rec = check_fused(q, view, parts, conf, split, dsm, timings)
    return fused, {**rec, "sources": ran, "second_pass": second}


def check_fused(
    q: QueryInput,
    view: MapView,
    parts: list[dict[str, Any]],
    conf: dict[str, Any],
    split: dict[str, Any],
    dsm: str | None,
    timings: dict[str, float],
) -> tuple[dict[str, Any], dict[str, Any]]:
    """Fusion (``fuse``), then the verifier's dense terms on the fused fit: the CFOG null scan
    (``small.null_check``, may replace a small query's fit), the orthophoto (``ortho_check``)
    and the map's elevation (``lidar_check``; ``dsm`` None: not run). Returns the fused result
    and the record: ``split``, ``parts``, the terms' records and ``timings_s``."""
    t1 = time.perf_counter()
    fused = fuse(q.features, view.source, parts, conf, q.gsd, q.seed)
    timings["fuse_match"] = time.perf_counter() - t1
    t1 = time.perf_counter()
    fused, nrec = small.null_check(q.u8, fused, view.source, conf, q.gsd, view.read_window,
                                   split.get("small"))  # fmt: skip
    if nrec is not None:
        timings["null_check"] = time.perf_counter() - t1
    t1 = time.perf_counter()
    fused, orec = ortho_check.apply(q.u8, fused, view.read_window, conf)
    fused = turn_weak_fit(q.u8, fused, view, conf, orec)
    if orec is not None and orec.get("seconds") is not None:
        timings["ortho_check"] = time.perf_counter() - t1
    t1 = time.perf_counter()
    fused, crec = context_refit(q.u8, fused, view, conf)
    if crec is not None:
        timings["context_refit"] = time.perf_counter() - t1
    H = None if fused.get("homography") is None else np.array(fused["homography"])
    t1 = time.perf_counter()
    lidar = lidar_check.run_check(q.primary, H, dsm, conf)
    if lidar is not None:
        timings["lidar_check"] = time.perf_counter() - t1
        fused = lidar_check.veto(fused, lidar)
    return fused, {"split": split, "parts": parts, "null_check": nrec, "ortho_check": orec,
                   "context_refit": crec, "lidar_check": lidar, "timings_s": timings}  # fmt: skip


def turn_weak_fit(u8: np.ndarray, fused: dict[str, Any], view: MapView, conf: dict[str, Any],
                  orec: dict[str, Any] | None) -> dict[str, Any]:
    """A feature fit the orthophoto check was due for (few inliers, ``ortho_check.max_inliers``)
    turned as rift's poses are (``rift.turned``, ``rift.turn_deg``; ``orec["turn"]``): the
    similarity the fit makes at the footprint's centre moved to the peak of the whole
    footprint's CFOG correlation with the orthophoto. A fit through a few inliers of one part
    extrapolates over the rest (SRIF optical-optical 131: a 24-inlier homography whose scale
    changes 1.38-1.77 across the query, 16 px off -> 11.6 px; 195: 8.5 -> 1.6 px; session 44).
    Rift's own poses are turned already; a map whose pixels are not square on the ground
    (``MapView.aspect``) is left alone (a similarity in its units is not one on the ground)."""
    deg = float(rift.rift_conf(conf.get("rift"))["turn_deg"])
    if (orec is None or fused.get("homography") is None or deg <= 0 or view.read_window is None
            or fused.get("pose_source") in ortho_check.POLISHED_SOURCES or abs(view.aspect - 1.0) > 1e-6
            or not ortho_check.due(fused, ortho_check.ortho_conf(conf))):  # fmt: skip
        return fused
    band = u8[0] if u8.ndim == 3 else u8
    h, w = band.shape
    S = centre_similarity(np.asarray(fused["homography"], float), w, h)
    H2, orec["turn"] = rift.turned(band, S, view.read_window, conf, deg, found=S)
    if orec["turn"] is None or orec["turn"].get("score") is None:
        return fused
    return {**fused, "homography": (H2 / H2[2, 2]).tolist()}


def context_refit(u8: np.ndarray, fused: dict[str, Any], view: MapView, conf: dict[str, Any]
                  ) -> tuple[dict[str, Any], dict[str, Any] | None]:  # fmt: skip
    """With the learned extra (``register.learned``), the registered pose re-fit by LightGlue's
    context matching against the orthophoto (``rift.context_refit``: the ground where our
    keypoints took the roofs). Returns the result and the record (None: not run)."""
    if (fused.get("homography") is None or view.read_window is None
            or abs(view.aspect - 1.0) > 1e-6 or not rift.learned_on(conf)):  # fmt: skip
        return fused, None
    H2, crec = rift.context_refit(u8, np.asarray(fused["homography"], float), view.read_window)
    log.info("context re-fit: %s", crec)
    if crec is not None and crec["taken"]:
        fused = {**fused, "homography": (H2 / H2[2, 2]).tolist()}
    return fused, crec


def centre_similarity(H: np.ndarray, w: int, h: int) -> np.ndarray:
    """The similarity (handedness kept) nearest to homography ``H``'s local linear map at the
    centre of a ``w`` x ``h`` image, through ``H``'s image of that centre."""
    c = np.array([(w - 1) / 2, (h - 1) / 2])
    J = acceptance.jacobian(H, c)[0]
    U, _, Vt = np.linalg.svd(J)
    S = np.eye(3)
    S[:2, :2] = (U @ Vt) * np.sqrt(abs(np.linalg.det(J)))
    S[:2, 2] = matching.apply_h(H, c[None])[0] - S[:2, :2] @ c
    return S


def register_query(
    u8: np.ndarray,
    source: MapSource,
    conf: dict[str, Any],
    gsd_m: float | None,
    factors: list[float],
    seed: int = 0,
    read_window: Any = None,
    prior: Any = None,
    read_level: Any = None,
    map_id: str | None = None,
    aspect: float = 1.0,
    read_elevation: Any = None,
    elevation_id: str | None = None,
) -> dict[str, Any]:
    """The workflow's search_part jobs and fuse_parts in one process (the library's entry point):
    split plan, every part, the other sources (the small-query ones when ``read_window`` is
    given), fusion and the verifier's terms (``decide``). ``prior``: an approximate location
    (``georeg.io.prior``: ``{"centre": [x, y], "radius_m": r}`` or ``{"box": [x0, y0, x1,
    y1]}``, ``"crs": "map"`` (default) or ``"lonlat"``; or map bounds): the map the sources see
    is clipped to it. ``read_level``: the orthophoto as a ``georeg.register.level.LevelReader``
    (a query much coarser than the map searches a level near its GSD). ``map_id``: the
    orthophoto's identity, under which what the sources compute from it is kept in memory for
    the next query (None: nothing kept). ``aspect``: ``MapView.aspect``. ``read_elevation`` /
    ``elevation_id``: the map's DSM as a window reader and its identity (the ``elevation``
    source; None: not run). Returns the fused result with ``split``, ``parts``,
    ``sources``, the terms' records, ``prior`` and ``level``."""
    bounds = prior_bounds(prior, source.crs_wkt)
    h, w = u8.shape[-2:]
    view, factors, lrec = map_for_query(source, bounds, w, h, gsd_m, factors, conf, read_window,
                                        read_level, map_id, aspect=aspect, read_elevation=read_elevation,
                                        elevation_id=elevation_id)  # fmt: skip
    full = query_features(u8, (0, h), factors, view.source.features_conf)
    n = int(conf.get("parts", 2))
    parts = [search_one_part(u8, k, view.source, conf, gsd_m, factors, seed, full)
             for k in range(n)]  # fmt: skip
    fused, rec = decide(QueryInput(u8, full, gsd_m, factors, seed), view, parts, conf)
    return {**fused, **rec, "prior": prior_record(prior, bounds), "level": lrec}


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
    cache_dir: str | None = None,
    elevation: bool = True,
) -> dict[str, Any]:
    """Rule fuse_parts: the other sources, fusion and the verifier's terms (``decide``); write
    geolocation.tif (all NaN when not found) and registration.json.

    ``ortho``: the orthophoto mosaic, read by the small-query sources and the orthophoto check;
    ``cache_dir``: where the sources keep what they compute from it for the next query
    (``ortho_identity``); ``elevation``: the map has elevation (``map.lidar`` or ``map.dem``; else
    ``dsm`` is nodata), which the elevation source then reads.
    The query's location prior (band.json ``prior``) clips the map as in the search_part jobs."""
    import json
    from pathlib import Path

    from georeg.io.atomic import write_json
    from georeg.io.versions import library_versions
    from georeg.map.grid import ground_aspect
    from georeg.register.band import feature_scales, read_query_bands
    from georeg.register.geolocation import evaluate, write_geolocation
    from georeg.register.search import gsd_in_map_units, load_source, map_centre

    t0 = time.perf_counter()
    meta = json.loads(Path(band_json).read_text())
    parts = sorted((json.loads(Path(p).read_text()) for p in part_jsons), key=lambda p: p["part"])
    source = load_source(index_path, grid_path)
    bounds = prior_bounds(meta.get("prior"), source.crs_wkt, band_json)
    u8 = read_query_bands(band_tif)  # every pooled band, the primary first
    h, w = u8.shape[-2:]
    gsd = gsd_in_map_units(meta.get("gsd_m"), source.crs_wkt, map_centre(source))
    timings: dict[str, Any] = {
        "query_band": meta.get("seconds"),
        "search_parts": {str(p["part"]): p.get("seconds") for p in parts},
    }
    t1 = time.perf_counter()
    factors = feature_scales(gsd, source.gsd_m, reg_conf.get("unknown_gsd_factors", [1.0]))
    view, factors, lrec = map_for_query(
        source, bounds, w, h, gsd, factors, reg_conf,
        None if not ortho else ortho_window_reader(ortho),
        None if not ortho else level.read_ortho_level(ortho),
        None if not ortho else ortho_identity(ortho), cache_dir, ground_aspect(grid_path),
        *((ortho_window_reader(dsm), ortho_identity(dsm)) if elevation and dsm and Path(dsm).exists() else ()),
    )  # fmt: skip
    full = query_features(u8, (0, h), factors, view.source.features_conf)
    timings["fuse_features"] = time.perf_counter() - t1
    fused, rec = decide(QueryInput(u8, full, gsd, factors, seed), view, parts, reg_conf, dsm)
    source = view.source
    parts = rec["parts"]
    timings.update(rec["timings_s"])
    H = None if fused.get("homography") is None else np.array(fused["homography"])
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
        "prior": prior_record(meta.get("prior"), bounds),
        "level": lrec,
        "sources": rec["sources"],
        "second_pass": rec["second_pass"],
        "split": rec["split"],
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
    for term in ("null_check", "ortho_check", "context_refit", "lidar_check"):
        if rec[term] is not None:
            reg[term] = rec[term]
    if truth:
        t1 = time.perf_counter()
        reg["evaluation"] = evaluate(H, truth, map_px)
        timings["evaluation"] = time.perf_counter() - t1
    timings["fuse_total"] = time.perf_counter() - t0
    reg["timings_s"] = timings
    reg["software"] = library_versions()
    write_json(out_json, reg)
    return reg


def ortho_identity(ortho: str) -> str:
    """The orthophoto's identity for caches: its path, size and modification time (the mosaic
    rule rewrites it whenever a tile changes)."""
    import os

    st = os.stat(ortho)
    return f"{os.path.abspath(ortho)}:{st.st_size}:{st.st_mtime_ns}"


def ortho_window_reader(ortho: str) -> Any:
    """bounds -> (gray window, NaN = nodata; 3 x 3 window pixel centre -> map x, y) or None.
    A one-band raster (the DSM mosaic) reads as its values."""
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
