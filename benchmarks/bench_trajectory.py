"""Video trajectory geo-referencing (issue 10): variants of ``georeference_video`` on the demo video.

    nice python benchmarks/bench_trajectory.py <results dir> [--runs N] [--out json]

``<results dir>`` holds a finished default workflow run: ``index/map``, ``map/mosaic/{ortho,dsm}.vrt``
and the demo video ``demo/video/{flight.mp4,truth.json}``. The configuration is the repository's
``config/config.yaml`` (``trajectory``, ``frame_loc``, ``frames.demo_video.camera``), as rule
``trajectory`` runs it. All in one process, printed as markdown tables:

1. ``default``: the default configuration, N times (median wall seconds per stage; errors compared
   across the runs);
2. ICP forced (``icp: {min_gain: 0, min_fitness: 0}``) vs ICP disabled (``icp: {enabled: false}``);
3. unknown camera (``camera: null``: SfM self-calibrates, the anchors use the SfM intrinsics);
4. the per-frame stage: tracking (default) vs relocalisation of every frame, N times each,
   interleaved with the default runs (the tracker is replaced by one that never tracks, so every
   frame between keyframes goes to ``PointMapLocalizer``; no code change in ``georeg``);
5. 1 vs 2 (default) vs 3 anchor keyframes.

Reuse: the default runs are complete; the variants reuse the SfM model and the single-frame anchor
registrations of the first default run when their inputs (keyframe images, camera, configuration)
are identical, so their SfM / anchor seconds are not meaningful. The incremental mapping is not
bit-reproducible with 2 threads (the repeated default runs show by how much), so the variants are
compared with default run 1, whose SfM and anchors they share: a difference is the variant's alone.
"""

from __future__ import annotations

import argparse
import copy
import hashlib
import json
import logging
import shutil
import statistics
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

import numpy as np
import yaml

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

import georeg.trajectory.pipeline as traj  # noqa: E402
import georeg.trajectory.sfm  # noqa: E402
from georeg.frames.localize import MapSources  # noqa: E402
from georeg.trajectory.relocalize import FramePose, Tracker  # noqa: E402
from georeg.trajectory.sim3 import umeyama  # noqa: E402

STAGES = ("keyframes_s", "sfm_s", "anchors_s", "sim3_s", "icp_s", "frames_s", "total_s")
METRICS = ("position_m", "horizontal_m", "vertical_m", "rotation_deg")


# --- reuse of the SfM model and of the anchor registrations between runs ---------------------


class Reuse:
    """Memoises ``run_sfm`` and ``localize_image`` by their inputs; ``enabled`` switches lookups
    (the first result for a key is always stored)."""

    def __init__(self) -> None:
        self.enabled = False
        self.sfm: dict[str, Any] = {}
        self.loc: dict[str, Any] = {}
        self._run_sfm = georeg.trajectory.sfm.run_sfm
        self._localize = traj.localize_image

    @staticmethod
    def _key(*parts: Any) -> str:
        h = hashlib.sha1()
        for p in parts:
            h.update(
                p if isinstance(p, bytes) else json.dumps(p, sort_keys=True, default=float).encode()
            )
        return h.hexdigest()

    def run_sfm(self, image_dir, work_dir, camera=None, conf=None):
        files = sorted(Path(image_dir).iterdir())
        key = self._key(camera, conf, *[f.name for f in files], *[f.read_bytes() for f in files])
        if self.enabled and key in self.sfm:
            return copy.deepcopy(self.sfm[key])
        model = self._run_sfm(image_dir, work_dir, camera, conf)
        self.sfm.setdefault(key, copy.deepcopy(model))
        return model

    def localize_image(self, rgb, name, camera, maps, frame_loc):
        key = self._key(np.ascontiguousarray(rgb).tobytes(), name, camera, frame_loc)
        if self.enabled and key in self.loc:
            return copy.deepcopy(self.loc[key])
        out = self._localize(rgb, name, camera, maps, frame_loc)
        self.loc.setdefault(key, copy.deepcopy(out))
        return out

    def install(self) -> None:
        georeg.trajectory.sfm.run_sfm = self.run_sfm  # georeg.trajectory.pipeline imports it at call time
        traj.localize_image = self.localize_image


