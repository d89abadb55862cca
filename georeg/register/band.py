"""Choose the query band (nearest wavelength, index or streamed mean) and the bands pooled with it,
mask nodata, stretch, resample."""

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
#: `bands: auto` pools the primary band with the band nearest the first of these (the centres
#: of the two other SWIR windows: the pair the cross-spectral protocol measured) that the cube
#: has within POOL_TOLERANCE_NM and that lies at least POOL_MIN_SEPARATION_NM from the primary
POOL_TARGETS_NM = (2200.0, 1650.0)
POOL_TOLERANCE_NM = 150.0
POOL_MIN_SEPARATION_NM = 300.0
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
        i = auto_index(wl)
        log.warning(
            "%s covers %.0f-%.0f nm, not %.0f nm: band auto -> index %d (%.1f nm)",
            cube.path, wl.min(), wl.max(), AUTO_NM, i, wl[i],
        )  # fmt: skip
        return i


def auto_index(wavelengths_nm: np.ndarray | None) -> int:
    """``band: auto`` from the wavelengths alone: the band nearest 1200 nm (0 without them)."""
    if wavelengths_nm is None or len(wavelengths_nm) == 0:
        return 0
    return int(np.argmin(np.abs(np.asarray(wavelengths_nm, np.float64) - AUTO_NM)))


def auto_partner(wavelengths_nm: np.ndarray | None, primary: int) -> int | None:
    """``bands: auto``'s second band for primary band ``primary``, or None.

    The band nearest 2200 nm, or nearest 1650 nm when that one is too close to the primary
    (e.g. a 2200 nm primary): the first target the cube has a band for within 150 nm that lies
    at least 300 nm from the primary. None without wavelengths (the band order says nothing) or
    when no band qualifies (one band, a narrow cube).
    """
    if wavelengths_nm is None or len(wavelengths_nm) < 2:
        return None
    wl = np.asarray(wavelengths_nm, np.float64)
    for target in POOL_TARGETS_NM:
        i = int(np.argmin(np.abs(wl - target)))
        if abs(wl[i] - target) <= POOL_TOLERANCE_NM and (
            abs(wl[i] - wl[primary]) >= POOL_MIN_SEPARATION_NM
        ):
            return i
    return None


def parse_bands_spec(spec: Any) -> str | list[BandSpec]:
    """``bands``: ``"auto"``, ``"one"`` (the primary band only) or a list of band specs pooled
    with the primary band."""
    if spec is None:
        return "auto"
    if isinstance(spec, str) and spec.strip().lower() in ("auto", "one"):
        return spec.strip().lower()
    if isinstance(spec, (list, tuple)):
        out = [parse_band_spec(s) for s in spec]
        if any(b.kind in ("mean", "auto") for b in out):
            raise InputError(
                None,
                f"bands {spec!r}: list wavelengths or indexes",
                "'mean'/'auto' cannot be pooled",
            )
        return out
    raise InputError(
        None,
        f"bands {spec!r} is not understood",
        "use 'auto', 'one' or a list like [1650nm, 2200nm]",
    )


def pooled_indices(cube: Cube, primary: int | None, spec: Any) -> list[int | None]:
    """Bands whose features are pooled, the primary first (None = the mean), duplicates dropped.

    ``auto``: the primary plus ``auto_partner`` (none for a ``mean`` primary); ``one``: the primary
    only; a list: the primary plus those bands.
    """
    ps = parse_bands_spec(spec)
    out: list[int | None] = [primary]
    if ps == "one" or (ps == "auto" and primary is None):
        return out
    if ps == "auto":
        extra = [auto_partner(cube.wavelengths_nm, primary)]  # type: ignore[arg-type]
    else:
        extra = [resolve_band(cube, b) for b in ps]  # type: ignore[union-attr]
    for i in extra:
        if i is not None and i not in out:
            out.append(i)
    return out


