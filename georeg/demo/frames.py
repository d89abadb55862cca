"""Demo drone frames: perspective views of the demo city with a known pose.

The city of ``generate_scene`` is rebuilt from ``scene.json`` (same seed streams, same layout,
texture and query-epoch changes), rasterised finely (0.25-1 m) around each frame's footprint, lit
by another sun than the orthophoto (afternoon), splatted with facades into a pinhole camera
(``georeg.frames.render``), then given another camera response (tone curve, white balance,
vignetting), blur, noise and radial-tangential lens distortion. Nothing here reads the map
products: the frames are independent of the LiDAR and the orthophoto they are registered to.
"""

from __future__ import annotations

import logging
import time
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from georeg.demo import spectra as S
from georeg.demo.changes import apply_changes, car_changes
from georeg.demo.layout import EPOCH_QUERY, make_layout
from georeg.demo.raster import Grid, Texture, rasterize
from georeg.demo.render import render_orthophoto
from georeg.demo.scene import LAYOUT_PAD_M, ORIGIN, RNG_STREAMS, place_inside, place_outside
from georeg.frames.render import (
    PinholeCamera,
    PointCloud,
    heightfield_cloud,
    pose_from_angles,
    render,
)
from georeg.io.atomic import atomic_path, write_json

log = logging.getLogger(__name__)

VIEW_CANDIDATES = 12  # valid poses drawn per view; the one with the most varied footprint wins
FRAME_SUN = S.Sun(225.0, 38.0)  # afternoon, another day: shadows towards the north-east
CAMERA = {"width": 800, "height": 600, "fx": 700.0, "fy": 700.0, "cx": 403.2, "cy": 297.1,
          "dist": [-0.06, 0.015, 0.0005, -0.0003, 0.0]}  # fmt: skip
# name, off-nadir (deg), height above ground (m), heading (deg), inside the map
DEFAULT_FRAMES = [
    {"name": "nadir_120", "off_nadir_deg": 0.0, "agl_m": 120.0, "heading_deg": 30.0},
    {"name": "oblique35_100", "off_nadir_deg": 35.0, "agl_m": 100.0, "heading_deg": 200.0},
    {"name": "oblique45_300", "off_nadir_deg": 45.0, "agl_m": 300.0, "heading_deg": 110.0},
    {
        "name": "outside",
        "off_nadir_deg": 20.0,
        "agl_m": 150.0,
        "heading_deg": 300.0,
        "outside": True,
    },
]


class World:
    """The demo city at query time, rebuilt exactly as ``generate_scene`` built it."""

    def __init__(self, scene: dict[str, Any]) -> None:
        c = scene["conf"]
        rngs = dict(zip(RNG_STREAMS, (np.random.default_rng(s) for s in
                    np.random.SeedSequence(int(c["seed"])).spawn(len(RNG_STREAMS))), strict=True))  # fmt: skip
        size = float(scene["map"]["width"]) * float(scene["map"]["gsd_m"])
        x0, y0 = ORIGIN
        self.map_bounds = tuple(scene["map"]["bounds"])
        self.world_bounds = tuple(scene["world_bounds"])
        w = self.world_bounds
        extent = (
            w[0] - LAYOUT_PAD_M,
            w[1] - LAYOUT_PAD_M,
            w[2] + LAYOUT_PAD_M,
            w[3] + LAYOUT_PAD_M,
        )
        self.layout = make_layout(rngs["layout"], extent, (x0 + size / 2, y0 - size / 2), size)
        self.texture = Texture(rngs["texture"], extent)
        q = c["query"]
        demo_fl = place_inside(rngs["demo_flight"], q, self.map_bounds, size)
        out_fl = place_outside(rngs["outside_flight"], q, self.map_bounds, float(c["margin_m"]))
        apply_changes(self.layout, rngs["changes"], demo_fl)
        car_changes(self.layout, [demo_fl.bbox(), out_fl.bbox()])

    def ground(self, x: float, y: float) -> float:
        return float(self.layout.terrain(np.array(x), np.array(y)))


