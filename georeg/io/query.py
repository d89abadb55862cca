"""Read query images band by band: ENVI cubes, multi-band rasters with wavelengths, plain images.

A cube is never read whole: ENVI data are memory-mapped and one band is copied out at a time, so a
multi-gigabyte cube costs the memory of one band.
"""

from __future__ import annotations

import logging
import re
import warnings
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from georeg.io.errors import InputError

log = logging.getLogger(__name__)

# ENVI "data type" codes -> numpy dtypes (complex types are refused: no use for registration)
ENVI_DTYPES: dict[int, str] = {
    1: "u1",
    2: "i2",
    3: "i4",
    4: "f4",
    5: "f8",
    12: "u2",
    13: "u4",
    14: "i8",
    15: "u8",
}
DATA_EXTENSIONS = ("", ".bil", ".bsq", ".bip", ".img", ".dat", ".raw")
_UNIT_TO_NM = {
    "nm": 1.0,
    "nanometers": 1.0,
    "nanometer": 1.0,
    "nanometres": 1.0,
    "um": 1000.0,
    "µm": 1000.0,
    "micrometers": 1000.0,
    "micrometer": 1000.0,
    "micrometres": 1000.0,
    "microns": 1000.0,
    "micron": 1000.0,
    "mm": 1.0e6,
    "millimeters": 1.0e6,
}
_WL_RE = re.compile(r"([0-9]+(?:\.[0-9]*)?)\s*(nm|um|µm|micrometers?|nanometers?|microns?)\b", re.I)


@dataclass
class Cube:
    """A band-addressable image: ``read_band(i)`` returns band ``i`` (0-based) as float32."""

    path: Path
    width: int
    height: int
    count: int
    wavelengths_nm: np.ndarray | None = None
    fwhm_nm: np.ndarray | None = None
    nodata: float | None = None
    band_names: list[str] = field(default_factory=list)

    def read_band(self, index: int) -> np.ndarray:  # pragma: no cover - abstract
        raise NotImplementedError

    def check_index(self, index: int) -> int:
        """Return ``index`` if the cube has that band, else raise an InputError listing the bands."""
        if not 0 <= int(index) < self.count:
            raise InputError(
                self.path,
                f"band index {index} does not exist",
                f"the image has {self.count} band(s): indices 0..{self.count - 1}; {self.describe()}",
            )
        return int(index)

    def describe(self) -> str:
        """One line: size, band count and wavelength range."""
        s = f"{self.width} x {self.height} px, {self.count} band(s)"
        if self.wavelengths_nm is not None and len(self.wavelengths_nm):
            s += (
                f", wavelengths {float(np.min(self.wavelengths_nm)):.1f}"
                f"-{float(np.max(self.wavelengths_nm)):.1f} nm"
            )
        else:
            s += ", no wavelengths"
        return s


@dataclass
class EnviCube(Cube):
    """An ENVI cube memory-mapped from its data file."""

    data_path: Path = Path()
    dtype: np.dtype = np.dtype("f4")
    interleave: str = "bsq"
    offset: int = 0
    header: dict[str, str] = field(default_factory=dict)

    def _memmap(self) -> np.memmap:
        shape = {
            "bsq": (self.count, self.height, self.width),
            "bil": (self.height, self.count, self.width),
            "bip": (self.height, self.width, self.count),
        }[self.interleave]
        return np.memmap(
            self.data_path, dtype=self.dtype, mode="r", offset=self.offset, shape=shape
        )

    def read_band(self, index: int) -> np.ndarray:
        i = self.check_index(index)
        mm = self._memmap()
        if self.interleave == "bsq":
            band = mm[i]
        elif self.interleave == "bil":
            band = mm[:, i, :]
        else:
            band = mm[:, :, i]
        out = np.asarray(band, dtype=np.float32)  # copies one band, native byte order
        del mm
        return out


@dataclass
class RasterCube(Cube):
    """Any rasterio-readable raster (GeoTIFF, PNG, JPEG ...), read one band at a time."""

    def read_band(self, index: int) -> np.ndarray:
        import rasterio

        i = self.check_index(index)
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", rasterio.errors.NotGeoreferencedWarning)
            with rasterio.open(self.path) as src:
                return src.read(i + 1).astype(np.float32)


