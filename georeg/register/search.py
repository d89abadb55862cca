"""Search the map for one part of the query: `paper` (random places) or `index` (ranked regions).

Every candidate region tried is recorded (centre, bounds, score, matches, inliers, NFA, accepted)
so that a later stage can draw the search.
"""

from __future__ import annotations

import logging
import math
import time
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import numpy as np

from georeg.index.features import dequantize, detect_and_describe, resample
from georeg.index.kdtree import kdtree, knn_search
from georeg.io.prior import prior_bounds, prior_record
from georeg.register import acceptance, level, matching

log = logging.getLogger(__name__)

Bounds = tuple[float, float, float, float]


# ----------------------------------------------------------------------------- map side


@dataclass
class MapSource:
    """The map's features: positions (map x, y), descriptors, feature GSD, CRS; optional index."""

    xy: np.ndarray
    desc: np.ndarray
    gsd_m: float
    crs_wkt: str | None = None
    index: Any = None  # georeg.index.map_index.MapIndex when loaded from disk
    angle: np.ndarray | None = None  # (n,) keypoint orientation (degrees), plain arrays only
    scale: np.ndarray | None = None  # (n,) keypoint diameter in map units, plain arrays only
    clip: Bounds | None = None  # a location prior: only the map inside these bounds is seen
    settings: dict[str, Any] | None = None  # features conf of plain arrays (an index has its own)
    extent: Bounds | None = None  # the map's extent, plain arrays (a level's: its features' is smaller)
    _nn: Any = field(default=None, init=False, repr=False, compare=False)  # PlainNearest cache

    @classmethod
    def from_index(cls, path: str | Path) -> MapSource:
        """Load a built map index (memory-mapped)."""
        from georeg.index.map_index import MapIndex

        idx = MapIndex.load(path)
        gsd = idx.gsd_m or (idx.meta.get("features_conf") or {}).get("gsd_m") or 1.0
        return cls(idx.xy, idx.desc, float(gsd), idx.crs_wkt, idx)

    @property
    def features_conf(self) -> dict[str, Any] | None:
        """The feature settings the map was built with (the query must use the same)."""
        return self.settings if self.index is None else self.index.meta.get("features_conf")

    def clipped(self, bounds: Bounds) -> MapSource:
        """The same map seen only inside ``bounds`` (a location prior); shares every array."""
        out = replace(self, clip=tuple(float(v) for v in bounds))
        out._nn = self._nn
        return out

    @property
    def bounds(self) -> Bounds:
        """Extent of the map (its tiles', ``extent``, else its features'; within ``clip``)."""
        if self.index is not None:
            b = np.asarray(self.index.tile_bounds, np.float64)
            b = b[np.isfinite(b).all(axis=1)]
            full = (b[:, 0].min(), b[:, 1].min(), b[:, 2].max(), b[:, 3].max())
        elif self.extent is not None:
            full = tuple(float(v) for v in self.extent)
        else:
            xy = np.asarray(self.xy)
            full = (*xy.min(axis=0), *xy.max(axis=0))
        return full if self.clip is None else intersect(full, self.clip)  # type: ignore[return-value]

    def features_in(self, bounds: Bounds) -> np.ndarray:
        """Ids of the map features inside ``bounds`` (and ``clip``)."""
        if self.clip is not None:
            bounds = intersect(bounds, self.clip)
            if bounds[0] > bounds[2] or bounds[1] > bounds[3]:
                return np.zeros(0, np.int64)
        if self.index is not None:
            return self.index.features_in(bounds)
        xy = np.asarray(self.xy)
        x0, y0, x1, y1 = bounds
        inside = (xy[:, 0] >= x0) & (xy[:, 0] <= x1) & (xy[:, 1] >= y0) & (xy[:, 1] <= y1)
        return np.flatnonzero(inside)

    def geometry(self, ids: np.ndarray) -> tuple[np.ndarray, np.ndarray] | None:
        """(angle degrees, keypoint diameter in map units) of feature ids, or None if unknown."""
        if self.index is None or not hasattr(self.index, "angle"):
            if self.angle is None or self.scale is None:
                return None
            return np.asarray(self.angle[ids], np.float64), np.asarray(self.scale[ids], np.float64)
        return (
            np.asarray(self.index.angle[ids], np.float64),
            np.asarray(self.index.scale[ids], np.float64),
        )

    def take(self, ids: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(xy float64, desc float32) of feature ids."""
        return np.asarray(self.xy[ids], np.float64), dequantize(np.asarray(self.desc[ids]))


def intersect(a: Bounds, b: Bounds) -> Bounds:
    """The intersection of two boxes (empty: x0 > x1 or y0 > y1)."""
    return (max(a[0], b[0]), max(a[1], b[1]), min(a[2], b[2]), min(a[3], b[3]))


def clip_to_prior(
    source: MapSource,
    prior: Bounds | None,
    width: int,
    height: int,
    gsd_m: float | None,
    factors: list[float],
) -> MapSource:
    """The map a query with a location prior sees: the prior box (where its centre may be)
    grown by half its ground diagonal (largest assumed GSD when unknown), so that every footprint
    centred in the box is inside. No prior: the source itself."""
    if prior is None:
        return source
    g = float(gsd_m) if gsd_m else source.gsd_m * max(factors)
    r = 0.5 * math.hypot(width, height) * g
    return source.clipped((prior[0] - r, prior[1] - r, prior[2] + r, prior[3] + r))


def map_for_query(
    source: MapSource,
    prior: Bounds | None,
    width: int,
    height: int,
    gsd_m: float | None,
    factors: list[float],
    conf: dict[str, Any],
    read_window: Any = None,
    read_level: level.LevelReader | None = None,
    ortho_id: str | None = None,
    cache_dir: str | None = None,
    aspect: float = 1.0,
    read_elevation: Any = None,
    elevation_id: str | None = None,
) -> tuple[MapView, list[float], dict[str, Any] | None]:
    """The map a query searches and the query's resize factors: the map clipped to the
    location prior (``clip_to_prior``), and, when the query is much coarser than the map's
    features (``register.level``), that map's orthophoto averaged to the query's GSD and its
    features (``georeg.register.level``) with the query at factor 1; the dense sources and checks
    then read the orthophoto ``level.WINDOW_FINER`` finer than that level (``level.window_reader``:
    the null scan, the small-query windows and the orthophoto check shrink the map to about the
    query's GSD anyway; rift searches at that finer GSD, ``MapView.read_gsd``). ``ortho_id`` / ``cache_dir`` / ``aspect`` / ``read_elevation`` / ``elevation_id``:
    ``MapView``'s. Returns (view, factors, the level's
    record or None when no level was asked for)."""
    source = clip_to_prior(source, prior, width, height, gsd_m, factors)
    view = MapView(source, read_window, ortho_id, cache_dir, aspect, read_elevation, elevation_id)
    lconf = {**level.DEFAULTS, **(conf.get("level") or {})}
    g = level.level_gsd(gsd_m, source.gsd_m, lconf)
    if g is None:
        return view, factors, None
    if read_level is None:
        return view, factors, {"gsd": g, "reason": "no orthophoto to read the level from"}
    feats, rec = level.level_features(read_level, source.bounds, g, source.features_conf,
                                      float(lconf["max_mpx"]))  # fmt: skip
    if feats is None:
        log.warning("map level not used: %s", rec.get("reason"))
        return view, factors, rec
    out = replace(
        view,
        source=MapSource(feats["xy"], feats["desc"], g, source.crs_wkt, angle=feats["angle"],
                         scale=feats["scale"], clip=source.clip, settings=source.features_conf,
                         extent=source.bounds),
        read_window=None if read_window is None
        else level.window_reader(read_level, g / level.WINDOW_FINER),
        read_gsd=g / level.WINDOW_FINER,
    )  # fmt: skip
    return out, [float(gsd_m) / g], rec


class PlainNearest:
    """What ``georeg.register.hough.hough_regions`` needs of an index, for plain map arrays:
    ``knn_words`` by an exact search over ALL map descriptors (faiss flat when small, FLANN
    kd-tree above ``matching.FLAT_MAX``, as ``matching.knn2``) -- the same as probing every word of
    an inverted file -- and the features' ``xy``, ``angle``, ``scale``."""

    def __init__(self, source: MapSource) -> None:
        self.xy = np.asarray(source.xy, np.float64)
        self.angle = np.asarray(source.angle, np.float64)
        self.scale = np.asarray(source.scale, np.float64)
        self._desc = np.ascontiguousarray(dequantize(np.asarray(source.desc)), np.float32)
        self._flat: Any = None

    def knn_words(
        self, query_desc: np.ndarray, k: int = 10, nprobe: int = 0
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """The ``k`` nearest map features of each query descriptor (``nprobe`` unused: every
        feature is compared). Flat arrays (query index, feature id, distance), nearest first."""
        q = np.ascontiguousarray(dequantize(query_desc), np.float32)
        n, m = len(q), len(self._desc)
        kk = min(max(1, int(k)), m)
        if n == 0 or m == 0:
            return np.zeros(0, np.int64), np.zeros(0, np.int64), np.zeros(0, np.float32)
        if m <= matching.FLAT_MAX:
            import faiss

            if self._flat is None:
                self._flat = faiss.IndexFlatL2(self._desc.shape[1])
                self._flat.add(self._desc)
            d2, ii = self._flat.search(q, kk)
        else:
            if self._flat is None:
                self._flat = kdtree(self._desc)
            ii, d2 = knn_search(self._flat, q, kk)
        ii = np.asarray(ii, np.int64)
        cq = np.repeat(np.arange(n, dtype=np.int64), kk)
        ok = ii.ravel() >= 0
        d = np.sqrt(np.maximum(np.asarray(d2, np.float32).ravel(), 0.0))
        return cq[ok], ii.ravel()[ok], d[ok]


def plain_nearest(source: MapSource) -> PlainNearest | None:
    """The cached ``PlainNearest`` of a plain-array source with keypoint geometry, else None."""
    if source.index is not None or source.angle is None or source.scale is None:
        return None
    if source._nn is None:
        source._nn = PlainNearest(source)
    return source._nn


# ----------------------------------------------------------------------------- query side


@dataclass
class QueryFeatures:
    """Features of (a part of) the query, positions in original query pixels (col, row)."""

    xy: np.ndarray
    desc: np.ndarray
    response: np.ndarray
    width: int
    height: int
    origin: tuple[int, int]  # (col0, row0) of this part in the full query
    factors: list[float]
    angle: np.ndarray | None = None  # (n,) keypoint orientation, degrees (OpenCV, row-down)
    size: np.ndarray | None = None  # (n,) keypoint diameter in feature pixels (at the map's GSD)
    factor: np.ndarray | None = None  # (n,) the resize factor each feature was detected at

    def __len__(self) -> int:
        return len(self.xy)


@dataclass
class QueryInput:
    """What every source of candidates sees of the query: its band(s) (uint8, 0 = nodata; the
    primary first), the whole query's features, its GSD in map units (None = unknown), the
    resize factors to the map's feature GSD, the seed, and ``tests_before``: the candidates the
    sources run before this one tried (``fuse.run_sources``), which a source's a-contrario count
    adds to its own, so that the NFA counts every test of the whole search."""

    u8: np.ndarray
    features: QueryFeatures
    gsd: float | None
    factors: list[float]
    seed: int = 0
    tests_before: int = 0

    @property
    def primary(self) -> np.ndarray:
        """The primary band (rows x cols)."""
        return self.u8 if self.u8.ndim == 2 else self.u8[0]


@dataclass
class MapView:
    """What every source sees of the map: its features (``MapSource``, clipped to the query's
    location prior when there is one) and the orthophoto window reader (``read_window(bounds)``
    -> (float gray, NaN = nodata; 3 x 3 window pixel centre -> map x, y) or None; None = no
    orthophoto). ``ortho_id``: the orthophoto's identity (None: unknown), which keys what the
    sources compute from it and keep (``georeg.register.rift.cached_map_features``): in memory,
    and on disk under ``cache_dir`` when given. ``aspect``: the width / height in map units of a
    map pixel that is square on the ground, when that may differ from 1 (a lon/lat orthophoto
    whose pixels are square on the ground, not in degrees: ``georeg.map.grid.ground_aspect``);
    rift's map-wide search (``rift.source``) searches it beside the square pixel.
    ``read_elevation`` / ``elevation_id``: the map's DSM, read and keyed like the orthophoto
    (None: no elevation), which the ``elevation`` source matches as an image
    (``rift.elevation_source``). ``read_gsd``: the pixel size ``read_window`` reads at when it is
    not the features' (a map level's windows are read ``level.WINDOW_FINER`` finer), the finest
    rift's search works at (``rift.working_gsd``)."""

    source: MapSource
    read_window: Any = None
    ortho_id: str | None = None
    cache_dir: str | None = None
    aspect: float = 1.0
    read_elevation: Any = None
    elevation_id: str | None = None
    read_gsd: float | None = None


SPLIT_DEFAULTS: dict[str, Any] = {
    "min_part_features": 1000,
    "min_part_side_px": 256.0,
    "whole_if_parts_fail": True,
    "parts_if_whole_fails": True,
    "count_searches": True,
}


def split_plan(
    n_features: int, width: int, height: int, factor: float, parts: int, conf: dict[str, Any]
) -> dict[str, Any]:
    """Whether to search ``parts`` along-track parts or the whole query, and why.

    ``n_features``: query features of the whole query at the map's feature GSD; ``factor``: query
    GSD / feature GSD (the largest guess when the GSD is unknown). The query is split only when
    each part keeps at least ``register.split.min_part_features`` features and its footprint's
    smaller side is at least ``min_part_side_px`` map feature pixels; otherwise one search covers
    the whole query. ``searches`` lists every search the plan may run (the NFA counts them all):
    a split query's parts, then the whole query if every part fails (``whole_if_parts_fail``);
    a whole query, then its parts if it fails (``parts_if_whole_fails``).
    """
    sc = {**SPLIT_DEFAULTS, **(conf.get("split") or {})}
    per = n_features / max(parts, 1)
    side = min(width, height / max(parts, 1)) * float(factor)
    plan: dict[str, Any] = {
        "configured_parts": int(parts),
        "query_features": int(n_features),
        "features_per_part": round(per, 1),
        "part_side_map_px": round(side, 1),
        "min_part_features": int(sc["min_part_features"]),
        "min_part_side_px": float(sc["min_part_side_px"]),
        "whole_if_parts_fail": bool(sc["whole_if_parts_fail"]),
        "parts_if_whole_fails": bool(sc["parts_if_whole_fails"]),
        "count_searches": bool(sc["count_searches"]),
    }
    names = [f"part {k}" for k in range(parts)]
    if parts <= 1:
        return {**plan, "parts": 1, "reason": "one part configured", "searches": ["whole"]}
    short = []
    if per < plan["min_part_features"]:
        short.append(f"{per:.0f} features per part < {plan['min_part_features']}")
    if side < plan["min_part_side_px"]:
        short.append(f"part side {side:.0f} map px < {plan['min_part_side_px']:.0f}")
    if short:
        then = names if plan["parts_if_whole_fails"] else []
        return {**plan, "parts": 1, "reason": "whole query searched: " + "; ".join(short),
                "searches": ["whole", *then]}  # fmt: skip
    then = ["whole"] if plan["whole_if_parts_fail"] else []
    return {**plan, "parts": int(parts), "reason": f"split in {parts}: each part large enough",
            "searches": [*names, *then]}  # fmt: skip


def search_count(plan: dict[str, Any]) -> int:
    """Searches the NFA counts for each search of the plan (1 when ``count_searches`` is off)."""
    return len(plan["searches"]) if plan.get("count_searches", True) else 1


def part_rows(height: int, parts: int, part: int) -> tuple[int, int]:
    """Rows [r0, r1) of part ``part`` of ``parts`` equal along-track slices."""
    edges = np.linspace(0, height, parts + 1).round().astype(int)
    return int(edges[part]), int(edges[part + 1])


def query_features(
    band_u8: np.ndarray,
    rows: tuple[int, int],
    factors: list[float],
    features_conf: dict[str, Any] | None,
) -> QueryFeatures:
    """Detect features on rows ``rows`` of the band at each resize factor; pool them.

    ``band_u8``: stretched band (rows, cols), 0 = nodata, or several co-registered bands
    (bands, rows, cols) whose features are pooled. A factor brings the query to the map's
    feature GSD (query_gsd / feature_gsd); keypoints are mapped back to original query pixels.
    """
    r0, r1 = rows
    stack = band_u8 if band_u8.ndim == 3 else band_u8[None]
    img = np.ascontiguousarray(stack[0, r0:r1])
    xs, ds, rs, angs, sizes, fs = [], [], [], [], [], []
    for f, b in ((f, b) for b in range(len(stack)) for f in factors):
        one = np.ascontiguousarray(stack[b, r0:r1])
        im, m, (sx, sy) = resample(one, float(f), one > 0)
        feats = detect_and_describe(im, m, features_conf or {})
        if len(feats) == 0:
            continue
        xy = (feats.xy.astype(np.float64) + 0.5) * np.array([sx, sy]) - 0.5
        xy[:, 1] += r0
        xs.append(xy)
        ds.append(feats.desc)
        rs.append(feats.response)
        angs.append(feats.angle.astype(np.float64))
        sizes.append(feats.scale.astype(np.float64))
        fs.append(np.full(len(feats), float(f)))
    if not xs:
        z = np.zeros(0)
        return QueryFeatures(
            np.zeros((0, 2)),
            np.zeros((0, 128), np.float32),
            z,
            img.shape[1],
            r1 - r0,
            (0, r0),
            factors,
        )
    return QueryFeatures(
        np.concatenate(xs),
        np.concatenate(ds).astype(np.float32),
        np.concatenate(rs),
        img.shape[1],
        r1 - r0,
        (0, r0),
        list(factors),
        np.concatenate(angs),
        np.concatenate(sizes),
        np.concatenate(fs),
    )


# ----------------------------------------------------------------------------- verification


def verify(
    qf: QueryFeatures,
    source: MapSource,
    bounds: Bounds,
    conf: dict[str, Any],
    gsd_m: float | None,
    n_candidates: int = 1,
    seed: int = 0,
    max_matches: int | None = None,
    guide: tuple[np.ndarray, float] | None = None,
) -> tuple[dict[str, Any], matching.Matches | None, matching.HomographyFit | None]:
    """Match the part against the map features in ``bounds``; fit, then accept or reject.

    ``guide`` = (H, radius): keep only matches whose map point lies within ``radius`` (map units)
    of H's prediction (guided matching around an already accepted homography).
    """
    t0 = time.perf_counter()
    ids = source.features_in(bounds)
    rec: dict[str, Any] = {
        "bounds": [float(v) for v in bounds],
        "centre": [0.5 * (bounds[0] + bounds[2]), 0.5 * (bounds[1] + bounds[3])],
        "map_features": len(ids),
        "matches": 0,
        "inliers": 0,
        "accepted": False,
    }
    if len(ids) < 8 or len(qf) < 4:
        rec.update(reason="too few features", seconds=time.perf_counter() - t0)
        return rec, None, None
    mxy, mdesc = source.take(ids)
    knn = matching.knn2(mdesc)
    nt = conf.get("max_matches", 100) if max_matches is None else max_matches
    hyps = _hypotheses(qf, source, ids, mxy, knn, conf, nt, mdesc, guide)
    rec["matcher"] = hyps[0][2]
    ext = mxy.max(axis=0) - mxy.min(axis=0)
    area_px = float(max(ext[0], source.gsd_m) * max(ext[1], source.gsd_m)) / source.gsd_m**2
    best: tuple | None = None
    for m, n_tests, _kind in hyps:
        if guide is not None:
            d = np.linalg.norm(matching.apply_h(guide[0], m.q_xy) - m.m_xy, axis=1)
            keep = np.flatnonzero(d <= guide[1])
            rec["guided_dropped"] = len(m) - len(keep)
            m = matching.Matches(
                m.q_idx[keep], m.m_idx[keep], m.q_xy[keep], m.m_xy[keep], m.dist[keep], m.n_examined
            )
        if len(m) < 4:
            if best is None:
                best = ((False, -math.inf, len(m)), m, None, None)
            continue
        fit = matching.fit_homography(m.q_xy, m.m_xy, source.gsd_m, conf.get("ransac", {}), seed)
        dec = acceptance.decide(
            fit.H,
            fit.residual_px,
            fit.n_inliers,
            area_px,
            qf.width,
            qf.height,
            gsd_m,
            conf.get("acceptance", {}),
            n_candidates=n_candidates * n_tests,
            origin=qf.origin,
            inlier_q_xy=None if fit.H is None else m.q_xy[fit.inliers],
        )
        lnfa = dec.get("log10_nfa")
        key = (
            bool(dec["accepted"]),
            -lnfa if lnfa is not None and math.isfinite(lnfa) else -math.inf,
            len(m),
        )
        if best is None or best[2] is None or key > best[0]:
            best = (key, m, fit, dec)
    assert best is not None
    _key, m, fit, dec = best
    rec["matches"] = len(m)
    rec["query_examined"] = m.n_examined
    if fit is None:
        rec.update(reason="fewer than 4 matches", seconds=time.perf_counter() - t0)
        return rec, m, None
    if dec["accepted"] and fit.H is not None:
        fit = final_model(fit, m, source.gsd_m, conf.get("ransac", {}), rec)
    rec.update(
        inliers=fit.n_inliers,
        accepted=bool(dec["accepted"]),
        log10_nfa=dec.get("log10_nfa"),
        reason=dec.get("reason", ""),
        plausibility={k: v for k, v in (dec.get("plausibility") or {}).items() if k != "ok"},
        spread=dec.get("spread"),
        ransac_rounds=fit.rounds,
        ransac_s=round(fit.seconds, 4),
        residual_px=fit.rms_px,
        area_px=area_px,
        homography=None if fit.H is None else fit.H.tolist(),
        seconds=time.perf_counter() - t0,
    )
    return rec, m, fit


def final_model(
    fit: matching.HomographyFit,
    m: matching.Matches,
    map_px_m: float,
    ransac_conf: dict[str, Any],
    rec: dict[str, Any],
) -> matching.HomographyFit:
    """An accepted fit refitted to its inliers with the model chosen by leave-one-out CV
    (``register.ransac.final_model: loo``; georeg.register.matching.choose_model), the same inliers,
    residuals re-measured; ``rec["final_model"]`` says which model and why. ``ransac`` (or a
    model that cannot be cross-validated) keeps the fit as it is."""
    how = str(ransac_conf.get("final_model", "loo"))
    if how not in ("loo", "ransac"):
        raise ValueError(f"unknown register.ransac.final_model {how!r} (loo | ransac)")
    if how == "ransac":
        return fit
    H, info = matching.choose_model(m.q_xy[fit.inliers], m.m_xy[fit.inliers], map_px_m)
    rec["final_model"] = info
    if H is None:
        return fit
    res = np.linalg.norm(matching.apply_h(H, m.q_xy) - m.m_xy, axis=1) / map_px_m
    return replace(fit, H=H, residual_px=np.where(np.isfinite(res), res, np.inf),
                   info={**fit.info, "model": info["model"]})  # fmt: skip


# ----------------------------------------------------------------------------- candidates


def _hypotheses(
    qf: QueryFeatures,
    source: MapSource,
    ids: np.ndarray,
    mxy: np.ndarray,
    knn: matching.KnnFn,
    conf: dict[str, Any],
    nt: int | None,
    mdesc: np.ndarray | None = None,
    guide: tuple[np.ndarray, float] | None = None,
) -> list[tuple[matching.Matches, int, str]]:
    """Correspondence sets to fit, each with its multiple-test count: ``register.matcher``.

    ``paper``: one set, the paper's ratio test (``register.ratio``, stop at Nt). ``vote``:
    both contrast polarities of the query, a loose ratio, keypoint-size agreement and
    the strongest rotation peaks (georeg.register.matching.rotation_hypotheses); falls back to
    ``paper`` when the map or the query has no keypoint geometry. With ``guide`` = (H, radius)
    (the fuse stage's re-match around an accepted part), ``vote`` matches every query feature
    among the map features within the radius of H's prediction, with the ratio test among
    those local candidates (``guided_ratio``, 0.8; georeg.register.matching.guided_matches).
    """
    mc = matching.matcher_conf(conf)
    method = str(mc.get("method", "paper"))
    if method not in ("paper", "vote"):
        raise ValueError(f"unknown register.matcher.method {method!r} (vote | paper)")
    q_xy, q_desc, q_resp, q_ang, q_size = qf.xy, qf.desc, qf.response, qf.angle, qf.size
    if mc.get("polarity") == "both" and len(qf):
        q_xy, q_desc, q_resp = matching.add_polarity(q_xy, q_desc, q_resp)
        if q_ang is not None and q_size is not None:
            q_ang = np.r_[q_ang, (q_ang + 180.0) % 360.0]
            q_size = np.r_[q_size, q_size]
    if method == "vote" and guide is not None and mdesc is not None:
        gm = matching.guided_matches(
            q_xy, q_desc, guide[0], mxy, mdesc, guide[1], float(mc.get("guided_ratio", 0.8)), knn
        )
        return [(gm, 1, "guided")]
    geom = source.geometry(ids) if method == "vote" else None
    if method == "vote" and geom is not None and q_ang is not None and q_size is not None:
        m_ang, m_scale = geom
        hyps = matching.rotation_hypotheses(
            q_xy, q_desc, q_ang, q_size, mxy, m_ang, m_scale / source.gsd_m, knn, mc
        )
        if hyps:
            return [(m, n, "vote") for m, n in hyps]
        z = np.zeros(0, np.int64)
        empty = matching.Matches(z, z, np.zeros((0, 2)), np.zeros((0, 2)), np.zeros(0), len(q_desc))
        return [(empty, 1, "vote")]
    m = matching.ratio_matches(q_xy, q_desc, q_resp, mxy, knn, float(conf.get("ratio", 0.7)), nt)
    return [(m, 1, "paper")]


def footprint_diagonal_m(qf: QueryFeatures, feature_gsd: float, gsd_m: float | None) -> float:
    """Ground diagonal of the part (largest assumed GSD when unknown)."""
    g = float(gsd_m) if gsd_m else feature_gsd * max(qf.factors)
    return math.hypot(qf.width, qf.height) * g


def paper_centres(bounds: Bounds, side: float, seed: int) -> np.ndarray:
    """Neighbourhood centres on a grid of stride side/2 over the map, in seeded random order
    (drawn without replacement)."""
    x0, y0, x1, y1 = bounds
    step = side / 2.0
    xs = np.arange(x0 + step / 2, max(x1, x0 + step / 2) + 1e-9, step)
    ys = np.arange(y0 + step / 2, max(y1, y0 + step / 2) + 1e-9, step)
    gx, gy = np.meshgrid(xs, ys)
    c = np.c_[gx.ravel(), gy.ravel()]
    rng = np.random.default_rng(seed)
    return c[rng.permutation(len(c))]


#: how the ``index`` strategy ranks candidate regions (``register.index.rank``)
RANKS = ("hough", "tiles", "regions")


def index_rank(reg_conf: dict[str, Any]) -> str | None:
    """The ranking a search with ``register`` config ``reg_conf`` uses (None for ``paper``)."""
    if str(reg_conf.get("strategy", "index")) != "index":
        return None
    return str((reg_conf.get("index") or {}).get("rank", RANKS[0]))


def index_candidates(
    qf: QueryFeatures, source: MapSource, diag_m: float, conf: dict[str, Any]
) -> list[tuple[Bounds, float | None]]:
    """Candidate regions, best first: ``rank`` hough (georeg.register.hough: nearest map
    features vote for the query's centre; on plain arrays through ``PlainNearest``), tiles
    (TF-IDF of visual words, each tile grown by the part's footprint) or regions (TF-IDF over
    sliding windows). Plain arrays without an index: ``tiles`` / ``regions``, or no keypoint
    geometry, mean 1-NN votes of the query descriptors on footprint-sized cells."""
    top = int(conf.get("top_candidates", 8))
    rank = str(conf.get("rank", RANKS[0]))
    if rank not in RANKS:
        raise ValueError(f"unknown register.index.rank {rank!r} (hough | tiles | regions)")
    g = diag_m
    out: list[tuple[Bounds, float | None]] = []
    if source.clip is not None:
        # a location prior: at most as many candidates as footprint-sized places it holds; a
        # prior of about two footprints a side is one candidate, the whole of it
        b = source.bounds
        places = max(1, math.ceil((b[2] - b[0]) * (b[3] - b[1]) / max(diag_m**2, 1e-9)))
        if places <= 4:
            return [(b, None)]
        top = min(top, places)
    nn = source.index if source.index is not None else plain_nearest(source)
    if nn is not None and rank == "hough":
        from georeg.register.hough import hough_regions

        out = [
            (b, s)
            for b, s in hough_regions(
                qf, nn, source.bounds, source.gsd_m, diag_m, top, conf.get("hough")
            )
        ]
        if len(out) >= top:
            return out
        # fewer voted places than the budget (a tiny query): the best tiles fill it
        return (
            out + index_candidates(qf, source, diag_m, {**conf, "rank": "tiles"})[: top - len(out)]
        )
    if source.index is not None and rank == "tiles":
        tb = np.asarray(source.index.tile_bounds, np.float64)
        ranked = source.index.rank_tiles(qf.desc, top if source.clip is None else len(tb))
        # tiles without a shared word (or a one-tile map, where idf = 0) follow, unranked
        seen = {t for t, _ in ranked}
        ok = np.isfinite(tb).all(axis=1)
        if source.clip is not None:  # only the tiles the prior reaches
            c = source.clip
            ok &= (tb[:, 0] <= c[2]) & (tb[:, 2] >= c[0]) & (tb[:, 1] <= c[3]) & (tb[:, 3] >= c[1])
            ranked = [(t, sc) for t, sc in ranked if ok[t]]
        rest = [(int(t), None) for t in np.flatnonzero(ok) if int(t) not in seen]
        for t, s in (ranked + rest)[:top]:
            b = tb[t]
            out.append(((b[0] - g, b[1] - g, b[2] + g, b[3] + g), s))
        return out
    if source.index is not None:
        for b, s in source.index.rank_regions(qf.desc, diag_m, diag_m / 2, top):
            h = g / 2
            out.append(((b[0] - h, b[1] - h, b[2] + h, b[3] + h), s))
        return out  # (with a prior, a region outside it is verified on no feature: rejected)
    # no index (plain arrays) and rank tiles / regions, or no keypoint geometry: 1-NN votes of
    # the query descriptors on cells of the footprint size
    mb = source.bounds
    d, ii = matching.knn2(dequantize(np.asarray(source.desc)))(qf.desc)
    ok = ii[:, 0] >= 0
    xy = np.asarray(source.xy)[ii[ok, 0]]
    if source.clip is not None:
        c = source.clip
        xy = xy[(xy[:, 0] >= c[0]) & (xy[:, 0] <= c[2]) & (xy[:, 1] >= c[1]) & (xy[:, 1] <= c[3])]
    cell = diag_m
    nx = max(1, int(math.ceil((mb[2] - mb[0]) / cell)))
    ny = max(1, int(math.ceil((mb[3] - mb[1]) / cell)))
    cx = np.clip(((xy[:, 0] - mb[0]) / cell).astype(int), 0, nx - 1)
    cy = np.clip(((xy[:, 1] - mb[1]) / cell).astype(int), 0, ny - 1)
    votes = np.bincount(cy * nx + cx, minlength=nx * ny)
    for c in np.argsort(-votes, kind="stable")[:top]:
        if votes[c] == 0:
            break
        r, k = divmod(int(c), nx)
        x0, y0 = mb[0] + k * cell, mb[1] + r * cell
        out.append(((x0 - g, y0 - g, x0 + cell + g, y0 + cell + g), float(votes[c])))
    return out


# ----------------------------------------------------------------------------- one part


def search_part(
    qf: QueryFeatures,
    source: MapSource,
    conf: dict[str, Any],
    gsd_m: float | None,
    seed: int,
    searches: int = 1,
) -> dict[str, Any]:
    """Search the map for one part; stop at the first accepted candidate or when the budget ends.

    ``conf`` is the ``register`` config section; ``searches``: how many searches of this query
    the split plan may run (multiplies the NFA's test count). Returns a JSON-ready dict (see
    docs/ARCHITECTURE.md).
    """
    t0 = time.perf_counter()
    strategy = str(conf.get("strategy", "index"))
    diag = footprint_diagonal_m(qf, source.gsd_m, gsd_m)
    cands: list[tuple[Bounds, float | None]]
    t_rank = 0.0
    if strategy == "paper":
        pc = conf.get("paper", {})
        side = float(pc.get("neighbourhood_factor", 2.0)) * diag
        centres = paper_centres(source.bounds, side, seed)
        budget = int(pc.get("max_candidates", 200))
        centres = centres[:budget]
        h = side / 2
        cands = [((x - h, y - h, x + h, y + h), None) for x, y in centres]
        max_s = float(pc.get("max_seconds", 600))
    elif strategy == "index":
        ic = conf.get("index", {})
        tr = time.perf_counter()
        cands = list(index_candidates(qf, source, diag, ic))
        t_rank = time.perf_counter() - tr
        max_s = float(ic.get("max_seconds", 300))
    else:
        raise ValueError(f"unknown search strategy {strategy!r} (index | paper)")
    tried: list[dict[str, Any]] = []
    best: tuple[dict[str, Any], matching.Matches, matching.HomographyFit] | None = None
    for i, (b, score) in enumerate(cands):
        if i > 0 and time.perf_counter() - t0 > max_s:
            log.info("search budget of %.0f s used after %d candidates", max_s, i)
            break
        n_tests = len(cands) * max(int(searches), 1)
        rec, m, fit = verify(qf, source, b, conf, gsd_m, n_candidates=n_tests, seed=seed + i)
        rec["rank"] = i
        rec["score"] = score
        tried.append(rec)
        log.info(
            "candidate %d: %d map features, %d matches, %d inliers, log10 NFA %s -> %s",
            i,
            rec["map_features"],
            rec["matches"],
            rec["inliers"],
            _fmt(rec.get("log10_nfa")),
            "ACCEPT" if rec["accepted"] else rec.get("reason", ""),
        )
        if rec["accepted"] and m is not None and fit is not None:
            best = (rec, m, fit)
            break
    out: dict[str, Any] = {
        "strategy": strategy,
        "rank": index_rank(conf),
        "rows": [qf.origin[1], qf.origin[1] + qf.height],
        "width": qf.width,
        "query_features": len(qf),
        "factors": qf.factors,
        "candidates_available": len(cands),
        "candidates_tried": len(tried),
        "candidates": tried,
        "rank_s": t_rank,
        "accepted": best is not None,
        "homography": None,
        "inliers": 0,
    }
    if best is not None:
        rec, m, fit = best
        inl = fit.inliers
        out.update(
            homography=fit.H.tolist(),  # type: ignore[union-attr]
            inliers=fit.n_inliers,
            matches=len(m),
            residual_px=fit.rms_px,
            log10_nfa=rec.get("log10_nfa"),
            region=rec["bounds"],
            inlier_query_xy=m.q_xy[inl].tolist(),
            inlier_map_xy=m.m_xy[inl].tolist(),
        )
    out["seconds"] = time.perf_counter() - t0
    return out


def _fmt(v: float | None) -> str:
    return "n/a" if v is None else f"{v:.1f}"


def load_source(index_path: str | Path, grid_path: str | Path | None = None) -> MapSource:
    """The map index as a MapSource; the feature GSD falls back to the map grid's pixel size."""
    src = MapSource.from_index(index_path)
    if src.index.gsd_m is None and not (src.features_conf or {}).get("gsd_m") and grid_path:
        import json

        a = json.loads(Path(grid_path).read_text())["transform"][0]
        src.gsd_m = abs(float(a))
    return src


def map_centre(source: MapSource) -> tuple[float, float]:
    """The centre of the map's features' bounds (map x, y)."""
    b = source.bounds
    return (float(b[0] + b[2]) / 2, float(b[1] + b[3]) / 2)


def gsd_in_map_units(gsd_m: float | None, crs_wkt: str | None,
                     at: tuple[float, float] | None = None) -> float | None:
    """The query's ``gsd_m`` (metres on the ground) in the map CRS's horizontal unit: / the
    unit's metres (feet maps: / 0.3048...), x the projection's scale at ``at`` (map x, y, the
    map's centre; none: 1): a Web Mercator map's metre is 1 / cos(latitude) ground metres
    (1.51 at 48.7 N, beyond the acceptance's scale tolerance), a UTM map's 0.9996-1.001.

    Everything on the map side (feature GSD, keypoint xy, homography scale) is in CRS units.
    """
    if not gsd_m or not crs_wkt:
        return gsd_m
    from pyproj import CRS, Proj, Transformer

    crs = CRS.from_user_input(crs_wkt)
    if not (crs.is_projected and crs.axis_info):
        return gsd_m
    k = 1.0
    if at is not None:
        lon, lat = Transformer.from_crs(crs, "EPSG:4326", always_xy=True).transform(*at)
        f = Proj(crs).get_factors(lon, lat)
        if math.isfinite(f.areal_scale) and abs(math.sqrt(f.areal_scale) - 1.0) > 0.01:
            k = math.sqrt(f.areal_scale)  # (UTM's, state planes' < 0.1 %: left out)
    return float(gsd_m) / float(crs.axis_info[0].unit_conversion_factor) * k


def run_search_part(
    band_tif: str,
    band_json: str,
    index_path: str,
    grid_path: str | None,
    part: int,
    reg_conf: dict[str, Any],
    seed: int,
    out_json: str,
    ortho: str | None = None,
) -> dict[str, Any]:
    """Rule search_part: features of one along-track part (pooled over band.tif's bands), then
    the configured search. ``ortho``: the orthophoto mosaic, read when the query needs a map
    level near its GSD (``map_for_query``)."""
    import json

    from georeg.io.atomic import write_json
    from georeg.register.band import feature_scales, read_query_bands

    t0 = time.perf_counter()
    meta = json.loads(Path(band_json).read_text())
    u8 = read_query_bands(band_tif)  # every pooled band, the primary first
    source = load_source(index_path, grid_path)
    t_load = time.perf_counter() - t0
    gsd = gsd_in_map_units(meta.get("gsd_m"), source.crs_wkt, map_centre(source))
    factors = feature_scales(gsd, source.gsd_m, reg_conf.get("unknown_gsd_factors", [1.0]))
    prior = prior_bounds(meta.get("prior"), source.crs_wkt, band_json)
    reader = None if not ortho else level.read_ortho_level(ortho)
    view, factors, lrec = map_for_query(source, prior, u8.shape[-1], u8.shape[-2], gsd, factors,
                                        reg_conf, None, reader)  # fmt: skip
    source = view.source
    t1 = time.perf_counter()
    res = search_one_part(u8, part, source, reg_conf, gsd, factors, seed)
    res["prior"] = prior_record(meta.get("prior"), prior)
    if lrec is not None:
        res["level"] = lrec
    res["timings_s"] = {"load": t_load, "features_and_search": time.perf_counter() - t1}
    res["seconds"] = time.perf_counter() - t0
    write_json(out_json, res)
    return res


def search_one_part(
    u8: np.ndarray,
    part: int,
    source: MapSource,
    reg_conf: dict[str, Any],
    gsd: float | None,
    factors: list[float],
    seed: int,
    full: QueryFeatures | None = None,
) -> dict[str, Any]:
    """Part ``part`` of the split plan: its own rows when the query is split; when it is not,
    part 0 searches the whole query and the other parts record that they were merged into it.
    ``full``: the whole query's features when already computed."""
    h, w = u8.shape[-2:]
    if full is None:
        full = query_features(u8, (0, h), factors, source.features_conf)
    plan = split_plan(len(full), w, h, max(factors), int(reg_conf.get("parts", 2)), reg_conf)
    log.info("part %d: %s", part, plan["reason"])
    n_s = search_count(plan)
    if plan["parts"] == 1 and part == 0:
        # the whole query; when it fails, each part in turn (in this job: the others are idle)
        res = search_part(full, source, reg_conf, gsd, seed, n_s)
        tried = [res]
        for k, name in enumerate(plan["searches"][1:]):
            if res["accepted"]:
                break
            rows = part_rows(h, int(plan["configured_parts"]), k)
            qf = query_features(u8, rows, factors, source.features_conf)
            log.info("whole query not found: %s rows %s, %d features", name, rows, len(qf))
            res = search_part(qf, source, reg_conf, gsd, seed + 1000 * (k + 1), n_s)
            tried.append(res)
        summary = [{"rows": r["rows"], "accepted": r["accepted"], "inliers": r["inliers"],
                    "candidates_tried": r["candidates_tried"]} for r in tried]  # fmt: skip
        res["candidates_tried"] = int(sum(r["candidates_tried"] for r in tried))
        res["candidates"] = [c for r in tried for c in r["candidates"]]  # the whole query's first
        return {"part": part, "split": plan, **res, "searched": summary, "whole_query": True}
    if plan["parts"] == 1 and part > 0:
        return {
            "part": part, "split": plan, "skipped": True, "rows": [0, 0], "width": w,
            "query_features": 0, "candidates_tried": 0, "candidates": [], "accepted": False,
            "homography": None, "inliers": 0, "seconds": 0.0,
            "reason": "merged into part 0 (whole query searched)",
        }  # fmt: skip
    qf = query_features(u8, part_rows(h, plan["parts"], part), factors, source.features_conf)
    log.info("part %d rows %s: %d query features at factors %s", part,
             [qf.origin[1], qf.origin[1] + qf.height], len(qf), factors)  # fmt: skip
    res = search_part(qf, source, reg_conf, gsd, seed + 1000 * part, n_s)
    return {"part": part, "split": plan, **res}
