"""Texture-free probes of the demo frame oblique35_100 (docs/BENCHMARKS.md "Frame
geo-localisation", paragraph oblique35_100; time-boxed, negative).

Reads a finished default run (``results/``: demo frames and truth, map mosaics, index, the
frames' poses.json is not needed) and prints, for a frame:

* ``cfog``: the frame orthorectified onto the DSM under a pose (1 m grid, cells occluded in a
  height-field render masked) and searched in the ortho window (+ ``margin`` m) by
  ``georeg.register.dense.dense_search`` (CFOG, FFT, robust z-score), rotations restricted to
  +-15 deg of the pose (``--all-rotations``: 0-360 deg in 5 deg steps); poses: the truth moved by
  a few offsets, then the coarse step's best nadir votes;
* ``mi``: ``georeg.frames.refine.refine_pose`` with a wide simplex from a 3 x 3 grid (+-24 m)
  around the best votes, and (``--basin``) from the truth's rotation with the position moved
  by 6 and 12 m in 4 directions; the final NMI + GC cost and the error.

    python benchmarks/diag_oblique35.py cfog [--frame oblique35_100.png] [--results results]
    python benchmarks/diag_oblique35.py mi [--frame outside.png] [--votes 2] [--basin]
    python benchmarks/diag_oblique35.py localize [--conf JSON]

``localize``: ``localize_frame`` (defaults, this checkout's code) on the 4 demo frames, with the
errors, the winning path, the intensity search's record and the seconds.
"""

from __future__ import annotations

import argparse
import inspect
import json
import sys
import time
from pathlib import Path

import cv2
import numpy as np
import rasterio
from rasterio.enums import Resampling
from rasterio.windows import from_bounds

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from georeg.frames.coarse import coarse_locate  # noqa: E402
from georeg.frames.localize import DEFAULTS, MapSources, camera_matrix  # noqa: E402
from georeg.frames.outputs import footprint_xy  # noqa: E402
from georeg.frames.refine import refine_pose  # noqa: E402
from georeg.frames.render import PinholeCamera, render  # noqa: E402
from georeg.index.features import rgb_to_gray  # noqa: E402
from georeg.register import dense  # noqa: E402


def rot_err(Ra, Rb) -> float:
    return float(np.degrees(np.arccos(np.clip((np.trace(Ra @ Rb.T) - 1) / 2, -1, 1))))


def read_win(path: str, b, res: float) -> np.ndarray:
    with rasterio.open(path) as s:
        W, H = int(round((b[2] - b[0]) / res)), int(round((b[3] - b[1]) / res))
        return s.read(window=from_bounds(*b, s.transform), out_shape=(s.count, H, W), boundless=True,
                      fill_value=0, resampling=Resampling.bilinear).astype(np.float32)  # fmt: skip


def restricted_search(angles: np.ndarray):
    """``dense.dense_search`` with the rotations given (a copy of its source, one line changed)."""
    src = inspect.getsource(dense.dense_search).replace(
        "angles = np.arange(0.0, 360.0, step_deg)", "angles = np.asarray(ANGLES, float) % 360.0")
    ns = {**vars(dense), "ANGLES": angles}
    exec(src, ns)  # noqa: S102 - a diagnostic variant, not library code
    return ns["dense_search"]


