"""Spectral-elevation segmentation: SWIR indices + nDSM rules -> seven land-cover classes.

The paper (section 5) proposes and leaves undone: a wetness index separates water-bearing
materials (live vegetation) from dry ones (roads, roofs), and elevation splits each group
(tall buildings / houses, trees / grass). Band choices and thresholds: docs/SEGMENTATION.md.

Indices (reflectance R averaged over a window of bands, windows in ``WINDOWS_NM``):

* ``d1450`` = 1 - R1450 / continuum(R1285, R1560): depth of the 1.45 um liquid-water absorption
  relative to a straight continuum; a continuum-removed depth, so a smooth change of the
  illumination (cast shadow lit by blue-ish skylight) barely changes it. Vegetation > 0.1.
* ``ndii`` = (R1240 - R1650) / (R1240 + R1650): normalized-difference infrared (moisture) index
  (Hardisky et al. 1983; Gao's NDWI uses 860/1240). Guards against noisy depths of dry surfaces.
* ``ndwi`` = (R1000 - R1240) / (R1000 + R1240): open water's reflectance collapses from 0.9 to
  1.2 um; with a very low brightness it flags water (shadows are dark but flatter).
* ``brightness`` = mean of R1000, R1240, R1650, R2200: shadow / water.
"""

from __future__ import annotations

import csv
import logging
import os
import warnings
from typing import Any

import numpy as np
import rasterio

from georeg.io.atomic import atomic_path
from georeg.io.errors import InputError
from georeg.io.query import Cube, EnviCube

log = logging.getLogger(__name__)

NODATA = 0
TALL_BUILDING, LOW_BUILDING, TREE, GRASS, ROAD_BARE, WATER, SHADOW = range(1, 8)
CLASSES: dict[int, dict[str, Any]] = {
    TALL_BUILDING: {"name": "tall_building", "label": "tall building", "color": (200, 40, 40)},
    LOW_BUILDING: {
        "name": "low_building",
        "label": "low building / house",
        "color": (235, 140, 60),
    },
    TREE: {"name": "tree", "label": "tall vegetation / trees", "color": (20, 110, 30)},
    GRASS: {"name": "grass", "label": "low vegetation / grass", "color": (130, 210, 90)},
    ROAD_BARE: {"name": "road_bare", "label": "road / parking / bare", "color": (150, 150, 150)},
    WATER: {"name": "water", "label": "water", "color": (30, 80, 220)},
    SHADOW: {"name": "shadow_unknown", "label": "shadow / unknown", "color": (20, 20, 20)},
}

#: band windows (nm) averaged into the reflectances the indices use
WINDOWS_NM: dict[str, tuple[float, float]] = {
    "r1000": (980.0, 1020.0),
    "r1240": (1220.0, 1260.0),
    "r1285": (1265.0, 1305.0),
    "r1450": (1430.0, 1480.0),
    "r1560": (1540.0, 1580.0),
    "r1650": (1620.0, 1680.0),
    "r2200": (2180.0, 2220.0),
}

DEFAULTS: dict[str, float] = {
    "shadow_max_brightness": 0.008,
    "veg_min_d1450": 0.10,
    "veg_min_ndii": -0.03,
    "water_max_brightness": 0.012,
    "water_min_ndwi": 0.30,
    "low_min_m": 2.5,
    "tall_min_m": 12.0,
    "tree_min_m": 2.5,
    "smooth_px": 1,
}

#: the demo generator's classes (georeg.demo.classes) -> segmentation classes
DEMO_TO_SEG = {1: ROAD_BARE, 2: ROAD_BARE, 3: ROAD_BARE, 4: ROAD_BARE, 5: GRASS, 6: TREE,
               7: LOW_BUILDING, 8: TALL_BUILDING, 9: WATER, 10: ROAD_BARE}  # fmt: skip


def reflectance_scale(cube: Cube, scale: float | None = None) -> float:
    """Divide DNs by this to get reflectance: ``scale``, else the ENVI header's, else 1."""
    if scale:
        return float(scale)
    if isinstance(cube, EnviCube) and "reflectance scale factor" in cube.header:
        try:
            return float(cube.header["reflectance scale factor"])
        except ValueError:
            pass
    return 1.0


def window_bands(wavelengths_nm: np.ndarray | None) -> dict[str, np.ndarray]:
    """Band indices of each window (the nearest band within 50 nm when the window has none)."""
    if wavelengths_nm is None:
        raise InputError(None, "the segmentation needs band wavelengths and the cube has none")
    wl = np.asarray(wavelengths_nm)
    out = {}
    for k, (lo, hi) in WINDOWS_NM.items():
        idx = np.flatnonzero((wl >= lo) & (wl <= hi))
        if idx.size == 0:
            j = int(np.argmin(np.abs(wl - (lo + hi) / 2)))
            if abs(wl[j] - (lo + hi) / 2) > 50:
                raise InputError(
                    None,
                    f"no band near {lo:.0f}-{hi:.0f} nm for the segmentation index '{k}'",
                    f"the cube covers {wl.min():.0f}-{wl.max():.0f} nm",
                )
            idx = np.array([j])
        out[k] = idx
    return out


