"""CPU cost of rule demo_video (georeg.demo.video.generate_video) with the default config.

    python benchmarks/bench_demo_video.py SCENE OUT_DIR
    python benchmarks/bench_demo_video.py SCENE --ab BASELINE_CHECKOUT [--every 8]

SCENE: a ``results/demo/scene.json`` of the default config (rule demo_scene). Generates the
default flight (``trajectory.demo_video`` of config/config.yaml) into OUT_DIR and prints the
process CPU seconds, the per-frame CPU the module logs, and the SHA-256 of flight.mp4,
truth.json and of the decoded frames. Run it once with ``PYTHONPATH`` at a checkout of the
baseline and once at the change: equal hashes = the same video.

``--ab``: the per-frame rendering (visible points + ``camera_image``) of the default flight by
BASELINE_CHECKOUT's ``georeg/frames/render.py`` and ``CloudBlocks`` and by this checkout's,
alternating frame by frame in one process (every ``--every``-th frame), CPU s per frame, their
ratio and whether the frames are identical (the planning and corridor are shared).
"""

from __future__ import annotations

import hashlib
import importlib.util
import json
import logging
import sys
import time
from pathlib import Path

import cv2
import yaml

from georeg.demo.video import generate_video


def _load(name: str, path: Path):
    spec = importlib.util.spec_from_file_location(name, path)
    mod = importlib.util.module_from_spec(spec)
    sys.modules[name] = mod
    spec.loader.exec_module(mod)
    return mod


def ab(scene_path: Path, base: Path, every: int) -> None:
    """Alternate the baseline's and this checkout's per-frame rendering (see the module doc)."""
    import numpy as np
    from threadpoolctl import threadpool_limits

    import georeg.demo.frames as F
    from georeg.demo import video as V

    old_r = _load("base_render", base / "georeg/frames/render.py")
    old_v = _load("base_video", base / "georeg/demo/video.py")
    conf = dict(yaml.safe_load(Path("config/config.yaml").read_text())["trajectory"]["demo_video"])
    seed = int(conf.pop("seed"))
    c, intr = V.video_conf(conf)
    scene = json.loads(scene_path.read_text())
    world = F.World(scene)
    ss_plan, ss_cloud, _ = np.random.SeedSequence([seed, int(scene["seed"])]).spawn(3)
    cams = V.plan_flight(world, c, intr, np.random.default_rng(ss_plan)).cameras(intr)
    zg, fps = V._footprints(world, cams)
    lo, hi = fps.reshape(-1, 2).min(0) - V.PAD_M, fps.reshape(-1, 2).max(0) + V.PAD_M
    bounds = (float(lo[0]), float(lo[1]), float(hi[0]), float(hi[1]))
    ground = np.concatenate([fps, np.broadcast_to(zg[:, None, None], fps[..., :1].shape)], axis=2)
    near = np.linalg.norm(ground - np.array([k.C for k in cams])[:, None], axis=2).min(1)
    res = min(F.frame_resolution(k, bounds, z, d, int(c["max_cells"]))
              for k, z, d in zip(cams, zg, near, strict=True))  # fmt: skip
    cloud = F.corridor_cloud(world, bounds, res, np.random.default_rng(ss_cloud))
    variants = {"baseline": (old_v.CloudBlocks(cloud), old_r.render),
                "this": (V.CloudBlocks(cloud), F.render)}  # fmt: skip
    lens = F.Lens(cams[0], intr["dist"], margin=None)
    cpu = dict.fromkeys(variants, 0.0)
    same, frames = True, range(every // 2, len(cams), every)
    with threadpool_limits(1, "blas"):
        for i in frames:
            imgs = []
            for name, (blocks, rend) in variants.items():
                F.render = rend
                t = time.process_time()
                vis = blocks.visible(lens.canvas(cams[i]))
                imgs.append(F.camera_image(vis, cams[i], lens, np.random.default_rng([i, 7])))
                cpu[name] += time.process_time() - t
            same &= bool(np.array_equal(*imgs))
    n = len(frames)
    print(f"{n} frames: baseline {cpu['baseline'] / n:.3f}, this {cpu['this'] / n:.3f} CPU s per "
          f"frame, ratio {cpu['this'] / cpu['baseline']:.3f}, frames identical: {same}")  # fmt: skip


def main() -> None:
    if "--ab" in sys.argv:
        i = sys.argv.index("--ab")
        every = int(sys.argv[sys.argv.index("--every") + 1]) if "--every" in sys.argv else 8
        ab(Path(sys.argv[1]), Path(sys.argv[i + 1]), every)
        return
    scene, out = Path(sys.argv[1]), Path(sys.argv[2])
    logging.basicConfig(level=logging.INFO, format="%(message)s")
    conf = dict(yaml.safe_load(Path("config/config.yaml").read_text())["trajectory"]["demo_video"])
    seed = int(conf.pop("seed"))
    t0, c0 = time.perf_counter(), time.process_time()
    generate_video(scene, out, conf, seed)
    cpu, wall = time.process_time() - c0, time.perf_counter() - t0
    h = hashlib.sha256()
    cap = cv2.VideoCapture(str(out / "flight.mp4"))
    while True:
        ok, img = cap.read()
        if not ok:
            break
        h.update(img.tobytes())
    cap.release()
    files = {p: hashlib.sha256((out / p).read_bytes()).hexdigest()[:16]
             for p in ("flight.mp4", "truth.json")}  # fmt: skip
    print(
        f"generate_video: {cpu:.1f} CPU s, {wall:.1f} s wall; sha256 {files}, "
        f"decoded frames {h.hexdigest()[:16]}"
    )


if __name__ == "__main__":
    main()
