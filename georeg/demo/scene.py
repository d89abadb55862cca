"""``generate_scene``: the deterministic demo scene (orthophoto, LiDAR, SWIR queries and truth)."""

from __future__ import annotations

import logging
import time
import warnings
from pathlib import Path
from typing import Any

import numpy as np
import pyproj
import rasterio
from rasterio.errors import NotGeoreferencedWarning

from georeg.demo import classes as C
from georeg.demo import spectra as S
from georeg.demo.changes import apply_changes, car_changes
from georeg.demo.layout import (
    BLOCK_TYPES,
    EPOCH_MAP,
    KIND_BUILDING,
    KIND_ROOFTOP,
    Layout,
    intersects,
    make_layout,
)
from georeg.demo.lidar import simulate_tile, strip_bounds, write_laz
from georeg.demo.pushbroom import Flight, render_query
from georeg.demo.raster import Grid, Surface, Texture, rasterize
from georeg.demo.render import render_orthophoto
from georeg.io.atomic import atomic_path, write_json
from georeg.io.errors import ConfigError

log = logging.getLogger(__name__)

MAP_EPSG = 32611  # WGS 84 / UTM zone 11N (Los Angeles)
ORIGIN = (384000.0, 3768000.0)  # top-left corner of the orthophoto
ORTHO_SUN = S.Sun(155.0, 62.0)  # late-morning summer sun
QUERY_SUN = S.Sun(255.0, 22.0)  # close to sunset: long shadows towards the east-north-east
LIDAR_OVERLAP_M = 16.0
ORTHO_PAD_M = 100.0  # map-grid margin so that shadows cast from outside the map are rendered
LAYOUT_PAD_M = 350.0  # city beyond the world edge: shadows reaching into the outside query
RNG_STREAMS = ("layout", "texture", "changes", "ortho", "lidar", "demo_flight", "demo_cube",
               "outside_flight", "outside_cube", "placement")  # fmt: skip

DEFAULTS: dict[str, Any] = {
    "seed": 7,
    "size_m": 2048,
    "gsd_m": 1.0,
    "margin_m": 768,
    "lidar_density": 2.0,
    "lidar_tiles": 2,
    "lidar_crs": "EPSG:2229",
    "query": {"samples": 829, "lines": 1163, "bands": 260, "gsd_m": 0.8, "heading_deg": 35.0},
}


def output_paths(outdir: str | Path, lidar_tiles: int) -> dict[str, Path]:
    """Every file ``generate_scene`` writes, by name."""
    o = Path(outdir)
    paths = {
        "orthophoto": o / "orthophoto.tif",
        "dsm": o / "truth" / "dsm.tif",
        "dtm": o / "truth" / "dtm.tif",
        "ndsm": o / "truth" / "ndsm.tif",
        "labels": o / "truth" / "labels.tif",
        "classes": o / "truth" / "classes.json",
        "outliers": o / "truth" / "outliers.npy",
        "scene": o / "scene.json",
    }
    for name in ("demo", "outside"):
        q = o / "queries"
        paths[f"{name}_hdr"] = q / f"{name}.hdr"
        paths[f"{name}_bil"] = q / f"{name}.bil"
        paths[f"{name}_truth"] = q / f"{name}_truth.tif"
        paths[f"{name}_labels"] = q / f"{name}_labels.tif"
        paths[f"{name}_ndsm"] = q / f"{name}_ndsm.tif"
    for i in range(lidar_tiles):
        paths[f"lidar_{i}"] = o / "lidar" / f"tile_{i}.laz"
    return paths


def _conf(conf: dict[str, Any]) -> dict[str, Any]:
    c = {**DEFAULTS, **(conf or {})}
    c["query"] = {**DEFAULTS["query"], **((conf or {}).get("query") or {})}
    if c["size_m"] / c["gsd_m"] < 64:
        raise ConfigError(
            f"demo.size_m / demo.gsd_m = {c['size_m'] / c['gsd_m']:.0f} px: need at least 64"
        )
    if int(c["lidar_tiles"]) < 1:
        raise ConfigError("demo.lidar_tiles must be >= 1")
    return c


