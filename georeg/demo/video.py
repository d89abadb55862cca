"""Demo drone video: a smooth flight over the demo city with a truth pose per frame.

The flight is a circular arc at constant altitude (``agl_m`` above the mean ground under it),
the camera ``off_nadir_deg`` from nadir looking ``look_deg`` from the direction of flight, with a
small smooth attitude wobble. Of ``candidates`` seeded placements whose every footprint lies in
the map (shrunk by ``inset_m``) and whose camera stays ``clearance_m`` above every surface within
60 m, the one seeing the most varied content (class entropy of its footprints) is flown. The city
is rasterised ONCE for the corridor (``georeg.demo.frames.corridor_cloud``: the afternoon sun of
the single frames) and every frame is rendered from that cloud through the same lens, camera
response and noise as the single frames (``camera_image``), a new noise draw per frame.
"""

from __future__ import annotations

import json
import logging
import time
from dataclasses import asdict, dataclass, replace
from pathlib import Path
from typing import Any

import cv2
import numpy as np
from threadpoolctl import threadpool_limits

from georeg.demo.frames import (
    CAMERA,
    FRAME_SUN,
    Lens,
    World,
    camera_image,
    corridor_cloud,
    frame_resolution,
    ground_footprint,
)
from georeg.demo.layout import EPOCH_QUERY
from georeg.demo.raster import Grid, rasterize
from georeg.frames.render import PinholeCamera, PointCloud, pose_from_angles
from georeg.io.atomic import atomic_path, write_json
from georeg.io.errors import ConfigError

log = logging.getLogger(__name__)

DEFAULTS: dict[str, Any] = {
    "n_frames": 240,
    "fps": 10.0,
    "speed_mps": 10.0,
    "agl_m": 130.0,  # above the mean ground under the path; the altitude is constant
    "off_nadir_deg": 30.0,
    "look_deg": 0.0,  # camera heading from the direction of flight: 0 forward, 90 right
    "turn_radius_m": 300.0,  # circular arc; 0 = straight line
    "wobble_deg": 0.3,  # attitude wobble amplitude (roll, pitch, yaw)
    "width": 640,
    "height": 480,
    "fx": 520.0,
    "dist": list(CAMERA["dist"]),
    "inset_m": 15.0,  # every footprint inside the map shrunk by this
    "clearance_m": 30.0,  # camera above every surface within 60 m of its ground point
    "candidates": 12,  # valid placements drawn; the most varied one is flown
    "max_cells": 8_000_000,  # corridor raster bound (coarser cells beyond)
}
PAD_M = 60.0  # corridor margin beyond the footprints (tall buildings, shadows)