class NoTracking(Tracker):
    """A tracker that never tracks: every frame between keyframes is relocalised."""

    def step(self, gray: np.ndarray) -> FramePose:
        self.prev = gray
        return FramePose(False, source="tracking")


# --- one run ------------------------------------------------------------------------------


def merge(base: dict, over: dict) -> dict:
    out = copy.deepcopy(base)
    for k, v in over.items():
        out[k] = merge(out[k], v) if isinstance(v, dict) and isinstance(out.get(k), dict) else v
    return out


def run_once(label: str, setup: dict, over: dict, work: Path, reuse: Reuse, *,
             cached: bool, relocalise: bool = False, camera: Any = "given") -> dict:  # fmt: skip
    out = work / label
    if out.exists():
        shutil.rmtree(out)
    fs = {"video": str(setup["video"]), "camera": setup["camera"] if camera == "given" else camera}
    conf = merge(setup["trajectory"], over)
    reuse.enabled = cached
    traj.Tracker = NoTracking if relocalise else Tracker
    t0 = time.perf_counter()
    try:
        traj.georeference_video(fs, setup["maps"], setup["frame_loc"], conf, out, work / "work",
                                str(setup["truth"]))  # fmt: skip
    finally:
        traj.Tracker = Tracker
    wall = time.perf_counter() - t0
    info = json.loads((out / "trajectory.json").read_text())
    poses = json.loads((out / "poses.json").read_text())
    r = summarize(info, poses, setup["truth_by_name"])
    r.update(label=label, wall_s=wall, cached=cached)
    print(f"[{time.strftime('%H:%M:%S')}] {label}: {wall:.1f} s, registered "
          f"{r['registered']}/{r['frames']}, position mean {fmt_v(r, 'position_m', 'mean')} m, "
          f"fps {r['fps']:.1f}", file=sys.stderr, flush=True)  # fmt: skip
    return r


def summarize(info: dict, poses: list[dict], truth: dict) -> dict:
    ev = info.get("evaluation") or {}
    reg = [p for p in poses if p["status"] == "registered"]
    nk = [p for p in poses if not p.get("keyframe")]
    nk_s = [p["timings_s"]["total_s"] for p in nk if "timings_s" in p]
    r: dict[str, Any] = {
        "frames": ev.get("frames", len(poses)), "registered": len(reg),
        "keyframes": info.get("keyframes"), "sfm_registered": (info.get("sfm") or {}).get("registered"),
        "sfm_points": (info.get("sfm") or {}).get("points"),
        "after": ev.get("after_icp", {}), "before": ev.get("before_icp", {}),
        "keyframes_after": ev.get("keyframes_after_icp", {}),
        "scale": (info.get("sim3") or {}).get("scale"), "true_scale": ev.get("true_scale"),
        "sim3": {k: v for k, v in (info.get("sim3") or {}).items() if k != "anchors"},
        "anchors_used": [a["name"] for a in (info.get("sim3") or {}).get("anchors", [])],
        "anchors_tried": len(info.get("anchors") or []),
        "icp": info.get("icp"), "timings": info.get("timings_s", {}),
        "fps": info.get("frames_per_second", float("nan")),
        "fps_between": len(nk_s) / max(sum(nk_s), 1e-9) if nk_s else float("nan"),
        "sources": {s: sum(1 for p in poses if p.get("source") == s)
                    for s in sorted({str(p.get("source")) for p in poses})},
        "fx": (poses[0].get("intrinsics") or {}).get("fx") if poses else None,
        "fx_source": (poses[0].get("intrinsics") or {}).get("source") if poses else None,
    }  # fmt: skip
    if r["scale"] and r["true_scale"]:
        r["scale_err_pct"] = 100 * (r["scale"] / r["true_scale"] - 1)
    est = np.array([p["camera_center_xyz"] for p in reg if p["image"] in truth], float)
    tru = np.array(
        [truth[p["image"]]["camera_center_xyz"] for p in reg if p["image"] in truth], float
    )
    if len(est) >= 3:
        d = est - tru
        r["bias_xyz_m"] = d.mean(0).tolist()  # systematic offset of the whole trajectory
        res = np.linalg.norm(umeyama(est, tru).apply(est) - tru, axis=1)
        r["shape"] = {"mean": float(res.mean()), "p90": float(np.percentile(res, 90))}
    return r


