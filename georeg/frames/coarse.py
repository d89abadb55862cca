"""Coarse location of a frame without GPS: the map's visual-word index, then PnP.

The frame is treated as an approximately nadir view of unknown ground sampling: its SIFT features
(the index's own settings, rotation-invariant, so no rotation search is needed unless the map was
built ``upright``: then the frame is tried at ``rotations``) are extracted at several scales
(``scales``: frame GSD unknown) and pooled. ``MapIndex.rank_regions`` ranks map windows by TF-IDF
votes; in each candidate window the features are 2-NN ratio matched against the map features,
which carry their 3-D position (x, y and the DSM z stored in the index), so a PnP in RANSAC gives
directly a full pose, not only an area and a heading. The first candidate whose pose passes the
checks (inliers, camera above the surface and looking down) is returned.
"""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass, field
from typing import Any

import cv2
import numpy as np

from georeg.frames.pnp import solve_pnp
from georeg.index.features import detect_and_describe

log = logging.getLogger(__name__)

DEFAULTS: dict[str, Any] = {
    "scales": [1.0, 0.5, 0.25, 0.125],  # frame resizes tried (unknown GSD), features pooled
    "max_frame_px": 3_000_000,  # scales shrunk so that the largest has at most this many pixels
    "window_m": 400.0,  # rank_regions window and stride
    "stride_m": 100.0,
    "top_candidates": 8,  # index regions voted in
    "dense_windows": 10,  # windows re-extracted densely (index-ranked first, then the rest of the map)
    "tilts_deg": [40.0],  # tilt hypotheses (besides nadir), each towards 4 image directions
    "pnp_per_window": 3,  # votes (tilt hypotheses) verified by PnP per window, most votes first
    "grow_m": 150.0,  # candidate window grown by this before matching
    "vote_ratio": 0.9,  # loose ratio test before the similarity vote
    "ratio": 0.8,  # ratio test of the re-match inside the voted footprint
    "footprint_grow": 1.5,  # voted footprint (frame diagonal x GSD) grown by this
    "reproj_px": 8.0,
    "max_iters": 5000,
    "min_inliers": 8,  # coarse PnP inliers (the render-match-PnP stage then verifies)
    "max_seconds": 60.0,
    "seed": 0,
}


@dataclass
class Coarse:
    ok: bool
    R: np.ndarray | None = None
    C: np.ndarray | None = None
    inliers: int = 0
    candidates: list[dict] | None = None
    reason: str = ""
    # nadir-vote poses (R, C, votes), most votes first: starting points for the render stage
    hypotheses: list = field(default_factory=list)
    budget: dict = field(default_factory=dict)  # what the search cost and tested (index mode)


@dataclass
class FrameKeys:
    xy: np.ndarray  # full-resolution undistorted pixels
    size: np.ndarray  # keypoint diameter, full-resolution pixels
    angle: np.ndarray  # degrees, in the frame's pixel axes
    desc: np.ndarray


def tilt_homography(K: np.ndarray, tilt_deg: float, towards_deg: float) -> np.ndarray:
    """Homography frame -> virtual nadir view of the same centre, for a camera tilted
    ``tilt_deg`` from nadir towards the image direction ``towards_deg`` (0 = image top,
    90 = right): H = K R K^-1 with R = Rz(psi) Rx(tilt) Rz(psi)^T."""
    t, p = np.radians(tilt_deg), np.radians(towards_deg)
    Rx = np.array([[1, 0, 0], [0, np.cos(t), -np.sin(t)], [0, np.sin(t), np.cos(t)]])
    Rz = np.array([[np.cos(p), -np.sin(p), 0], [np.sin(p), np.cos(p), 0], [0, 0, 1]])
    return K @ (Rz @ Rx @ Rz.T) @ np.linalg.inv(K)


