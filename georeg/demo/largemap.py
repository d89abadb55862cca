"""Large synthetic maps (hundreds of megapixels, many tiles, many LAZ files) in bounded memory.

The demo's procedural city (``georeg.demo.layout`` / ``raster`` / ``render`` / ``lidar``) is
generated **chunk by chunk**: the map is cut into square chunks of ``chunk_px`` pixels, and each
chunk is rasterised, rendered and LiDAR-scanned on its own, then written as one tiled GeoTIFF and
one LAZ file. A VRT (``orthophoto.vrt``) mosaics the chunks. Peak memory is that of one chunk
(plus its shadow pad) whatever the map size.

Consistency across chunks (no seams) comes from making everything a function of global
coordinates and one seed, never of the chunk:

* terrain (analytic cosines), the street grid (1-D intervals over the whole world: a few kB even
  for 100 km) and the diagonal avenue are global;
* the contents of city block ``(i, j)`` (between streets ``i, i+1`` and ``j, j+1``) are drawn
  from ``SeedSequence(seed, spawn_key=(BLOCK_STREAM, i, j))``, with the demo's own block
  builders: a chunk regenerates exactly the blocks that reach it (or its pad), identical to
  what its neighbour generates;
* urban centres (downtown intensity) are one per ``CENTRE_CELL_M`` cell, seeded per cell;
* surface texture is value noise whose lattice values are a hash of the global lattice index
  (``HashTexture``), so any window samples the same field.

Only the per-pixel camera noise of the orthophoto (sigma 1.5 DN) and the LiDAR pulse positions
are drawn per chunk. Usage::

    python -m georeg.demo.largemap --size-m 8192 --out /tmp/big --workers 2
    snakemake --cores 2 -d /tmp/bigrun --configfile /tmp/big/map.yaml

``map.yaml`` holds the workflow's ``map:`` section (the VRT, the LAZ grid) and one SWIR query
flown inside the map (``queries:``). See docs/SCALING.md.
"""

from __future__ import annotations

import argparse
import json
import logging
import math
import os
import time
from concurrent.futures import ProcessPoolExecutor
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import pyproj
import rasterio
from rasterio.windows import Window

from georeg.demo.layout import (
    BLOCK_TYPES,
    SIDEWALK_M,
    Layout,
    Streets,
    Terrain,
    _Builder,
    _street_intervals,
    drop_on_avenue,
    populate_block,
)
from georeg.demo.lidar import simulate_tile, write_laz
from georeg.demo.pushbroom import Flight, render_query
from georeg.demo.raster import Grid, Surface, rasterize
from georeg.demo.render import render_orthophoto
from georeg.demo.scene import MAP_EPSG, ORIGIN, ORTHO_SUN, QUERY_SUN, write_geotiff
from georeg.io.atomic import atomic_path, write_json
from georeg.io.errors import ConfigError
from georeg.io.raster import write_vrt

log = logging.getLogger(__name__)

CHUNK_PAD_M = 100.0  # rendered around each chunk: shadows cast from the neighbours, blur support
BLOCK_REACH_M = 40.0  # blocks this far beyond the padded chunk are generated too (tree crowns)
CENTRE_CELL_M = 3000.0  # one urban centre per cell of this side
QUERY_LAYOUT_PAD_M = 350.0  # as the demo's LAYOUT_PAD_M: low query sun, long shadows
STREAMS = {"global": 0, "block": 1, "centre": 2, "ortho": 3, "lidar": 4, "query": 5}
OTHERS = np.array([0.52, 0.13, 0.07, 0.08, 0.10, 0.10])  # as make_layout: non-downtown types