# --- tables -------------------------------------------------------------------------------


def fmt_v(r: dict, metric: str, stat: str, key: str = "after") -> str:
    v = (r.get(key) or {}).get(metric, {}).get(stat)
    return "-" if v is None else f"{v:.2f}"


def err_cells(r: dict, key: str = "after") -> str:
    return " | ".join(f"{fmt_v(r, m, 'mean', key)} / {fmt_v(r, m, 'p90', key)}" for m in METRICS)


ERR_HEAD = "position m | horizontal m | vertical m | rotation deg"
ERR_SEP = "---:|---:|---:|---:"


def table_default(runs: list[dict]) -> list[str]:
    L = [f"**1. Default configuration**, {len(runs)} complete runs (wall seconds per stage):", "",
         "| stage | median s | min | max |", "|---|---:|---:|---:|"]  # fmt: skip
    for s in STAGES:
        v = [r["timings"].get(s) for r in runs if r["timings"].get(s) is not None]
        if v:
            L.append(f"| {s[:-2]} | {statistics.median(v):.1f} | {min(v):.1f} | {max(v):.1f} |")
    fps = [r["fps"] for r in runs]
    L.append(f"| per-frame stage, frames per second | {statistics.median(fps):.1f} | {min(fps):.1f} | "
             f"{max(fps):.1f} |")  # fmt: skip
    r = runs[0]
    L += ["", f"Errors (mean / p90 over the frames; run 1; {determinism(runs)}):", "",
          f"| frames | n | {ERR_HEAD} |", f"|---|---:|{ERR_SEP}|",
          f"| all, after ICP (final) | {r['after'].get('n')} | {err_cells(r)} |",
          f"| all, before ICP | {r['before'].get('n')} | {err_cells(r, 'before')} |",
          f"| keyframes only | {r['keyframes_after'].get('n')} | {err_cells(r, 'keyframes_after')} |",
          ""]  # fmt: skip
    L.append(f"Registered {r['registered']}/{r['frames']} frames ({r['keyframes']} keyframes, "
             f"{r['sfm_registered']} in the SfM, {r['sfm_points']} points with track >= 4); Sim(3) "
             f"scale {r['scale']:.3f} vs true {r['true_scale']:.3f} ({r['scale_err_pct']:+.2f} %); "
             f"{icp_text(r)}; mean offset of the trajectory (x, y, z) "
             f"{', '.join(f'{v:+.2f}' for v in r['bias_xyz_m'])} m; trajectory shape after the "
             f"best Sim(3) to the truth: mean {r['shape']['mean']:.2f} m, p90 "
             f"{r['shape']['p90']:.2f} m; sources {r['sources']}.")  # fmt: skip
    L += ["", "Per run (all frames after ICP, mean / p90):", "",
          f"| run | SfM points | Sim(3) scale error | ICP gain | {ERR_HEAD} |",
          f"|---|---:|---:|---:|{ERR_SEP}|"]  # fmt: skip
    for k, x in enumerate(runs, 1):
        gain = f"{100 * x['icp']['gain']:.1f} %" if x.get("icp") else "-"
        L.append(f"| {k} | {x['sfm_points']} | {x['scale_err_pct']:+.2f} % | {gain} | "
                 f"{err_cells(x)} |")  # fmt: skip
    return L


def determinism(runs: list[dict]) -> str:
    keys = ("after", "before", "keyframes_after", "scale", "registered", "sources")
    first = json.dumps({k: runs[0].get(k) for k in keys}, sort_keys=True)
    if all(json.dumps({k: r.get(k) for k in keys}, sort_keys=True) == first for r in runs[1:]):
        return f"identical in all {len(runs)} runs, to the last digit"
    spread = {m: max(r["after"][m]["mean"] for r in runs) - min(r["after"][m]["mean"] for r in runs)
              for m in METRICS}  # fmt: skip
    return "NOT identical across the runs: spread of the means " + ", ".join(
        f"{m} {v:.3f}" for m, v in spread.items()
    )


def icp_text(r: dict) -> str:
    i = r.get("icp")
    if not i:
        return "ICP disabled"
    state = "accepted" if i.get("accepted") else f"refused ({i.get('reason')})"
    return (
        f"ICP {state}: gain {100 * i['gain']:.1f} %, fitness {i['fitness']:.2f}, "
        f"translation {i['translation_m']:.2f} m, rotation {i['rotation_deg']:.2f} deg"
    )