def frame_keys(gray: np.ndarray, conf: dict, feat_conf: dict, K: np.ndarray | None = None,
               tilt: tuple[float, float] = (0.0, 0.0)) -> tuple[FrameKeys, FrameKeys, dict]:  # fmt: skip
    """Features of the frame seen as a nadir view under the tilt hypothesis ``tilt``
    (degrees, towards), at every scale of ``conf['scales']``. Returns (keys in the virtual
    nadir image (for the vote), the same keys with positions in the frame (for PnP), the
    virtual view: its principal point ``pp`` (the nadir point), focal scale ``sc`` and the
    camera rotation ``R_rel`` (real camera -> virtual nadir camera axes))."""
    h, w = gray.shape
    img, Hn, mask, sc, T = gray, np.eye(3), None, 1.0, np.eye(3)
    R_rel = np.eye(3)
    if tilt[0] and K is not None:
        Hn = tilt_homography(K, *tilt)
        R_rel = np.linalg.inv(K) @ Hn @ K
        corners = cv2.perspectiveTransform(
            np.array([[[0, 0]], [[w, 0]], [[w, h]], [[0, h]]], np.float64), Hn
        )
        lo, hi = corners.reshape(-1, 2).min(0), corners.reshape(-1, 2).max(0)
        sc = min(1.0, 1.3 * np.hypot(w, h) / np.hypot(*(hi - lo)))
        T = np.array([[sc, 0, -sc * lo[0]], [0, sc, -sc * lo[1]], [0, 0, 1]])
        Hn = T @ Hn
        size = (int(np.ceil(sc * (hi - lo)[0])), int(np.ceil(sc * (hi - lo)[1])))
        img = cv2.warpPerspective(gray, Hn, size, flags=cv2.INTER_LINEAR)
        mask = cv2.warpPerspective(np.full_like(gray, 255), Hn, size, flags=cv2.INTER_NEAREST)
    xy_all, sz, an, d_all = [], [], [], []
    top = min(1.0, float(np.sqrt(float(conf.get("max_frame_px") or np.inf) / (h * w))))
    for s in (top * float(v) for v in conf["scales"]):
        small = cv2.resize(img, None, fx=s, fy=s, interpolation=cv2.INTER_AREA) if s < 1 else img
        ms = (
            None
            if mask is None
            else (
                cv2.resize(mask, (small.shape[1], small.shape[0]), interpolation=cv2.INTER_NEAREST)
                > 0
            )
        )
        f = detect_and_describe(small, ms, feat_conf)
        if not len(f):
            continue
        xy_all.append((f.xy.astype(np.float64) + 0.5) / s - 0.5)
        sz.append(f.scale.astype(np.float64) / s)
        an.append(f.angle.astype(np.float64))
        d_all.append(f.desc.astype(np.float32))
    if not xy_all:
        e = FrameKeys(np.zeros((0, 2)), np.zeros(0), np.zeros(0), np.zeros((0, 128), np.float32))
        return e, e, {}
    virt = FrameKeys(
        np.concatenate(xy_all), np.concatenate(sz), np.concatenate(an), np.concatenate(d_all)
    )
    orig_xy = cv2.perspectiveTransform(virt.xy.reshape(-1, 1, 2), np.linalg.inv(Hn)).reshape(-1, 2)
    pp = (
        (T @ np.array([K[0, 2], K[1, 2], 1.0]))[:2]
        if K is not None
        else np.array([(w - 1) / 2, (h - 1) / 2])
    )
    view = {"pp": pp, "sc": sc, "R_rel": R_rel}
    return virt, FrameKeys(orig_xy, virt.size, virt.angle, virt.desc), view


def vote_similarity(fk: FrameKeys, qi: np.ndarray, mf: dict, centre: np.ndarray,
                    angle_tol: float = 20.0, log2_tol: float = 0.6, pos_tol: float = 0.35,
                    ) -> tuple[np.ndarray, dict]:  # fmt: skip
    """Matches consistent with one nadir similarity (heading, GSD, position of the frame centre).

    Each match predicts the rotation frame -> map (keypoint angles), the ground size of a frame
    pixel (keypoint sizes) and where the frame centre lies on the map; the match agreeing with
    the most others (pairwise, both keypoint-angle sign conventions) wins. Returns the indices
    into ``qi`` of the consistent matches and the vote (heading_deg, gsd_m, centre_xy).
    """
    n = len(qi)
    if n == 0:
        return np.zeros(0, np.int64), {}
    g = mf["scale"].astype(np.float64) / fk.size[qi]
    lg = np.log2(np.maximum(g, 1e-9))
    best_idx, best_info = np.zeros(0, np.int64), {}
    for sign in (1.0, -1.0):
        phi = np.radians(sign * (mf["angle"].astype(np.float64) - fk.angle[qi]))
        off = centre[None, :] - fk.xy[qi]  # frame pixels (col, row)
        dc = g * (np.cos(phi) * off[:, 0] - np.sin(phi) * off[:, 1])
        dr = g * (np.sin(phi) * off[:, 0] + np.cos(phi) * off[:, 1])
        cx = mf["xy"][:, 0] + dc
        cy = mf["xy"][:, 1] - dr  # map rows run south
        diag = 2 * np.linalg.norm(centre)
        best_n, best_k = -1, -1
        for a in range(0, n, 512):
            sl = slice(a, min(n, a + 512))
            dphi = np.abs((np.degrees(phi[sl, None] - phi[None, :]) + 180) % 360 - 180)
            tol = pos_tol * diag * np.maximum(g[sl, None], g[None, :])
            cons = (dphi < angle_tol) & (np.abs(lg[sl, None] - lg[None, :]) < log2_tol)
            cons &= np.hypot(cx[sl, None] - cx[None, :], cy[sl, None] - cy[None, :]) < tol
            cnt = cons.sum(axis=1)
            k = int(np.argmax(cnt))
            if cnt[k] > best_n:
                best_n, best_k = int(cnt[k]), a + k
        if best_n > len(best_idx):
            k = best_k
            dphi = np.abs((np.degrees(phi[k] - phi) + 180) % 360 - 180)
            tol = pos_tol * diag * np.maximum(g[k], g)
            cons = (dphi < angle_tol) & (np.abs(lg[k] - lg) < log2_tol)
            cons &= np.hypot(cx[k] - cx, cy[k] - cy) < tol
            idx = np.flatnonzero(cons)
            best_idx = idx
            ph = float(np.arctan2(np.sin(phi[idx]).mean(), np.cos(phi[idx]).mean()))
            best_info = {"phi_rad": ph, "heading_deg": float(np.degrees(ph) % 360),
                         "gsd_m": float(np.median(g[idx])),
                         "centre_xy": [float(np.median(cx[idx])), float(np.median(cy[idx]))]}  # fmt: skip
    return best_idx, best_info


