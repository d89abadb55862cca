"""The test digests ignore only what their standards make a writing time."""

from __future__ import annotations

import datetime

import laspy
import numpy as np
from digests import las_digest


def _write(path, day: datetime.date, z_shift: float = 0.0) -> None:
    header = laspy.LasHeader(point_format=7, version="1.4")
    header.scales = np.array([0.001, 0.001, 0.001])
    header.creation_date = day
    las = laspy.LasData(header)
    rng = np.random.default_rng(0)
    las.x, las.y = rng.uniform(0, 100, 50), rng.uniform(0, 100, 50)
    las.z = rng.uniform(0, 10, 50) + z_shift
    las.write(str(path))


def test_las_digest_ignores_the_creation_date_only(tmp_path):
    for ext in ("las", "laz"):
        a, b, c = (tmp_path / f"{n}.{ext}" for n in "abc")
        _write(a, datetime.date(2026, 11, 27))
        _write(b, datetime.date(2026, 11, 28))  # the same points, written after midnight
        _write(c, datetime.date(2026, 11, 27), z_shift=0.01)
        assert a.read_bytes() != b.read_bytes()
        assert las_digest(a) == las_digest(b)
        assert las_digest(a) != las_digest(c)