class Probe:
    def __init__(self, results: Path, name: str) -> None:
        self.dsm = str(results / "map/mosaic/dsm.vrt")
        self.ortho = str(results / "map/mosaic/ortho.vrt")
        self.ms = MapSources(results / "index/map", self.ortho, self.dsm)
        t = {d["image"]: d for d in json.loads((results / "demo/frames/truth.json").read_text())}[name]
        rgb = cv2.cvtColor(cv2.imread(str(results / "demo/frames" / name)), cv2.COLOR_BGR2RGB)
        h, w = rgb.shape[:2]
        self.K, dist = camera_matrix(t["intrinsics"], w, h)
        self.gray = cv2.cvtColor(cv2.undistort(rgb, self.K, dist), cv2.COLOR_RGB2GRAY)
        self.truth = (self.cam(np.array(t["R_world_to_cam"]), np.array(t["camera_center_xyz"]))
                      if t.get("status") == "registered" else None)  # fmt: skip
        t0 = time.perf_counter()
        co = coarse_locate(self.gray, self.K, self.ms.coarse_index, {}, self.ms.dense)
        self.votes = co.hypotheses
        print(f"coarse: ok {co.ok}, {time.perf_counter() - t0:.1f} s; best votes:")
        for R, C, v in self.votes[:5]:
            print(f"  {v} votes at {C.round(1)}" + self.err(R, C))

    def cam(self, R, C) -> PinholeCamera:
        K, (h, w) = self.K, self.gray.shape
        return PinholeCamera(K[0, 0], K[1, 1], K[0, 2], K[1, 2], w, h, R, C)

    def err(self, R, C) -> str:
        if self.truth is None:
            return ""
        return f" ({np.linalg.norm(C - self.truth.C):.1f} m, {rot_err(R, self.truth.R):.1f} deg from the truth)"

    def rectified(self, cam: PinholeCamera, b, res: float) -> np.ndarray:
        """The frame on the DSM cells of window b (uint8, 0 = outside or occluded)."""
        dsm = read_win(self.dsm, b, res)[0]
        H, W = dsm.shape
        X, Y = np.meshgrid(b[0] + (np.arange(W) + 0.5) * res, b[3] - (np.arange(H) + 0.5) * res)
        Z = np.where(dsm > -1000, dsm, self.ms.ground_z(cam.C))
        uv, z = cam.project(np.c_[X.ravel(), Y.ravel(), Z.ravel()])
        r = render(self.ms.cloud_around(cam, DEFAULTS), cam.scaled(0.5))
        u2 = np.clip(np.rint((uv[:, 0] + 0.5) * 0.5 - 0.5).astype(int), 0, r.depth.shape[1] - 1)
        v2 = np.clip(np.rint((uv[:, 1] + 0.5) * 0.5 - 0.5).astype(int), 0, r.depth.shape[0] - 1)
        vis = (z > 0) & (uv[:, 0] >= 0) & (uv[:, 0] < cam.width - 1) & (uv[:, 1] >= 0)
        vis &= (uv[:, 1] < cam.height - 1) & (z <= r.depth[v2, u2] * 1.03 + 1.0)
        q = cv2.remap(self.gray.astype(np.float32), uv[:, 0].reshape(H, W).astype(np.float32),
                      uv[:, 1].reshape(H, W).astype(np.float32), cv2.INTER_LINEAR)  # fmt: skip
        return np.where(vis.reshape(H, W), np.clip(q, 1, 255), 0).astype(np.uint8)

    def cfog(self, cam: PinholeCamera, search, margin: float, res: float = 1.0) -> str:
        fp = footprint_xy(cam, self.ms.ground_z(cam.C))
        cx, cy, lim = cam.C[0], cam.C[1], 250.0
        b = (max(fp[:, 0].min(), cx - lim), max(fp[:, 1].min(), cy - lim),
             min(fp[:, 0].max(), cx + lim), min(fp[:, 1].max(), cy + lim))  # fmt: skip
        q = self.rectified(cam, b, res)
        bm = (b[0] - margin, b[1] - margin, b[2] + margin, b[3] + margin)
        o = read_win(self.ortho, bm, res)
        m = np.where(o[:3].max(0) > 0, np.clip(rgb_to_gray(o[:3]), 1, 255), 0).astype(np.uint8)
        d = search(q, 1.0, m, step_deg=5.0, max_side=160)
        if d is None:
            return "no overlap"
        e = d.S @ np.array([q.shape[1] / 2, q.shape[0] / 2, 1.0])
        sx, sy = (e[0] - q.shape[1] / 2) * res - margin, -((e[1] - q.shape[0] / 2) * res - margin)
        return (f"angle {d.angle_deg:.0f}, shift ({sx:.1f}, {sy:.1f}) m, z {d.z:.2f}, "
                f"second ratio {d.second_ratio:.3f}")  # fmt: skip