@dataclass(frozen=True)
class LargeMapSpec:
    """Everything that defines a large map; same spec, same bytes."""

    size_m: float = 4096.0
    gsd_m: float = 1.0
    seed: int = 7
    chunk_px: int = 2048
    lidar_density: float = 0.5
    lidar_crs: str = f"EPSG:{MAP_EPSG}"
    query_samples: int = 829  # the paper's (and the demo's) cube size
    query_lines: int = 1163
    query_bands: int = 24
    query_gsd_m: float = 0.8
    query_heading_deg: float = 35.0

    @property
    def npx(self) -> int:
        return int(round(self.size_m / self.gsd_m))

    @property
    def bounds(self) -> tuple[float, float, float, float]:
        x0, y1 = ORIGIN
        s = self.npx * self.gsd_m
        return (x0, y1 - s, x0 + s, y1)

    @property
    def world(self) -> tuple[float, float, float, float]:
        """Extent of the global street grid: the map plus every pad any chunk or query uses."""
        x0, y0, x1, y1 = self.bounds
        m = QUERY_LAYOUT_PAD_M + CHUNK_PAD_M + 2 * BLOCK_REACH_M + 200.0
        return (x0 - m, y0 - m, x1 + m, y1 + m)

    def chunks(self) -> list[tuple[int, int]]:
        n = math.ceil(self.npx / self.chunk_px)
        return [(r, c) for r in range(n) for c in range(n)]

    def chunk_grid(self, r: int, c: int) -> Grid:
        x0, _, _, y1 = self.bounds
        h = min(self.chunk_px, self.npx - r * self.chunk_px)
        w = min(self.chunk_px, self.npx - c * self.chunk_px)
        return Grid(x0 + c * self.chunk_px * self.gsd_m, y1 - r * self.chunk_px * self.gsd_m,
                    self.gsd_m, w, h)  # fmt: skip


def _ss(spec: LargeMapSpec, *key: int) -> np.random.Generator:
    return np.random.default_rng(np.random.SeedSequence(int(spec.seed), spawn_key=tuple(key)))


# ---------------------------------------------------------------------------------- texture


def _hash_normal(seed: int, octave: int, iy: np.ndarray, ix: np.ndarray) -> np.ndarray:
    """Standard-normal values as a pure function of (seed, octave, iy, ix): splitmix64 + Box-Muller."""
    with np.errstate(over="ignore"):
        k = (np.uint64(seed) * np.uint64(0x9E3779B97F4A7C15)) ^ (np.uint64(octave) << np.uint64(56))
        h = (iy.astype(np.int64).astype(np.uint64)[:, None] * np.uint64(0xD1B54A32D192ED03)) ^ (
            ix.astype(np.int64).astype(np.uint64)[None, :] * np.uint64(0xABC98388FB8FAC03)
        )
        h ^= k

        def mix(z: np.ndarray) -> np.ndarray:
            z = z + np.uint64(0x9E3779B97F4A7C15)
            z = (z ^ (z >> np.uint64(30))) * np.uint64(0xBF58476D1CE4E5B9)
            z = (z ^ (z >> np.uint64(27))) * np.uint64(0x94D049BB133111EB)
            return z ^ (z >> np.uint64(31))

        a = mix(h)
        b = mix(a)
    u1 = ((a >> np.uint64(11)).astype(np.float64) + 0.5) / float(1 << 53)
    u2 = (b >> np.uint64(11)).astype(np.float64) / float(1 << 53)
    return (np.sqrt(-2.0 * np.log(u1)) * np.cos(2.0 * np.pi * u2)).astype(np.float32)


