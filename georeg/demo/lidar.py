"""Airborne LiDAR point cloud of the map epoch: LAS 1.4 point format 6, LAZ, in the LiDAR CRS.

Pulses fall uniformly at ``density`` per m2 (one last return each); tree pulses get up to four
returns (canopy first, ground last); water drops most pulses; ~5 cm range noise; injected outliers:
"birds" far above the roofs (class 1) and multipath points below the ground (class 7 or 1).
"""

from __future__ import annotations

import datetime
from dataclasses import dataclass
from pathlib import Path

import laspy
import numpy as np
import pyproj

from georeg.demo import classes as C
from georeg.demo import spectra as S
from georeg.demo.layout import Terrain
from georeg.demo.raster import Surface
from georeg.io.atomic import atomic_path

RANGE_NOISE_M = 0.05
BIRDS_PER_KM2 = 75.0
LOW_NOISE_PER_KM2 = 60.0


@dataclass
class TileResult:
    path: Path
    bounds_map: tuple[float, float, float, float]
    n_points: int
    outliers_high: np.ndarray  # (n, 3) map-CRS xyz (metres)
    outliers_low: np.ndarray


def strip_bounds(map_bounds: tuple[float, float, float, float], n_tiles: int, overlap: float,
                 i: int) -> tuple[float, float, float, float]:  # fmt: skip
    """x-strip ``i`` of ``n_tiles`` over the map extent, widened by ``overlap`` (clipped to the map)."""
    x0, y0, x1, y1 = map_bounds
    w = (x1 - x0) / n_tiles
    return (max(x0, x0 + i * w - overlap), y0, min(x1, x0 + (i + 1) * w + overlap), y1)


def _las_class(label: np.ndarray) -> np.ndarray:
    lut = np.ones(256, np.uint8)
    for k, v in C.LAS_CLASS.items():
        lut[k] = v
    return lut[label]


