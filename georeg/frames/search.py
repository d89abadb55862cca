"""Intensity pose search: the last resort of a frame whose feature matching found nothing.

Feature matching needs texture the frame and the map share; a low oblique view of a facade the
map has no texture for and of a parking lot whose cars moved has almost none (docs/BENCHMARKS.md
"Frame geo-localisation", oblique35_100). The shape of the scene is still there: a tower's
silhouette, the edge of a lot, a kerb. This step compares the frame with the map *rendered*,
by the same similarity as the intensity refinement (``georeg.frames.refine``: normalised mutual
information + gradient correlation), over a grid of poses around a coarse hypothesis (a nadir
vote of ``georeg.frames.coarse``), then refines the best cells and accepts a pose only when its
refined similarity clears a fixed bound (measured against wrong places) and, because the
similarity's scale depends on the frame (a textured nadir frame reaches at a wrong place what a
low oblique one reaches at its own), 1.5 x the best similarity the same search reaches from decoy
starts 250 m away: the frame's own chance level after the same optimisation.

The grid is cheap because the map is rendered once: at the hypothesis, on a canvas ``canvas``
times the frame (low resolution, ``scale``), its visible pixels become 3-D points carrying the
render's intensity and gradients; each grid pose projects them into the (reduced) frame and
samples it there (visibility frozen at the hypothesis). Grid: camera centre moved by
+-``span_m`` in x and y every ``step_m``, pitched (about the camera x axis) by ``pitch_deg``
and turned about the vertical by ``heading_deg``.
"""

from __future__ import annotations

import dataclasses
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import cv2
import numpy as np

from georeg.frames.refine import _grad, frame_channels, refine_pose, similarity
from georeg.frames.render import PinholeCamera, PointCloud, render

DEFAULTS: dict[str, Any] = {
    "enabled": True,
    "votes": 1,  # best nadir votes of the coarse step searched around
    "scale": 0.2,  # grid evaluated on the frame reduced to this
    "canvas": 2.0,  # the map rendered on this x the frame (covers the moved poses)
    "span_m": 48.0,  # camera centre moved +- this in x and y ...
    "step_m": 4.0,  # ... every step_m
    "pitch_deg": [-6.0, -3.0, 0.0, 3.0, 6.0],
    "heading_deg": [-4.0, 0.0, 4.0],
    "max_points": 4000,  # render points the grid projects
    "min_coverage": 0.8,  # similarity scaled down below this fraction of the frame covered
    "candidates": 2,  # best grid cells (>= separation_m apart) refined
    "separation_m": 10.0,
    "refine": {"trans_step_m": 1.0, "rot_step_deg": 0.5},  # georeg.frames.refine overrides
    "accept_similarity": 0.25,  # refined NMI + GC needed (wrong places: <= 0.27 measured) ...
    "decoys_m": [[250.0, 0.0], [-250.0, 0.0]],  # ... and the same search from starts moved by these
    "decoy_ratio": 1.5,  # ... must stay below 1 / decoy_ratio of it (the frame's own chance level)
    "cloud_margin_m": 150.0,
    "seed": 0,
}


@dataclass
class SearchResult:
    cam: PinholeCamera | None  # the accepted pose, or None
    info: dict[str, Any] = field(default_factory=dict)


def _rx(deg: float) -> np.ndarray:
    c, s = np.cos(np.radians(deg)), np.sin(np.radians(deg))
    return np.array([[1.0, 0, 0], [0, c, -s], [0, s, c]])


def _rz(deg: float) -> np.ndarray:
    c, s = np.cos(np.radians(deg)), np.sin(np.radians(deg))
    return np.array([[c, -s, 0], [s, c, 0], [0, 0, 1.0]])


def moved(cam: PinholeCamera, pitch: float, heading: float, dx: float, dy: float) -> PinholeCamera:
    """``cam`` pitched about its x axis, turned about the world vertical, moved in x, y."""
    return cam.with_pose(_rx(pitch) @ np.asarray(cam.R, float) @ _rz(heading),
                         np.asarray(cam.C, float) + np.array([dx, dy, 0.0]))  # fmt: skip