def spectral_indices(
    cube: Cube, scale: float | None = None, smooth_px: int = 1
) -> dict[str, np.ndarray]:
    """``brightness``, ``d1450``, ``ndii``, ``ndwi`` (float32, query geometry) and ``valid``.

    Streams the needed bands one at a time (about 45 of 260).
    """
    import cv2

    s = reflectance_scale(cube, scale)
    win = window_bands(cube.wavelengths_nm)
    valid = np.ones((cube.height, cube.width), bool)
    R: dict[str, np.ndarray] = {}
    for k, idx in win.items():
        acc = np.zeros((cube.height, cube.width), np.float32)
        for i in idx:
            b = cube.read_band(int(i))
            bad = ~np.isfinite(b)
            if cube.nodata is not None:
                bad |= b == cube.nodata
            valid &= ~bad
            acc += np.where(bad, 0.0, b)
        acc /= len(idx) * s
        if smooth_px > 1:
            acc = cv2.blur(acc, (int(smooth_px), int(smooth_px)))
        R[k] = acc
    eps = np.float32(1e-6)
    cont = R["r1285"] + (R["r1560"] - R["r1285"]) * np.float32((1455 - 1285) / (1560 - 1285))
    out = {
        "brightness": (R["r1000"] + R["r1240"] + R["r1650"] + R["r2200"]) / 4,
        "d1450": 1 - R["r1450"] / np.maximum(cont, eps),
        "ndii": (R["r1240"] - R["r1650"]) / np.maximum(R["r1240"] + R["r1650"], eps),
        "ndwi": (R["r1000"] - R["r1240"]) / np.maximum(R["r1000"] + R["r1240"], eps),
    }
    out = {k: v.astype(np.float32) for k, v in out.items()}
    out["valid"] = valid
    return out


def classify(
    ind: dict[str, np.ndarray], ndsm: np.ndarray, conf: dict[str, Any] | None = None
) -> np.ndarray:
    """Class per pixel (uint8, 0 = nodata) from the indices and the nDSM (m).

    Rules, later ones overriding earlier ones:
    ground non-vegetation -> road/bare; nDSM >= low_min_m -> low building; >= tall_min_m -> tall
    building; vegetation (d1450 and NDII above their minima) -> tree if nDSM >= tree_min_m else
    grass; dark (brightness < shadow_max_brightness) and not elevated -> shadow/unknown; dark,
    low, water-shaped (NDWI) and not elevated -> water. No nDSM -> shadow/unknown.
    """
    c = {**DEFAULTS, **(conf or {})}
    b, d, ndii, ndwi = ind["brightness"], ind["d1450"], ind["ndii"], ind["ndwi"]
    h = np.asarray(ndsm, np.float32)
    known = np.isfinite(h)
    hz = np.where(known, h, 0.0)
    out = np.full(h.shape, ROAD_BARE, np.uint8)
    out[hz >= c["low_min_m"]] = LOW_BUILDING
    out[hz >= c["tall_min_m"]] = TALL_BUILDING
    veg = (d >= c["veg_min_d1450"]) & (ndii >= c["veg_min_ndii"])
    out[veg & (hz >= c["tree_min_m"])] = TREE
    out[veg & (hz < c["tree_min_m"])] = GRASS
    ground = hz < c["low_min_m"]
    dark = b < c["shadow_max_brightness"]
    out[dark & ground] = SHADOW
    out[~known] = SHADOW
    water = (b < c["water_max_brightness"]) & (ndwi >= c["water_min_ndwi"]) & ground & known
    out[water] = WATER
    out[~ind["valid"]] = NODATA
    return out


def confusion(pred: np.ndarray, truth: np.ndarray, n: int = 8) -> np.ndarray:
    """Confusion matrix (truth rows, predicted columns) over pixels where both are > 0."""
    m = (pred > 0) & (truth > 0)
    return np.bincount(truth[m].astype(np.int64) * n + pred[m], minlength=n * n).reshape(n, n)


def accuracy(pred: np.ndarray, truth: np.ndarray) -> dict[str, Any]:
    """Overall accuracy and per-class recall / precision / F1 (None when undefined); truth in seg classes."""
    cm = confusion(pred, truth)
    total = cm.sum()
    out: dict[str, Any] = {
        "pixels": int(total),
        "overall": float(np.trace(cm) / total) if total else 0.0,
    }
    per = {}
    for k, info in CLASSES.items():
        tp, t, p = cm[k, k], cm[k].sum(), cm[:, k].sum()
        rec = float(tp / t) if t else None
        prec = float(tp / p) if p else None
        f1 = (
            2 * rec * prec / (rec + prec)
            if rec is not None and prec is not None and rec + prec
            else None
        )
        per[info["name"]] = {"truth_pixels": int(t), "recall": rec, "precision": prec, "f1": f1}
    out["classes"] = per
    out["confusion"] = cm.tolist()
    return out