class DenseWindow:
    """Dense map features of one window (the index's detector, no per-megapixel cap), with the
    slice of the ``MapIndex`` API the coarse search uses (``knn``, ``features``, ``features_in``).

    The index stores at most ``max_features_per_mpx`` features: a 100 m drone footprint then
    holds ~60 map features, too few to verify; the window re-extracts them densely from the
    orthophoto and DSM mosaics (cost ~1 s per 0.5 km2 at 1 m). ``gsd``: features extracted at
    this ground sampling (None: the ortho's); the window is read decimated when it would exceed
    ``max_px`` pixels. ``dsm`` None: every feature at the height ``flat_z``. Any band count and
    bit depth: the ortho goes through ``rgb_to_gray`` and ``to_uint8``.
    """

    def __init__(self, ortho: str, dsm: str | None, bounds, feat_conf: dict, gsd: float | None = None,
                 max_px: int = 16_000_000, flat_z: float = 0.0) -> None:  # fmt: skip
        import rasterio
        from affine import Affine
        from rasterio.enums import Resampling
        from rasterio.windows import from_bounds

        from georeg.index.features import rgb_to_gray, tile_features

        with rasterio.open(ortho) as so:
            win = from_bounds(*bounds, so.transform).round_offsets().round_lengths()
            try:
                win = win.intersection(rasterio.windows.Window(0, 0, so.width, so.height))
            except rasterio.errors.WindowError:  # the window is off the map
                win = rasterio.windows.Window(0, 0, 1, 1)
            native = abs(so.transform.a)
            dec = max(1.0, (gsd or native) / native, np.sqrt(win.width * win.height / max_px))
            shape = (max(1, int(win.height / dec)), max(1, int(win.width / dec)))
            bands = list(range(1, min(3, so.count) + 1))
            rs = Resampling.average if dec > 1 else Resampling.nearest
            rgb = so.read(bands, window=win, out_shape=(len(bands), *shape), resampling=rs)
            mask = so.read_masks(1, window=win, out_shape=shape) > 0
            t0 = so.window_transform(win)
            tr = Affine(t0.a * win.width / shape[1], 0, t0.c, 0, t0.e * win.height / shape[0], t0.f)
            wb = rasterio.windows.bounds(win, so.transform)
        if dsm is not None:
            with rasterio.open(dsm) as sd:
                wd = from_bounds(*wb, sd.transform).round_offsets().round_lengths()
                z = sd.read(1, window=wd, boundless=True,
                            fill_value=sd.nodata if sd.nodata is not None else np.nan)  # fmt: skip
                elev = (z, sd.window_transform(wd), sd.nodata)
        else:
            elev = None
        conf = {**feat_conf, "max_features_per_mpx": None, "gsd_m": None}
        tf = tile_features(rgb_to_gray(rgb), mask, tr, conf, None, elev)
        self.bounds = tuple(float(v) for v in bounds)
        self.gsd = float(abs(tr.a))
        self.xy = tf.xy
        self.z = tf.z.astype(np.float64) if elev is not None else np.full(len(tf), float(flat_z))
        self.scale, self.angle = tf.scale, tf.angle
        self.desc = tf.desc.astype(np.float32) / 512.0
        self._ix = None

    def __len__(self) -> int:
        return len(self.xy)

    def features_in(self, b) -> np.ndarray:
        xy = self.xy
        return np.flatnonzero(
            (xy[:, 0] >= b[0]) & (xy[:, 0] <= b[2]) & (xy[:, 1] >= b[1]) & (xy[:, 1] <= b[3])
        )

    def features(self, ids) -> dict[str, np.ndarray]:
        ids = np.asarray(ids, np.int64)
        return {
            "xy": self.xy[ids],
            "z": self.z[ids],
            "scale": self.scale[ids],
            "angle": self.angle[ids],
        }

    def knn(self, q: np.ndarray, ids: np.ndarray, k: int = 2) -> tuple[np.ndarray, np.ndarray]:
        import faiss

        ids = np.asarray(ids, np.int64)
        if len(ids) < k:
            return np.full((len(q), k), np.inf, np.float32), np.full((len(q), k), -1, np.int64)
        ix = faiss.IndexFlatL2(self.desc.shape[1])
        ix.add(np.ascontiguousarray(self.desc[ids]))
        d, i = ix.search(np.ascontiguousarray(q, np.float32), k)
        return np.sqrt(np.maximum(d, 0)), np.where(i >= 0, ids[np.maximum(i, 0)], -1)


