"""Evaluation of one query against its truth: registration error, outcome, parts, segmentation.

Inputs are the registration stage's files (``registration.json``, ``geolocation.tif``) and the
query's truth raster (2 bands: the true map x, y of every query pixel, NaN where unknown). The
result, ``evaluation.json``, says how far each query pixel landed from where it really is
(median / p90 / max / RMSE, in map pixels and metres), classifies the outcome, and repeats the
error for each along-track part's own homography (over the whole query and over its own rows), so
that the gain of fusing the parts is visible. When the products stage wrote a segmentation
(``products.json``) and the query has truth labels, the segmentation accuracy is added.

Outcomes (``OUTCOMES``):

* ``success``: registered and the error statistic (``success_stat``, default the median) is at
  most ``success_error_px`` map pixels;
* ``false_accept``: registered, but wrong (error above the bound);
* ``correct_not_found``: not found, and less than ``min_inside_fraction`` of the query's truth
  pixels lie inside the map: there was nothing to find;
* ``missed``: not found although the query lies inside the map;
* ``no_truth``: no truth raster, only the status is reported.
"""

from __future__ import annotations

import json
import logging
import warnings
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from georeg.io.errors import InputError

log = logging.getLogger(__name__)

OUTCOMES = ("success", "false_accept", "correct_not_found", "missed", "no_truth")
STATS = ("median", "p90", "max", "rmse")

DEFAULT_CONF: dict[str, Any] = {
    "success_error_px": 5.0,
    "success_stat": "median",
    "min_inside_fraction": 0.5,
}


# ----------------------------------------------------------------------------- raster helpers


def read_truth(path: str | Path) -> tuple[np.ndarray, np.ndarray]:
    """True map x, y (float64, query geometry) of every query pixel; NaN where unknown."""
    import rasterio

    with warnings.catch_warnings():
        warnings.simplefilter("ignore", rasterio.errors.NotGeoreferencedWarning)
        try:
            with rasterio.open(path) as ds:
                if ds.count < 2:
                    raise InputError(path, f"truth raster has {ds.count} band(s), needs 2 (x, y)")
                tx = ds.read(1).astype(np.float64)
                ty = ds.read(2).astype(np.float64)
                nodata = ds.nodata
        except rasterio.errors.RasterioIOError as exc:
            raise InputError(path, f"cannot read the truth raster: {exc}") from exc
    if nodata is not None and np.isfinite(nodata):
        bad = (tx == nodata) | (ty == nodata)
        tx[bad] = np.nan
        ty[bad] = np.nan
    return tx, ty


def read_geolocation(path: str | Path) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """x, y, z (float64, query geometry) from ``geolocation.tif``; NaN where not located."""
    import rasterio

    with warnings.catch_warnings():
        warnings.simplefilter("ignore", rasterio.errors.NotGeoreferencedWarning)
        try:
            with rasterio.open(path) as ds:
                a = ds.read().astype(np.float64)
        except rasterio.errors.RasterioIOError as exc:
            raise InputError(path, f"cannot read the geolocation raster: {exc}") from exc
    if a.shape[0] < 2:
        raise InputError(path, "geolocation raster needs bands x, y (and z)")
    z = a[2] if a.shape[0] > 2 else np.full(a.shape[1:], np.nan)
    return a[0], a[1], z


def map_xy(H: np.ndarray, width: int, height: int) -> tuple[np.ndarray, np.ndarray]:
    """Map x, y of every query pixel centre (col, row) through H (NaN behind the horizon)."""
    from georeg.register.geolocation import map_xy as _map_xy

    return _map_xy(np.asarray(H, np.float64), width, height)


# ----------------------------------------------------------------------------- statistics


def error_field(x: np.ndarray, y: np.ndarray, tx: np.ndarray, ty: np.ndarray) -> np.ndarray:
    """Per-pixel distance (map units) between estimated and true positions.

    NaN where the truth is unknown; +inf where the truth is known but the estimate is not.
    """
    valid = np.isfinite(tx) & np.isfinite(ty)
    e = np.hypot(x - tx, y - ty)
    e = np.where(np.isfinite(e), e, np.inf)
    return np.where(valid, e, np.nan)


def error_stats(e: np.ndarray, map_px: float, m_per_unit: float = 1.0) -> dict[str, Any]:
    """median / p90 / max / RMSE of an error field (map units) in map pixels and metres.

    Pixels without truth (NaN) are ignored; pixels without an estimate (inf) count as infinite
    error (the statistics then become inf and are written as null in JSON).
    """
    v = e[~np.isnan(e)]
    out: dict[str, Any] = {"pixels": int(v.size)}
    if v.size == 0:
        return out
    with np.errstate(over="ignore", invalid="ignore"):
        units = {
            "median": float(np.median(v)),
            "p90": float(np.percentile(v, 90)),
            "max": float(v.max()),
            "rmse": float(np.sqrt(np.mean(v**2))),
        }
    out["px"] = {k: _finite(u / map_px) for k, u in units.items()}
    out["m"] = {k: _finite(u * m_per_unit) for k, u in units.items()}
    return out