def table_icp(forced: dict, off: dict) -> list[str]:
    L = ["**2. ICP** (errors over all frames, mean / p90):", "",
         f"| variant | {ERR_HEAD} | ICP |", f"|---|{ERR_SEP}|---|",
         f"| ICP disabled | {err_cells(off)} | - |",
         f"| ICP forced (min_gain 0, min_fitness 0) | {err_cells(forced)} | {icp_text(forced)} |",
         f"| (forced run, before its ICP) | {err_cells(forced, 'before')} | |"]  # fmt: skip
    return L


def table_camera(known: dict, unknown: dict) -> list[str]:
    L = ["**3. Unknown camera** (errors over all frames, mean / p90):", "",
         f"| camera | registered | focal px | Sim(3) scale error | {ERR_HEAD} |",
         f"|---|---:|---:|---:|{ERR_SEP}|"]  # fmt: skip
    for name, r in (
        ("given (fx 520, distortion undone)", known),
        ("null: SfM self-calibration", unknown),
    ):
        se = f"{r['scale_err_pct']:+.2f} %" if "scale_err_pct" in r else "-"
        fx = f"{r['fx']:.1f}" if r.get("fx") else "-"
        L.append(f"| {name} | {r['registered']}/{r['frames']} | {fx} | {se} | {err_cells(r)} |")
    return L


def table_frames(track: list[dict], reloc: list[dict]) -> list[str]:
    def med(rs, k):
        return statistics.median(r[k] for r in rs)

    L = [f"**4. Per-frame stage** (median of {len(track)} runs each, interleaved; frames per second "
         "of the per-frame loop: undistortion, tracking or relocalisation, PnP, evaluation; video "
         "decoding excluded):", "",
         f"| mode | fps, all frames | fps, between keyframes | stage s | registered | {ERR_HEAD} |",
         f"|---|---:|---:|---:|---:|{ERR_SEP}|"]  # fmt: skip
    for name, rs in (
        ("tracking (LK + PnP; default)", track),
        ("relocalisation of every frame", reloc),
    ):
        r = rs[0]
        L.append(f"| {name} | {med(rs, 'fps'):.1f} | {med(rs, 'fps_between'):.1f} | "
                 f"{statistics.median(x['timings']['frames_s'] for x in rs):.1f} | "
                 f"{r['registered']}/{r['frames']} | {err_cells(r)} |")  # fmt: skip
    L += ["", f"Ratio relocalisation / tracking, frames per second: all frames "
          f"{med(reloc, 'fps') / med(track, 'fps'):.2f}, between keyframes "
          f"{med(reloc, 'fps_between') / med(track, 'fps_between'):.2f}. Sources "
          f"(relocalisation run): {reloc[0]['sources']}."]  # fmt: skip
    return L


def table_anchors(rs: list[tuple[int, dict]]) -> list[str]:
    L = ["**5. Anchors** (keyframes registered by the single-frame method; errors over all frames, "
         "mean / p90):", "",
         f"| anchors | used | Sim(3) inliers | scale (true) | scale error | {ERR_HEAD} |",
         f"|---:|---|---:|---:|---:|{ERR_SEP}|"]  # fmt: skip
    for n, r in rs:
        sim = r.get("sim3") or {}
        used = ", ".join(
            a.replace("kf_", "").replace(".png", "").lstrip("0") for a in r["anchors_used"]
        )
        L.append(f"| {n} | {used or '-'} | {sim.get('n_inliers', '-')}/{sim.get('n_correspondences', '-')} | "
                 f"{r['scale']:.3f} ({r['true_scale']:.3f}) | {r['scale_err_pct']:+.2f} % | "
                 f"{err_cells(r)} |" if r.get("scale") else f"| {n} | failed | | | | | | | |")  # fmt: skip
    return L


# --- main ---------------------------------------------------------------------------------