def localize_demo(results: Path, conf: dict) -> None:
    from georeg.frames.localize import localize_frame

    for t in json.loads((results / "demo/frames/truth.json").read_text()):
        ms = MapSources(results / "index/map", results / "map/mosaic/ortho.vrt", results / "map/mosaic/dsm.vrt")
        t0 = time.perf_counter()
        rec, _ = localize_frame(str(results / "demo/frames" / t["image"]), t["intrinsics"], ms, conf)
        s = f"{t['image']}: {rec['status']} (expected {t['status']}), path {rec.get('path')}"
        if rec["status"] == "registered" and t["status"] == "registered":
            C, Ct = np.array(rec["camera_center_xyz"]), np.array(t["camera_center_xyz"])
            s += (f", h {np.linalg.norm(C[:2] - Ct[:2]):.2f} v {abs(C[2] - Ct[2]):.2f} m, "
                  f"{rot_err(np.array(rec['R_world_to_cam']), np.array(t['R_world_to_cam'])):.2f} deg")  # fmt: skip
        print(f"{s}, {time.perf_counter() - t0:.1f} s, stages {rec.get('timings_s')}")
        for sa in rec.get("search_attempts") or []:
            print("  search:", json.dumps(sa, default=float))


def main(argv: list[str]) -> None:
    ap = argparse.ArgumentParser(prog="diag_oblique35.py")
    ap.add_argument("probe", choices=["cfog", "mi", "localize"])
    ap.add_argument("--conf", type=json.loads, default=None, help="localize: frame_loc overrides")
    ap.add_argument("--frame", default="oblique35_100.png")
    ap.add_argument("--results", type=Path, default=REPO / "results")
    ap.add_argument("--votes", type=int, default=1, help="best nadir votes probed")
    ap.add_argument("--margin", type=float, default=50.0)
    ap.add_argument("--all-rotations", action="store_true")
    ap.add_argument("--basin", action="store_true", help="mi: also from the truth's rotation, moved")
    a = ap.parse_args(argv)
    if a.probe == "localize":
        localize_demo(a.results, a.conf or {})
        return
    p = Probe(a.results, a.frame)
    if a.probe == "cfog":
        search = dense.dense_search if a.all_rotations else restricted_search(np.arange(-15, 16, 3.0))
        if p.truth is not None:
            for off in [(0, 0), (10, -10), (36, 7), (-25, 20)]:
                cam = p.truth.with_pose(p.truth.R, p.truth.C + np.array([*off, 0.0]))
                print(f"truth moved by {off} m (expected shift {(-off[0], -off[1])}): "
                      + p.cfog(cam, search, a.margin))  # fmt: skip
        for R, C, v in p.votes[: a.votes]:
            print(f"vote ({v}){p.err(R, C)}: " + p.cfog(p.cam(R, C), search, a.margin))
        return
    conf = {"trans_step_m": 4.0, "rot_step_deg": 1.5, "max_evals": 200, "octaves": 3}
    starts = [(f"vote {i} ({v}) + ({dx}, {dy}) m", R, C + np.array([dx, dy, 0.0]))
              for i, (R, C, v) in enumerate(p.votes[: a.votes]) for dx in (-24, 0, 24) for dy in (-24, 0, 24)]  # fmt: skip
    if a.basin and p.truth is not None:
        for d in (6, 12):
            for ang in (0, 90, 180, 270):
                off = d * np.array([np.cos(np.radians(ang)), np.sin(np.radians(ang)), 0.0])
                starts.append((f"truth + {d} m at {ang} deg", p.truth.R, p.truth.C + off))
    for lab, R, C in starts:
        t0 = time.perf_counter()
        cam = p.cam(R, C)
        ref = refine_pose(p.gray, cam, p.ms.cloud_around(cam, DEFAULTS), conf)
        cost = ref.info["octaves"][-1]["cost_end"]
        print(f"{lab}{p.err(R, C)}: cost {cost:.4f} ->{p.err(ref.R, ref.C) or ' (no truth)'}, "
              f"{time.perf_counter() - t0:.1f} s")  # fmt: skip


if __name__ == "__main__":
    main(sys.argv[1:])
