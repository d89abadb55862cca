"""SIFT features of the map (per tile) and of the query: one function so both are comparable.

Conventions (also in docs/INDEX_FORMAT.md):

* Gray image: an RGB orthophoto becomes gray by ITU-R BT.601 luminance
  (0.299 R + 0.587 G + 0.114 B, OpenCV ``COLOR_RGB2GRAY``). Luminance keeps the structure that
  survives in a broadband SWIR band best among cheap choices (edges of roofs, roads, shadows),
  and it is what OpenCV and most SIFT pipelines use, so the descriptor statistics are standard.
* Pixel coordinates: ``Features.xy`` is OpenCV's keypoint ``pt``: (col, row) with the centre of
  pixel (0, 0) at (0, 0). In GDAL/rasterio corner convention that point is (col + 0.5, row + 0.5),
  so the map coordinate is ``transform * (col + 0.5, row + 0.5)``.
* Descriptors: float32, every row L2-normalised (SIFT), or RootSIFT (L1-normalise, element-wise
  square root: the rows are then L2-unit too, and Euclidean distance between RootSIFT rows is the
  Hellinger kernel distance of SIFT histograms).
* Stored descriptors (per tile and in the index) are quantised to uint8 as
  ``round(desc * DESC_SCALE)`` saturated to 255; ``dequantize`` inverts it. With unit rows a
  component above 255 / 512 ~ 0.5 is rare (SIFT clips components at 0.2 before renormalising);
  it is exactly OpenCV's own uint8 SIFT encoding for plain SIFT.
"""

from __future__ import annotations

import hashlib
import json
import logging
import math
import shutil
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from georeg.io.errors import ConfigError, InputError

log = logging.getLogger(__name__)

DESC_DIM = 128
DESC_SCALE = 512.0  # uint8 code = round(desc * DESC_SCALE), saturated
FEATURE_ARRAYS = ("xy", "z", "ndsm", "scale", "angle", "response", "desc")

DEFAULT_CONF: dict[str, Any] = {
    "gsd_m": None,
    "sift": {
        "nfeatures": 0,
        "n_octave_layers": 3,
        "contrast_threshold": 0.04,
        "edge_threshold": 10.0,
        "sigma": 1.6,
    },
    "rootsift": True,
    "upright": False,
    "max_features_per_mpx": 8000,
}


@dataclass
class Features:
    """Keypoints and descriptors of one image, in that image's pixel coordinates.

    xy: (N, 2) float32 (col, row), pixel-centre convention (centre of pixel (0, 0) is (0, 0)).
    scale: (N,) float32 keypoint diameter in pixels (OpenCV ``KeyPoint.size``).
    angle: (N,) float32 orientation in degrees [0, 360) (OpenCV convention); 0 when upright.
    response: (N,) float32 detector response (DoG contrast).
    desc: (N, 128) float32 unit-norm SIFT or RootSIFT descriptors.
    """

    xy: np.ndarray
    scale: np.ndarray
    angle: np.ndarray
    response: np.ndarray
    desc: np.ndarray

    def __len__(self) -> int:
        return int(self.xy.shape[0])

    def subset(self, keep: np.ndarray) -> Features:
        """The features selected by a boolean mask or an index array."""
        return Features(
            self.xy[keep], self.scale[keep], self.angle[keep], self.response[keep], self.desc[keep]
        )

    @staticmethod
    def empty() -> Features:
        z = np.zeros(0, np.float32)
        return Features(
            np.zeros((0, 2), np.float32), z, z.copy(), z.copy(), np.zeros((0, DESC_DIM), np.float32)
        )


def merged_conf(conf: dict | None) -> dict[str, Any]:
    """The features config with defaults filled in (for use outside Snakemake)."""
    out = json.loads(json.dumps(DEFAULT_CONF))
    for key, val in (conf or {}).items():
        if key == "sift" and isinstance(val, dict):
            out["sift"].update(val)
        else:
            out[key] = val
    return out


def conf_hash(conf: dict | None) -> str:
    """A short stable hash of the features config: map and query must agree on it."""
    text = json.dumps(merged_conf(conf), sort_keys=True)
    return hashlib.sha256(text.encode()).hexdigest()[:16]


