"""A map level near the query's GSD, for queries much coarser than the map (issue 34 item 5).

A 30 m SWIR query on a 3.6 m orthophoto is ~8x coarser than the map's features: resized to the
feature GSD it becomes 64x as many pixels of interpolated blur (SIFT on 69 Mpx for a 1000 px
EnMAP scene) whose few coarse keypoints meet a map index of fine-scale ones. Instead the map is
read once more, averaged down to a level near the query's own GSD, and its features there are
the map the search sees; the query keeps (about) its own pixels. The homography is in map
coordinates whatever the level, so the geolocation, the verifier and the refinement stage (at
the orthophoto's full resolution) follow unchanged.
"""

from __future__ import annotations

import logging
import math
import time
from collections.abc import Callable
from typing import Any

import numpy as np

from georeg.index.features import detect_and_describe

log = logging.getLogger(__name__)

Bounds = tuple[float, float, float, float]
#: ``read_level(bounds, gsd)`` -> (gray uint8, 0 = nodata; 3 x 3 affine: level pixel centre ->
#: map x, y) of the orthophoto over ``bounds`` averaged to pixels of ``gsd`` map units, or None
LevelReader = Callable[[Bounds, float], "tuple[np.ndarray, np.ndarray] | None"]

#: the dense sources and checks (CFOG null scan, small-query windows, orthophoto check) read the
#: orthophoto this many times finer than the level: they correlate a small query enlarged to
#: ~96-400 px (the 63 px Sentinel-2 norcia query: found with windows at 2x, missed at 1x)
WINDOW_FINER = 2.0

DEFAULTS: dict[str, Any] = {
    "min_ratio": 3.0,  # query GSD / map feature GSD from which the search uses a map level
    "max_mpx": 64.0,  # the level's largest size; a larger map needs a location prior
}


def level_gsd(gsd: float | None, feature_gsd: float, conf: dict[str, Any] | None) -> float | None:
    """The level's pixel size (map units): the query's own GSD when it is at least
    ``min_ratio`` x the map's feature GSD; None (search the index) otherwise or when the
    query's GSD is unknown."""
    c = {**DEFAULTS, **(conf or {})}
    if not gsd or not c.get("min_ratio") or gsd / feature_gsd < float(c["min_ratio"]):
        return None
    return float(gsd)


def level_features(
    read_level: LevelReader, bounds: Bounds, gsd: float, features_conf: dict[str, Any] | None,
    max_mpx: float,
) -> tuple[dict[str, np.ndarray] | None, dict[str, Any]]:  # fmt: skip
    """SIFT features of the orthophoto over ``bounds`` at pixels of ``gsd``: xy (map), desc,
    angle (deg), scale (keypoint diameter, map units); None when the level would exceed
    ``max_mpx``, the map cannot be read or holds no features there. Returns (features, record)."""
    t0 = time.perf_counter()
    w, h = (bounds[2] - bounds[0]) / gsd, (bounds[3] - bounds[1]) / gsd
    rec: dict[str, Any] = {"gsd": gsd, "width": math.ceil(w), "height": math.ceil(h)}
    if w * h / 1e6 > max_mpx:
        rec["reason"] = (f"the map at {gsd:g} map units is {w * h / 1e6:.0f} Mpx > "
                         f"register.level.max_mpx {max_mpx:g}: give the query a location prior")  # fmt: skip
        return None, rec
    got = read_level(bounds, gsd)
    if got is None:
        rec["reason"] = "the orthophoto could not be read at the level"
        return None, rec
    gray, A = got
    f = detect_and_describe(gray, gray > 0, features_conf or {})
    if len(f) == 0:  # a map a few query pixels wide, or featureless: the index searches instead
        rec["reason"] = f"no features in the map at {gsd:g} map units ({gray.shape[1]} x {gray.shape[0]} px)"
        return None, rec
    px = f.xy.astype(np.float64)
    xy = px @ A[:2, :2].T + A[:2, 2]
    unit = math.sqrt(abs(np.linalg.det(A[:2, :2])))
    rec.update(width=int(gray.shape[1]), height=int(gray.shape[0]), features=len(f),
               seconds=round(time.perf_counter() - t0, 3))  # fmt: skip
    log.info("map level at %.3g map units: %d x %d px, %d features (%.1f s)", gsd,
             gray.shape[1], gray.shape[0], len(f), rec["seconds"])  # fmt: skip
    feats = {"xy": xy, "desc": f.desc, "angle": f.angle.astype(np.float64),
             "scale": f.scale.astype(np.float64) * unit}  # fmt: skip
    return feats, rec


def read_ortho_level(ortho: str) -> LevelReader:
    """The orthophoto mosaic (VRT or GeoTIFF) as a ``LevelReader``: one averaged (decimated)
    read; GDAL streams the source, memory is the level's (``max_mpx``)."""
    import rasterio
    from rasterio.enums import Resampling
    from rasterio.errors import WindowError
    from rasterio.windows import Window, from_bounds

    from georeg.index.features import rgb_to_gray

    def read(b: Bounds, gsd: float) -> tuple[np.ndarray, np.ndarray] | None:
        with rasterio.open(ortho) as ds:
            win = from_bounds(*b, ds.transform).round_offsets().round_lengths()
            try:
                win = win.intersection(Window(0, 0, ds.width, ds.height))
            except WindowError:  # the bounds miss the orthophoto
                return None
            f = gsd / abs(ds.transform.a)
            ow, oh = max(1, round(win.width / f)), max(1, round(win.height / f))
            bands = min(ds.count, 3)
            data = ds.read(list(range(1, bands + 1)), window=win, out_shape=(bands, oh, ow),
                           resampling=Resampling.average)  # fmt: skip
            m = ds.read_masks(1, window=win, out_shape=(oh, ow), resampling=Resampling.nearest)
            g = rgb_to_gray(data if bands == 3 else data[0])
            gray = np.where(m > 0, np.clip(g, 1, 255), 0).astype(np.uint8)
            tr = ds.window_transform(win)
        sx, sy = tr.a * win.width / ow, tr.e * win.height / oh
        A = np.array([[sx, 0, tr.c + 0.5 * sx], [0, sy, tr.f + 0.5 * sy], [0, 0, 1.0]])
        return gray, A

    return read


def window_reader(read_level: LevelReader, gsd: float) -> Callable[[Bounds], Any]:
    """A ``LevelReader`` at ``gsd`` as the sources' orthophoto window reader (``MapView``):
    bounds -> (float gray, NaN = nodata; 3 x 3 level pixel centre -> map x, y) or None."""

    def read(b: Bounds) -> tuple[np.ndarray, np.ndarray] | None:
        got = read_level(b, gsd)
        if got is None:
            return None
        gray, A = got
        return np.where(gray > 0, gray.astype(np.float32), np.nan), A

    return read
