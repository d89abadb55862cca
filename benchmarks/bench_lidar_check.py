"""The LiDAR check (georeg/register/lidar_check.py) on true and deliberately wrong registrations.

    nice -n 10 python benchmarks/bench_lidar_check.py demo      # after the default demo run
    nice -n 10 python benchmarks/bench_lidar_check.py autzen    # ../shared/data/autzen

``demo``: the demo query's band (results/queries/demo/band.tif) with the homography fitted to its
truth raster, that homography shifted by 5 / 20 / 100 map px and rotated by 10 / 30 / 90 deg
about the footprint's centre, the fused registration, and every candidate of the `outside`
query's searches (all wrong: the query lies outside the map). ``autzen``: the orthophoto over the
LiDAR area, one band, rotated and rescaled, as the query; the DSM / nDSM rasterized from
autzen_trim.laz with georeg.map.elevation.lidar_tile on the orthophoto's grid; truth from the
orthophoto's geotransform. Both layers, every hypothesis; prints one line per check.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import cv2
import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from georeg.register import lidar_check as lc  # noqa: E402
from georeg.register.geolocation import apply_h  # noqa: E402
from georeg.register.refine import MapImage  # noqa: E402

AUTZEN = ROOT.parent / "shared" / "data" / "autzen"


def perturbed(H: np.ndarray, w: int, h: int, map_px: float) -> dict[str, np.ndarray]:
    """H shifted by 5 / 20 / 100 map px (diagonal) and rotated about the footprint's centre."""
    cx, cy = apply_h(H, np.array([w / 2]), np.array([h / 2]))
    out = {}
    for d in (5, 20, 100):
        t = d * map_px / np.sqrt(2)
        out[f"shift {d} px"] = np.array([[1, 0, t], [0, 1, t], [0, 0, 1.0]]) @ H
    for a in (10, 30, 90):
        c, s = np.cos(np.radians(a)), np.sin(np.radians(a))
        T = np.array([[1, 0, cx[0]], [0, 1, cy[0]], [0, 0, 1.0]])
        R = np.array([[c, -s, 0], [s, c, 0], [0, 0, 1.0]])
        out[f"rotated {a} deg"] = T @ R @ np.linalg.inv(T) @ H
    return out


def show(name: str, rec: dict) -> None:
    f = {k: (round(v, 2) if isinstance(v, float) else v) for k, v in rec.items()
         if k in ("outcome", "coherent", "coherent_null", "gain", "tie_points", "offset_map_px", "valid_frac", "seconds",
                  "resolution_map_px", "reason")}  # fmt: skip
    print(f"{name:38s} {f}", flush=True)


def truth_h(truth: str) -> np.ndarray:
    import rasterio

    with rasterio.open(truth) as ds:
        tx, ty = ds.read(1).astype(float), ds.read(2).astype(float)
    r, c = np.mgrid[0 : tx.shape[0] : 8, 0 : tx.shape[1] : 8]
    ok = np.isfinite(tx[r, c]) & np.isfinite(ty[r, c])
    src = np.column_stack([c[ok], r[ok]]).astype(np.float64)
    dst = np.column_stack([tx[r, c][ok], ty[r, c][ok]])
    H, _ = cv2.findHomography(src, dst, 0)
    return H


def demo(layers: list[str], conf: dict) -> None:
    from georeg.register.band import read_query_band

    res = ROOT / "results"
    q = read_query_band(str(res / "queries/demo/band.tif"))
    h, w = q.shape
    H = truth_h(str(res / "demo/queries/demo_truth.tif"))
    reg = json.loads((res / "queries/demo/registration_global.json").read_text())
    hyps = {"truth (homography fit)": H, "fused registration": np.array(reg["homography"]),
            **perturbed(H, w, h, 1.0)}  # fmt: skip
    oq = read_query_band(str(res / "queries/outside/band.tif"))
    cands = []
    for pj in sorted((res / "queries/outside/parts").glob("part_*.json")):
        for k, c in enumerate(json.loads(pj.read_text()).get("candidates", [])):
            if c.get("homography") is not None:
                cands.append((f"outside {pj.stem} cand {k} ({c['inliers']} inl)",
                              np.array(c["homography"])))  # fmt: skip
    for layer in layers:
        path = lc.elevation_path(str(res / "map/mosaic/dsm.vrt"), layer)
        c = {**conf, "layer": layer}
        for name, Hx in hyps.items():
            show(f"[{layer}] demo {name}", _check(q, Hx, path, c))
        for name, Hx in cands:
            show(f"[{layer}] {name}", _check(oq, Hx, path, c))