def ground_footprint(cam: PinholeCamera, z_ground: float, n: int = 8) -> np.ndarray:
    """Image border rays intersected with the plane z = z_ground: (4 n, 2) map x, y."""
    W, H = cam.width - 1, cam.height - 1
    t = np.linspace(0, 1, n, endpoint=False)
    uv = np.concatenate([np.c_[t * W, 0 * t], np.c_[W + 0 * t, t * H], np.c_[W - t * W, H + 0 * t],
                         np.c_[0 * t, H - t * H]])  # fmt: skip
    d = cam.rays(uv)
    s = (z_ground - cam.C[2]) / np.minimum(d[:, 2], -1e-3)
    return cam.C[None, :2] + s[:, None] * d[:, :2]


def _camera(intr: dict, R: np.ndarray, C: np.ndarray) -> PinholeCamera:
    return PinholeCamera(intr["fx"], intr["fy"], intr["cx"], intr["cy"], intr["width"],
                         intr["height"], R, C)  # fmt: skip


def place_frame(world: World, spec: dict, rng: np.random.Generator, intr: dict) -> PinholeCamera:
    """A camera pose for ``spec``: footprint inside the map shrunk by 15 m (or entirely outside
    it, grown by 15 m, for ``outside``), camera at least 30 m above every surface nearby; of
    ``VIEW_CANDIDATES`` such poses, the one whose footprint has the highest class entropy."""
    mx0, my0, mx1, my1 = world.map_bounds
    wx0, wy0, wx1, wy1 = world.world_bounds
    outside = bool(spec.get("outside"))
    best, best_score, found = None, -1.0, 0
    for _ in range(4000):
        if found >= int(spec.get("candidates", VIEW_CANDIDATES)):
            break
        if outside:
            x, y = rng.uniform(wx0, wx1), rng.uniform(wy0, wy1)
        else:
            x, y = rng.uniform(mx0, mx1), rng.uniform(my0, my1)
        zg = world.ground(x, y)
        C = np.array([x, y, zg + float(spec["agl_m"])])
        R = pose_from_angles(C, float(spec["heading_deg"]), float(spec["off_nadir_deg"]))
        cam = _camera(intr, R, C)
        fp = ground_footprint(cam, zg)
        bx = (fp[:, 0].min(), fp[:, 1].min(), fp[:, 0].max(), fp[:, 1].max())
        if outside:
            ok = bx[0] > mx1 + 15 or bx[2] < mx0 - 15 or bx[1] > my1 + 15 or bx[3] < my0 - 15
            ok &= (
                bx[0] > wx0 - 300 and bx[2] < wx1 + 300 and bx[1] > wy0 - 300 and bx[3] < wy1 + 300
            )
        else:
            ok = bx[0] > mx0 + 15 and bx[2] < mx1 - 15 and bx[1] > my0 + 15 and bx[3] < my1 - 15
        if not ok:
            continue
        g = Grid(x - 60, y + 60, 2.0, 60, 60)
        surf = rasterize(world.layout, g, EPOCH_QUERY, world.texture)
        if float(surf.dsm.max()) >= C[2] - 30:
            continue
        found += 1
        # a view a pilot would take: of the candidates, the footprint with the most varied
        # content (class entropy): a bare roof or a parking lot whose cars moved since the map
        # would leave nothing to match
        res = max(2.0, (bx[2] - bx[0]) / 200)
        fg = Grid(
            bx[0],
            bx[3],
            res,
            max(1, int((bx[2] - bx[0]) / res)),
            max(1, int((bx[3] - bx[1]) / res)),
        )
        p = np.bincount(rasterize(world.layout, fg, EPOCH_QUERY, world.texture).label.ravel()) / (
            fg.width * fg.height
        )
        p = p[p > 0]
        score = float(-(p * np.log(p)).sum())
        if score > best_score:
            best, best_score = cam, score
    if best is not None:
        return best
    raise ValueError(f"demo frame {spec['name']}: no pose fits (map too small for this view?)")


def _facade(rgb_roof: np.ndarray, z: np.ndarray, base: np.ndarray) -> np.ndarray:
    """Facade colour: light concrete with darker window bands every 3.5 m storey."""
    floor = ((z - base) % 3.5) < 1.3
    col = np.array([172, 166, 156], np.float32)[None, :] * np.where(floor, 0.55, 0.95)[:, None]
    return np.clip(0.75 * col + 0.25 * rgb_roof, 0, 255).astype(np.uint8)