def valid_mask(band: np.ndarray, nodata: float | None) -> np.ndarray:
    """True where the pixel is finite and not the nodata value."""
    m = np.isfinite(band)
    if nodata is not None and np.isfinite(nodata):
        m &= band != np.float32(nodata)
    return m


FILL_LEVEL = 0.015  # a fill: within this fraction of the band's range of its minimum ...
FILL_FLOOR = 0.02  # ... that minimum at most this fraction of the band's 99th percentile (near 0)
FILL_MIN = 0.01  # ... covering at least this fraction of the image


def border_fill(band: np.ndarray, mask: np.ndarray) -> np.ndarray:
    """The dark fill around a rotated or cut image that states no nodata (a JPEG: its black
    corners are JPEG-noisy zeros, not exact ones): pixels whose 5 x 5 mean is within
    ``FILL_LEVEL`` of the range above a near-zero minimum, connected to the image's edge,
    grown by 3 px (the compression's ringing). Empty when that is under ``FILL_MIN`` of the
    image. Treated as content, its edge is structure the map does not have (SRIF's rotated
    query JPEGs: session 34)."""
    h, w = band.shape
    none = np.zeros((h, w), bool)
    if not mask.any() or min(h, w) < 8:
        return none
    v = band[mask]
    lo, hi = float(v.min()), float(np.percentile(v, 99))
    if hi <= lo or lo > FILL_FLOOR * hi:
        return none
    mean = cv2.blur(np.where(mask, band, lo).astype(np.float32), (5, 5))
    near = (mean <= lo + FILL_LEVEL * (hi - lo)).astype(np.uint8)
    _, lab = cv2.connectedComponents(near, connectivity=4)
    edge = np.unique(np.r_[lab[0], lab[-1], lab[:, 0], lab[:, -1]])
    fill = np.isin(lab, edge[edge > 0])
    if fill.mean() < FILL_MIN:
        return none
    return cv2.dilate(fill.astype(np.uint8), np.ones((7, 7), np.uint8)) > 0


