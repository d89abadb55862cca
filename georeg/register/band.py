"""Choose the query band (nearest wavelength, index or streamed mean), mask nodata, stretch, resample."""

from __future__ import annotations

import logging
import re
from dataclasses import dataclass
from typing import Any

import cv2
import numpy as np

from georeg.io.errors import InputError
from georeg.io.query import _UNIT_TO_NM, Cube

log = logging.getLogger(__name__)

#: the paper's band (near 1.2 um), what `band: auto` looks for first
AUTO_NM = 1200.0
_SPEC_RE = re.compile(r"^\s*([0-9]+(?:\.[0-9]+)?)\s*(nm|um|µm)\s*$", re.I)


@dataclass(frozen=True)
class BandSpec:
    """What the user asked for: a wavelength (nm), a 0-based index, or the mean of all bands."""

    kind: str  # "wavelength" | "index" | "mean" | "auto"
    value: float | int | None = None


def parse_band_spec(spec: Any) -> BandSpec:
    """Parse ``"1200nm"``, ``"1.2um"``, ``14`` or ``"mean"``."""
    if isinstance(spec, bool):
        raise InputError(None, f"band {spec!r} is not a wavelength, index or 'mean'")
    if isinstance(spec, (int, np.integer)):
        return BandSpec("index", int(spec))
    s = str(spec).strip()
    if s.lower() in ("mean", "auto"):
        return BandSpec(s.lower())
    if s.isdigit():
        return BandSpec("index", int(s))
    m = _SPEC_RE.match(s)
    if not m:
        raise InputError(
            None, f"band {spec!r} is not understood", "use e.g. '1200nm', '1.2um', 14 or 'mean'"
        )
    return BandSpec("wavelength", float(m.group(1)) * _UNIT_TO_NM[m.group(2).lower()])


def nearest_band(cube: Cube, wavelength_nm: float, tolerance_nm: float | None = None) -> int:
    """Index of the band nearest ``wavelength_nm``; an error if the cube does not cover it."""
    wl = cube.wavelengths_nm
    if wl is None:
        if cube.count == 1:
            log.warning(
                "%s has one band and no wavelengths: using it for %.0f nm", cube.path, wavelength_nm
            )
            return 0
        raise InputError(
            cube.path,
            f"cannot select {wavelength_nm:g} nm: the image has no wavelengths",
            f"{cube.describe()}; give the band as an index 0..{cube.count - 1} or 'mean'",
        )
    i = int(np.argmin(np.abs(wl - wavelength_nm)))
    if tolerance_nm is None:
        # half a band (FWHM, or half the band spacing up to 25 nm) beyond the ends is still "in"
        spacing = float(np.median(np.abs(np.diff(np.sort(wl))))) if len(wl) > 1 else 0.0
        fwhm = float(np.nanmax(cube.fwhm_nm)) if cube.fwhm_nm is not None else 0.0
        tolerance_nm = max(fwhm / 2.0, min(spacing / 2.0, 25.0), 1.0)
    if wavelength_nm < wl.min() - tolerance_nm or wavelength_nm > wl.max() + tolerance_nm:
        raise InputError(
            cube.path,
            f"wavelength {wavelength_nm:g} nm is outside the cube",
            f"the cube covers {wl.min():.1f}-{wl.max():.1f} nm in {cube.count} bands",
        )
    return i


def resolve_band(cube: Cube, bs: BandSpec) -> int | None:
    """0-based band index for a spec (None for ``mean``), from the cube's metadata only.

    ``auto``: the paper's band, nearest 1200 nm, when the cube covers it; else the band nearest
    1200 nm that the cube has (e.g. 1610 nm of a two-band SWIR image); band 0 when the cube has
    no wavelengths. The choice is logged and recorded in the band info.
    """
    if bs.kind == "mean":
        return None
    if bs.kind == "index":
        return cube.check_index(int(bs.value))  # type: ignore[arg-type]
    if bs.kind == "wavelength":
        return nearest_band(cube, float(bs.value))  # type: ignore[arg-type]
    wl = cube.wavelengths_nm
    if wl is None:
        if cube.count > 1:
            log.warning("%s has no wavelengths: band auto -> band index 0", cube.path)
        return 0
    try:
        return nearest_band(cube, AUTO_NM)
    except InputError:
        i = int(np.argmin(np.abs(wl - AUTO_NM)))
        log.warning(
            "%s covers %.0f-%.0f nm, not %.0f nm: band auto -> index %d (%.1f nm)",
            cube.path, wl.min(), wl.max(), AUTO_NM, i, wl[i],
        )  # fmt: skip
        return i


def valid_mask(band: np.ndarray, nodata: float | None) -> np.ndarray:
    """True where the pixel is finite and not the nodata value."""
    m = np.isfinite(band)
    if nodata is not None and np.isfinite(nodata):
        m &= band != np.float32(nodata)
    return m


