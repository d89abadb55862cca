"""The SWIR tie points as a GeoPackage table (sqlite3 by hand): readable by sqlite3 and, where
installed, by GDAL/OGR (pyogrio); geometries and attributes as written."""

from __future__ import annotations

import json
import sqlite3
import struct

import numpy as np
import pytest
import rasterio

from georeg.export.tie_points import export_tie_points

CRS = "EPSG:32633"


def _registration(tmp_path, with_points=True):
    h, w = 60, 80
    rows, cols = np.mgrid[0:h, 0:w].astype(float)
    x, y = 400_000 + 2.0 * cols + 0.1 * rows, 5_800_000 - 2.0 * rows
    z = 30 + 0.01 * cols
    geo = tmp_path / "geolocation.tif"
    with rasterio.open(geo, "w", driver="GTiff", width=w, height=h, count=3, dtype="float64") as ds:
        ds.write(np.stack([x, y, z]))
    pts = {"col": [10.0, 20.5, 70.0], "row": [5.0, 30.0, 50.5], "score": [0.8, None, 0.6],
           "accepted": [True, False, True], "before": [[0.5, -0.2], [3.0, 4.0], [0.0, 0.1]],
           "after": [[0.3, 0.4], [2.0, 0.0], [0.0, -0.05]], "accepted_after": [True, False, True]}  # fmt: skip
    reg = {"query": "q", "status": "registered", "crs": CRS,
           "refine": {"model": "per_line", "query_px_m": 2.0, **({"points": pts} if with_points else
                                                                 {"reason": "query not registered"})}}  # fmt: skip
    rj = tmp_path / "registration.json"
    rj.write_text(json.dumps(reg))
    return rj, geo


def test_tie_points_gpkg(tmp_path):
    rj, geo = _registration(tmp_path)
    out = tmp_path / "tie_points.gpkg"
    assert export_tie_points(rj, geo, out)["tie_points"] == 3
    con = sqlite3.connect(out)
    assert con.execute("PRAGMA application_id").fetchone()[0] == 0x47504B47
    assert con.execute("PRAGMA integrity_check").fetchone()[0] == "ok"
    assert con.execute("SELECT srs_id, z FROM gpkg_geometry_columns WHERE table_name='tie_points'").fetchone() == (32633, 1)
    rows = con.execute("SELECT geom, query_col, query_row, map_x, map_y, map_z, residual_px, score, accepted "
                       "FROM tie_points ORDER BY fid").fetchall()  # fmt: skip
    assert len(rows) == 3
    g, c, r, mx, my, mz, res, score, acc = rows[1]
    assert g[:2] == b"GP"
    srs, = struct.unpack("<i", g[4:8])
    _, gtype, gx, gy, gz = struct.unpack("<BIddd", g[8:])
    assert srs == 32633 and gtype == 1001
    assert (gx, gy, gz) == pytest.approx((400_000 + 2 * 20.5 + 0.1 * 30, 5_800_000 - 60, 30.205))
    assert (mx, my, mz) == pytest.approx((gx, gy, gz))
    assert (c, r, res, score, acc) == (20.5, 30.0, pytest.approx(2.0), None, 0)
    assert rows[0][6] == pytest.approx(0.5)
    con.close()


def test_tie_points_gpkg_reads_in_gdal(tmp_path):
    pyogrio = pytest.importorskip("pyogrio")
    rj, geo = _registration(tmp_path)
    out = tmp_path / "tie_points.gpkg"
    export_tie_points(rj, geo, out)
    info = pyogrio.read_info(out, layer="tie_points")
    assert info["features"] == 3 and info["geometry_type"] == "Point Z"
    assert "32633" in info["crs"]
    _, _, geom, fields = pyogrio.raw.read(out, layer="tie_points")
    assert len(geom) == 3 and "residual_px" in info["fields"]


def test_not_registered_gives_an_empty_table(tmp_path):
    rj, geo = _registration(tmp_path, with_points=False)
    out = tmp_path / "tie_points.gpkg"
    assert export_tie_points(rj, geo, out) == {"tie_points": 0, "reason": "query not registered"}
    con = sqlite3.connect(out)
    assert con.execute("SELECT count(*) FROM tie_points").fetchone()[0] == 0
    assert "query not registered" in con.execute("SELECT description FROM gpkg_contents").fetchone()[0]


def test_bad_registration_names_the_file(tmp_path):
    from georeg.io.errors import InputError

    rj = tmp_path / "registration.json"
    rj.write_text("[")
    with pytest.raises(InputError, match="registration.json"):
        export_tie_points(rj, tmp_path / "g.tif", tmp_path / "t.gpkg")
    assert not (tmp_path / "t.gpkg").exists()