def _without_fill(band: np.ndarray, mask: np.ndarray, nodata: float | None, info: dict[str, Any]) -> np.ndarray:
    """``mask`` without the border fill of an 8-bit file that states no nodata (a JPEG, a PNG;
    ``info["fill_fraction"]``). Other data keep every valid pixel: a float or 16-bit cube's
    darkest pixels are water as often as fill (the EnMAP Potsdam tile: its lakes, 42 % of it,
    touch the edge)."""
    if nodata is not None or not mask.any():
        return mask
    v = band[mask][:: max(1, int(mask.sum()) // 100_000)]
    if float(v.min()) < 0 or float(v.max()) > 255 or not np.array_equal(v, np.round(v)):
        return mask
    fill = border_fill(band, mask)
    info["fill_fraction"] = round(float(fill.mean()), 4)
    return mask & ~fill


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
        mask = _without_fill(band, mask, cube.nodata, info)
        info.update(index=None, wavelength_nm=None, bands_used=cube.count)
        return band, mask, info
    idx = resolve_band(cube, bs)
    assert idx is not None
    band = cube.read_band(idx)
    mask = valid_mask(band, cube.nodata)
    mask = _without_fill(band, mask, cube.nodata, info)
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
    bands_spec: Any = "auto",
    prior: Any = None,
) -> dict[str, Any]:
    """Rule query_band: select, mask and stretch the band and the bands pooled with it; write
    band.tif (uint8, 0 = nodata, in query geometry; band 1 = the primary band, then the pooled
    ones, see ``pooled_indices``) and band.json (what was chosen, stretch, valid fraction, time;
    ``pooled_bands``: one record per band of band.tif; ``prior``: the query's location prior as
    configured, checked here, read by the search_part and fuse_parts jobs)."""
    import time
    import warnings

    import rasterio

    from georeg.io.atomic import atomic_path, write_json
    from georeg.io.prior import check_prior
    from georeg.io.query import georeferenced_gsd_m, open_query

    t0 = time.perf_counter()
    try:
        check_prior(prior)
    except ValueError as exc:
        raise InputError(image, f"queries prior: {exc}", "see config/README.md") from None
    cube = open_query(image)
    gsd_source = "config" if gsd_m else None
    if not gsd_m and (gsd_m := georeferenced_gsd_m(cube)):  # the pixel size the file states
        gsd_source = "geotransform"
        log.info("%s: gsd_m not given; %.3g m from the file's georeferencing (its position is "
                 "not used)", image, gsd_m)  # fmt: skip
    band, mask, info = select_band(cube, band_spec)
    if not mask.any():  # before writing anything: a failed step leaves no output
        if not np.isfinite(band).any():
            raise InputError(image, f"band {band_spec} has no valid pixel: every value is NaN",
                             "the cube holds no data: check how it was exported")  # fmt: skip
        raise InputError(image, f"band {band_spec} has no valid pixel", "check 'data ignore value'")
    u8, stretch = stretch_uint8(band, mask, *percentiles)
    valid_fraction = float(mask.mean())
    del band, mask  # one float band in memory at a time
    stack = [u8]
    pooled = [{**_band_record(info), "stretch": stretch, "valid_fraction": valid_fraction}]
    for i in pooled_indices(cube, info["index"], bands_spec)[1:]:
        b, m, bi = select_band(cube, BandSpec("index", i))
        if not m.any():
            log.warning("%s: pooled band %d has no valid pixel: not pooled", image, i)
            continue
        bu8, bst = stretch_uint8(b, m, *percentiles)
        stack.append(bu8)
        pooled.append({**_band_record(bi), "stretch": bst, "valid_fraction": float(m.mean())})
        del b, m
    log.info(
        "query bands pooled: %s",
        ", ".join(f"{p['index']} ({_nm(p['wavelength_nm'])})" for p in pooled),
    )
    profile = {
        "driver": "GTiff",
        "width": cube.width,
        "height": cube.height,
        "count": len(stack),
        "dtype": "uint8",
        "nodata": 0,
        "compress": "deflate",
    }
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", rasterio.errors.NotGeoreferencedWarning)
        with atomic_path(out_tif) as tmp, rasterio.open(tmp, "w", **profile) as dst:
            for k, plane in enumerate(stack, start=1):
                dst.write(plane, k)
    meta = {
        "image": str(image),
        "cube": cube.describe(),
        "width": cube.width,
        "height": cube.height,
        "bands": cube.count,
        "band": info,
        "bands_spec": bands_spec if isinstance(bands_spec, str) else list(bands_spec),
        "pooled_bands": pooled,
        "gsd_m": gsd_m,
        "gsd_source": gsd_source,  # config | geotransform (not given: the file's) | None (unknown)
        "prior": prior,
        "stretch": {"percentiles": list(percentiles), **stretch},
        "valid_fraction": valid_fraction,
        "seconds": time.perf_counter() - t0,
    }
    write_json(out_json, meta)
    return meta


def _band_record(info: dict[str, Any]) -> dict[str, Any]:
    return {"index": info.get("index"), "wavelength_nm": info.get("wavelength_nm")}


def _nm(v: float | None) -> str:
    return "mean" if v is None else f"{v:.0f} nm"


def read_query_band(path: str) -> np.ndarray:
    """The stretched primary band written by ``write_query_band`` (uint8, 0 = nodata)."""
    import warnings

    import rasterio

    with warnings.catch_warnings():
        warnings.simplefilter("ignore", rasterio.errors.NotGeoreferencedWarning)
        with rasterio.open(path) as src:
            return src.read(1)


def read_query_bands(path: str) -> np.ndarray:
    """Every band written by ``write_query_band``: (bands, rows, cols) uint8, the primary first
    (a one-band file gives one plane: pooling degenerates to the primary band)."""
    import warnings

    import rasterio

    with warnings.catch_warnings():
        warnings.simplefilter("ignore", rasterio.errors.NotGeoreferencedWarning)
        with rasterio.open(path) as src:
            return src.read()