def load_setup(results: Path, config: Path) -> dict:
    cfg = yaml.safe_load(config.read_text())
    fl = {k: v for k, v in (cfg.get("frame_loc") or {}).items() if k != "demo_frames"}
    tj = {k: v for k, v in (cfg.get("trajectory") or {}).items() if k != "demo_video"}
    vid = results / "demo" / "video"
    truth = vid / "truth.json"
    return {
        "video": vid / "flight.mp4", "truth": truth,
        "truth_by_name": {t["image"]: t for t in json.loads(truth.read_text())},
        "camera": cfg["frames"]["demo_video"]["camera"], "frame_loc": fl, "trajectory": tj,
        "maps": MapSources(results / "index" / "map", results / "map" / "mosaic" / "ortho.vrt",
                           results / "map" / "mosaic" / "dsm.vrt", [],
                           dense_coarse=bool(fl.get("dense_coarse", True))),
    }  # fmt: skip


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument(
        "results", type=Path, nargs="?", help="results directory of a default workflow run"
    )
    ap.add_argument("--runs", type=int, default=3, help="default and relocalisation runs (timing)")
    ap.add_argument("--out", type=Path, help="write every run's summary to this JSON file")
    ap.add_argument("--config", type=Path, default=REPO / "config" / "config.yaml")
    ap.add_argument("--workdir", type=Path, help="keep the runs' outputs here (default: temporary)")
    ap.add_argument("--tables-from", type=Path, help="print the tables of an earlier --out JSON")
    ap.add_argument("-v", "--verbose", action="store_true", help="georeg INFO log on stderr")
    args = ap.parse_args()
    logging.basicConfig(level=logging.INFO if args.verbose else logging.WARNING,
                        format="%(asctime)s %(name)s %(message)s")  # fmt: skip
    if args.results is None and args.tables_from is None:
        ap.error("a results directory (or --tables-from) is needed")
    if args.tables_from:
        allr = json.loads(args.tables_from.read_text())
    else:
        allr = run_all(args)
        if args.out:
            args.out.parent.mkdir(parents=True, exist_ok=True)
            args.out.write_text(json.dumps(allr, indent=1, default=float))
    print("\n".join(tables(allr)))


def run_all(args: argparse.Namespace) -> dict:
    setup = load_setup(args.results.resolve(), args.config)
    work = args.workdir or Path(tempfile.mkdtemp(prefix="bench_trajectory_"))
    work.mkdir(parents=True, exist_ok=True)
    reuse = Reuse()
    reuse.install()
    t0 = time.perf_counter()
    try:
        default, reloc = [], []
        for k in range(args.runs):  # interleaved: same load conditions for the fps ratio
            default.append(run_once(f"default_{k + 1}", setup, {}, work, reuse, cached=False))
            reloc.append(run_once(f"relocalise_{k + 1}", setup, {"overlays": 0}, work, reuse,
                                  cached=True, relocalise=True))  # fmt: skip
        forced = run_once("icp_forced", setup, {"overlays": 0, "icp": {"min_gain": 0, "min_fitness": 0}},
                          work, reuse, cached=True)  # fmt: skip
        off = run_once("icp_off", setup, {"overlays": 0, "icp": {"enabled": False}}, work, reuse,
                       cached=True)  # fmt: skip
        anchors = {str(n): run_once(f"anchors_{n}", setup, {"overlays": 0, "anchors": n}, work,
                                    reuse, cached=True) for n in (1, 3)}  # fmt: skip
        unknown = run_once(
            "camera_null", setup, {"overlays": 0}, work, reuse, cached=True, camera=None
        )
    finally:
        if args.workdir is None:
            shutil.rmtree(work, ignore_errors=True)
    return {
        "default": default,
        "relocalise": reloc,
        "icp_forced": forced,
        "icp_off": off,
        "anchors": anchors,
        "camera_null": unknown,
        "total_s": time.perf_counter() - t0,
    }


def tables(a: dict) -> list[str]:
    default = a["default"]
    anchors = [(1, a["anchors"]["1"]), (2, default[0]), (3, a["anchors"]["3"])]
    return [*table_default(default), "", *table_icp(a["icp_forced"], a["icp_off"]), "",
            *table_camera(default[0], a["camera_null"]), "", *table_frames(default, a["relocalise"]),
            "", *table_anchors(anchors), "", f"Benchmark wall time: {a['total_s'] / 60:.1f} min."]  # fmt: skip


if __name__ == "__main__":
    main()