def _ratio_match(
    index, fk: FrameKeys, ids: np.ndarray, ratio: float
) -> tuple[np.ndarray, np.ndarray]:
    """2-NN ratio matches frame -> map features ``ids``; one frame feature per map keypoint."""
    if len(ids) < 2:
        return np.zeros(0, np.int64), np.zeros(0, np.int64)
    d, fid = index.knn(fk.desc, ids, k=2)
    ok = (fid[:, 1] >= 0) & (d[:, 0] < ratio * d[:, 1])
    qi, mi, dd = np.flatnonzero(ok), fid[ok, 0], d[ok, 0]
    order = np.lexsort((dd, mi))
    first = np.ones(len(order), bool)
    first[1:] = mi[order][1:] != mi[order][:-1]
    return qi[order[first]], mi[order[first]]


def nadir_hypothesis(vote: dict, view: dict, K: np.ndarray, index) -> tuple[np.ndarray, np.ndarray]:
    """Camera pose implied by a vote: the virtual nadir camera sits above the voted nadir point at
    height gsd x f (virtual focal), its image x axis along the voted rotation; the real camera
    is that rotated back by the tilt hypothesis (R = R_rel^T R_virtual)."""
    c, s = np.cos(vote["phi_rad"]), np.sin(vote["phi_rad"])
    R_virt = np.array([[c, -s, 0.0], [-s, -c, 0.0], [0.0, 0.0, -1.0]])
    x, y = vote["centre_xy"]
    ids = index.features_in((x - 150, y - 150, x + 150, y + 150))
    z = np.asarray(index.features(ids)["z"], float) if len(ids) else np.zeros(0)
    z = z[np.isfinite(z)]
    zg = float(np.median(z)) if z.size else 0.0
    height = vote["gsd_m"] * K[0, 0] * view["sc"]
    return view["R_rel"].T @ R_virt, np.array([x, y, zg + height])


def plausible(R: np.ndarray, C: np.ndarray, xyz: np.ndarray) -> str:
    """'' when the pose looks like an aerial view of ``xyz``, else the reason."""
    if C[2] < np.percentile(xyz[:, 2], 90) + 5:
        return "camera below the scene"
    if R[2, 2] > -0.1:  # optical axis (row 2 of R) must point downwards
        return "camera not looking down"
    return ""


def strong_inliers(conf: dict | None) -> int:
    """The coarse PnP inliers that end a search (regions, or the focal candidates of an
    unknown camera): twice ``min_inliers`` of ``conf`` over ``DEFAULTS``."""
    return 2 * int({**DEFAULTS, **(conf or {})}["min_inliers"])


