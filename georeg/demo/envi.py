"""Minimal ENVI writer: a text header plus a raw BIL data file written line block by line block."""

from __future__ import annotations

from pathlib import Path
from typing import BinaryIO

import numpy as np

ENVI_CODES = {
    np.dtype("uint8"): 1,
    np.dtype("int16"): 2,
    np.dtype("float32"): 4,
    np.dtype("uint16"): 12,
}


def _list(values: np.ndarray, fmt: str = "{:.3f}") -> str:
    body = ",\n ".join(
        ", ".join(fmt.format(v) for v in values[i : i + 8]) for i in range(0, len(values), 8)
    )
    return "{\n " + body + "}"


def envi_header(samples: int, lines: int, bands: int, dtype: np.dtype, wavelength: np.ndarray,
                fwhm: np.ndarray, description: str, extra: dict[str, str] | None = None) -> str:  # fmt: skip
    """ENVI header text for a little-endian BIL cube (no map info: not geo-referenced)."""
    dtype = np.dtype(dtype)
    rows = [
        "ENVI",
        "description = {" + description.replace("{", "(").replace("}", ")") + "}",
        f"samples = {samples}",
        f"lines = {lines}",
        f"bands = {bands}",
        "header offset = 0",
        "file type = ENVI Standard",
        f"data type = {ENVI_CODES[dtype]}",
        "interleave = bil",
        "byte order = 0",
        "sensor type = Unknown",
        "wavelength units = Nanometers",
    ]
    for k, v in (extra or {}).items():
        rows.append(f"{k} = {v}")
    rows.append("band names = {" + ", ".join(f"{w:.1f} nm" for w in wavelength) + "}")
    rows.append("wavelength = " + _list(np.asarray(wavelength)))
    rows.append("fwhm = " + _list(np.asarray(fwhm)))
    return "\n".join(rows) + "\n"


def write_bil_block(fh: BinaryIO, block: np.ndarray, dtype: np.dtype) -> None:
    """Append a (lines, samples, bands) block to an open BIL file (line, band, sample order)."""
    fh.write(
        np.ascontiguousarray(
            block.transpose(0, 2, 1), dtype=np.dtype(dtype).newbyteorder("<")
        ).tobytes()
    )


def data_path(header: str | Path) -> Path:
    """The .bil data file that goes with ``header``."""
    return Path(header).with_suffix(".bil")