def grid_scores(gray: np.ndarray, cam0: PinholeCamera, cloud: PointCloud,
                conf: dict | None = None) -> np.ndarray:  # fmt: skip
    """Similarity (NMI - 1 + gradient correlation, scaled down below ``min_coverage``) of every
    grid pose: rows (score, pitch, heading, dx, dy), best first."""
    c = {**DEFAULTS, **(conf or {})}
    cs = cam0.scaled(float(c["scale"]))
    W, H = int(cs.width * float(c["canvas"])), int(cs.height * float(c["canvas"]))
    wide = dataclasses.replace(cs, width=W, height=H, cx=cs.cx + (W - cs.width) / 2,
                               cy=cs.cy + (H - cs.height) / 2)  # fmt: skip
    rr = render(cloud, wide)
    rg = rr.gray().astype(np.float32)
    rgx, rgy = _grad(rg)
    valid = rr.mask & (cv2.erode(rr.mask.astype(np.uint8), np.ones((3, 3), np.uint8)) > 0)
    rows, cols = np.nonzero(valid)
    n_valid = rows.size
    if n_valid < 200:
        return np.zeros((0, 5))
    if n_valid > int(c["max_points"]):
        k = np.random.default_rng(int(c["seed"])).choice(n_valid, int(c["max_points"]), replace=False)
        rows, cols = rows[k], cols[k]
    X = wide.backproject(np.c_[cols, rows].astype(float), rr.depth[rows, cols])
    ref3 = np.c_[rg[rows, cols], rgx[rows, cols], rgy[rows, cols]]
    img3 = frame_channels(cv2.resize(gray, (cs.width, cs.height), interpolation=cv2.INTER_AREA))
    offs = np.arange(-float(c["span_m"]), float(c["span_m"]) + 1e-6, float(c["step_m"]))
    per_px = n_valid / len(X) / (cs.width * cs.height)  # render pixels per sampled point / frame px
    dx, dy = (a.ravel() for a in np.meshgrid(offs, offs, indexing="ij"))  # dx outer, dy inner
    shift = np.c_[dx, dy, np.zeros_like(dx)]
    out = []
    for p in c["pitch_deg"]:
        for h in c["heading_deg"]:
            Rp = moved(cs, p, h, 0.0, 0.0).R  # the translations leave the rotation as is
            mi, gc, frac = similarity(img3, cs, Rp,
                                      np.asarray(cs.C, float) + shift, X, ref3, 32)  # fmt: skip
            cover = frac * len(X) * per_px
            score = (mi + gc) * np.minimum(1.0, cover / float(c["min_coverage"]))
            out += [(s_, p, h, a, b) for s_, a, b in zip(score, dx, dy, strict=True)]
    out = np.array(out, float)
    return out[np.argsort(-out[:, 0], kind="stable")]


def search_pose(gray: np.ndarray, cam0: PinholeCamera, cloud: PointCloud, conf: dict | None = None,
                cloud_at: Callable[[PinholeCamera], PointCloud] | None = None) -> SearchResult:  # fmt: skip
    """Grid search around ``cam0``, the best ``candidates`` cells refined (NMI + GC); the best
    refined pose is accepted when its similarity reaches ``accept_similarity`` and ``decoy_ratio``
    x the best similarity the same search reaches from the decoy starts (``cam0`` moved by
    ``decoys_m``, their map read by ``cloud_at``): how similar this frame gets to a wrong place
    after the same optimisation. No decoy evaluated (no ``cloud_at``, the map empty there): refused."""
    c = {**DEFAULTS, **(conf or {})}
    t0 = time.perf_counter()
    g = grid_scores(gray, cam0, cloud, c)
    info: dict[str, Any] = {"grid_poses": len(g), "accept_similarity": float(c["accept_similarity"])}
    if not len(g):
        info.update(reason="the map renders nothing at the hypothesis", seconds=time.perf_counter() - t0)
        return SearchResult(None, info)
    med = float(np.median(g[:, 0]))
    info["grid_best"] = float(g[0, 0])
    info["grid_z"] = float((g[0, 0] - med) / (1.4826 * np.median(np.abs(g[:, 0] - med)) + 1e-12))
    picked: list[np.ndarray] = []
    for row in g:
        if all(np.hypot(row[3] - q[3], row[4] - q[4]) >= float(c["separation_m"]) for q in picked):
            picked.append(row)
        if len(picked) >= int(c["candidates"]):
            break
    info["grid_s"] = time.perf_counter() - t0
    best, tried = None, []
    for row in picked:
        cam1 = moved(cam0, *row[1:])
        ref = refine_pose(gray, cam1, cloud, c["refine"])
        sim = -float(ref.info["octaves"][-1]["cost_end"]) if ref.info["octaves"] else 0.0
        tried.append({"grid_score": float(row[0]), "pitch_deg": float(row[1]), "heading_deg": float(row[2]),
                      "shift_m": [float(row[3]), float(row[4])], "refined_similarity": sim,
                      "refined_center_xyz": [float(v) for v in ref.C]})  # fmt: skip
        if best is None or sim > best[0]:
            best = (sim, cam1.with_pose(ref.R, ref.C))
    info["candidates"] = tried
    if best is None or best[0] < float(c["accept_similarity"]):
        info.update(reason=f"best refined similarity {best[0]:.3f} < {float(c['accept_similarity'])}",
                    seconds=time.perf_counter() - t0)  # fmt: skip
        return SearchResult(None, info)
    decoys = []
    for dx, dy in c["decoys_m"] if cloud_at is not None else []:
        cam_d = moved(cam0, 0.0, 0.0, float(dx), float(dy))
        d = search_pose(gray, cam_d, cloud_at(cam_d), {**c, "accept_similarity": -np.inf, "decoys_m": []})
        if d.info.get("candidates"):  # the map renders there
            decoys.append(max(t["refined_similarity"] for t in d.info["candidates"]))
    info.update(decoy_similarity=decoys, seconds=time.perf_counter() - t0)
    bound = float(c["decoy_ratio"]) * max(decoys) if decoys else np.inf
    if best[0] >= bound:
        info["similarity"] = best[0]
        return SearchResult(best[1], info)
    info["reason"] = (f"refined similarity {best[0]:.3f} < {float(c['decoy_ratio'])} x the decoys' "
                      f"{max(decoys):.3f}" if decoys else "no decoy start evaluated")  # fmt: skip
    return SearchResult(None, info)