def frame_resolution(cam: PinholeCamera, bounds: tuple[float, float, float, float], zg: float,
                     near: float, max_cells: int) -> float:  # fmt: skip
    """Raster cell (m) of a cloud for ``cam``: ~0.6 of the ground pixel at the nearest ground point,
    0.2-1 m, coarser if ``bounds`` would exceed ``max_cells`` cells."""
    x0, y0, x1, y1 = bounds
    res = float(np.clip(0.6 * min(cam.C[2] - zg, near) / cam.fx, 0.2, 1.0))
    return max(res, float(np.sqrt((x1 - x0) * (y1 - y0) / max_cells)))


def corridor_cloud(world: World, bounds: tuple[float, float, float, float], res: float,
                   rng: np.random.Generator) -> PointCloud:  # fmt: skip
    """The query-epoch city in ``bounds`` (x0, y0, x1, y1) as a height-field cloud of ``res`` m
    cells lit by ``FRAME_SUN``, with storeyed facades (one ``rng`` draw: the surface noise)."""
    x0, y0, x1, y1 = bounds
    grid = Grid(x0, y1, res, int((x1 - x0) / res), int((y1 - y0) / res))
    surf = rasterize(world.layout, grid, EPOCH_QUERY, world.texture)
    rgb = render_orthophoto(surf, FRAME_SUN, rng).transpose(1, 2, 0)
    n_surf = surf.dsm.size
    cloud = heightfield_cloud(np.ascontiguousarray(rgb), surf.dsm, grid.transform,
                              wall_step_m=res, wall_min_m=max(1.0, 2 * res))  # fmt: skip
    walls = slice(n_surf, None)
    base = world.layout.terrain(cloud.xyz[walls, 0], cloud.xyz[walls, 1])
    cloud.rgb[walls] = _facade(cloud.rgb[walls].astype(np.float32), cloud.xyz[walls, 2], base)
    return cloud


class Lens:
    """What one camera's intrinsics do to every frame: the radial-tangential distortion (a remap
    from a pinhole canvas ``margin`` x the image size larger on each side; None: just what the
    distortion needs, + 3 px) and the vignetting."""

    def __init__(self, cam: PinholeCamera, dist: list[float], margin: float | None = 0.12) -> None:
        self.size = (cam.width, cam.height)
        uu, vv = np.meshgrid(
            np.arange(cam.width, dtype=np.float64), np.arange(cam.height, dtype=np.float64)
        )
        pts = np.c_[uu.ravel(), vv.ravel()].reshape(-1, 1, 2)
        und = cv2.undistortPoints(pts, cam.K, np.asarray(dist, float), R=None, P=cam.K,
                                  criteria=(cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 40, 1e-6)).reshape(-1, 2)  # fmt: skip
        if margin is None:
            over = np.r_[-und.min(0), und.max(0) - [cam.width - 1, cam.height - 1]] + 3
            margin = float(max(0.0, *(over / [cam.width, cam.height, cam.width, cam.height])))
        self.margin = m = margin
        self.mx = (und[:, 0] + m * cam.width).reshape(cam.height, cam.width).astype(np.float32)
        self.my = (und[:, 1] + m * cam.height).reshape(cam.height, cam.width).astype(np.float32)
        r2 = ((uu - cam.cx) ** 2 + (vv - cam.cy) ** 2) / (cam.width**2 / 4 + cam.height**2 / 4)
        self.vignette = (1.0 - 0.25 * r2)[..., None].astype(np.float32)

    def canvas(self, cam: PinholeCamera) -> PinholeCamera:
        """The ideal pinhole rendered before distortion: same pose and focal, larger image."""
        m = self.margin
        return PinholeCamera(cam.fx, cam.fy, cam.cx + m * cam.width, cam.cy + m * cam.height,
                             int(cam.width * (1 + 2 * m)), int(cam.height * (1 + 2 * m)), cam.R, cam.C)  # fmt: skip