def write_geotiff(path: Path, data: np.ndarray, grid: Grid | None = None, crs: Any = None,
                  nodata: float | None = None, tags: dict[str, str] | None = None) -> None:  # fmt: skip
    """Tiled, deflate-compressed GeoTIFF; ``data`` is (bands, rows, cols) or (rows, cols)."""
    arr = data[None] if data.ndim == 2 else data
    profile = {
        "driver": "GTiff",
        "width": arr.shape[2],
        "height": arr.shape[1],
        "count": arr.shape[0],
        "dtype": arr.dtype,
        "tiled": True,
        "blockxsize": 256,
        "blockysize": 256,
        "compress": "deflate",
        "predictor": 3 if arr.dtype.kind == "f" else 2,
    }
    if grid is not None:
        profile.update(crs=crs, transform=grid.transform)
    if nodata is not None:
        profile["nodata"] = nodata
    if arr.shape[0] == 3 and arr.dtype == np.uint8:
        profile["photometric"] = "RGB"
    with atomic_path(path) as tmp, warnings.catch_warnings():
        warnings.simplefilter("ignore", NotGeoreferencedWarning)
        with rasterio.open(tmp, "w", **profile) as dst:
            dst.write(arr)
            if tags:
                dst.update_tags(**tags)


def _crop(surf: Surface, r0: int, c0: int, h: int, w: int) -> Surface:
    s = (slice(r0, r0 + h), slice(c0, c0 + w))
    return Surface(surf.grid.crop(r0, c0, h, w), surf.label[s], surf.mat[s], surf.c1[s], surf.c2[s],
                   surf.dsm[s], surf.dtm[s])  # fmt: skip


def place_inside(rng: np.random.Generator, q: dict, map_bounds, size: float) -> Flight:
    """Demo flight: footprint fully inside the map, near the centre with a seeded offset."""
    x0, y0, x1, y1 = map_bounds
    fl = Flight.random(
        rng,
        (0.0, 0.0),
        float(q["heading_deg"]),
        float(q["gsd_m"]),
        int(q["samples"]),
        int(q["lines"]),
    )
    hx, hy = fl.half_extent()
    buf = 4.0
    rx, ry = (x1 - x0) / 2 - hx - buf, (y1 - y0) / 2 - hy - buf
    if rx < 0 or ry < 0:
        raise ConfigError(
            f"the demo query footprint ({2 * hx:.0f} x {2 * hy:.0f} m) does not fit in the "
            f"{size:.0f} m map: reduce demo.query samples/lines/gsd_m or raise demo.size_m"
        )
    cx = (x0 + x1) / 2 + rng.uniform(-1, 1) * min(rx, 0.2 * size)
    cy = (y0 + y1) / 2 + rng.uniform(-1, 1) * min(ry, 0.2 * size)
    fl.centre = (float(cx), float(cy))
    return fl