@dataclass(frozen=True)
class Flight:
    """An arc flown at constant speed and altitude; headings clockwise from north (degrees)."""

    x0: float
    y0: float
    heading_deg: float  # direction of flight at the start
    turn: int  # +1 right (clockwise), -1 left
    radius_m: float  # 0: straight
    z_m: float
    speed_mps: float
    fps: float
    n_frames: int
    look_deg: float
    off_nadir_deg: float
    wobble: tuple[tuple[float, float, float], ...]  # (axis, frequency Hz, phase rad) terms
    wobble_deg: float

    def times(self) -> np.ndarray:
        return np.arange(self.n_frames) / self.fps

    def track(self) -> tuple[np.ndarray, np.ndarray]:
        """Camera ground positions (n, 2) and directions of flight (n,) in degrees."""
        s = self.speed_mps * self.times()
        h0 = np.radians(self.heading_deg)
        if self.radius_m > 0:
            k = self.turn / self.radius_m
            h = h0 + k * s
            x = self.x0 + (np.cos(h0) - np.cos(h)) / k
            y = self.y0 + (np.sin(h) - np.sin(h0)) / k
        else:
            h = np.full_like(s, h0)
            x, y = self.x0 + s * np.sin(h0), self.y0 + s * np.cos(h0)
        return np.c_[x, y], np.degrees(h)

    def wobble_rad(self) -> np.ndarray:
        """(n, 3) small rotation vectors (camera axes) of the attitude wobble."""
        t = self.times()
        w = np.zeros((self.n_frames, 3))
        for axis, f, ph in self.wobble:
            w[:, int(axis)] += np.sin(2 * np.pi * f * t + ph)
        return np.radians(self.wobble_deg) * w / max(1, len(self.wobble) // 3)

    def cameras(self, intr: dict, frames: np.ndarray | None = None) -> list[PinholeCamera]:
        """The camera of every frame (or of ``frames``)."""
        xy, heading = self.track()
        sel = slice(None) if frames is None else np.asarray(frames)
        out = []
        for p, h, w in zip(xy[sel], heading[sel], self.wobble_rad()[sel], strict=True):
            C = np.array([p[0], p[1], self.z_m])
            R = cv2.Rodrigues(w)[0] @ pose_from_angles(C, h + self.look_deg, self.off_nadir_deg)
            out.append(PinholeCamera(intr["fx"], intr["fy"], intr["cx"], intr["cy"],
                                     intr["width"], intr["height"], R, C))  # fmt: skip
        return out


def video_conf(conf: dict | None) -> tuple[dict, dict]:
    """(conf with defaults, intrinsics) of a ``demo_video`` configuration; ConfigError if bad."""
    unknown = sorted(set(conf or {}) - set(DEFAULTS) - {"fy", "cx", "cy"})
    if unknown:
        raise ConfigError(f"demo_video: unknown keys {unknown} (known: {sorted(DEFAULTS)})")
    c = {**DEFAULTS, **{k: v for k, v in (conf or {}).items() if v is not None}}
    checks = {"n_frames": c["n_frames"] >= 2, "fps": c["fps"] > 0, "speed_mps": c["speed_mps"] >= 0,
              "agl_m": c["agl_m"] > 0, "width": c["width"] >= 32, "height": c["height"] >= 32,
              "fx": c["fx"] > 0, "off_nadir_deg": 0 <= c["off_nadir_deg"] < 60,
              "turn_radius_m": c["turn_radius_m"] >= 0, "candidates": c["candidates"] >= 1}  # fmt: skip
    bad = [k for k, ok in checks.items() if not ok]
    if bad:
        raise ConfigError(f"demo_video: bad {', '.join(f'{k} = {c[k]!r}' for k in bad)}")
    w, h = int(c["width"]), int(c["height"])
    intr = {"width": w, "height": h, "fx": float(c["fx"]), "fy": float(c.get("fy") or c["fx"]),
            "cx": float(c.get("cx") or 0.504 * w), "cy": float(c.get("cy") or 0.495 * h),
            "dist": [float(v) for v in c["dist"]]}  # fmt: skip
    return c, intr


def _footprints(world: World, cams: list[PinholeCamera]) -> tuple[np.ndarray, np.ndarray]:
    """Ground z under each camera (n,) and its footprint on that plane (n, 32, 2)."""
    zg = np.array([world.ground(*c.C[:2]) for c in cams])
    return zg, np.stack([ground_footprint(c, z) for c, z in zip(cams, zg, strict=True)])


def _inside(world: World, cams: list[PinholeCamera], inset: float,
            fps: np.ndarray | None = None) -> bool:  # fmt: skip
    """Are all the footprints inside the map shrunk by ``inset``?"""
    pts = (_footprints(world, cams)[1] if fps is None else fps).reshape(-1, 2)
    mx0, my0, mx1, my1 = world.map_bounds
    lo, hi = pts.min(0), pts.max(0)
    return bool(lo[0] > mx0 + inset and lo[1] > my0 + inset and hi[0] < mx1 - inset
                and hi[1] < my1 - inset)  # fmt: skip


def _entropy(labels: np.ndarray) -> float:
    p = np.bincount(labels.ravel()) / max(1, labels.size)
    p = p[p > 0]
    return float(-(p * np.log(p)).sum())


def _score(world: World, cams: list[PinholeCamera], fps: np.ndarray, clearance: float) -> float:
    """Mean + minimum class entropy of 8 footprints along the path, or -1 if a camera comes
    closer than ``clearance`` to a surface within 60 m of its ground point."""
    xy = np.array([c.C[:2] for c in cams])
    pts = np.concatenate([fps.reshape(-1, 2), xy - PAD_M, xy + PAD_M])
    x0, y0 = pts.min(0)
    x1, y1 = pts.max(0)
    res = max(2.0, (x1 - x0) / 300, (y1 - y0) / 300)
    g = Grid(x0, y1, res, max(1, int((x1 - x0) / res)), max(1, int((y1 - y0) / res)))
    surf = rasterize(world.layout, g, EPOCH_QUERY, world.texture)
    k = 2 * int(PAD_M / res) + 1
    top = cv2.dilate(surf.dsm, np.ones((k, k), np.uint8))
    c, r = g.to_pixel(xy[:, 0], xy[:, 1])
    r = np.clip(np.rint(r).astype(int), 0, g.height - 1)
    c = np.clip(np.rint(c).astype(int), 0, g.width - 1)
    if np.any(top[r, c] > np.array([cam.C[2] for cam in cams]) - clearance):
        return -1.0
    ent = []
    for i in np.linspace(0, len(cams) - 1, 8).round().astype(int):
        fc, fr = g.to_pixel(fps[i, :, 0], fps[i, :, 1])
        mask = np.zeros((g.height, g.width), np.uint8)
        cv2.fillPoly(mask, [np.rint(np.c_[fc, fr]).astype(np.int32)], 1)
        ent.append(_entropy(surf.label[mask > 0]))
    return float(np.mean(ent) + np.min(ent))


def plan_flight(world: World, conf: dict, intr: dict, rng: np.random.Generator) -> Flight:
    """The most varied of ``candidates`` seeded flights that fit the map (see the module doc)."""
    mx0, my0, mx1, my1 = world.map_bounds
    inset = float(conf["inset_m"])
    best, best_score, found = None, -1.0, 0
    for _ in range(4000):
        if found >= int(conf["candidates"]):
            break
        wob = tuple((float(a), float(rng.uniform(0.08, 0.4)), float(rng.uniform(0, 2 * np.pi)))
                    for a in (0, 0, 1, 1, 2, 2))  # fmt: skip
        fl = Flight(float(rng.uniform(mx0, mx1)), float(rng.uniform(my0, my1)),
                    float(rng.uniform(0, 360)), int(rng.choice([-1, 1])), float(conf["turn_radius_m"]),
                    0.0, float(conf["speed_mps"]), float(conf["fps"]), int(conf["n_frames"]),
                    float(conf["look_deg"]), float(conf["off_nadir_deg"]), wob,
                    float(conf["wobble_deg"]))  # fmt: skip
        xy, _ = fl.track()
        if xy.min(0)[0] < mx0 or xy.min(0)[1] < my0 or xy.max(0)[0] > mx1 or xy.max(0)[1] > my1:
            continue
        z = float(np.mean(world.layout.terrain(xy[:, 0], xy[:, 1]))) + float(conf["agl_m"])
        fl = replace(fl, z_m=z)
        some = np.linspace(0, fl.n_frames - 1, 9).round().astype(int)
        if not _inside(world, fl.cameras(intr, some), inset):
            continue  # quick rejection on 9 frames
        cams = fl.cameras(intr)
        _, fps = _footprints(world, cams)
        if not _inside(world, cams, inset, fps):
            continue
        score = _score(world, cams, fps, float(conf["clearance_m"]))
        if score < 0:
            continue
        found += 1
        if score > best_score:
            best, best_score = fl, score
    if best is None:
        raise ConfigError(
            "demo_video: no flight fits the map: shorten it (n_frames, speed_mps), fly lower "
            "(agl_m) or closer to nadir (off_nadir_deg), or use a larger demo map"
        )
    log.info("demo video: flight chosen of %d candidates (entropy score %.2f)", found, best_score)
    return best


class CloudBlocks:
    """A cloud sorted into ``block_m`` ground squares (column by column), so that a camera's
    points are cheap to find: every block is cut into chunks of at most ``chunk`` consecutive
    points (strips of its raster rows for a height-field cloud) with their bounding boxes; the
    chunks in view form runs of the sorted cloud, in its order."""

    def __init__(self, cloud: PointCloud, block_m: float = 12.0, chunk: int = 1024) -> None:
        ij = np.floor((cloud.xyz[:, :2] - cloud.xyz[:, :2].min(0)) / block_m).astype(np.int64)
        key = ij[:, 0] * (int(ij[:, 1].max()) + 1) + ij[:, 1]
        order = np.argsort(key, kind="stable")
        self.cloud = PointCloud(cloud.xyz[order], cloud.rgb[order], cloud.spacing)
        _, b0, bn = np.unique(key[order], return_index=True, return_counts=True)
        per = -(-bn // chunk)  # chunks per block
        k = np.arange(int(per.sum())) - np.repeat(np.cumsum(per) - per, per)
        self.start = np.repeat(b0, per) + k * chunk
        self.counts = np.minimum(chunk, np.repeat(b0 + bn, per) - self.start)
        lo = np.minimum.reduceat(self.cloud.xyz, self.start)
        hi = np.maximum.reduceat(self.cloud.xyz, self.start)
        pick = np.array([[i & 1, (i >> 1) & 1, (i >> 2) & 1] for i in range(8)], bool)
        self.corners = np.where(pick[None], hi[:, None], lo[:, None])  # (chunks, 8, 3)

    def visible(self, cam: PinholeCamera, near: float = 0.5, pad_px: float = 8.0) -> PointCloud:
        """The points of the chunks whose box projects onto ``cam``'s image grown by ``pad_px``
        (``render``'s largest splat reaches in from there) or crosses the ``near`` plane; a box
        wholly behind it has no point ``render`` would draw."""
        uv, z = cam.project(self.corners.reshape(-1, 3))
        uv, z = uv.reshape(-1, 8, 2), z.reshape(-1, 8)
        lo, hi = uv.min(1), uv.max(1)
        front = z > near
        keep = front.any(1) & (~front.all(1) | (
            (hi[:, 0] >= -pad_px) & (lo[:, 0] <= cam.width + pad_px)
            & (hi[:, 1] >= -pad_px) & (lo[:, 1] <= cam.height + pad_px)
        ))  # fmt: skip
        # runs of consecutive kept chunks -> contiguous slices of the sorted cloud
        edge = np.diff(np.r_[0, keep.astype(np.int8), 0])
        first, last = np.flatnonzero(edge == 1), np.flatnonzero(edge == -1) - 1
        runs = list(zip(self.start[first], self.start[last] + self.counts[last], strict=True))
        c = self.cloud
        xyz = np.concatenate([c.xyz[i:j] for i, j in runs]) if runs else c.xyz[:0]
        rgb = np.concatenate([c.rgb[i:j] for i, j in runs]) if runs else c.rgb[:0]
        return PointCloud(xyz, rgb, self.cloud.spacing)


def _write_mp4(path: Path, frames_bgr, n: int, fps: float, size: tuple[int, int]) -> None:
    """Write the frames (an iterable of BGR images) as MPEG-4 (mp4v), atomically; the file is
    re-opened to check it decodes to ``n`` frames of ``size``."""
    with atomic_path(path) as tmp:
        vw = cv2.VideoWriter(str(tmp), cv2.VideoWriter_fourcc(*"mp4v"), float(fps), size)
        if not vw.isOpened():
            raise RuntimeError(f"{path}: OpenCV cannot write mp4v video here")
        try:
            for img in frames_bgr:
                vw.write(img)
        finally:
            vw.release()
        cap = cv2.VideoCapture(str(tmp))
        got, shape = 0, None
        while True:
            ok, img = cap.read()
            if not ok:
                break
            got, shape = got + 1, img.shape[1::-1]
        cap.release()
        if got != n or shape != tuple(size):
            raise RuntimeError(f"{path}: wrote {n} frames of {size}, reads back {got} of {shape}")


def generate_video(scene_path: str | Path, out_dir: str | Path, conf: dict | None = None,
                   seed: int = 10, video_name: str = "flight.mp4",
                   truth_name: str = "truth.json") -> list[dict]:  # fmt: skip
    """Write ``out_dir/flight.mp4``, ``out_dir/truth.json`` (one record per frame, the frames
    contract) and ``out_dir/flight.json`` (the flight); returns the truth records."""
    t0 = time.perf_counter()
    c, intr = video_conf(conf)
    scene = json.loads(Path(scene_path).read_text())
    world = World(scene)
    ss_plan, ss_cloud, ss_frames = np.random.SeedSequence([int(seed), int(scene["seed"])]).spawn(3)
    flight = plan_flight(world, c, intr, np.random.default_rng(ss_plan))
    cams = flight.cameras(intr)
    zg, fps = _footprints(world, cams)
    lo, hi = fps.reshape(-1, 2).min(0) - PAD_M, fps.reshape(-1, 2).max(0) + PAD_M
    bounds = (float(lo[0]), float(lo[1]), float(hi[0]), float(hi[1]))
    ground = np.concatenate([fps, np.broadcast_to(zg[:, None, None], fps[..., :1].shape)], axis=2)
    near = np.linalg.norm(ground - np.array([cam.C for cam in cams])[:, None], axis=2).min(1)
    res = min(frame_resolution(cam, bounds, z, d, int(c["max_cells"]))
              for cam, z, d in zip(cams, zg, near, strict=True))  # fmt: skip
    t1 = time.perf_counter()
    blocks = CloudBlocks(corridor_cloud(world, bounds, res, np.random.default_rng(ss_cloud)))
    t2, cpu2 = time.perf_counter(), time.process_time()
    log.info("demo video: corridor %.0f x %.0f m at %.2f m, %d points (%.1f s)",
             bounds[2] - bounds[0], bounds[3] - bounds[1], res, len(blocks.cloud), t2 - t1)  # fmt: skip
    lens = Lens(cams[0], intr["dist"], margin=None)
    rngs = [np.random.default_rng(s) for s in ss_frames.spawn(len(cams))]
    out = Path(out_dir)

    def frames():
        for i, (cam, rng) in enumerate(zip(cams, rngs, strict=True)):
            img = camera_image(blocks.visible(lens.canvas(cam)), cam, lens, rng)
            if i % 40 == 0:
                log.info("demo video: frame %d / %d", i, len(cams))
            yield cv2.cvtColor(img, cv2.COLOR_RGB2BGR)

    with threadpool_limits(1, "blas"):  # (N, 3) @ (3, 3) per frame: threads only spin
        _write_mp4(
            out / video_name, frames(), len(cams), flight.fps, (intr["width"], intr["height"])
        )
    t3, cpu3 = time.perf_counter(), time.process_time()
    _, heading = flight.track()
    truth = [{
        "image": f"{video_name}#{i:06d}",
        "frame": i,
        "time_s": round(i / flight.fps, 6),
        "status": "registered",
        "camera_center_xyz": [float(v) for v in cam.C],
        "R_world_to_cam": np.asarray(cam.R).tolist(),
        "intrinsics": dict(intr),
        "view": {"off_nadir_deg": flight.off_nadir_deg, "agl_m": float(cam.C[2] - z),
                 "heading_deg": float((heading[i] + flight.look_deg) % 360)},
        "ground_z": float(z),
        "footprint_xy": ground_footprint(cam, z, 2).tolist(),
        "sun": vars(FRAME_SUN),
    } for i, (cam, z) in enumerate(zip(cams, zg, strict=True))]  # fmt: skip
    write_json(out / truth_name, truth)
    write_json(out / Path(video_name).with_suffix(".json"), {
        "video": video_name, "seed": int(seed), "scene_seed": int(scene["seed"]), "conf": c,
        "flight": asdict(flight), "corridor_bounds": bounds, "corridor_res_m": res,
        "corridor_points": len(blocks.cloud),
    })  # fmt: skip
    n = len(cams)
    log.info("demo video: %d frames in %.1f s (plan %.1f s, corridor %.1f s, %.2f s per frame, "
             "%.2f s CPU)", n, t3 - t0, t1 - t0, t2 - t1, (t3 - t2) / n, (cpu3 - cpu2) / n)  # fmt: skip
    return truth