def georeferenced_gsd_m(cube: Cube) -> float | None:
    """The ground sample distance (m) the query file's own georeferencing states (a GeoTIFF's
    geotransform, an ENVI header's ``map info``), or None when it has none. Only the pixel size is
    taken, never the position. Projected CRS: the pixel's side in metres (the geometric mean of
    its width and height); longitude/latitude: the same on the ground at the image's centre."""
    import rasterio

    path = getattr(cube, "data_path", None) or cube.path
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", rasterio.errors.NotGeoreferencedWarning)
            with rasterio.open(path) as src:
                crs, t, w, h = src.crs, src.transform, src.width, src.height
    except rasterio.errors.RasterioError:
        return None
    if crs is None or t.is_identity:
        return None
    if crs.is_projected:
        unit = crs.linear_units_factor[1] if crs.linear_units_factor else 1.0
        return float(np.sqrt(abs(t.a * t.e - t.b * t.d)) * unit)
    if crs.is_geographic:
        from georeg.io.raster import degree_pixel_ground_m

        across, along = degree_pixel_ground_m(*(t * (w / 2.0, h / 2.0)), t.a, t.e)
        return float(np.sqrt(across * along)) if across > 0 and along > 0 else None
    return None


# ----------------------------------------------------------------------------- ENVI header


def parse_envi_header(path: str | Path) -> dict[str, str]:
    """Parse an ENVI ``.hdr`` into lower-case keys -> raw string values ({...} kept without braces)."""
    path = Path(path)
    try:
        text = path.read_text(errors="replace")
    except OSError as exc:
        raise InputError(path, f"cannot read the ENVI header: {exc.strerror}") from exc
    if not text.lstrip().upper().startswith("ENVI"):
        raise InputError(path, "not an ENVI header (the first line must be 'ENVI')")
    out: dict[str, str] = {}
    body = text.lstrip()[4:]
    i, n = 0, len(body)
    while i < n:
        eq = body.find("=", i)
        if eq < 0:
            break
        key = body[i:eq].strip().splitlines()[-1].strip().lower() if body[i:eq].strip() else ""
        j = eq + 1
        while j < n and body[j] in " \t":
            j += 1
        if j < n and body[j] == "{":
            end = body.find("}", j)
            if end < 0:
                raise InputError(path, f"unterminated '{{' in header value of '{key}'")
            value = body[j + 1 : end].strip()
            i = end + 1
        else:
            end = body.find("\n", j)
            end = n if end < 0 else end
            value = body[j:end].strip()
            i = end + 1
        if key:
            out[key] = value
    return out


def _header_int(hdr: dict[str, str], key: str, path: Path, default: int | None = None) -> int:
    if key not in hdr:
        if default is not None:
            return default
        raise InputError(
            path, f"ENVI header has no '{key}'", "samples, lines and bands are required"
        )
    try:
        return int(float(hdr[key]))
    except ValueError as exc:
        raise InputError(path, f"ENVI header '{key} = {hdr[key]}' is not a number") from exc


def _header_list(value: str | None) -> list[str]:
    if not value:
        return []
    return [v.strip() for v in value.replace("\n", " ").split(",") if v.strip()]


def _unit_scale(units: str | None, values: np.ndarray) -> float:
    """Factor from the header's wavelength units to nanometres (guessed from magnitude if absent)."""
    u = (units or "").strip().lower()
    if u in _UNIT_TO_NM:
        return _UNIT_TO_NM[u]
    if u and u not in ("unknown", "index"):
        log.warning("unknown wavelength units %r: guessing from the values", units)
    # no/unknown units: micrometres if every value is below 30, else nanometres
    return 1000.0 if len(values) and float(np.nanmax(values)) < 30 else 1.0


def _float_list(values: list[str], path: Path, key: str) -> np.ndarray:
    try:
        return np.array([float(v) for v in values], dtype=np.float64)
    except ValueError as exc:
        raise InputError(path, f"ENVI header '{key}' has a non-numeric entry") from exc


def find_envi_data(header: Path) -> Path:
    """The data file next to ``header``: same stem with or without a data extension, any case."""
    stem = header.with_suffix("")
    cands: list[Path] = []
    for ext in DATA_EXTENSIONS:
        cands += [Path(f"{stem}{ext}"), Path(f"{stem}{ext.upper()}")]
    # `name.bil.hdr` style: the data file is the header name minus `.hdr`
    for c in cands:
        if c.is_file() and c != header:
            return c
    raise InputError(
        header,
        "no ENVI data file next to the header",
        f"looked for {stem.name} with extensions {', '.join(e or '(none)' for e in DATA_EXTENSIONS)}",
    )


def find_envi_header(data: Path) -> Path | None:
    """The header for a data file (``x.hdr``, ``x.HDR``, ``x.bil.hdr``), or None."""
    for c in (
        data.with_suffix(".hdr"),
        data.with_suffix(".HDR"),
        Path(f"{data}.hdr"),
        Path(f"{data}.HDR"),
    ):
        if c.is_file() and c != data:
            return c
    return None


