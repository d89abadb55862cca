"""Digest of a GeoPackage by its tables' rows: two runs that write the same tie points give the
same digest, although ``gpkg_contents.last_change`` (the time of writing, as the standard asks)
makes their bytes differ."""

from __future__ import annotations

import hashlib
import sqlite3
from pathlib import Path


def gpkg_digest(path: Path) -> str:
    with sqlite3.connect(path) as db:
        tables = [r[0] for r in db.execute("SELECT name FROM sqlite_master WHERE type = 'table' ORDER BY name")]
        rows = {t: sorted(map(repr, db.execute(f'SELECT * FROM "{t}"'))) for t in tables if t != "gpkg_contents"}
        rows["gpkg_contents"] = sorted(map(repr, db.execute(
            "SELECT table_name, data_type, identifier, description, min_x, min_y, max_x, max_y, srs_id "
            "FROM gpkg_contents")))  # fmt: skip
    return hashlib.sha256(repr(rows).encode()).hexdigest()