def _finite(v: float) -> float | None:
    return float(v) if np.isfinite(v) else None


def inside_fraction(
    tx: np.ndarray, ty: np.ndarray, bounds: tuple[float, float, float, float] | None
) -> float | None:
    """Share of the query's truth pixels whose true position lies inside the map bounds."""
    if bounds is None:
        return None
    valid = np.isfinite(tx) & np.isfinite(ty)
    if not valid.any():
        return 0.0
    x0, y0, x1, y1 = bounds
    x, y = tx[valid], ty[valid]
    inside = (x >= x0) & (x <= x1) & (y >= y0) & (y <= y1)
    return float(inside.mean())


def classify(
    registered: bool,
    stats: dict[str, Any] | None,
    inside: float | None,
    conf: dict[str, Any],
) -> str:
    """One of ``OUTCOMES`` for a registration (see the module docstring)."""
    c = {**DEFAULT_CONF, **(conf or {})}
    if registered:
        if not stats or "px" not in stats:
            return "no_truth"
        v = stats["px"].get(str(c["success_stat"]))
        return "success" if v is not None and v <= float(c["success_error_px"]) else "false_accept"
    if inside is None:
        return "no_truth"
    return "missed" if inside >= float(c["min_inside_fraction"]) else "correct_not_found"


# ----------------------------------------------------------------------------- segmentation


def segmentation_accuracy(
    pred: np.ndarray, truth: np.ndarray, names: dict[int, str] | None = None
) -> dict[str, Any]:
    """Overall accuracy, per-class IoU / recall / precision and mean IoU of a label map.

    ``pred`` and ``truth`` are integer labels of the same shape; 0 = no data in either.
    """
    if pred.shape != truth.shape:
        raise ValueError(f"label shapes differ: {pred.shape} vs {truth.shape}")
    ok = (pred > 0) & (truth > 0)
    p = pred[ok].astype(np.int64)
    t = truth[ok].astype(np.int64)
    out: dict[str, Any] = {"pixels": int(ok.sum()), "truth_pixels": int((truth > 0).sum())}
    if p.size == 0:
        out["status"] = "no overlapping labelled pixel"
        return out
    classes = np.union1d(np.unique(p), np.unique(t))
    idx = {int(c): i for i, c in enumerate(classes)}
    k = len(classes)
    cm = np.zeros((k, k), np.int64)
    np.add.at(cm, (np.searchsorted(classes, t), np.searchsorted(classes, p)), 1)
    tp = np.diag(cm).astype(np.float64)
    per: dict[str, Any] = {}
    ious = []
    for c, i in idx.items():
        union = cm[i, :].sum() + cm[:, i].sum() - cm[i, i]
        iou = float(tp[i] / union) if union else None
        if cm[i, :].sum() > 0 and iou is not None:
            ious.append(iou)
        per[str(c)] = {
            "name": (names or {}).get(c, str(c)),
            "truth_pixels": int(cm[i, :].sum()),
            "iou": iou,
            "recall": float(tp[i] / cm[i, :].sum()) if cm[i, :].sum() else None,
            "precision": float(tp[i] / cm[:, i].sum()) if cm[:, i].sum() else None,
        }
    out.update(
        overall_accuracy=float(tp.sum() / cm.sum()),
        mean_iou=float(np.mean(ious)) if ious else None,
        classes=per,
        confusion={"labels": [int(c) for c in classes], "matrix": cm.tolist()},
    )
    return out


def read_labels(path: str | Path) -> np.ndarray:
    """Band 1 of a label raster as int64 (0 = no data, also where the raster says nodata)."""
    import rasterio

    with warnings.catch_warnings():
        warnings.simplefilter("ignore", rasterio.errors.NotGeoreferencedWarning)
        try:
            with rasterio.open(path) as ds:
                a = ds.read(1)
                nodata = ds.nodata
        except rasterio.errors.RasterioIOError as exc:
            raise InputError(path, f"cannot read the label raster: {exc}") from exc
    a = np.where(np.isfinite(a), a, 0) if a.dtype.kind == "f" else a
    out = a.astype(np.int64)
    if nodata is not None and np.isfinite(nodata):
        out[a == nodata] = 0
    return out


@dataclass
class ProductSegmentation:
    """The products stage's segmentation of one query (from its ``products.json`` manifest)."""

    path: Path  # segmentation.tif, query geometry, uint8 class codes, 0 = no data
    names: dict[int, str]
    colours: dict[int, tuple[int, int, int]]
    accuracy: dict[str, Any] | None  # the products stage's own score, when it had labels
    truth_lut: dict[int, int] | None  # truth label code -> segmentation class (demo classes)


