"""Accepted fits of the cross-spectral sets, saved for checking them against the orthophoto.

    . /work/main/.venv/bin/activate
    nice -n 10 python benchmarks/diag_ortho_check.py collect --set tiny --names names.txt --out fits_tiny.pkl
    nice -n 10 python benchmarks/diag_ortho_check.py check fits_tiny.pkl [fits_small.pkl ...]

``collect`` runs the workflow default (``wf_default`` of bench_crossspectral.py, seeds as there)
on the named queries and saves each accepted homography with the query band, its truth and the
error; ``check`` runs the ortho check (georeg.register.ortho_check) on every saved fit and on
moved / distorted copies of the true fits (10 map px shift, 5 deg rotation, an affine
distortion of 15 map px at the corners), and prints its figures per fit.
"""

from __future__ import annotations

import argparse
import json
import pickle
import sys
from pathlib import Path
from typing import Any

import cv2
import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
import bench_crossspectral as bc  # noqa: E402


def build(set_name: str, seed: int):
    if set_name == "tiny":
        return bc.build_small_set(5, seed, bc.TINY_SIDES, "tiny_", 600)
    if set_name == "small":
        return bc.build_small_set(6, seed)
    return bc.build_set(3, seed, 1)


def collect(a: argparse.Namespace) -> None:
    names = [ln.split()[0] for ln in Path(a.names).read_text().splitlines() if ln.strip()]
    scenes, qs = build(a.set, a.seed)
    by = {s.name: s for s in scenes}
    spec = bc.METHODS[a.method]
    out = []
    for qi, q in enumerate(qs):
        if q.name not in names:
            continue
        sc = by[q.map_scene]
        res = bc.run_method(q, sc, spec, a.seed + qi)
        j = bc.judge(q, sc, res)
        print(q.name, j["outcome"], j["error_px"], j["p90_px"], res["inliers"], flush=True)
        if res["H"] is None:
            continue
        band = bc.query_stack(q, "auto")
        out.append({"name": q.name, "set": a.set, "band": band[0] if band.ndim == 3 else band,
                    "H": res["H"], "truth": q.truth, "truth_map": q.truth_map,
                    "map_scene": q.map_scene, "inliers": res["inliers"], **j})  # fmt: skip
    Path(a.out).write_bytes(pickle.dumps({"fits": out, "seed": a.seed, "set": a.set}))


def truth_h(f: dict[str, Any], g: float) -> np.ndarray:
    """The affine map query px -> map x, y fitted to the truth grid."""
    dst = f["truth_map"] * np.array([g, -g])
    A = cv2.estimateAffine2D(f["truth"].astype(np.float32), dst.astype(np.float32),
                             method=cv2.LMEDS)[0]  # fmt: skip
    return np.r_[A, [[0, 0, 1.0]]]


def variants(f: dict[str, Any], g: float) -> list[tuple[str, np.ndarray]]:
    """The fit itself and, for a success, moved / distorted copies of the truth."""
    out = [("fit", f["H"])]
    if f["outcome"] != "success":
        return out
    Ht = truth_h(f, g)
    h, w = f["band"].shape
    c = np.array([(w - 1) / 2, (h - 1) / 2])
    shift = np.eye(3)
    shift[:2, 2] = np.array([10.0, 10.0]) / np.sqrt(2) * g
    out.append(("truth", Ht))
    out.append(("shift10", shift @ Ht))
    t = np.radians(5)
    R = np.array([[np.cos(t), -np.sin(t), 0], [np.sin(t), np.cos(t), 0], [0, 0, 1]])
    T = np.array([[1, 0, c[0]], [0, 1, c[1]], [0, 0, 1.0]])
    out.append(("rot5", Ht @ T @ R @ np.linalg.inv(T)))
    # an affine distortion about the centre: corners ~15 map px off
    qpx = np.sqrt(abs(np.linalg.det(Ht[:2, :2]))) / g  # map px per query px
    k = 15.0 / (qpx * np.hypot(*c))
    D = np.array([[1 + k, k, 0], [0, 1 - k, 0], [0, 0, 1.0]])
    out.append(("distort15", Ht @ T @ D @ np.linalg.inv(T)))
    return out


def check(a: argparse.Namespace) -> None:
    from georeg.register import ortho_check

    conf = json.loads(a.conf) if a.conf else {}
    scenes = {s.name: s for s in bc.all_scenes()}
    for path in a.pickles:
        d = pickle.loads(Path(path).read_bytes())
        for f in d["fits"]:
            sc = scenes[f["map_scene"]]
            img = bc.map_image(sc)
            for tag, H in variants(f, sc.map_gsd):
                Hu, rec = ortho_check.verify(f["band"], H, img, conf)
                rf = rec.get("refit") or {}
                e0, e1 = truth_error(H, f, sc.map_gsd), truth_error(Hu, f, sc.map_gsd)
                print(f"{f['name']:36s} {f['outcome'][:7]:7s} inl {f['inliers']:3d} {tag:9s} "
                      f"{rec['outcome']:9s} err {e0[0]:5.1f}/{e0[1]:5.1f} -> {e1[0]:5.1f}/"
                      f"{e1[1]:5.1f} sup {_fmt(rec.get('supported'))} gain {_fmt(rec.get('gain'))} "
                      f"tp {rec.get('tie_points')} refit {str(rf.get('accepted'))[0]}"
                      f"{str(rf.get('kept'))[0]} moved {_fmt(rf.get('moved_corners_map_px'))} "
                      f"cv {_fmt((rf.get('cv_rms_map_px') or {}).get('refit'))} "
                      f"{rec['seconds']:.2f}s", flush=True)  # fmt: skip


def truth_error(H: np.ndarray, f: dict[str, Any], g: float) -> tuple[float, float]:
    """Median and p90 error (map px) of H at the truth grid."""
    est = bc.matching.apply_h(H, f["truth"]) / np.array([g, -g])
    e = np.linalg.norm(est - f["truth_map"], axis=1)
    e = np.where(np.isfinite(e), e, np.inf)
    return float(np.median(e)), float(np.percentile(e, 90))


def _fmt(v: Any) -> str:
    if isinstance(v, float):
        return f"{v:.2f}"
    if isinstance(v, list):
        return "[" + ",".join(_fmt(x) for x in v) + "]"
    return str(v)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__)
    sub = ap.add_subparsers(dest="cmd", required=True)
    c = sub.add_parser("collect")
    c.add_argument("--set", choices=("tiny", "small", "protocol"), required=True)
    c.add_argument("--names", required=True, help="file: one query name per line (first word)")
    c.add_argument("--method", default="wf_default")
    c.add_argument("--seed", type=int, default=11)
    c.add_argument("--out", required=True)
    k = sub.add_parser("check")
    k.add_argument("pickles", nargs="+")
    k.add_argument("--conf", default="", help="JSON overrides of ortho_check.DEFAULTS")
    a = ap.parse_args()
    cv2.setNumThreads(1)
    collect(a) if a.cmd == "collect" else check(a)


if __name__ == "__main__":
    main()
