"""The glue every stage relies on: atomic writes and one-line errors."""

from __future__ import annotations

import json
import subprocess
import sys

import pytest

from georeg.io.atomic import atomic_path, write_json
from georeg.io.errors import InputError


def test_atomic_path_renames_on_success(tmp_path):
    out = tmp_path / "sub" / "a.txt"
    with atomic_path(out) as tmp:
        assert tmp != out and tmp.parent == out.parent
        tmp.write_text("hello")
        assert not out.exists()
    assert out.read_text() == "hello"
    assert [p.name for p in out.parent.iterdir()] == ["a.txt"]


def test_atomic_path_leaves_nothing_on_failure(tmp_path):
    out = tmp_path / "a.tif"
    with pytest.raises(RuntimeError), atomic_path(out) as tmp:
        tmp.write_bytes(b"half")
        raise RuntimeError("boom")
    assert list(tmp_path.iterdir()) == []


def test_write_json_numpy(tmp_path):
    import numpy as np

    write_json(tmp_path / "x.json", {"a": np.float32(1.5), "b": np.arange(3)})
    assert json.loads((tmp_path / "x.json").read_text()) == {"a": 1.5, "b": [0, 1, 2]}


def test_write_json_is_strict_json(tmp_path):
    """NaN / infinity (a fit with no residual, an empty statistic) become null: a strict parser
    (jq, a browser's JSON.parse) refuses Python's NaN token."""
    import numpy as np

    write_json(tmp_path / "x.json", {"r": float("nan"), "s": [np.float64(np.inf), 2.0],
                                     "t": np.array([np.nan, 1.0]), "u": (np.int64(3), "a")})  # fmt: skip
    text = (tmp_path / "x.json").read_text()
    assert "NaN" not in text and "Infinity" not in text
    strict = json.loads(text, parse_constant=lambda c: pytest.fail(f"non-standard token {c}"))
    assert strict == {"r": None, "s": [None, 2.0], "t": [None, 1.0], "u": [3, "a"]}


def test_input_error_names_file():
    err = InputError("/data/ortho.tif", "has no CRS", "set map.crs or add a .aux.xml")
    assert str(err) == "/data/ortho.tif: has no CRS (set map.crs or add a .aux.xml)"


def test_run_reports_one_line_and_exits_1(tmp_path):
    code = (
        "from types import SimpleNamespace\n"
        "from georeg.io.scripting import run\n"
        "from georeg.io.errors import InputError\n"
        f"sm = SimpleNamespace(log=[{str(tmp_path / 'r.log')!r}], rule='demo')\n"
        "def main(sm):\n"
        "    raise InputError('q.hdr', 'wavelength 3000 nm is outside the cube (900-2500 nm)')\n"
        "run(sm, main)\n"
    )
    proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True)
    assert proc.returncode == 1
    assert "Traceback" not in proc.stderr
    assert "q.hdr: wavelength 3000 nm is outside the cube" in proc.stderr
    assert "q.hdr" in (tmp_path / "r.log").read_text()
