"""Digests of products whose bytes carry their writing time, as their standards ask, so that two
runs that write the same content give the same digest.

- GeoPackage: ``gpkg_contents.last_change`` is the time of writing; digested by its tables' rows.
- LAS/LAZ: the header's file creation day and year (bytes 90-93) are the day of writing, so two
  runs on either side of midnight differ there; digested with those four bytes zeroed.
"""

from __future__ import annotations

import hashlib
import sqlite3
from pathlib import Path

LAS_CREATION_DATE = slice(90, 94)  # File Creation Day of Year, File Creation Year (uint16 each)


def gpkg_digest(path: Path) -> str:
    with sqlite3.connect(path) as db:
        tables = [r[0] for r in db.execute("SELECT name FROM sqlite_master WHERE type = 'table' ORDER BY name")]
        rows = {t: sorted(map(repr, db.execute(f'SELECT * FROM "{t}"'))) for t in tables if t != "gpkg_contents"}
        rows["gpkg_contents"] = sorted(map(repr, db.execute(
            "SELECT table_name, data_type, identifier, description, min_x, min_y, max_x, max_y, srs_id "
            "FROM gpkg_contents")))  # fmt: skip
    return hashlib.sha256(repr(rows).encode()).hexdigest()


def las_digest(path: Path) -> str:
    data = bytearray(Path(path).read_bytes())
    if data[:4] != b"LASF":
        raise ValueError(f"{path}: not a LAS/LAZ file")
    data[LAS_CREATION_DATE] = bytes(4)
    return hashlib.sha256(bytes(data)).hexdigest()