def select_band(cube: Cube, spec: Any) -> tuple[np.ndarray, np.ndarray, dict[str, Any]]:
    """Return (band float32, valid mask, info) for ``spec``; ``mean`` streams band by band."""
    bs = spec if isinstance(spec, BandSpec) else parse_band_spec(spec)
    info: dict[str, Any] = {"spec": str(spec), "kind": bs.kind}
    if bs.kind == "mean":
        acc = np.zeros((cube.height, cube.width), np.float64)
        cnt = np.zeros((cube.height, cube.width), np.int32)
        for i in range(cube.count):
            b = cube.read_band(i)
            m = valid_mask(b, cube.nodata)
            acc[m] += b[m]
            cnt += m
        band = np.where(cnt > 0, acc / np.maximum(cnt, 1), np.nan).astype(np.float32)
        mask = cnt > 0
        info.update(index=None, wavelength_nm=None, bands_used=cube.count)
        return band, mask, info
    idx = resolve_band(cube, bs)
    assert idx is not None
    band = cube.read_band(idx)
    mask = valid_mask(band, cube.nodata)
    wl = None if cube.wavelengths_nm is None else float(cube.wavelengths_nm[idx])
    info.update(index=idx, wavelength_nm=wl)
    if bs.kind in ("wavelength", "auto") and wl is not None:
        log.info("band %s -> index %d at %.1f nm", spec, idx, wl)
    return band, mask, info


def stretch_uint8(
    band: np.ndarray, mask: np.ndarray, lo_pct: float = 1.0, hi_pct: float = 99.0
) -> tuple[np.ndarray, dict[str, float]]:
    """Robust linear stretch of valid pixels to 1..255 (0 = nodata) between two percentiles."""
    out = np.zeros(band.shape, np.uint8)
    if not mask.any():
        return out, {"lo": float("nan"), "hi": float("nan")}
    v = band[mask]
    lo, hi = (float(x) for x in np.percentile(v, [lo_pct, hi_pct]))
    if hi <= lo:
        hi = lo + 1.0
    scaled = np.clip((band - lo) / (hi - lo), 0.0, 1.0) * 254.0 + 1.0
    out[mask] = np.round(scaled[mask]).astype(np.uint8)
    return out, {"lo": lo, "hi": hi}


def resample(img: np.ndarray, mask: np.ndarray, factor: float) -> tuple[np.ndarray, np.ndarray]:
    """Resize an image and its mask by ``factor`` (area averaging when shrinking)."""
    if abs(factor - 1.0) < 1e-6:
        return img, mask
    h, w = img.shape
    size = (max(1, round(w * factor)), max(1, round(h * factor)))
    interp = cv2.INTER_AREA if factor < 1 else cv2.INTER_LINEAR
    out = cv2.resize(img, size, interpolation=interp)
    # a resampled pixel is valid only if all the pixels it draws from are
    m = cv2.resize(mask.astype(np.uint8) * 255, size, interpolation=interp) >= 255
    return out, m


def feature_scales(
    query_gsd_m: float | None, feature_gsd_m: float, guesses: list[float]
) -> list[float]:
    """Resize factors bringing the query to the map's feature GSD (several guesses when unknown)."""
    if query_gsd_m:
        return [float(query_gsd_m) / float(feature_gsd_m)]
    return [float(g) for g in guesses]


def write_query_band(
    image: str,
    band_spec: Any,
    gsd_m: float | None,
    out_tif: str,
    out_json: str,
    percentiles: tuple[float, float] = (1.0, 99.0),
) -> dict[str, Any]:
    """Rule query_band: select, mask and stretch the band; write band.tif (uint8, 0 = nodata)
    in query geometry and band.json (what was chosen, stretch, valid fraction, time)."""
    import time
    import warnings

    import rasterio

    from georeg.io.atomic import atomic_path, write_json
    from georeg.io.query import open_query

    t0 = time.perf_counter()
    cube = open_query(image)
    band, mask, info = select_band(cube, band_spec)
    if not mask.any():  # before writing anything: a failed step leaves no output
        raise InputError(image, f"band {band_spec} has no valid pixel", "check 'data ignore value'")
    u8, stretch = stretch_uint8(band, mask, *percentiles)
    profile = {
        "driver": "GTiff",
        "width": cube.width,
        "height": cube.height,
        "count": 1,
        "dtype": "uint8",
        "nodata": 0,
        "compress": "deflate",
    }
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", rasterio.errors.NotGeoreferencedWarning)
        with atomic_path(out_tif) as tmp, rasterio.open(tmp, "w", **profile) as dst:
            dst.write(u8, 1)
    meta = {
        "image": str(image),
        "cube": cube.describe(),
        "width": cube.width,
        "height": cube.height,
        "bands": cube.count,
        "band": info,
        "gsd_m": gsd_m,
        "stretch": {"percentiles": list(percentiles), **stretch},
        "valid_fraction": float(mask.mean()),
        "seconds": time.perf_counter() - t0,
    }
    write_json(out_json, meta)
    return meta


def read_query_band(path: str) -> np.ndarray:
    """The stretched band written by ``write_query_band`` (uint8, 0 = nodata)."""
    import warnings

    import rasterio

    with warnings.catch_warnings():
        warnings.simplefilter("ignore", rasterio.errors.NotGeoreferencedWarning)
        with rasterio.open(path) as src:
            return src.read(1)