def coarse_locate(gray: np.ndarray, K: np.ndarray, index, conf: dict | None = None,
                  dense: tuple | None = None) -> Coarse:  # fmt: skip
    """Candidate areas from the index, a nadir vote (area, heading, GSD) per tilt hypothesis,
    then a PnP pose from a re-match inside the voted footprint. ``dense`` = (ortho, dsm[, flat z])
    mosaics (dsm None: flat ground at that z): the votes and re-matches use dense features of the candidate windows
    (``DenseWindow``) instead of the index's capped ones."""
    c = {**DEFAULTS, **(conf or {})}
    feat_conf = index.meta.get("features_conf") or {}
    t0 = time.perf_counter()
    h, w = gray.shape
    hyps = [(0.0, 0.0)] + [
        (float(t), float(d)) for t in c["tilts_deg"] if t for d in (0, 90, 180, 270)
    ]
    keys = [frame_keys(gray, c, feat_conf, K, hy) for hy in hyps]
    all_desc = np.concatenate([k[0].desc for k in keys])
    if len(all_desc) < 10:
        return Coarse(False, reason=f"only {len(all_desc)} frame features")
    regions = index.rank_regions(all_desc, float(c["window_m"]), float(c["stride_m"]),
                                 top=int(c["top_candidates"]))  # fmt: skip
    if not regions:  # e.g. a one-tile map: idf = 0 everywhere, every window scores 0
        tb = np.asarray(index.tile_bounds, float)
        tb = tb[np.isfinite(tb).all(axis=1)]
        if len(tb):
            regions = [((tb[:, 0].min(), tb[:, 1].min(), tb[:, 2].max(), tb[:, 3].max()), 0.0)]
    if dense is not None:  # after the ranked windows, the rest of the map (budget permitting)
        tb = np.asarray(index.tile_bounds, float)
        tb = tb[np.isfinite(tb).all(axis=1)]
        if len(tb):
            step = float(c["window_m"])
            xs = np.arange(tb[:, 0].min(), tb[:, 2].max(), step)
            ys = np.arange(tb[:, 1].min(), tb[:, 3].max(), step)
            regions = list(regions) + [((x, y, x + step, y + step), 0.0) for y in ys for x in xs]
    return _search_regions(K, index, c, keys, hyps, regions, dense, (w, h), t0)


def _search_regions(K: np.ndarray, index, c: dict, keys: list, hyps: list, regions: list,
                    dense: tuple | None, wh: tuple[int, int], t0: float,
                    clip: tuple | None = None) -> Coarse:  # fmt: skip
    """Visit ``regions`` in order (dense windows when ``dense``): nadir votes per tilt
    hypothesis, the best verified by PnP; stops at a pose with 2 x ``min_inliers``, after
    ``dense_windows`` dense windows or ``max_seconds``. ``clip``: no map feature outside it."""
    w, h = wh
    feat_conf = index.meta.get("features_conf") or {}
    cands: list[dict] = []
    g = float(c["grow_m"])
    windows: list[Any] = []
    best = Coarse(False, candidates=cands, reason="no candidate region", hypotheses=[])
    min_inl = int(c["min_inliers"])
    tried = 0
    seen: list[tuple[int, float, float]] = []

    def verify(rec: dict) -> None:
        nonlocal best, tried
        virt, orig, view = keys[rec["_hyp"]]
        vote = rec["vote"]
        if any(hh == rec["_hyp"] and np.hypot(x - vote["centre_xy"][0], y - vote["centre_xy"][1]) < 20
               for hh, x, y in seen):  # fmt: skip
            rec["reason"] = "same vote as a candidate already verified"
            return
        seen.append((rec["_hyp"], *vote["centre_xy"]))
        tried += 1
        hyp_pose = nadir_hypothesis(vote, view, K, index)
        rec["hypothesis_center_xyz"] = [float(v) for v in hyp_pose[1]]
        best.hypotheses.append((hyp_pose[0], hyp_pose[1], rec["votes"]))
        half = 0.5 * vote["gsd_m"] * np.hypot(w, h) * float(c["footprint_grow"]) + 30.0
        cxy = vote["centre_xy"]
        src = rec["_src"]
        ids2 = src.features_in((cxy[0] - half, cxy[1] - half, cxy[0] + half, cxy[1] + half))
        qi2, mi2 = _ratio_match(src, orig, ids2, float(c["ratio"]))
        f = src.features(mi2)
        xyz = np.c_[f["xy"].astype(np.float64), f["z"].astype(np.float64)]
        good = np.isfinite(xyz).all(axis=1)
        res = solve_pnp(xyz[good], orig.xy[qi2[good]], K, float(c["reproj_px"]), int(c["max_iters"]),
                        int(c["seed"]) + tried)  # fmt: skip
        rec.update(rematches=int(good.sum()), inliers=int(res.inliers))
        why = plausible(res.R, res.C, xyz[good]) if res.ok else "PnP failed"
        if res.ok:
            rec["camera_center_xyz"] = [float(v) for v in res.C]
        if not why and res.inliers < min_inl:
            why = "too few inliers"
        rec["reason"] = why
        log.info("coarse: region %d tilt %s: %d votes, %d re-matches, %d inliers %s", rec["region"],
                 rec["tilt"], rec["votes"], rec["rematches"], rec["inliers"], why)  # fmt: skip
        if not why and res.inliers > best.inliers:
            best = Coarse(True, res.R, res.C, res.inliers, cands, hypotheses=best.hypotheses)

    visited = 0
    for k, (b, score) in enumerate(regions):
        gb = (b[0] - g, b[1] - g, b[2] + g, b[3] + g)
        if clip is not None:
            gb = (max(gb[0], clip[0]), max(gb[1], clip[1]), min(gb[2], clip[2]), min(gb[3], clip[3]))
        src = index
        if dense is not None:
            if len(windows) >= int(c["dense_windows"]):
                break
            if any(w.bounds[0] <= b[0] and w.bounds[1] <= b[1] and w.bounds[2] >= b[2] and w.bounds[3] >= b[3]
                   for w in windows):  # fmt: skip
                continue  # already searched densely
            src = DenseWindow(dense[0], dense[1], gb, feat_conf, gsd=feat_conf.get("gsd_m"),
                              flat_z=float(dense[2]) if len(dense) > 2 else 0.0)  # fmt: skip
            windows.append(src)
            log.info("coarse: dense window %d: %d map features", len(windows), len(src))
        ids = src.features_in(gb)
        visited += 1
        here = []
        for hi, (virt, _orig, view) in enumerate(keys):
            if not view:
                continue
            qi, mi = _ratio_match(src, virt, ids, float(c["vote_ratio"]))
            # the vote predicts where the virtual view's principal point (the nadir) lies
            cons, vote = vote_similarity(virt, qi, src.features(mi), view["pp"])
            here.append({"region": k, "bounds": [float(v) for v in b], "score": score,
                         "tilt": list(hyps[hi]), "matches": int(len(qi)), "votes": int(len(cons)),
                         "vote": vote, "_hyp": hi, "_src": src})  # fmt: skip
        here.sort(key=lambda r: -r["votes"])
        cands.extend(here)
        for rec in here[: int(c["pnp_per_window"])]:
            if rec["votes"] >= 4:
                verify(rec)
        if best.ok and best.inliers >= strong_inliers(c):
            break
        if time.perf_counter() - t0 > float(c["max_seconds"]):
            break
    cands.sort(key=lambda r: (-int("inliers" in r), -r["votes"]))
    best.candidates = cands
    for rec in cands:
        rec.pop("_hyp", None)
        rec.pop("_src", None)
        if rec.get("vote"):
            rec["vote"] = {k: v for k, v in rec["vote"].items()}
    if not best.ok:
        best.reason = "no candidate gave a plausible pose with enough inliers"
    best.hypotheses.sort(key=lambda t: -t[2])
    best.candidates = cands[: max(tried, 8)]
    best.budget = {"regions_searched": visited, "pnp_tests": tried}
    return best