def open_envi(header: str | Path) -> EnviCube:
    """Open an ENVI cube from its header: validates type, interleave, size; nothing is read yet."""
    header = Path(header)
    hdr = parse_envi_header(header)
    samples = _header_int(hdr, "samples", header)
    lines = _header_int(hdr, "lines", header)
    bands = _header_int(hdr, "bands", header)
    offset = _header_int(hdr, "header offset", header, default=0)
    dtype_code = _header_int(hdr, "data type", header)
    if dtype_code not in ENVI_DTYPES:
        raise InputError(
            header,
            f"unsupported ENVI data type {dtype_code}",
            f"supported: {', '.join(map(str, ENVI_DTYPES))} (complex types are not)",
        )
    order = _header_int(hdr, "byte order", header, default=0)
    if order not in (0, 1):
        raise InputError(header, f"byte order must be 0 or 1, not {order}")
    dtype = np.dtype(ENVI_DTYPES[dtype_code]).newbyteorder("<" if order == 0 else ">")
    interleave = hdr.get("interleave", "bsq").strip().lower()
    if interleave not in ("bsq", "bil", "bip"):
        raise InputError(header, f"unknown interleave '{interleave}'", "expected bsq, bil or bip")
    if hdr.get("file compression", "0").strip() not in ("0", ""):
        raise InputError(
            header,
            "the data file is gzip-compressed (file compression = 1) and cannot be memory-mapped",
            "decompress it (gunzip) and set 'file compression = 0' in the header",
        )
    if min(samples, lines, bands) < 1:
        raise InputError(header, f"empty cube: samples={samples} lines={lines} bands={bands}")
    data = find_envi_data(header)
    need = offset + samples * lines * bands * dtype.itemsize
    have = data.stat().st_size
    if have < need:
        raise InputError(
            data,
            f"data file is {have} bytes but the header ({samples} x {lines} x {bands} "
            f"{np.dtype(ENVI_DTYPES[dtype_code]).name}, offset {offset}) needs {need}",
            "the file is truncated or the header does not describe it",
        )
    wl = fw = None
    if "wavelength" in hdr:
        raw = _float_list(_header_list(hdr["wavelength"]), header, "wavelength")
        if len(raw) != bands:
            raise InputError(header, f"{len(raw)} wavelengths for {bands} bands")
        scale = _unit_scale(hdr.get("wavelength units"), raw)
        wl = raw * scale
        if "fwhm" in hdr:
            f = _float_list(_header_list(hdr["fwhm"]), header, "fwhm")
            fw = f * scale if len(f) == bands else None
    nodata = None
    if "data ignore value" in hdr:
        try:
            nodata = float(hdr["data ignore value"])
        except ValueError:
            log.warning("%s: ignoring non-numeric 'data ignore value'", header)
    return EnviCube(
        path=header,
        width=samples,
        height=lines,
        count=bands,
        wavelengths_nm=wl,
        fwhm_nm=fw,
        nodata=nodata,
        band_names=_header_list(hdr.get("band names")),
        data_path=data,
        dtype=dtype,
        interleave=interleave,
        offset=offset,
        header=hdr,
    )


# ----------------------------------------------------------------------------- rasters


def wavelength_from_text(text: str | None) -> float | None:
    """Wavelength in nm from a description like '418.24 nm' or '1.65 um', else None."""
    if not text:
        return None
    m = _WL_RE.search(text)
    if not m:
        return None
    return float(m.group(1)) * _UNIT_TO_NM[m.group(2).lower()]


def open_raster(path: str | Path) -> RasterCube:
    """Open a rasterio-readable image; wavelengths come from band descriptions or band metadata."""
    import rasterio

    from georeg.io.raster import open_raster as open_checked

    path = Path(path)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", rasterio.errors.NotGeoreferencedWarning)
        with open_checked(path, require_crs=False) as src:  # missing / unreadable: InputError
            count, width, height = src.count, src.width, src.height
            descs = list(src.descriptions)
            nodata = src.nodata
            wls: list[float | None] = []
            for b in range(1, count + 1):
                tags = src.tags(b)
                w = wavelength_from_text(descs[b - 1])
                if w is None and "wavelength" in tags:
                    try:
                        v = float(tags["wavelength"])
                        unit = tags.get("wavelength_units", "")
                        w = v * _unit_scale(unit, np.array([v]))
                    except ValueError:
                        w = None
                wls.append(w)
    wl = np.array(wls, dtype=np.float64) if all(w is not None for w in wls) else None
    return RasterCube(
        path=path,
        width=width,
        height=height,
        count=count,
        wavelengths_nm=wl,
        nodata=None if nodata is None or np.isnan(nodata) else float(nodata),
        band_names=[d or "" for d in descs],
    )


def open_query(path: str | Path) -> Cube:
    """Open a query image: ENVI (header or data file given), else any rasterio-readable raster."""
    path = Path(path)
    if not path.exists():
        raise InputError(path, "query image does not exist")
    if path.suffix.lower() == ".hdr":
        return open_envi(path)
    hdr = find_envi_header(path)
    if hdr is not None:
        return open_envi(hdr)
    return open_raster(path)