def rgb_to_gray(rgb: np.ndarray) -> np.ndarray:
    """Gray image used for features from an RGB(A) image, bands last or first (rasterio order).

    BT.601 luminance, uint8 output for uint8 input (float32 otherwise). A single band passes
    through.
    """
    a = np.asarray(rgb)
    if a.ndim == 2:
        return a
    if a.ndim != 3:
        raise ValueError(f"expected an (H, W, C) or (C, H, W) image, got shape {a.shape}")
    if a.shape[0] in (1, 3, 4) and a.shape[-1] not in (1, 3, 4):
        a = np.moveaxis(a, 0, -1)
    if a.shape[-1] == 1:
        return a[..., 0]
    a = np.ascontiguousarray(a[..., :3])
    if a.dtype == np.uint8:
        return cv2.cvtColor(a, cv2.COLOR_RGB2GRAY)
    a = a.astype(np.float32, copy=False)
    return (0.299 * a[..., 0] + 0.587 * a[..., 1] + 0.114 * a[..., 2]).astype(np.float32)


def to_uint8(gray: np.ndarray, mask: np.ndarray | None = None) -> np.ndarray:
    """OpenCV SIFT needs 8-bit input: uint8 passes; anything else is stretched linearly so that
    the 0.5 and 99.5 percentiles of the valid (mask, finite) pixels map to 0 and 255."""
    if gray.dtype == np.uint8:
        return gray
    g = gray.astype(np.float32, copy=False)
    valid = np.isfinite(g)
    if mask is not None:
        valid &= mask.astype(bool)
    if not valid.any():
        return np.zeros(g.shape, np.uint8)
    vals = g[valid]
    if vals.size > 1_000_000:  # bounded cost: a deterministic stride sample is plenty
        vals = vals[:: vals.size // 1_000_000]
    lo, hi = np.percentile(vals, [0.5, 99.5])
    scale = 255.0 / (hi - lo) if hi > lo else 0.0
    out = np.nan_to_num((g - lo) * scale, nan=0.0, posinf=255.0, neginf=0.0)
    return np.clip(out + 0.5, 0, 255).astype(np.uint8)


def resample_factor(native_gsd: float, gsd_m: float | None) -> float:
    """Size factor (new / old pixel count along an axis) that brings ``native_gsd`` to ``gsd_m``."""
    if gsd_m is None or native_gsd <= 0:
        return 1.0
    f = float(native_gsd) / float(gsd_m)
    return 1.0 if abs(f - 1.0) < 1e-6 else f


def resample(
    img: np.ndarray, factor: float, mask: np.ndarray | None = None
) -> tuple[np.ndarray, np.ndarray | None, tuple[float, float]]:
    """Resample an image (and its mask) by ``factor`` (INTER_AREA down, INTER_LINEAR up).

    Returns the image, the mask and (sx, sy): the size of a new pixel in old pixels, so that a
    pixel-centre coordinate u in the new image is ``(u + 0.5) * s - 0.5`` in the old one.
    """
    if factor == 1.0:
        return img, mask, (1.0, 1.0)
    h, w = img.shape[:2]
    nw, nh = max(1, round(w * factor)), max(1, round(h * factor))
    interp = cv2.INTER_AREA if factor < 1 else cv2.INTER_LINEAR
    out = cv2.resize(img, (nw, nh), interpolation=interp)
    m = None
    if mask is not None:
        m = cv2.resize(mask.astype(np.uint8), (nw, nh), interpolation=cv2.INTER_NEAREST) > 0
    return out, m, (w / nw, h / nh)


def _sift(conf: dict, n_pixels: int) -> cv2.SIFT:
    s = conf["sift"]
    nfeat = int(s.get("nfeatures") or 0)
    cap = conf.get("max_features_per_mpx")
    if cap:
        by_area = max(1, int(math.ceil(float(cap) * n_pixels / 1e6)))
        nfeat = by_area if nfeat <= 0 else min(nfeat, by_area)
    try:
        return cv2.SIFT_create(
            nfeatures=nfeat,
            nOctaveLayers=int(s["n_octave_layers"]),
            contrastThreshold=float(s["contrast_threshold"]),
            edgeThreshold=float(s["edge_threshold"]),
            sigma=float(s["sigma"]),
            # index-aligned 2x upscale of the first octave: without it OpenCV's keypoints are
            # biased by +0.25 px in x and y (measured: mean +0.25, with it +0.00 +- 0.03 px)
            enable_precise_upscale=True,
        )
    except cv2.error as exc:  # pragma: no cover - bad values are caught by the schema first
        raise ConfigError(f"features.sift: OpenCV rejected the SIFT settings: {exc}") from exc


def normalise_descriptors(desc: np.ndarray, rootsift: bool) -> np.ndarray:
    """L2-normalised SIFT, or RootSIFT (L1-normalise then sqrt), float32, in place when possible."""
    d = np.asarray(desc, dtype=np.float32)
    if d.shape[0] == 0:
        return d.reshape(0, DESC_DIM)
    if rootsift:
        d /= np.maximum(d.sum(axis=1, keepdims=True), 1e-12)
        np.sqrt(d, out=d)
    else:
        d /= np.maximum(np.linalg.norm(d, axis=1, keepdims=True), 1e-12)
    return d


def quantize_desc(desc: np.ndarray) -> np.ndarray:
    """Unit-norm float descriptors -> uint8 codes (``round(desc * DESC_SCALE)``, saturated)."""
    return np.clip(np.rint(np.asarray(desc, np.float32) * DESC_SCALE), 0, 255).astype(np.uint8)


def dequantize(desc: np.ndarray) -> np.ndarray:
    """uint8 codes -> float32 descriptors in the same space as ``detect_and_describe`` output.

    Float input is returned as float32 unchanged.
    """
    d = np.asarray(desc)
    if d.dtype == np.uint8:
        return d.astype(np.float32) * np.float32(1.0 / DESC_SCALE)
    return d.astype(np.float32, copy=False)


def detect_and_describe(gray: np.ndarray, mask: np.ndarray | None, conf: dict) -> Features:
    """SIFT keypoints and descriptors of a gray image (the same function for map and query).

    gray: (H, W) uint8 or float (float is stretched to uint8, see ``to_uint8``).
    mask: (H, W) bool/uint8, nonzero = valid, or None. Keypoints are detected only where valid;
      the mask is eroded by 2 px so that the nodata border does not create corners.
    conf: the ``features:`` config section. ``gsd_m`` is NOT applied here: the caller resamples
      (``resample``) so that the image is at the feature GSD; ``max_features_per_mpx`` caps the
      count per megapixel of this image (the strongest responses are kept).
    """
    conf = merged_conf(conf)
    if gray.ndim != 2:
        raise ValueError(f"detect_and_describe needs a 2-D gray image, got shape {gray.shape}")
    img = to_uint8(gray, mask)
    m8 = None
    n_valid = img.size
    if mask is not None:
        m = np.asarray(mask).astype(bool)
        n_valid = int(m.sum())
        if n_valid == 0:
            return Features.empty()
        if n_valid < m.size:
            m8 = cv2.erode(m.astype(np.uint8) * 255, np.ones((5, 5), np.uint8))
    sift = _sift(conf, n_valid)
    if conf.get("upright"):
        kps = sift.detect(img, m8)
        # SIFT duplicates a keypoint per dominant orientation: upright keeps one of them.
        seen: set[tuple[float, float, float, int]] = set()
        uniq = []
        for kp in kps:
            key = (kp.pt[0], kp.pt[1], kp.size, kp.octave)
            if key not in seen:
                seen.add(key)
                kp.angle = 0.0
                uniq.append(kp)
        kps, desc = sift.compute(img, uniq)
    else:
        kps, desc = sift.detectAndCompute(img, m8)
    if not kps or desc is None:
        return Features.empty()
    n = len(kps)
    xy = np.array([k.pt for k in kps], np.float32).reshape(n, 2)
    size = np.array([k.size for k in kps], np.float32)
    angle = np.array([k.angle for k in kps], np.float32)
    resp = np.array([k.response for k in kps], np.float32)
    if conf.get("upright"):
        angle[:] = 0.0
    desc = normalise_descriptors(desc, bool(conf.get("rootsift")))
    return Features(xy, size, angle, resp, desc)


# --------------------------------------------------------------------------------------------
# Per-tile extraction with map coordinates and elevations


def pixel_to_map(transform: Any, col: np.ndarray, row: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Pixel-centre coordinates (OpenCV convention) -> map x, y through an affine geotransform."""
    a, b, c, d, e, f = (float(v) for v in tuple(transform)[:6])
    u = np.asarray(col, np.float64) + 0.5
    v = np.asarray(row, np.float64) + 0.5
    return a * u + b * v + c, d * u + e * v + f


def map_to_pixel(transform: Any, x: np.ndarray, y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Map x, y -> pixel-centre coordinates (col, row) (inverse of ``pixel_to_map``)."""
    a, b, c, d, e, f = (float(v) for v in tuple(transform)[:6])
    det = a * e - b * d
    if det == 0:
        raise ValueError("singular geotransform")
    dx = np.asarray(x, np.float64) - c
    dy = np.asarray(y, np.float64) - f
    u = (e * dx - b * dy) / det
    v = (-d * dx + a * dy) / det
    return u - 0.5, v - 0.5


def sample_bilinear(
    band: np.ndarray, col: np.ndarray, row: np.ndarray, nodata: float | None = None
) -> np.ndarray:
    """Bilinear sample of a raster at pixel-centre coordinates, float32, NaN outside.

    Where a bilinear neighbour is nodata/NaN the nearest valid-or-not pixel is used instead
    (so a keypoint next to a LiDAR hole still gets the value of its own pixel when that is valid).
    """
    a = np.asarray(band, np.float32)
    h, w = a.shape
    col = np.asarray(col, np.float64)
    row = np.asarray(row, np.float64)
    out = np.full(col.shape, np.nan, np.float32)
    inside = (col > -0.5) & (row > -0.5) & (col < w - 0.5) & (row < h - 0.5)
    if not inside.any():
        return out
    c = np.clip(col[inside], 0, w - 1)
    r = np.clip(row[inside], 0, h - 1)
    c0 = np.minimum(np.floor(c).astype(np.int64), max(w - 2, 0))
    r0 = np.minimum(np.floor(r).astype(np.int64), max(h - 2, 0))
    c1 = np.minimum(c0 + 1, w - 1)
    r1 = np.minimum(r0 + 1, h - 1)
    fc = (c - c0).astype(np.float32)
    fr = (r - r0).astype(np.float32)
    v00, v01, v10, v11 = a[r0, c0], a[r0, c1], a[r1, c0], a[r1, c1]
    val = (v00 * (1 - fc) + v01 * fc) * (1 - fr) + (v10 * (1 - fc) + v11 * fc) * fr
    bad = ~np.isfinite(val)
    if nodata is not None and not (isinstance(nodata, float) and math.isnan(nodata)):
        bad |= (v00 == nodata) | (v01 == nodata) | (v10 == nodata) | (v11 == nodata)
    if bad.any():
        rn = np.clip(np.rint(r[bad]).astype(np.int64), 0, h - 1)
        cn = np.clip(np.rint(c[bad]).astype(np.int64), 0, w - 1)
        near = a[rn, cn]
        if nodata is not None:
            near = np.where(near == nodata, np.nan, near)
        val[bad] = near
    out[inside] = val
    return out


@dataclass
class TileFeatures:
    """Features of one map tile in map coordinates (what ``save_tile_features`` writes)."""

    xy: np.ndarray  # (N, 2) float64 map x, y (CRS units)
    z: np.ndarray  # (N,) float32 DSM elevation (NaN when unknown)
    ndsm: np.ndarray  # (N,) float32 height above ground (NaN when unknown)
    scale: np.ndarray  # (N,) float32 keypoint diameter in map units (CRS units)
    angle: np.ndarray  # (N,) float32 degrees, OpenCV convention in the tile's pixel grid
    response: np.ndarray  # (N,) float32
    desc: np.ndarray  # (N, 128) uint8, quantised (see DESC_SCALE)

    def __len__(self) -> int:
        return int(self.xy.shape[0])


def _read_band(path: str | Path) -> tuple[np.ndarray, Any, float | None]:
    import rasterio

    try:
        with rasterio.open(path) as ds:
            return ds.read(1, out_dtype="float32"), ds.transform, ds.nodata
    except rasterio.errors.RasterioIOError as exc:
        raise InputError(path, f"cannot read raster: {exc}") from exc


def read_ortho_gray(path: str | Path) -> tuple[np.ndarray, np.ndarray | None, Any, Any]:
    """Gray image (``rgb_to_gray``), validity mask (None when all valid), transform and CRS."""
    import rasterio

    try:
        with rasterio.open(path) as ds:
            data = ds.read()
            all_valid = rasterio.enums.MaskFlags.all_valid
            has_mask = any(all_valid not in flags for flags in ds.mask_flag_enums)
            msk = ds.dataset_mask() if has_mask else None
            transform, crs = ds.transform, ds.crs
    except rasterio.errors.RasterioIOError as exc:
        raise InputError(path, f"cannot read orthophoto tile: {exc}") from exc
    gray = rgb_to_gray(data[:3] if data.shape[0] >= 3 else data[0])
    mask = None
    if msk is not None:
        m = msk > 0
        mask = None if m.all() else m
    return gray, mask, transform, crs


def tile_features(
    gray: np.ndarray,
    mask: np.ndarray | None,
    transform: Any,
    conf: dict,
    core_window: tuple[int, int, int, int] | None = None,
    dsm: tuple[np.ndarray, Any, float | None] | None = None,
    ndsm: tuple[np.ndarray, Any, float | None] | None = None,
) -> TileFeatures:
    """Features of one tile in map coordinates.

    gray/mask/transform: the tile image at native resolution and its geotransform.
    core_window: (col_off, row_off, width, height) in native tile pixels: only keypoints whose
      native pixel position (corner convention) is in [col_off, col_off + width) x
      [row_off, row_off + height) are kept, so that tiles overlapping by a margin keep each
      keypoint once (half-open: a point on a shared edge belongs to exactly one tile).
    dsm/ndsm: (array, transform, nodata) sampled bilinearly at the keypoints (NaN if absent).
    """
    conf = merged_conf(conf)
    native_gsd = math.sqrt(abs(transform.a * transform.e - transform.b * transform.d))
    factor = resample_factor(native_gsd, conf.get("gsd_m"))
    img, m, (sx, sy) = resample(gray, factor, mask)
    f = detect_and_describe(img, m, conf)
    # feature-image pixel centre -> native pixel centre coordinates
    col = (f.xy[:, 0].astype(np.float64) + 0.5) * sx - 0.5
    row = (f.xy[:, 1].astype(np.float64) + 0.5) * sy - 0.5
    if core_window is not None:
        c0, r0, w, h = (float(v) for v in core_window)
        u, v = col + 0.5, row + 0.5
        keep = (u >= c0) & (u < c0 + w) & (v >= r0) & (v < r0 + h)
        f = f.subset(keep)
        col, row = col[keep], row[keep]
    x, y = pixel_to_map(transform, col, row)
    xy = np.stack([x, y], axis=1)

    def _elev(src: tuple[np.ndarray, Any, float | None] | None) -> np.ndarray:
        if src is None:
            return np.full(len(f), np.nan, np.float32)
        band, tr, nodata = src
        cc, rr = map_to_pixel(tr, x, y)
        return sample_bilinear(band, cc, rr, nodata)

    return TileFeatures(
        xy=xy,
        z=_elev(dsm),
        ndsm=_elev(ndsm),
        scale=(f.scale * np.float32(native_gsd * math.sqrt(sx * sy))).astype(np.float32),
        angle=f.angle.astype(np.float32),
        response=f.response.astype(np.float32),
        desc=quantize_desc(f.desc),
    )


def extract_tile(
    ortho: str | Path,
    conf: dict,
    core_window: tuple[int, int, int, int] | None = None,
    dsm: str | Path | None = None,
    ndsm: str | Path | None = None,
) -> tuple[TileFeatures, dict[str, Any]]:
    """Read one tile's rasters and extract its features; returns the features and meta info."""
    gray, mask, transform, crs = read_ortho_gray(ortho)
    tf = tile_features(
        gray,
        mask,
        transform,
        conf,
        core_window,
        _read_band(dsm) if dsm else None,
        _read_band(ndsm) if ndsm else None,
    )
    native_gsd = math.sqrt(abs(transform.a * transform.e - transform.b * transform.d))
    meta = {
        "n": len(tf),
        "crs_wkt": crs.to_wkt() if crs else None,
        "transform": list(transform)[:6],
        "width": int(gray.shape[1]),
        "height": int(gray.shape[0]),
        "native_gsd": native_gsd,
        "gsd_m": merged_conf(conf).get("gsd_m") or native_gsd,
        "core_window": list(core_window) if core_window is not None else None,
        "features_conf": merged_conf(conf),
        "features_conf_hash": conf_hash(conf),
        "desc_dtype": "uint8",
        "desc_scale": DESC_SCALE,
    }
    return tf, meta


def save_tile_features(out_dir: str | Path, tf: TileFeatures, meta: dict[str, Any]) -> None:
    """Write ``<name>.npy`` for every array plus ``meta.json``, atomically as a directory."""
    from georeg.io.atomic import atomic_path

    with atomic_path(out_dir) as tmp:
        tmp.mkdir(parents=True, exist_ok=True)
        for name in FEATURE_ARRAYS:
            np.save(tmp / f"{name}.npy", np.ascontiguousarray(getattr(tf, name)))
        (tmp / "meta.json").write_text(json.dumps(meta, indent=2) + "\n")
        if Path(out_dir).exists():  # os.replace cannot replace a non-empty directory
            shutil.rmtree(out_dir)


def load_tile_features(path: str | Path, mmap: bool = True) -> tuple[TileFeatures, dict[str, Any]]:
    """Read a directory written by ``save_tile_features`` (memory-mapped by default)."""
    p = Path(path)
    try:
        meta = json.loads((p / "meta.json").read_text())
        arrs = {n: np.load(p / f"{n}.npy", mmap_mode="r" if mmap else None) for n in FEATURE_ARRAYS}
    except (OSError, ValueError) as exc:
        raise InputError(
            p, f"cannot read tile features: {exc}", "rerun rule tile_features"
        ) from exc
    return TileFeatures(**arrs), meta


def grid_tile_info(grid_path: str | Path, tile: str) -> dict[str, Any]:
    """The tile's entry of ``results/map/grid.json`` plus its core window in tile pixels.

    grid.json gives ``window`` and ``core`` as [col_off, row_off, width, height] in map-grid
    pixels; the core in tile pixels is the core shifted by the window offset.
    """
    try:
        grid = json.loads(Path(grid_path).read_text())
        t = grid["tiles"][tile]
        win, core = t["window"], t["core"]
    except (OSError, ValueError, KeyError) as exc:
        raise InputError(
            grid_path, f"no usable entry for tile {tile}: {exc}", "rerun map_grid"
        ) from exc
    local = (core[0] - win[0], core[1] - win[1], core[2], core[3])
    return {**t, "core_local": local, "crs": grid.get("crs")}


def extract_tile_from_grid(
    grid_path: str | Path,
    tile: str,
    ortho: str | Path,
    dsm: str | Path | None,
    ndsm: str | Path | None,
    conf: dict,
    out_dir: str | Path,
) -> dict[str, Any]:
    """Rule ``tile_features``: extract one grid tile (core window from grid.json) and save it."""
    info = grid_tile_info(grid_path, tile)
    tf, meta = extract_tile(ortho, conf, info["core_local"], dsm, ndsm)
    meta.update(tile=tile, grid_window=info["window"], grid_core=info["core"])
    if not meta.get("crs_wkt"):
        meta["crs_wkt"] = info.get("crs")
    save_tile_features(out_dir, tf, meta)
    log.info("tile %s: %d features kept in the core window", tile, len(tf))
    return meta