class HashTexture:
    """``georeg.demo.raster.Texture`` with lattices hashed from global indices: window-independent.

    Same octaves, weights and cubic interpolation as the demo's texture; lattice point ``(k, l)``
    of an octave with spacing ``s`` sits at ``(X0 + l s, Y1 - k s)`` for the world corner
    ``(X0, Y1)``, whichever window samples it.
    """

    SPACINGS = (40.0, 9.0, 2.0)
    WEIGHTS = (0.55, 0.45, 0.55)
    CROWN_SPACING = 0.9

    def __init__(self, seed: int, world: tuple[float, float, float, float]) -> None:
        self.seed = int(seed)
        self.xmin, self.ymax = float(world[0]), float(world[3])

    def _sample(self, octave: int, spacing: float, grid: Grid) -> np.ndarray:
        fx = (grid.xs() - self.xmin) / spacing
        fy = (self.ymax - grid.ys()) / spacing
        ix0, iy0 = int(np.floor(fx.min())) - 2, int(np.floor(fy.min())) - 2
        ix1, iy1 = int(np.floor(fx.max())) + 3, int(np.floor(fy.max())) + 3
        lat = _hash_normal(self.seed, octave, np.arange(iy0, iy1 + 1), np.arange(ix0, ix1 + 1))
        mapx = np.broadcast_to((fx - ix0).astype(np.float32)[None, :], (grid.height, grid.width))
        mapy = np.broadcast_to((fy - iy0).astype(np.float32)[:, None], (grid.height, grid.width))
        return cv2.remap(lat, np.ascontiguousarray(mapx), np.ascontiguousarray(mapy), cv2.INTER_CUBIC,
                         borderMode=cv2.BORDER_REFLECT)  # fmt: skip

    def field(self, grid: Grid) -> np.ndarray:
        out = np.zeros((grid.height, grid.width), np.float32)
        for o, (s, wgt) in enumerate(zip(self.SPACINGS, self.WEIGHTS, strict=True)):
            out += wgt * self._sample(o, s, grid)
        return out

    def crown_field(self, grid: Grid) -> np.ndarray:
        return self._sample(len(self.SPACINGS), self.CROWN_SPACING, grid)


# ---------------------------------------------------------------------------------- layout


@dataclass
class WorldFrame:
    """The global, cheap part of the city: terrain, street grid, avenue (a few kB)."""

    terrain: Terrain
    streets: Streets
    texture: HashTexture


def world_frame(spec: LargeMapSpec) -> WorldFrame:
    rng = _ss(spec, STREAMS["global"])
    xmin, ymin, xmax, ymax = spec.world
    terrain = Terrain.random(rng)
    sx, sx_age = _street_intervals(rng, xmin, xmax)
    sy, sy_age = _street_intervals(rng, ymin, ymax)
    ang = rng.uniform(np.radians(25), np.radians(65)) * rng.choice([-1, 1])
    x0, y0, x1, y1 = spec.bounds
    centre = np.array([(x0 + x1) / 2, (y0 + y1) / 2])
    diag_pt = centre + rng.uniform(-0.3, 0.3, 2) * min(x1 - x0, 4000.0)
    streets = Streets(sx, sy, sx_age, sy_age, diag_pt, np.array([np.cos(ang), np.sin(ang)]),
                      float(rng.uniform(24, 32)))  # fmt: skip
    return WorldFrame(terrain, streets, HashTexture(spec.seed, spec.world))


def _centres(spec: LargeMapSpec, box) -> list[tuple[float, float, float, float]]:
    """Urban centres (x, y, radius, strength) that can influence ``box``: one per seeded cell."""
    X0, _, _, Y1 = spec.world
    reach = 3 * 380.0
    c0 = int(np.floor((box[0] - reach - X0) / CENTRE_CELL_M))
    c1 = int(np.floor((box[2] + reach - X0) / CENTRE_CELL_M))
    r0 = int(np.floor((Y1 - box[3] - reach) / CENTRE_CELL_M))
    r1 = int(np.floor((Y1 - box[1] + reach) / CENTRE_CELL_M))
    out = []
    for r in range(r0, r1 + 1):
        for c in range(c0, c1 + 1):
            rng = _ss(spec, STREAMS["centre"], r + 1_000_000, c + 1_000_000)
            x = X0 + (c + rng.uniform(0.15, 0.85)) * CENTRE_CELL_M
            y = Y1 - (r + rng.uniform(0.15, 0.85)) * CENTRE_CELL_M
            big = rng.random() < 0.35
            out.append((x, y, 380.0 if big else rng.uniform(180, 300),
                        1.0 if big else rng.uniform(0.5, 0.8)))  # fmt: skip
    return out