# --------------------------------------------------------------------------- index-based search

#: the index search (``mode: index``, default): settings added to ``DEFAULTS``
INDEX_DEFAULTS: dict[str, Any] = {
    "mode": "index",  # index (region votes of the map index near the frame's footprint) | plain
    "index_min_px": 16_000_000,  # maps below this many pixels take the plain search (the index
    # search missed the demo's 35 deg oblique frame on its 4.2 Mpx map, which plain registers)
    "window_frac": 1.5,  # region window = this x the frame's diagonal seen at the map GSD
    "stride_frac": 0.5,  # region stride = this x the window
    "max_regions": 16,  # candidate budget: distinct regions searched at most per stage
    "grow_frac": 0.25,  # a region is searched grown by this x the window on every side
    "nprobe": 2,  # frame descriptors matched to the region features of their nearest words only
    "index_scales": [1.0, 0.5, 0.25],  # frame resizes (the window assumes a GSD near the map's)
    "frame_features_per_mpx": 3000,  # strongest frame features kept per Mpx of each resize
    "nadir_first": True,  # the nadir hypothesis alone first, the tilts only when it is not enough
    "direct_margin_m": 40.0,  # direct matching window margin around its PnP pose (within metres)
    "index_max_seconds": 300.0,  # wall-time safeguard per stage's region search (not the budget)
}