def camera_image(cloud: PointCloud, cam: PinholeCamera, lens: Lens,
                 rng: np.random.Generator) -> np.ndarray:  # fmt: skip
    """``cloud`` seen by ``cam`` through ``lens``, with another camera response: white balance,
    tone curve, vignetting, blur and noise (one ``rng`` draw); RGB (H, W, 3) uint8."""
    if lens.size != (cam.width, cam.height):
        raise ValueError(f"lens for {lens.size}, camera {cam.width} x {cam.height}")
    ideal = render(cloud, lens.canvas(cam)).image
    hole = ~np.any(ideal > 0, axis=2)
    if hole.any():
        ideal = cv2.inpaint(ideal, hole.astype(np.uint8), 3, cv2.INPAINT_TELEA)
    img = cv2.remap(ideal, lens.mx, lens.my, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REFLECT)
    img = img.astype(np.float32) / 255.0 * np.array([1.06, 1.0, 0.88], np.float32)
    img = np.clip(img, 0, 1) ** 0.8
    img *= lens.vignette
    img = cv2.GaussianBlur(img, (0, 0), 0.6)
    img = 255 * img + rng.normal(0, 2.5, img.shape).astype(np.float32)
    return np.clip(np.rint(img), 0, 255).astype(np.uint8)


def render_frame(world: World, cam: PinholeCamera, dist: list[float], rng: np.random.Generator,
                 max_cells: int = 5_000_000) -> np.ndarray:  # fmt: skip
    """The distorted, re-toned, noisy RGB frame (H, W, 3) uint8 seen by ``cam``."""
    zg = world.ground(*cam.C[:2])
    fp = ground_footprint(cam, zg)
    pad = 60.0
    bounds = (fp[:, 0].min() - pad, fp[:, 1].min() - pad, fp[:, 0].max() + pad,
              fp[:, 1].max() + pad)  # fmt: skip
    near = float(np.min(np.linalg.norm(np.c_[fp, np.full(len(fp), zg)] - cam.C, axis=1)))
    res = frame_resolution(cam, bounds, zg, near, max_cells)
    cloud = corridor_cloud(world, bounds, res, rng)
    return camera_image(cloud, cam, Lens(cam, dist), rng)


def generate_frames(scene_path: str | Path, outdir: str | Path, frames: list[dict] | None = None,
                    seed: int = 9, camera: dict | None = None) -> list[dict]:  # fmt: skip
    """Write ``outdir/<name>.png`` for each frame spec and ``outdir/truth.json``; returns the truth.

    truth.json: a list in the frames contract (image, status expected, camera_center_xyz,
    R_world_to_cam, intrinsics with dist) plus the view parameters and the ground footprint.
    """
    import json

    t0 = time.perf_counter()
    scene = json.loads(Path(scene_path).read_text())
    world = World(scene)
    intr = {**CAMERA, **(camera or {})}
    out = Path(outdir)
    out.mkdir(parents=True, exist_ok=True)
    truth = []
    specs = frames if frames is not None else DEFAULT_FRAMES
    rngs = np.random.SeedSequence([int(seed), int(scene["seed"])]).spawn(len(specs))
    for spec, ss in zip(specs, rngs, strict=True):
        rng = np.random.default_rng(ss)
        cam = place_frame(world, spec, rng, intr)
        img = render_frame(world, cam, intr["dist"], rng)
        path = out / f"{spec['name']}.png"
        with atomic_path(path) as tmp:
            cv2.imwrite(str(tmp), cv2.cvtColor(img, cv2.COLOR_RGB2BGR))
        zg = world.ground(*cam.C[:2])
        truth.append({
            "image": path.name,
            "status": "not_found" if spec.get("outside") else "registered",
            "camera_center_xyz": [float(v) for v in cam.C],
            "R_world_to_cam": np.asarray(cam.R).tolist(),
            "intrinsics": dict(intr),
            "view": {k: spec[k] for k in ("off_nadir_deg", "agl_m", "heading_deg")},
            "ground_z": zg,
            "footprint_xy": ground_footprint(cam, zg, 2).tolist(),
            "sun": vars(FRAME_SUN),
        })  # fmt: skip
        log.info(
            "demo frame %s: C = %s (%.1f s)",
            spec["name"],
            np.round(cam.C, 1),
            time.perf_counter() - t0,
        )
    write_json(out / "truth.json", truth)
    return truth