def local_layout(spec: LargeMapSpec, frame: WorldFrame, box) -> Layout:
    """The city over ``box`` (xmin, ymin, xmax, ymax): every block reaching it, seeded per block."""
    st = frame.streets
    xmin, ymin, xmax, ymax = box
    # street intervals bracketing the box (one extra on each side), global block indices
    i0 = max(int(np.searchsorted(st.x[:, 1], xmin - BLOCK_REACH_M)) - 1, 0)
    i1 = min(int(np.searchsorted(st.x[:, 0], xmax + BLOCK_REACH_M)) + 1, len(st.x) - 1)
    j0 = max(int(np.searchsorted(st.y[:, 1], ymin - BLOCK_REACH_M)) - 1, 0)
    j1 = min(int(np.searchsorted(st.y[:, 0], ymax + BLOCK_REACH_M)) + 1, len(st.y) - 1)
    if st.x[i0, 0] > xmin or st.x[i1, 1] < xmax or st.y[j0, 0] > ymin or st.y[j1, 1] < ymax:
        raise ConfigError(f"box {box} reaches beyond the large map's world {spec.world}")
    sx, sy = st.x[i0 : i1 + 1], st.y[j0 : j1 + 1]
    streets = Streets(sx, sy, st.x_age[i0 : i1 + 1], st.y_age[j0 : j1 + 1], st.diag_point,
                      st.diag_dir, st.diag_width)  # fmt: skip
    centres = _centres(spec, box)
    nbx, nby = len(sx) - 1, len(sy) - 1
    btype = np.zeros((nby, nbx), np.int32)
    blabel = np.zeros((nby, nbx), np.uint8)
    bmat = np.zeros((nby, nbx), np.uint8)
    bc1 = np.zeros((nby, nbx))
    bc2 = np.zeros((nby, nbx))
    b = _Builder()
    n_gx = len(st.x)
    for jj in range(nby):
        for ii in range(nbx):
            gi, gj = i0 + ii, j0 + jj
            rng = _ss(spec, STREAMS["block"], gj, gi)
            bc1[jj, ii], bc2[jj, ii] = rng.normal(0, 0.08), rng.random()
            bx = (sx[ii, 1] + SIDEWALK_M, sy[jj, 1] + SIDEWALK_M,
                  sx[ii + 1, 0] - SIDEWALK_M, sy[jj + 1, 0] - SIDEWALK_M)  # fmt: skip
            cx, cy = 0.5 * (bx[0] + bx[2]), 0.5 * (bx[1] + bx[3])
            u = max((s * np.exp(-(((cx - ux) ** 2 + (cy - uy) ** 2) / r**2))
                     for ux, uy, r, s in centres), default=0.0)  # fmt: skip
            t = 0 if rng.random() < 0.9 * u else 1 + int(rng.choice(6, p=OTHERS / OTHERS.sum()))
            btype[jj, ii] = t
            bid = (gj * n_gx + gi) * 1000  # globally unique building ids per block
            blabel[jj, ii], bmat[jj, ii], c2_scale, _ = populate_block(
                b, rng, bx, BLOCK_TYPES[t], u, frame.terrain, bid
            )
            bc2[jj, ii] *= c2_scale
    rects, trees = drop_on_avenue(streets, *b.arrays())
    return Layout(tuple(box), frame.terrain, streets, btype, blabel, bmat, bc1, bc2, rects, trees,
                  [(c[0], c[1]) for c in centres])  # fmt: skip


# ---------------------------------------------------------------------------------- rendering


