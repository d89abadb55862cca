"""Orthophotos as they come -> the map's 8-bit RGB: which bands are visible, and one stretch.

An orthophoto may be panchromatic (1 band), RGB, RGB + alpha, RGB + NIR (or NIR first), 8 or 16
bit or float. The map tiles are always 3-band uint8 RGB with a validity mask, so every later stage
(features, overview, figures, frame rendering, point colours) reads one format:

* **Bands** (``visible_bands``): alpha bands are never chosen (they become the mask). One band
  left: panchromatic, replicated to R = G = B. Else the bands whose colour interpretation is red,
  green, blue; else the bands whose description names them (``red``/``green``/``blue``, Sentinel-2
  ``B04``/``B03``/``B02``) or gives a wavelength (the band nearest 650 / 550 / 470 nm, within
  400-700 nm); else the first three bands.
* **Stretch** (``map_stretch``): 8-bit sources pass unchanged. Others get one linear stretch for
  the whole map and all three bands (the colour balance is kept, tiles have no seams): the 0.5
  and 99.5 percentiles of the valid pixels of decimated reads (<= 1024 px a side) of every
  orthophoto map to 1 and 255.
"""

from __future__ import annotations

import math
import re
from collections.abc import Sequence
from typing import Any

import numpy as np
from rasterio.enums import ColorInterp

from georeg.io.errors import InputError
from georeg.io.raster import open_raster, read, read_masks

_NAMES = {
    "red": (r"\bred\b|\bb0?4\b|\br\b", 650.0),
    "green": (r"\bgreen\b|\bb0?3\b|\bg\b", 550.0),
    "blue": (r"\bblue\b|\bb0?2\b|\bb\b", 470.0),
}
_WAVELENGTH = re.compile(r"([0-9]+(?:\.[0-9]+)?)\s*(nm|um|µm|micrometers?|nanometers?)", re.I)
SAMPLE_PX = 1024


def _wavelength_nm(desc: str | None) -> float | None:
    m = _WAVELENGTH.search(desc or "")
    if not m:
        return None
    v = float(m.group(1))
    return v if m.group(2).lower().startswith("n") else v * 1000.0


def visible_bands(ds: Any) -> tuple[list[int], str]:
    """1-based band indexes giving R, G, B (one index for a panchromatic image) and how chosen."""
    interp = list(ds.colorinterp)
    candidates = [i + 1 for i, c in enumerate(interp) if c != ColorInterp.alpha]
    if not candidates:
        raise InputError(ds.name, "has only alpha bands", "an orthophoto needs an image band")
    if len(candidates) < 3:
        how = "one band: panchromatic" if len(candidates) == 1 else "fewer than 3 bands: band 1 as panchromatic"
        return [candidates[0]], how
    by_interp = {c: i + 1 for i, c in enumerate(interp)}
    if all(c in by_interp for c in (ColorInterp.red, ColorInterp.green, ColorInterp.blue)):
        rgb = [by_interp[ColorInterp.red], by_interp[ColorInterp.green], by_interp[ColorInterp.blue]]
        return rgb, "colour interpretation (red, green, blue)"
    descs = list(ds.descriptions or [None] * ds.count)
    named: dict[str, int] = {}
    for colour, (pattern, _) in _NAMES.items():
        hits = [b for b in candidates if descs[b - 1] and re.search(pattern, descs[b - 1], re.I)]
        if len(hits) == 1:
            named[colour] = hits[0]
    if len(named) == 3:
        return [named["red"], named["green"], named["blue"]], "band descriptions (names)"
    wl = {b: _wavelength_nm(descs[b - 1]) for b in candidates}
    vis = {b: w for b, w in wl.items() if w is not None and 400.0 <= w <= 700.0}
    if len(vis) >= 3:
        pick = [min(vis, key=lambda b, t=target: abs(vis[b] - t)) for _, target in _NAMES.values()]
        if len(set(pick)) == 3:
            return pick, "band descriptions (wavelengths nearest 650/550/470 nm)"
    return candidates[:3], "first three bands (no colour interpretation or band names)"


def map_stretch(paths: Sequence[str], bands: Sequence[int]) -> list[float] | None:
    """One (lo, hi) for the whole map from decimated reads; None when the sources are 8-bit."""
    samples = []
    for path in paths:
        with open_raster(path) as ds:
            if ds.dtypes[0] == "uint8":
                return None
            f = max(1, math.ceil(max(ds.width, ds.height) / SAMPLE_PX))
            shape = (max(1, ds.height // f), max(1, ds.width // f))
            arr = read(ds, out_shape=(len(bands), *shape), path=path, indexes=list(bands))
            valid = (read_masks(ds, out_shape=shape, path=path, indexes=list(bands)) > 0) & np.isfinite(arr).all(0)
            samples.append(arr[:, valid].astype(np.float64).ravel())
    vals = np.concatenate(samples) if samples else np.empty(0)
    if vals.size == 0:
        raise InputError(paths[0], "no valid pixels in any orthophoto", "check nodata/masks")
    lo, hi = np.percentile(vals, [0.5, 99.5])
    if not hi > lo:
        hi = lo + 1.0
    return [float(lo), float(hi)]


def to_rgb8(data: np.ndarray, stretch: Sequence[float] | None) -> np.ndarray:
    """(bands, rows, cols) of the visible bands -> (3, rows, cols) uint8 (pan replicated)."""
    if stretch is None:
        out = data.astype(np.uint8, copy=False)
    else:
        lo, hi = stretch
        scaled = (data.astype(np.float32) - lo) * (254.0 / (hi - lo)) + 1.0
        out = np.clip(np.nan_to_num(scaled, nan=0.0) + 0.5, 0, 255).astype(np.uint8)
    return np.repeat(out, 3, axis=0) if out.shape[0] == 1 else out