class WordIndex:
    """A map index whose ``knn`` compares each descriptor only with the candidate features that
    share one of its ``nprobe`` nearest visual words (the inverted file's own restriction), so a
    region's matching costs |frame| x nprobe x the region's features per word, not |frame| x the
    region's features. Everything else is the wrapped index's."""

    def __init__(self, index, nprobe: int = 2) -> None:
        self._index, self._nprobe = index, int(nprobe)

    def __getattr__(self, name: str):
        return getattr(self._index, name)

    def _region(self, ids: np.ndarray):
        """The candidate features sorted by word, their float descriptors and squared norms
        (kept for the next call with the same ids: every tilt hypothesis searches one region)."""
        from georeg.index.features import dequantize

        key = (len(ids), int(ids[0]), int(ids[-1]), int(ids.sum()))
        if getattr(self, "_key", None) != key:
            mw = np.asarray(self._index.word[ids], np.int64)
            o = np.argsort(mw, kind="stable")
            sid = ids[o]
            md = dequantize(np.asarray(self._index.desc[np.sort(sid)]))[np.argsort(np.argsort(sid))]
            self._key, self._reg = key, (sid, mw[o], md, (md**2).sum(axis=1))
        return self._reg

    def knn(self, q: np.ndarray, ids: np.ndarray, k: int = 2) -> tuple[np.ndarray, np.ndarray]:
        n = len(q)
        dist, fid = np.full((n, k), np.inf, np.float32), np.full((n, k), -1, np.int64)
        ids = np.asarray(ids, np.int64)
        if n == 0 or len(ids) == 0:
            return dist, fid
        qd = np.ascontiguousarray(q, np.float32)
        _, qw = self._index.quantize(qd, self._nprobe)
        sid, mw, md, mn = self._region(ids)
        qq = np.repeat(np.arange(n), qw.shape[1])
        ww = qw.ravel()
        o = np.argsort(ww, kind="stable")
        qq, ww = qq[o], ww[o]
        uw, first = np.unique(ww, return_index=True)
        last = np.r_[first[1:], len(ww)]
        lo, hi = np.searchsorted(mw, uw, "left"), np.searchsorted(mw, uw, "right")
        qn = (qd**2).sum(axis=1)
        rows = []
        for a, b, m0, m1 in zip(first.tolist(), last.tolist(), lo.tolist(), hi.tolist(), strict=True):
            if m1 <= m0:
                continue
            qs = qq[a:b]
            d2 = qn[qs, None] - 2.0 * (qd[qs] @ md[m0:m1].T) + mn[None, m0:m1]
            kk = min(k, m1 - m0)
            part = np.argpartition(d2, kk - 1, axis=1)[:, :kk] if kk < m1 - m0 else \
                np.broadcast_to(np.arange(m1 - m0), (len(qs), m1 - m0))  # fmt: skip
            rows.append((np.repeat(qs, kk), sid[m0 + part].ravel(),
                         np.take_along_axis(d2, part, axis=1).ravel()))  # fmt: skip
        if not rows:
            return dist, fid
        cq, cf, cd = (np.concatenate(c) for c in zip(*rows, strict=True))
        o = np.lexsort((cd, cq))
        cq, cf, cd = cq[o], cf[o], cd[o]
        start = np.r_[0, np.flatnonzero(np.diff(cq)) + 1]
        rank = np.arange(len(cq)) - np.repeat(start, np.diff(np.r_[start, len(cq)]))
        keep = rank < k
        dist[cq[keep], rank[keep]] = np.sqrt(np.maximum(cd[keep], 0.0))
        fid[cq[keep], rank[keep]] = cf[keep]
        return dist, fid


def index_window_m(w: int, h: int, map_gsd: float, conf: dict) -> tuple[float, float]:
    """(window, stride) of the region vote: the frame's footprint if its GSD were the map's."""
    win = float(conf["window_frac"]) * float(map_gsd) * float(np.hypot(w, h))
    return win, float(conf["stride_frac"]) * win