def render_window(spec: LargeMapSpec, frame: WorldFrame, grid: Grid, rng: np.random.Generator,
                  pad_m: float = CHUNK_PAD_M) -> tuple[Surface, np.ndarray]:  # fmt: skip
    """Surface (map epoch) and RGB orthophoto of ``grid``, rendered with ``pad_m`` of context."""
    from georeg.demo.layout import EPOCH_MAP

    pad = int(np.ceil(pad_m / grid.res))
    big = Grid(grid.x0 - pad * grid.res, grid.y0 + pad * grid.res, grid.res,
               grid.width + 2 * pad, grid.height + 2 * pad)  # fmt: skip
    layout = local_layout(spec, frame, big.bounds)
    surf = rasterize(layout, big, EPOCH_MAP, frame.texture)
    rgb = render_orthophoto(surf, ORTHO_SUN, rng)
    s = (slice(pad, pad + grid.height), slice(pad, pad + grid.width))
    surf = Surface(
        grid, surf.label[s], surf.mat[s], surf.c1[s], surf.c2[s], surf.dsm[s], surf.dtm[s]
    )
    return surf, np.ascontiguousarray(rgb[:, s[0], s[1]])


def output_paths(outdir: str | Path, spec: LargeMapSpec) -> dict[str, Any]:
    o = Path(outdir)
    return {
        "vrt": o / "orthophoto.vrt",
        "config": o / "map.yaml",
        "manifest": o / "largemap.json",
        "chunks": {
            rc: o / "ortho" / f"chunk_r{rc[0]:03d}_c{rc[1]:03d}.tif" for rc in spec.chunks()
        },
        "lidar": {rc: o / "lidar" / f"lidar_r{rc[0]:03d}_c{rc[1]:03d}.laz" for rc in spec.chunks()},
        "query_hdr": o / "queries" / "q0.hdr",
        "query_truth": o / "queries" / "q0_truth.tif",
    }


def write_chunk(spec: LargeMapSpec, outdir: str | Path, r: int, c: int,
                frame: WorldFrame | None = None) -> dict[str, Any]:  # fmt: skip
    """Render chunk (r, c): its orthophoto GeoTIFF and its LAZ file (skipped when both exist)."""
    t0 = time.perf_counter()
    paths = output_paths(outdir, spec)
    tif, laz = paths["chunks"][(r, c)], paths["lidar"][(r, c)]
    grid = spec.chunk_grid(r, c)
    info = {"chunk": [r, c], "ortho": str(tif), "lidar": str(laz), "bounds": list(grid.bounds)}
    if tif.exists() and laz.exists():
        with rasterio.open(tif) as ds:
            info["points"] = None
            info["pixels"] = ds.width * ds.height
        return info
    frame = frame or world_frame(spec)
    map_crs = pyproj.CRS.from_epsg(MAP_EPSG)
    surf, rgb = render_window(spec, frame, grid, _ss(spec, STREAMS["ortho"], r, c))
    write_geotiff(tif, rgb, grid, map_crs)
    del rgb
    pts, high, low = simulate_tile(surf, frame.terrain, grid.bounds, spec.lidar_density,
                                   _ss(spec, STREAMS["lidar"], r, c))  # fmt: skip
    del surf
    n = write_laz(laz, pts, map_crs, pyproj.CRS.from_user_input(spec.lidar_crs),
                  source_id=(r * 1000 + c) % 65535 + 1)  # fmt: skip
    info.update(points=n, outliers=int(high.shape[0] + low.shape[0]), pixels=grid.width * grid.height,
                seconds=round(time.perf_counter() - t0, 2))  # fmt: skip
    log.info(
        "chunk r%03d c%03d: %d px, %d points (%.1f s)", r, c, info["pixels"], n, info["seconds"]
    )
    return info


def _chunk_job(args: tuple) -> dict[str, Any]:
    spec_d, outdir, r, c = args
    return write_chunk(LargeMapSpec(**spec_d), outdir, r, c)