def products_segmentation(products_json: str | Path | None) -> ProductSegmentation | None:
    """Read the segmentation entry of ``results/products/{name}/products.json``.

    None when there is no manifest, the query was not found or no segmentation was written.
    Class names come from the manifest, colours from the GeoTIFF colour table, and the mapping of
    the demo's truth labels to segmentation classes from ``georeg.products.segmentation.DEMO_TO_SEG``.
    """
    if not products_json or not Path(products_json).exists():
        return None
    try:
        m = json.loads(Path(products_json).read_text())
    except (OSError, json.JSONDecodeError) as exc:
        log.warning("cannot read %s: %s", products_json, exc)
        return None
    rel = (m.get("files") or {}).get("segmentation")
    if m.get("status") == "not_found" or not rel:
        return None
    path = Path(products_json).parent / rel
    if not path.exists():
        return None
    seg = m.get("segmentation") or {}
    names = {int(k): str(v) for k, v in (seg.get("classes") or {}).items()}
    colours: dict[int, tuple[int, int, int]] = {}
    import rasterio

    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        try:
            with rasterio.open(path) as ds:
                colours = {int(k): tuple(v[:3]) for k, v in ds.colormap(1).items()}
        except (ValueError, rasterio.errors.RasterioError):
            colours = {}
    try:
        from georeg.products.segmentation import DEMO_TO_SEG

        lut: dict[int, int] | None = dict(DEMO_TO_SEG)
    except ImportError:  # pragma: no cover - the products stage ships with it
        lut = None
    return ProductSegmentation(path, names, colours, seg.get("accuracy"), lut)


def map_truth_labels(truth: np.ndarray, lut: dict[int, int] | None) -> np.ndarray:
    """Truth labels translated to segmentation classes (unchanged when codes fall outside)."""
    if not lut:
        return truth
    codes = {int(c) for c in np.unique(truth) if c > 0}
    if not codes <= set(lut):
        return truth
    table = np.zeros(max(max(lut), int(truth.max())) + 1, np.int64)
    for k, v in lut.items():
        table[k] = v
    return table[truth]


# ----------------------------------------------------------------------------- one query


def map_bounds_units(
    grid_path: str | Path | None,
) -> tuple[tuple[float, float, float, float] | None, float, float]:
    """(map bounds, map pixel size in map units, metres per map unit) from ``grid.json``."""
    if not grid_path or not Path(grid_path).exists():
        return None, 1.0, 1.0
    from rasterio.transform import array_bounds

    from georeg.map.grid import MapGrid

    g = MapGrid.load(grid_path)
    b = array_bounds(g.height, g.width, g.transform)
    west, south, east, north = b
    px = abs(float(g.transform.a))
    try:
        from georeg.map.elevation import Grid

        mpu = float(Grid(g.crs, g.transform, g.width, g.height).metres_per_unit()[0])
    except Exception:  # noqa: BLE001 - a CRS without a linear unit: report map units
        mpu = 1.0
    return (west, south, east, north), px, mpu