def simulate_tile(surf: Surface, terrain: Terrain, bounds: tuple[float, float, float, float],
                  density: float, rng: np.random.Generator) -> tuple[dict[str, np.ndarray], np.ndarray, np.ndarray]:  # fmt: skip
    """Points of one tile in map CRS: a dict of columns, plus the injected high/low outliers."""
    x0, y0, x1, y1 = bounds
    area = (x1 - x0) * (y1 - y0)
    n = int(rng.poisson(density * area))
    px = rng.uniform(x0, x1, n)
    py = rng.uniform(y0, y1, n)
    g = surf.grid
    col = np.clip(((px - g.x0) / g.res).astype(np.int64), 0, g.width - 1)
    row = np.clip(((g.y0 - py) / g.res).astype(np.int64), 0, g.height - 1)
    label, mat = surf.label[row, col], surf.mat[row, col]
    keep = (label != C.WATER) | (rng.random(n) < 0.2)  # specular water: most pulses lost
    px, py, row, col, label, mat = px[keep], py[keep], row[keep], col[keep], label[keep], mat[keep]
    order = np.lexsort((px, np.floor((y1 - py) / 8.0)))  # scan-line-like order
    px, py, row, col, label, mat = (
        px[order],
        py[order],
        row[order],
        col[order],
        label[order],
        mat[order],
    )
    n = px.size
    ground = terrain(px, py)
    top = surf.dsm[row, col].astype(np.float64)
    m1064, v1064 = S.reflectance_at(1064.0)
    refl = np.clip(m1064[mat] * (1 + surf.c1[row, col]) + surf.c2[row, col] * v1064[mat], 0.01, 1.0)
    cls = _las_class(label)
    is_ground_cls = cls == 2
    top = np.where(is_ground_cls, ground, top)
    tree = label == C.TREE
    nret = np.ones(n, np.int64)
    nret[tree] = rng.choice([1, 2, 3, 4], size=int(tree.sum()), p=[0.3, 0.35, 0.25, 0.1])
    pulse = np.repeat(np.arange(n), nret)
    starts = np.cumsum(nret) - nret
    rn = np.arange(pulse.size) - np.repeat(starts, nret) + 1
    nr = nret[pulse]
    z = top[pulse].copy()
    c = cls[pulse].copy()
    inten = refl[pulse] * 30000.0
    g_p = ground[pulse]
    last = (rn == nr) & (nr > 1)
    hits_ground = last & (rng.random(pulse.size) < 0.8)
    z[hits_ground] = g_p[hits_ground]
    c[hits_ground] = 2
    mid = (rn > 1) & ~hits_ground
    z[mid] = (
        g_p[mid]
        + 1.0
        + rng.random(int(mid.sum())) * np.maximum(top[pulse][mid] - g_p[mid] - 1.0, 0.0)
    )
    hag = z - g_p
    c[mid] = np.where(hag[mid] >= 5.0, 5, np.where(hag[mid] >= 2.0, 4, 3))
    m1064_ground = m1064[S.SOIL]
    inten[hits_ground] = m1064_ground * 30000.0
    inten *= np.where(nr > 1, 0.8 / nr, 1.0) * (1.0 + 0.08 * rng.standard_normal(pulse.size))
    z += rng.normal(0.0, RANGE_NOISE_M, pulse.size)
    pts = {
        "x": px[pulse],
        "y": py[pulse],
        "z": z,
        "intensity": np.clip(inten, 1, 65535).astype(np.uint16),
        "return_number": rn.astype(np.uint8),
        "number_of_returns": nr.astype(np.uint8),
        "classification": c.astype(np.uint8),
    }
    # outliers
    km2 = area / 1e6
    nh, nl = int(rng.poisson(BIRDS_PER_KM2 * km2)), int(rng.poisson(LOW_NOISE_PER_KM2 * km2))
    hx, hy = rng.uniform(x0, x1, nh), rng.uniform(y0, y1, nh)
    high = np.column_stack([hx, hy, terrain(hx, hy) + rng.uniform(140.0, 450.0, nh)])
    lx, ly = rng.uniform(x0, x1, nl), rng.uniform(y0, y1, nl)
    low = np.column_stack([lx, ly, terrain(lx, ly) - rng.uniform(0.5, 25.0, nl)])
    low_cls = np.where(rng.random(nl) < 0.5, 7, 1).astype(np.uint8)
    out = np.concatenate([high, low])
    nout = out.shape[0]
    ins = np.sort(rng.integers(0, pts["x"].size + 1, nout))  # interleave them in acquisition order
    extra = {
        "x": out[:, 0],
        "y": out[:, 1],
        "z": out[:, 2],
        "intensity": rng.integers(5, 400, nout).astype(np.uint16),
        "return_number": np.ones(nout, np.uint8),
        "number_of_returns": np.ones(nout, np.uint8),
        "classification": np.concatenate([np.ones(nh, np.uint8), low_cls]),
    }
    order = rng.permutation(nout)
    for k in pts:
        pts[k] = np.insert(pts[k], ins, extra[k][order])
    return pts, high, low


def write_laz(path: str | Path, pts: dict[str, np.ndarray], map_crs: pyproj.CRS, las_crs: pyproj.CRS,
              source_id: int) -> int:  # fmt: skip
    """Reproject map-CRS points to ``las_crs`` (horizontal and vertical units) and write LAZ."""
    tr = pyproj.Transformer.from_crs(map_crs, las_crs, always_xy=True)
    x, y = tr.transform(pts["x"], pts["y"])
    unit = las_crs.axis_info[0].unit_conversion_factor if las_crs.axis_info else 1.0
    z = pts["z"] / unit
    header = laspy.LasHeader(point_format=6, version="1.4")
    header.scales = np.array([0.01, 0.01, 0.01])
    header.offsets = np.array(
        [np.floor(x.min() / 1000) * 1000, np.floor(y.min() / 1000) * 1000, 0.0]
    )
    header.add_crs(las_crs)
    header.system_identifier = "georeg demo scene"
    header.generating_software = "georeg.demo.lidar"
    header.creation_date = datetime.date(2024, 1, 1)  # fixed: identical bytes for identical input
    las = laspy.LasData(header)
    las.x, las.y, las.z = x, y, z
    for k in ("intensity", "return_number", "number_of_returns", "classification"):
        setattr(las, k, pts[k])
    las.point_source_id = np.full(x.size, source_id, np.uint16)
    las.gps_time = 1.0e8 + source_id * 1.0e4 + np.arange(x.size) * 2.0e-6
    with atomic_path(path) as tmp:
        las.write(str(tmp), laz_backend=laspy.LazBackend.Lazrs)
    return int(x.size)