def coarse_index(gray: np.ndarray, K: np.ndarray, index, map_gsd: float, conf: dict | None = None,
                 prior: tuple | None = None) -> Coarse:  # fmt: skip
    """Coarse location through the map index only, with a bounded cost on any map size.

    Visual words of the frame (the tilt hypotheses and scales, pooled) vote for map windows of
    about the frame's footprint at the map GSD (``MapIndex.rank_regions``: TF-IDF over the
    inverted file, the SWIR search's region ranking); within a ``prior`` box (x0, y0, x1, y1)
    only when given. The best ``max_regions`` are searched on the index's own features (no
    dense re-extraction: the direct 2-D/3-D match re-extracts the footprint afterwards): nadir
    vote, then PnP, as ``coarse_locate``. ``nadir_first``: the nadir hypothesis alone first; the
    tilt hypotheses only when it gives no pose with 2 x ``min_inliers``. ``budget`` in the result
    records the regions ranked and searched and the PnP tests run over both stages (the
    a-contrario count of the coarse step).
    """
    c = {**DEFAULTS, **INDEX_DEFAULTS, **(conf or {})}
    feat_conf = index.meta.get("features_conf") or {}
    t0 = time.perf_counter()
    h, w = gray.shape
    hyps = [(0.0, 0.0)] + [
        (float(t), float(d)) for t in c["tilts_deg"] if t for d in (0, 90, 180, 270)
    ]
    fconf = {**feat_conf, "max_features_per_mpx": c["frame_features_per_mpx"]}
    kc = {**c, "scales": c["index_scales"]}
    win, stride = index_window_m(w, h, map_gsd, c)
    stages = [1, len(hyps)] if c["nadir_first"] and len(hyps) > 1 else [len(hyps)]
    keys: list = []
    res, spent = Coarse(False, reason="no frame features"), {"regions_searched": 0, "pnp_tests": 0}
    times = {"features_s": 0.0, "rank_s": 0.0, "search_s": 0.0}
    ranked, n_desc = 0, 0
    for n in stages:
        t1 = time.perf_counter()
        keys += [frame_keys(gray, kc, fconf, K, hy) for hy in hyps[len(keys) : n]]
        times["features_s"] += time.perf_counter() - t1
        all_desc = np.concatenate([k[0].desc for k in keys])
        n_desc = len(all_desc)
        if n_desc < 10:
            continue
        t2 = time.perf_counter()
        regions, ranked = _index_regions(index, all_desc, win, stride, int(c["max_regions"]), prior)
        t3 = time.perf_counter()
        times["rank_s"] += t3 - t2
        res = _index_search(K, index, c, keys, hyps[:n], regions, (w, h), win, prior, t0)
        times["search_s"] += time.perf_counter() - t3
        for k in spent:
            spent[k] += res.budget.get(k, 0)
        if res.ok and res.inliers >= strong_inliers(c):
            break
    res.budget = {"mode": "index", "window_m": round(win, 1), "stride_m": round(stride, 1),
                  "regions_ranked": ranked, "regions_budget": int(c["max_regions"]), **spent,
                  "hypotheses": len(keys), "prior": list(prior) if prior is not None else None,
                  "frame_features": int(n_desc), **{k: round(v, 3) for k, v in times.items()}}  # fmt: skip
    return res


def _index_regions(index, desc: np.ndarray, win: float, stride: float, budget: int,
                   prior: tuple | None) -> tuple[list, int]:  # fmt: skip
    """The best ``budget`` distinct regions voted by ``desc`` (meeting ``prior``), and how many
    were ranked; a one-tile map (idf = 0) or no shared word: the whole map (or prior)."""
    regions = index.rank_regions(desc, win, stride, top=None)  # a few thousand windows at 1 Gpx
    if prior is not None:
        regions = [(b, s) for b, s in regions
                   if b[0] < prior[2] and b[2] > prior[0] and b[1] < prior[3] and b[3] > prior[1]]  # fmt: skip
    ranked = len(regions)
    regions = _distinct_regions(regions, win, budget)
    if not regions:
        tb = np.asarray(index.tile_bounds, float)
        tb = tb[np.isfinite(tb).all(axis=1)]
        if len(tb):
            b = (tb[:, 0].min(), tb[:, 1].min(), tb[:, 2].max(), tb[:, 3].max())
            if prior is not None:
                b = (max(b[0], prior[0]), max(b[1], prior[1]), min(b[2], prior[2]), min(b[3], prior[3]))
            regions = [(b, 0.0)]
    return regions, ranked


def _index_search(K: np.ndarray, index, c: dict, keys: list, hyps: list, regions: list,
                  wh: tuple[int, int], win: float, prior: tuple | None, t0: float) -> Coarse:  # fmt: skip
    """``_search_regions`` on the index's features (word-restricted matching), regions grown by
    ``grow_frac`` x the window, features clipped to the prior grown by half a window (a prior
    bounds where the frame's centre can be)."""
    c = {**c, "grow_m": float(c["grow_frac"]) * win, "dense_windows": int(c["max_regions"])}
    src = WordIndex(index, int(c["nprobe"])) if int(c["nprobe"]) > 0 else index
    clip = None if prior is None else (prior[0] - 0.5 * win, prior[1] - 0.5 * win,
                                       prior[2] + 0.5 * win, prior[3] + 0.5 * win)  # fmt: skip
    c["max_seconds"] = float(c["index_max_seconds"])  # the region count is the budget; a safeguard
    return _search_regions(K, src, c, keys, hyps, regions, None, wh, time.perf_counter(), clip)


def _distinct_regions(regions: list, win: float, n: int) -> list:
    """The best ``n`` regions whose centres are at least half a window apart (overlapping
    sliding windows of one place count once)."""
    out: list = []
    for b, s in regions:
        cx, cy = 0.5 * (b[0] + b[2]), 0.5 * (b[1] + b[3])
        if all(np.hypot(cx - 0.5 * (o[0] + o[2]), cy - 0.5 * (o[1] + o[3])) >= 0.5 * win for o, _ in out):
            out.append((b, s))
            if len(out) >= n:
                break
    return out