def colormap() -> dict[int, tuple[int, int, int, int]]:
    cmap = {i: (0, 0, 0, 0) for i in range(256)}
    for k, info in CLASSES.items():
        cmap[k] = (*info["color"], 255)
    return cmap


def write_classes_query(
    path: str | os.PathLike, seg: np.ndarray, gcps: list | None = None, crs_wkt: str | None = None
) -> None:
    """Segmentation in query geometry: uint8, nodata 0, colour table, GCPs to the map."""
    from georeg.products.elevation_sampling import open_query_raster

    with warnings.catch_warnings():
        warnings.simplefilter("ignore", rasterio.errors.NotGeoreferencedWarning)
        with atomic_path(path) as tmp:
            with open_query_raster(
                tmp, seg.shape[1], seg.shape[0], 1, "uint8", NODATA, ["class"], gcps, crs_wkt
            ) as dst:
                dst.write(seg, 1)
                dst.write_colormap(1, colormap())
                dst.update_tags(**class_tags())


def class_tags() -> dict[str, str]:
    return {f"CLASS_{k}": info["label"] for k, info in CLASSES.items()} | {"CLASS_0": "nodata"}


def write_classes_geo(
    path: str | os.PathLike, seg_geo: np.ndarray, crs_wkt: str, transform
) -> None:
    """Segmentation on the product grid: COG, uint8, nodata 0, colour table."""
    import rasterio.shutil
    from rasterio.crs import CRS
    from rasterio.io import MemoryFile

    profile = {
        "driver": "GTiff",
        "width": seg_geo.shape[1],
        "height": seg_geo.shape[0],
        "count": 1,
        "dtype": "uint8",
        "crs": CRS.from_wkt(crs_wkt),
        "transform": transform,
        "nodata": NODATA,
        "tiled": True,
        "blockxsize": 256,
        "blockysize": 256,
    }
    with MemoryFile() as mem, mem.open(**profile) as ds:
        ds.write(seg_geo, 1)
        ds.write_colormap(1, colormap())
        ds.set_band_description(1, "class")
        ds.update_tags(**class_tags())
        with atomic_path(path) as tmp:
            rasterio.shutil.copy(
                ds, tmp, driver="COG", compress="DEFLATE", overview_resampling="nearest"
            )


def pixel_areas(x: np.ndarray, y: np.ndarray, unit_m: float = 1.0) -> np.ndarray:
    """Ground area (m2) of each query pixel from the geolocation (|Jacobian| of (col,row)->(x,y))."""
    xr, yr = x - np.nanmean(x), y - np.nanmean(y)
    dxr, dxc = np.gradient(xr)
    dyr, dyc = np.gradient(yr)
    a = np.abs(dxc * dyr - dxr * dyc) * unit_m**2
    return np.where(np.isfinite(a), a, np.nanmedian(a) if np.isfinite(a).any() else 0.0)


def class_areas(seg: np.ndarray, areas: np.ndarray) -> list[dict[str, Any]]:
    """Rows class, name, pixels, area_m2, fraction (of the classified, non-nodata pixels)."""
    valid = seg > 0
    n = int(valid.sum())
    counts = np.bincount(seg.ravel(), minlength=8)
    area = np.bincount(seg.ravel(), weights=areas.ravel(), minlength=8)
    return [
        {
            "class": k,
            "name": info["name"],
            "pixels": int(counts[k]),
            "area_m2": round(float(area[k]), 2),
            "fraction": round(counts[k] / n, 6) if n else 0.0,
        }
        for k, info in CLASSES.items()
    ]


def write_class_areas(path: str | os.PathLike, rows: list[dict[str, Any]]) -> None:
    with atomic_path(path) as tmp, open(tmp, "w", newline="") as fh:
        w = csv.DictWriter(fh, fieldnames=["class", "name", "pixels", "area_m2", "fraction"])
        w.writeheader()
        w.writerows(rows)


def write_legend(path: str | os.PathLike, rows: list[dict[str, Any]] | None = None) -> None:
    """A PNG legend: colour swatch, class label and (when given) area per class."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.patches import Patch

    by = {r["class"]: r for r in rows or []}
    handles = []
    for k, info in CLASSES.items():
        label = f"{k} {info['label']}"
        if k in by:
            label += f"  ({by[k]['area_m2']:.0f} m², {100 * by[k]['fraction']:.1f}%)"
        handles.append(Patch(facecolor=np.array(info["color"]) / 255, edgecolor="k", label=label))
    fig = plt.figure(figsize=(4.8, 2.6), dpi=100)
    fig.legend(handles=handles, loc="center", frameon=False, title="spectral-elevation classes")
    with atomic_path(path) as tmp:
        fig.savefig(tmp, format="png")
    plt.close(fig)