def evaluate_query(
    registration: dict[str, Any],
    geolocation: str | Path | None,
    truth: str | Path | None,
    grid_path: str | Path | None = None,
    conf: dict[str, Any] | None = None,
    labels: str | Path | None = None,
    products: str | Path | None = None,
) -> dict[str, Any]:
    """The content of ``evaluation.json`` for one query (see the module docstring).

    ``products``: the products stage's ``products.json``; with ``labels`` (truth labels in query
    geometry) the segmentation is scored (and the products stage's own score copied).
    """
    c = {**DEFAULT_CONF, **(conf or {})}
    status = registration.get("status", "unknown")
    registered = status == "registered"
    out: dict[str, Any] = {
        "status": status,
        "registered": registered,
        "inliers": registration.get("inliers", 0),
        "method": (registration.get("fuse") or {}).get("method"),
        "reason": registration.get("reason"),
    }
    if not truth:
        out["outcome"] = "no_truth"
        return out
    bounds, px_units, mpu = map_bounds_units(grid_path)
    if grid_path is None or not Path(grid_path).exists():
        px_units = float(registration.get("map_px_m") or 1.0)
    tx, ty = read_truth(truth)
    h, w = tx.shape
    inside = inside_fraction(tx, ty, bounds)
    out.update(
        truth=str(truth),
        bound={"stat": c["success_stat"], "px": float(c["success_error_px"])},
        map_px=px_units,
        map_px_m=px_units * mpu,
        m_per_map_unit=mpu,
        truth_pixels=int((np.isfinite(tx) & np.isfinite(ty)).sum()),
        inside_fraction=inside,
    )
    H = registration.get("homography")
    fused_e = None
    if registered:
        if geolocation and Path(geolocation).exists():
            x, y, _ = read_geolocation(geolocation)
            if x.shape != tx.shape:
                raise InputError(
                    geolocation, f"shape {x.shape} differs from the truth's {tx.shape}"
                )
        elif H is not None:
            x, y = map_xy(np.array(H), w, h)
        else:
            raise InputError(None, "registered query without homography or geolocation")
        fused_e = error_field(x, y, tx, ty)
        out["error"] = error_stats(fused_e, px_units, mpu)
    out["outcome"] = classify(registered, out.get("error"), inside, c)
    # each part's own homography, before fusing: over the whole query and over its own rows
    parts_out = []
    for p in registration.get("parts") or []:
        entry: dict[str, Any] = {
            "part": p.get("part"),
            "rows": p.get("rows"),
            "accepted": bool(p.get("accepted")),
            "inliers": p.get("inliers", 0),
        }
        Hp = p.get("homography")
        if Hp is not None:
            px_, py_ = map_xy(np.array(Hp), w, h)
            e = error_field(px_, py_, tx, ty)
            entry["error_whole"] = error_stats(e, px_units, mpu)
            r0, r1 = p.get("rows") or (0, h)
            entry["error_own_rows"] = error_stats(e[r0:r1], px_units, mpu)
            if fused_e is not None:
                entry["fused_error_own_rows"] = error_stats(fused_e[r0:r1], px_units, mpu)
        entry["outcome"] = classify(
            bool(p.get("accepted")) and Hp is not None, entry.get("error_whole"), inside, c
        )
        parts_out.append(entry)
    out["parts"] = parts_out
    out["fusion_gain"] = _fusion_gain(out.get("error"), parts_out)
    # segmentation accuracy (optional: needs the products' segmentation and truth labels)
    seg = products_segmentation(products) if registered else None
    if seg is not None and labels:
        try:
            truth_lab = map_truth_labels(read_labels(labels), seg.truth_lut)
            pred = read_labels(seg.path)
            if pred.shape != truth_lab.shape:
                raise ValueError(f"segmentation {pred.shape} vs labels {truth_lab.shape}")
            out["segmentation"] = segmentation_accuracy(pred, truth_lab, seg.names)
            out["segmentation"]["path"] = str(seg.path)
            if seg.accuracy is not None:
                out["segmentation"]["products_accuracy"] = seg.accuracy
        except (InputError, ValueError, OSError) as exc:
            log.warning("segmentation accuracy skipped: %s", exc)
            out["segmentation"] = {"status": f"skipped: {exc}"}
    skipped = products_skipped(products) if registered else {}
    if skipped:
        out["products_skipped"] = skipped
    return out


def products_skipped(products_json: str | Path | None) -> dict[str, str]:
    """Products the products stage skipped or wrote without heights, with the reason of each."""
    if not products_json or not Path(products_json).exists():
        return {}
    try:
        return dict(json.loads(Path(products_json).read_text()).get("skipped") or {})
    except (OSError, json.JSONDecodeError) as exc:
        log.warning("cannot read %s: %s", products_json, exc)
        return {}


def _fusion_gain(
    fused: dict[str, Any] | None, parts: list[dict[str, Any]]
) -> dict[str, Any] | None:
    """Median error (px) of the best part's homography over the whole query vs the fused one."""
    if not fused or "px" not in fused:
        return None
    cands = [
        p["error_whole"]["px"]["median"]
        for p in parts
        if p.get("error_whole", {}).get("px", {}).get("median") is not None
    ]
    if not cands:
        return None
    best = min(cands)
    f = fused["px"]["median"]
    return {
        "best_part_median_px": best,
        "fused_median_px": f,
        "improvement_px": None if f is None else best - f,
    }


def run_evaluate_query(
    registration_json: str | Path,
    geolocation: str | Path | None,
    truth: str | Path | None,
    grid_path: str | Path | None,
    conf: dict[str, Any] | None,
    out_json: str | Path,
    labels: str | Path | None = None,
    products: str | Path | None = None,
) -> dict[str, Any]:
    """Rule evaluate_query: read the registration, evaluate, write ``evaluation.json``."""
    from georeg.io.atomic import write_json

    try:
        reg = json.loads(Path(registration_json).read_text())
    except (OSError, json.JSONDecodeError) as exc:
        raise InputError(registration_json, f"cannot read the registration: {exc}") from exc
    ev = evaluate_query(reg, geolocation, truth, grid_path, conf, labels, products)
    err = (ev.get("error") or {}).get("px") or {}
    log.info(
        "%s: %s, outcome %s, median error %s px",
        registration_json,
        ev["status"],
        ev["outcome"],
        "n/a" if err.get("median") is None else f"{err['median']:.2f}",
    )
    write_json(out_json, ev)
    return ev
