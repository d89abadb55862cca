"""A GeoPackage (OGC 12-128r18, version 1.4) point table written with the standard library's
sqlite3: the two required metadata tables, the geometry-columns table and one feature table
of POINT Z geometries (GeoPackage binary header + ISO WKB). No GDAL needed to write it; GDAL,
QGIS and ArcGIS read it. Written to a temp name and renamed."""

from __future__ import annotations

import datetime as _dt
import sqlite3
import struct
from pathlib import Path

import numpy as np
import pyproj

from georeg.io.atomic import atomic_path

APPLICATION_ID = 0x47504B47  # "GPKG"
USER_VERSION = 10400  # 1.4.0
CUSTOM_SRS_ID = 100000  # a CRS without an EPSG code


def point_blob(x: float, y: float, z: float, srs_id: int) -> bytes:
    """GeoPackage geometry: 'GP', version 0, flags (little-endian, no envelope), srs id, then the
    ISO WKB POINT Z (type 1001)."""
    return b"GP" + struct.pack("<BBi", 0, 0b00000001, srs_id) + struct.pack("<BIddd", 1, 1001, x, y, z)


def _sql_type(a: np.ndarray) -> str:
    if a.dtype == bool:
        return "BOOLEAN"
    return "INTEGER" if np.issubdtype(a.dtype, np.integer) else "DOUBLE"


def write_points(path: str | Path, table: str, xyz: np.ndarray, columns: dict[str, np.ndarray],
                 crs_wkt: str, description: str = "") -> None:  # fmt: skip
    """One feature table ``table`` (POINT Z in the CRS, plus numeric ``columns``) in a new
    GeoPackage at ``path``; NaN attributes become NULL, points with a NaN coordinate get an
    empty geometry (NULL)."""
    xyz = np.asarray(xyz, float).reshape(-1, 3)
    crs = pyproj.CRS.from_user_input(crs_wkt)
    epsg = crs.to_epsg()
    srs_id = int(epsg) if epsg else CUSTOM_SRS_ID
    now = _dt.datetime.now(_dt.timezone.utc).strftime("%Y-%m-%dT%H:%M:%S.000Z")
    ok = np.all(np.isfinite(xyz), axis=1)
    bb = (xyz[ok, :2].min(0).tolist() + xyz[ok, :2].max(0).tolist()) if ok.any() else [None] * 4
    cols = {k: np.asarray(v) for k, v in columns.items()}
    with atomic_path(path) as tmp:
        con = sqlite3.connect(str(tmp))
        try:
            con.execute(f"PRAGMA application_id = {APPLICATION_ID}")
            con.execute(f"PRAGMA user_version = {USER_VERSION}")
            con.executescript("""
                CREATE TABLE gpkg_spatial_ref_sys (srs_name TEXT NOT NULL, srs_id INTEGER PRIMARY KEY,
                  organization TEXT NOT NULL, organization_coordsys_id INTEGER NOT NULL,
                  definition TEXT NOT NULL, description TEXT);
                CREATE TABLE gpkg_contents (table_name TEXT NOT NULL PRIMARY KEY, data_type TEXT NOT NULL,
                  identifier TEXT UNIQUE, description TEXT DEFAULT '',
                  last_change DATETIME NOT NULL DEFAULT (strftime('%Y-%m-%dT%H:%M:%fZ','now')),
                  min_x DOUBLE, min_y DOUBLE, max_x DOUBLE, max_y DOUBLE, srs_id INTEGER,
                  CONSTRAINT fk_gc_r_srs_id FOREIGN KEY (srs_id) REFERENCES gpkg_spatial_ref_sys(srs_id));
                CREATE TABLE gpkg_geometry_columns (table_name TEXT NOT NULL, column_name TEXT NOT NULL,
                  geometry_type_name TEXT NOT NULL, srs_id INTEGER NOT NULL, z TINYINT NOT NULL,
                  m TINYINT NOT NULL, CONSTRAINT pk_geom_cols PRIMARY KEY (table_name, column_name),
                  CONSTRAINT fk_gc_tn FOREIGN KEY (table_name) REFERENCES gpkg_contents(table_name),
                  CONSTRAINT fk_gc_srs FOREIGN KEY (srs_id) REFERENCES gpkg_spatial_ref_sys (srs_id));
            """)  # fmt: skip
            srs = [("Undefined cartesian SRS", -1, "NONE", -1, "undefined", "undefined cartesian coordinate reference system"),
                   ("Undefined geographic SRS", 0, "NONE", 0, "undefined", "undefined geographic coordinate reference system"),
                   ("WGS 84 geodetic", 4326, "EPSG", 4326, pyproj.CRS.from_epsg(4326).to_wkt("WKT1_GDAL"),
                    "longitude/latitude coordinates in decimal degrees on the WGS 84 spheroid")]  # fmt: skip
            if srs_id != 4326:
                wkt = crs.to_wkt("WKT1_GDAL") or crs.to_wkt()
                srs.append((crs.name, srs_id, "EPSG" if epsg else "NONE", srs_id, wkt, ""))
            con.executemany("INSERT INTO gpkg_spatial_ref_sys VALUES (?, ?, ?, ?, ?, ?)", srs)
            con.execute("INSERT INTO gpkg_contents VALUES (?, 'features', ?, ?, ?, ?, ?, ?, ?, ?)",
                        (table, table, description, now, *bb, srs_id))  # fmt: skip
            con.execute("INSERT INTO gpkg_geometry_columns VALUES (?, 'geom', 'POINT', ?, 1, 0)", (table, srs_id))
            defs = ", ".join(f'"{k}" {_sql_type(v)}' for k, v in cols.items())
            con.execute(f'CREATE TABLE "{table}" (fid INTEGER PRIMARY KEY AUTOINCREMENT, geom POINT'
                        + (f", {defs}" if defs else "") + ")")  # fmt: skip
            names = ", ".join(f'"{k}"' for k in cols)
            marks = ", ".join("?" for _ in range(len(cols) + 1))
            rows = []
            for i in range(len(xyz)):
                g = point_blob(*xyz[i], srs_id) if ok[i] else None
                vals = []
                for v in cols.values():
                    e = v[i].item() if hasattr(v[i], "item") else v[i]
                    vals.append(None if isinstance(e, float) and not np.isfinite(e) else e)
                rows.append((g, *vals))
            con.executemany(f'INSERT INTO "{table}" (geom{", " + names if names else ""}) VALUES ({marks})', rows)
            con.commit()
        finally:
            con.close()