def place_outside(rng: np.random.Generator, q: dict, map_bounds, margin: float) -> Flight:
    """Outside flight: half-size query (smaller if needed) flown in the margin around the map."""
    x0, y0, x1, y1 = map_bounds
    buf = 8.0
    samples, lines = max(16, int(q["samples"]) // 2), max(16, int(q["lines"]) // 2)
    while True:
        fl = Flight.random(
            rng, (0.0, 0.0), float(q["heading_deg"]), float(q["gsd_m"]), samples, lines
        )
        hx, hy = fl.half_extent()
        if 2 * min(hx, hy) <= margin - 2 * buf:
            break
        if samples <= 16 and lines <= 16:
            raise ConfigError(
                f"demo.margin_m = {margin} is too narrow for the 'outside' query (needs about "
                f"{2 * min(hx, hy) + 2 * buf:.0f} m at demo.query.gsd_m = {q['gsd_m']})"
            )
        samples, lines = max(16, int(samples * 0.85)), max(16, int(lines * 0.85))
    # sides where the footprint fits across the margin band: 0 west, 1 east, 2 south, 3 north
    sides = [s for s in range(4) if 2 * (hx if s < 2 else hy) <= margin - 2 * buf]
    side = int(rng.choice(sides))
    along = rng.uniform(-1, 1)
    if side < 2:
        cx = x0 - margin / 2 if side == 0 else x1 + margin / 2
        span = (y1 - y0) / 2 + margin - hy - buf
        cy = (y0 + y1) / 2 + along * span
    else:
        cy = y0 - margin / 2 if side == 2 else y1 + margin / 2
        span = (x1 - x0) / 2 + margin - hx - buf
        cx = (x0 + x1) / 2 + along * span
    fl.centre = (float(cx), float(cy))
    return fl


def _buildings_json(layout: Layout, boxes) -> list[dict]:
    r = layout.rects
    sel = np.isin(r["kind"], (KIND_BUILDING, KIND_ROOFTOP)) & (r["epoch"] > 0)
    near = np.zeros_like(sel)
    for b in boxes:
        near |= intersects(r, b)
    out: dict[int, dict] = {}
    for k in np.flatnonzero(sel & near):
        bid = int(r["bid"][k])
        top = float(r["h"][k] + r["ridge_h"][k])
        part = [round(float(r[f][k]), 2) for f in ("x0", "y0", "x1", "y1")] + [round(top, 2)]
        if bid not in out:
            out[bid] = {
                "id": bid,
                "class": C.CLASSES[int(r["label"][k])]["name"],
                "roof": S.MATERIAL_NAMES[int(r["mat"][k])],
                "roof_shape": "gable" if r["ridge"][k] else "flat",
                "base_m": round(float(r["base"][k]), 2),
                "height_m": round(top, 2),
                "epochs": {1: "map", 2: "query", 3: "both"}[int(r["epoch"][k])],
                "parts": [],
            }
        e = out[bid]
        e["parts"].append(part)
        e["height_m"] = max(e["height_m"], round(top, 2))
    for e in out.values():
        p = np.array(e["parts"])
        e["bbox"] = [
            float(p[:, 0].min()),
            float(p[:, 1].min()),
            float(p[:, 2].max()),
            float(p[:, 3].max()),
        ]
    return [out[k] for k in sorted(out)]


def generate_scene(conf: dict[str, Any], outdir: str | Path) -> dict[str, str]:
    """Generate the whole demo scene under ``outdir``; returns {name: path} of the files written."""
    t_start = time.perf_counter()
    c = _conf(conf)
    q = c["query"]
    paths = output_paths(outdir, int(c["lidar_tiles"]))
    rngs = dict(
        zip(
            RNG_STREAMS,
            (
                np.random.default_rng(s)
                for s in np.random.SeedSequence(int(c["seed"])).spawn(len(RNG_STREAMS))
            ),
            strict=True,
        )
    )
    size, gsd, margin = float(c["size_m"]), float(c["gsd_m"]), float(c["margin_m"])
    npx = int(round(size / gsd))
    size = npx * gsd
    x0, y0 = ORIGIN
    map_bounds = (x0, y0 - size, x0 + size, y0)
    world = (x0 - margin, y0 - size - margin, x0 + size + margin, y0 + margin)
    extent = (
        world[0] - LAYOUT_PAD_M,
        world[1] - LAYOUT_PAD_M,
        world[2] + LAYOUT_PAD_M,
        world[3] + LAYOUT_PAD_M,
    )
    map_crs = pyproj.CRS.from_epsg(MAP_EPSG)
    las_crs = pyproj.CRS.from_user_input(c["lidar_crs"])

    layout = make_layout(rngs["layout"], extent, (x0 + size / 2, y0 - size / 2), size)
    texture = Texture(rngs["texture"], extent)
    demo_fl = place_inside(rngs["demo_flight"], q, map_bounds, size)
    out_fl = place_outside(rngs["outside_flight"], q, map_bounds, margin)
    changes = apply_changes(layout, rngs["changes"], demo_fl)
    changes += car_changes(layout, [demo_fl.bbox(), out_fl.bbox()])
    log.info("layout: %d rectangles, %d trees (%.1f s)", layout.rects["x0"].size, layout.trees["cx"].size,
             time.perf_counter() - t_start)  # fmt: skip

    # ---- map epoch: orthophoto, truth rasters, LiDAR
    pad = int(np.ceil(ORTHO_PAD_M / gsd))
    grid = Grid(x0 - pad * gsd, y0 + pad * gsd, gsd, npx + 2 * pad, npx + 2 * pad)
    surf = rasterize(layout, grid, EPOCH_MAP, texture)
    rgb = render_orthophoto(surf, ORTHO_SUN, rngs["ortho"])[:, pad : pad + npx, pad : pad + npx]
    msurf = _crop(surf, pad, pad, npx, npx)
    del surf
    mgrid = msurf.grid
    tags = {"GEOREG_DEMO": "truth, map epoch (orthophoto/LiDAR time)"}
    write_geotiff(paths["orthophoto"], np.ascontiguousarray(rgb), mgrid, map_crs)
    write_geotiff(paths["dsm"], msurf.dsm.astype(np.float32), mgrid, map_crs, tags=tags)
    write_geotiff(paths["dtm"], msurf.dtm.astype(np.float32), mgrid, map_crs, tags=tags)
    write_geotiff(
        paths["ndsm"], (msurf.dsm - msurf.dtm).astype(np.float32), mgrid, map_crs, tags=tags
    )
    write_geotiff(
        paths["labels"], msurf.label.astype(np.uint8), mgrid, map_crs, nodata=0, tags=tags
    )
    write_json(paths["classes"], C.classes_json())
    log.info("orthophoto and truth rasters written (%.1f s)", time.perf_counter() - t_start)

    tiles, highs, lows = [], [], []
    lidar_rngs = rngs["lidar"].spawn(int(c["lidar_tiles"]))
    for i in range(int(c["lidar_tiles"])):
        b = strip_bounds(map_bounds, int(c["lidar_tiles"]), LIDAR_OVERLAP_M, i)
        pts, high, low = simulate_tile(
            msurf, layout.terrain, b, float(c["lidar_density"]), lidar_rngs[i]
        )
        n = write_laz(paths[f"lidar_{i}"], pts, map_crs, las_crs, source_id=i + 1)
        highs.append(high)
        lows.append(low)
        tiles.append({"path": paths[f"lidar_{i}"].name, "bounds_map": list(b), "points": n,
                      "outliers_high": int(high.shape[0]), "outliers_low": int(low.shape[0])})  # fmt: skip
        del pts
    outliers = np.concatenate(highs + lows)
    with atomic_path(paths["outliers"]) as tmp:
        np.save(tmp, outliers)
    del msurf
    log.info("LiDAR written (%.1f s)", time.perf_counter() - t_start)

    # ---- query epoch: the two SWIR cubes
    queries = {}
    for name, fl, rng in (
        ("demo", demo_fl, rngs["demo_cube"]),
        ("outside", out_fl, rngs["outside_cube"]),
    ):
        desc = (
            f"georeg synthetic SWIR pushbroom query '{name}' (seed {c['seed']}): reflectance x 10000, "
            f"int16, not geo-referenced; truth in {name}_truth.tif"
        )
        prod = render_query(
            layout, texture, fl, QUERY_SUN, int(q["bands"]), paths[f"{name}_hdr"], rng, desc
        )
        qtags = {"GEOREG_DEMO": f"query '{name}' pixel geometry", "MAP_CRS": f"EPSG:{MAP_EPSG}"}
        write_geotiff(
            paths[f"{name}_truth"],
            prod.truth,
            tags={**qtags, "BANDS": "1: map x, 2: map y (pixel centres)"},
        )
        write_geotiff(paths[f"{name}_labels"], prod.labels, nodata=0, tags=qtags)
        write_geotiff(paths[f"{name}_ndsm"], prod.ndsm, tags=qtags)
        queries[name] = {**fl.to_json(), "bands": int(q["bands"]), "truth_bbox": [
            float(prod.truth[0].min()), float(prod.truth[1].min()), float(prod.truth[0].max()), float(prod.truth[1].max())]}  # fmt: skip
        log.info("query %s written (%.1f s)", name, time.perf_counter() - t_start)

    wl, fwhm = S.wavelengths(int(q["bands"]))
    scene = {
        "seed": int(c["seed"]),
        "conf": c,
        "map": {
            "crs_epsg": MAP_EPSG,
            "crs_wkt": map_crs.to_wkt(),
            "bounds": list(map_bounds),
            "gsd_m": gsd,
            "width": npx,
            "height": npx,
            "transform": list(mgrid.transform)[:6],
        },
        "world_bounds": list(world),
        "lidar": {
            "crs": las_crs.to_string(),
            "crs_wkt": las_crs.to_wkt(),
            "overlap_m": LIDAR_OVERLAP_M,
            "range_noise_m": 0.05,
            "tiles": tiles,
        },  # fmt: skip
        "outliers": {
            "file": "truth/outliers.npy",
            "rows_high_first": int(sum(h.shape[0] for h in highs)),
            "high": int(sum(h.shape[0] for h in highs)),
            "low": int(sum(v.shape[0] for v in lows)),
            "note": "rows: all high outliers (birds, class 1) first, then all low ones (class 7 or 1)",
        },  # fmt: skip
        "sun": {"ortho": vars(ORTHO_SUN), "query": vars(QUERY_SUN)},
        "queries": queries,
        "wavelength_nm": [float(w) for w in wl],
        "materials": list(S.MATERIAL_NAMES),
        "classes": C.classes_json(),
        "block_types": list(BLOCK_TYPES),
        "urban_centres": [list(p) for p in layout.centres],
        "changes": changes,
        "buildings": _buildings_json(layout, [map_bounds, demo_fl.bbox(), out_fl.bbox()]),
    }
    write_json(paths["scene"], scene)
    log.info("demo scene complete in %.1f s: %s", time.perf_counter() - t_start, Path(outdir))
    return {k: str(v) for k, v in paths.items()}