def _check(q: np.ndarray, H: np.ndarray, path: str, c: dict) -> dict:
    elev = lc.read_elevation(path, q.shape, H, c)
    if elev is None:  # a wrong candidate may leave the map
        return {"outcome": "skipped", "reason": "the footprint does not overlap the elevation"}
    return lc.check(q, H, elev, c)


def autzen_scene(scale: float = 1.5, angle: float = 35.0, band: int = 1, inner: float = 0.8):
    """(query u8, true H, {layer: MapImage}) from the Autzen orthophoto and autzen_trim.laz."""
    import rasterio
    from rasterio.windows import Window

    from georeg.map.elevation import Grid, lidar_tile

    ortho = AUTZEN / "autzen.jpg"
    laz = AUTZEN / "autzen_trim.laz"
    with rasterio.open(ortho) as ds:
        tr = ds.transform
        x0, x1, y0, y1 = 636001.0, 637179.0, 848935.0, 849498.0  # the LAZ header's extent
        c0, r0 = int(np.floor((x0 - tr.c) / tr.a)), int(np.floor((y1 - tr.f) / tr.e))
        c1 = int(np.ceil((x1 - tr.c) / tr.a))
        r1 = min(ds.height, int(np.ceil((y0 - tr.f) / tr.e)))
        win = Window(c0, r0, c1 - c0, r1 - r0)
        img = ds.read(band, window=win).astype(np.float32)
        wtr = ds.window_transform(win)
        grid = Grid(ds.crs, wtr, int(win.width), int(win.height))
    surf, _ = lidar_tile(grid, [str(laz)])
    layers = {k: MapImage(surf[k].astype(np.float32), wtr) for k in ("dsm", "ndsm")}
    # query: the central `inner` of the window, rotated by `angle`, pixels `scale` x larger
    gh, gw = img.shape
    qw, qh = int(gw * inner / scale), int(gh * inner / scale)
    c, s = scale * np.cos(np.radians(angle)), scale * np.sin(np.radians(angle))
    # query px (col, row) -> window px: rotate about the query centre, scale, to the window centre
    A = np.array([[c, -s, 0], [s, c, 0], [0, 0, 1.0]])
    A[:2, 2] = np.array([gw / 2 - 0.5, gh / 2 - 0.5]) - A[:2, :2] @ np.array([qw / 2 - 0.5, qh / 2 - 0.5])
    blur = cv2.GaussianBlur(img, (0, 0), 0.5 * scale)
    q = cv2.warpAffine(blur, A[:2], (qw, qh), flags=cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP,
                       borderValue=np.nan)  # fmt: skip
    valid = np.isfinite(q)
    lo, hi = np.percentile(q[valid], [1, 99])
    qu8 = np.where(valid, np.clip((q - lo) / (hi - lo), 0, 1) * 254 + 1, 0).astype(np.uint8)
    W = np.array([[wtr.a, wtr.b, wtr.c], [wtr.d, wtr.e, wtr.f], [0, 0, 1.0]])
    H = W @ np.array([[1, 0, 0.5], [0, 1, 0.5], [0, 0, 1.0]]) @ A
    return qu8, H, layers


def autzen(layers: list[str], conf: dict) -> None:
    for scale, angle in ((1.5, 35.0), (3.0, 120.0)):
        t0 = time.perf_counter()
        q, H, elev = autzen_scene(scale, angle)
        print(f"autzen query {q.shape[1]} x {q.shape[0]} px, scale {scale}, {angle} deg "
              f"(scene {time.perf_counter() - t0:.1f} s)", flush=True)  # fmt: skip
        h, w = q.shape
        hyps = {"truth": H, **perturbed(H, w, h, 1.0)}
        for layer in layers:
            for name, Hx in hyps.items():
                show(f"[{layer}] autzen x{scale} {name}", lc.check(q, Hx, elev[layer],
                                                                   {**conf, "layer": layer}))


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("scene", choices=["demo", "autzen"])
    ap.add_argument("--layers", default="dsm,ndsm")
    ap.add_argument("--conf", default="{}", help="JSON overrides of lidar_check.DEFAULTS")
    a = ap.parse_args()
    cv2.setNumThreads(1)
    conf = {**lc.DEFAULTS, **json.loads(a.conf)}
    {"demo": demo, "autzen": autzen}[a.scene](a.layers.split(","), conf)


if __name__ == "__main__":
    main()