def place_query(spec: LargeMapSpec) -> Flight:
    """The query flight: fully inside the map, at a seeded position (away from the edges)."""
    rng = _ss(spec, STREAMS["query"], 0)
    fl = Flight.random(rng, (0.0, 0.0), spec.query_heading_deg, spec.query_gsd_m,
                       spec.query_samples, spec.query_lines)  # fmt: skip
    hx, hy = fl.half_extent()
    x0, y0, x1, y1 = spec.bounds
    if 2 * hx + 16 > x1 - x0 or 2 * hy + 16 > y1 - y0:
        raise ConfigError("the query footprint does not fit in the large map: raise --size-m")
    fl.centre = (
        float(rng.uniform(x0 + hx + 8, x1 - hx - 8)),
        float(rng.uniform(y0 + hy + 8, y1 - hy - 8)),
    )
    return fl


def write_query(spec: LargeMapSpec, outdir: str | Path, frame: WorldFrame | None = None) -> dict:
    """Render the SWIR query 'q0' (ENVI) and its truth with a layout around its footprint only."""
    paths = output_paths(outdir, spec)
    frame = frame or world_frame(spec)
    fl = place_query(spec)
    bx = fl.bbox()
    p = QUERY_LAYOUT_PAD_M
    layout = local_layout(spec, frame, (bx[0] - p, bx[1] - p, bx[2] + p, bx[3] + p))
    prod = render_query(layout, frame.texture, fl, QUERY_SUN, spec.query_bands, paths["query_hdr"],
                        _ss(spec, STREAMS["query"], 1), "georeg large synthetic map query q0")  # fmt: skip
    write_geotiff(paths["query_truth"], prod.truth,
                  tags={"MAP_CRS": f"EPSG:{MAP_EPSG}", "BANDS": "1: map x, 2: map y"})  # fmt: skip
    return fl.to_json()


def write_config(spec: LargeMapSpec, outdir: str | Path) -> Path:
    """``map.yaml``: the workflow's ``map:`` and ``queries:`` sections for this large map."""
    paths = output_paths(outdir, spec)
    o = Path(outdir).resolve()
    lines = [
        f"# large synthetic map: {spec.npx} x {spec.npx} px ({spec.npx**2 / 1e6:.0f} Mpx), "
        f"{len(paths['chunks'])} chunks; generated by georeg.demo.largemap",
        "map:",
        f"  orthophoto: {o / paths['vrt'].name}",
        "  lidar:",
        *[f"    - {(o / p.relative_to(outdir)).as_posix()}" for p in paths["lidar"].values()],
        "  lidar_crs: null",
        "  dem: null",
        "  crs: null",
        "queries:",
        "  q0:",
        f"    image: {o / 'queries' / 'q0.hdr'}",
        "    band: 1200nm",
        f"    gsd_m: {spec.query_gsd_m}",
        f"    truth: {o / 'queries' / 'q0_truth.tif'}",
    ]
    with atomic_path(paths["config"]) as tmp:
        Path(tmp).write_text("\n".join(lines) + "\n")
    return paths["config"]


def generate_large_map(outdir: str | Path, spec: LargeMapSpec | None = None, workers: int = 1,
                       query: bool = True) -> dict[str, Any]:  # fmt: skip
    """Write the large map under ``outdir`` chunk by chunk; returns the manifest.

    Files: ``ortho/chunk_rRRR_cCCC.tif`` (tiled deflate RGB GeoTIFF, EPSG:32611), ``orthophoto.vrt``
    (their mosaic), ``lidar/lidar_rRRR_cCCC.laz`` (one LAZ per chunk, ``spec.lidar_crs``),
    ``queries/q0.hdr|.bil|_truth.tif``, ``map.yaml`` (workflow config) and ``largemap.json``.
    Chunks already on disk are kept (restartable). ``workers`` > 1 renders chunks in parallel
    processes: memory ~ workers x one chunk.
    """
    spec = spec or LargeMapSpec()
    if spec.npx < 256:
        raise ConfigError("size_m / gsd_m must give at least 256 px")
    if spec.chunk_px % 256:
        raise ConfigError("chunk_px must be a multiple of 256 (the GeoTIFF block size)")
    t0 = time.perf_counter()
    outdir = Path(outdir)
    paths = output_paths(outdir, spec)
    jobs = [(asdict(spec), str(outdir), r, c) for r, c in spec.chunks()]
    if workers > 1:
        with ProcessPoolExecutor(workers) as ex:
            infos = list(ex.map(_chunk_job, jobs))
    else:
        frame = world_frame(spec)
        infos = [write_chunk(spec, outdir, r, c, frame) for r, c in spec.chunks()]
    x0, _, _, y1 = spec.bounds
    sources = []
    for (r, c), tif in paths["chunks"].items():
        g = spec.chunk_grid(r, c)
        sources.append((tif, Window(0, 0, g.width, g.height),
                        Window(c * spec.chunk_px, r * spec.chunk_px, g.width, g.height)))  # fmt: skip
    transform = Grid(x0, y1, spec.gsd_m, spec.npx, spec.npx).transform
    write_vrt(paths["vrt"], sources, f"EPSG:{MAP_EPSG}", transform, spec.npx, spec.npx, 3, "uint8")
    manifest: dict[str, Any] = {
        "spec": asdict(spec),
        "bounds": list(spec.bounds),
        "width": spec.npx,
        "height": spec.npx,
        "megapixels": spec.npx**2 / 1e6,
        "crs": f"EPSG:{MAP_EPSG}",
        "chunks": infos,
    }
    if query:
        manifest["query"] = write_query(spec, outdir)
    write_config(spec, outdir)
    manifest["seconds"] = round(time.perf_counter() - t0, 1)
    write_json(paths["manifest"], manifest)
    log.info("large map %d x %d px, %d chunks in %.1f s: %s", spec.npx, spec.npx, len(infos),
             manifest["seconds"], outdir)  # fmt: skip
    return manifest


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(
        prog="python -m georeg.demo.largemap", description=__doc__.split("\n")[0]
    )
    p.add_argument("--out", required=True, help="output directory")
    p.add_argument("--size-m", type=float, default=4096.0, help="map side (m)")
    p.add_argument("--gsd-m", type=float, default=1.0)
    p.add_argument("--seed", type=int, default=7)
    p.add_argument("--chunk-px", type=int, default=2048, help="chunk side (px, multiple of 256)")
    p.add_argument("--lidar-density", type=float, default=0.5, help="pulses per m2")
    p.add_argument("--lidar-crs", default=f"EPSG:{MAP_EPSG}")
    p.add_argument("--query-bands", type=int, default=24)
    p.add_argument("--query-gsd-m", type=float, default=LargeMapSpec.query_gsd_m)
    p.add_argument("--query-samples", type=int, default=LargeMapSpec.query_samples)
    p.add_argument("--query-lines", type=int, default=LargeMapSpec.query_lines)
    p.add_argument("--no-query", action="store_true")
    p.add_argument("--workers", type=int, default=1, help="chunks rendered in parallel")
    a = p.parse_args(argv)
    logging.basicConfig(
        level=logging.INFO, format="%(asctime)s %(levelname)s %(name)s: %(message)s"
    )
    spec = LargeMapSpec(size_m=a.size_m, gsd_m=a.gsd_m, seed=a.seed, chunk_px=a.chunk_px,
                        lidar_density=a.lidar_density, lidar_crs=a.lidar_crs,
                        query_bands=a.query_bands, query_gsd_m=a.query_gsd_m,
                        query_samples=a.query_samples, query_lines=a.query_lines)  # fmt: skip
    m = generate_large_map(a.out, spec, workers=max(1, a.workers), query=not a.no_query)
    print(json.dumps({k: m[k] for k in ("width", "height", "megapixels", "seconds")}))
    print(os.path.join(a.out, "map.yaml"))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
