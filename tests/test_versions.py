"""constraints.txt (the versions the suite last passed with) and how a result states its own."""

from __future__ import annotations

import re
from importlib import metadata

from georeg.io.versions import CONSTRAINTS, differing, library_versions, pinned


def test_pinned_reads_name_version_lines_by_normalised_name(tmp_path):
    p = tmp_path / "c.txt"
    p.write_text("# comment\nopencv_python.Headless==5.0.0.93\nnumpy == 2.4.6  # why\nscipy>=1\n\n")
    assert pinned(p) == {"opencv-python-headless": "5.0.0.93", "numpy": "2.4.6"}
    assert pinned(tmp_path / "absent.txt") == {}


def test_differing_names_only_installed_packages_pinned_otherwise(tmp_path):
    p = tmp_path / "c.txt"
    p.write_text("opencv-python-headless==5.0.0.93\nnumpy==2.4.6\ntorch==2.13.0+cpu\n")
    have = {"opencv-python-headless": "5.1.0.95", "numpy": "2.4.6", "torch": "-", "scipy": "9"}
    assert differing(have, p) == {"opencv-python-headless": "5.0.0.93"}


def test_constraints_pin_every_requirement():
    """A package added to requirements*.txt without its tested version would be resolved anew."""
    pins = pinned(CONSTRAINTS)
    req = CONSTRAINTS.parent
    names = []
    for f in ("requirements.txt", "requirements-learned.txt"):
        for line in (req / f).read_text().splitlines():
            m = re.match(r"^\s*([A-Za-z0-9_.\-]+)", line)
            if m and not line.lstrip().startswith("#"):
                names.append(re.sub(r"[-_.]+", "-", m.group(1)).lower())
    assert names and not [n for n in names if n not in pins]


def test_library_versions_are_the_installed_ones():
    v = library_versions()
    assert v["numpy"] == metadata.version("numpy")
    assert v["opencv-python-headless"] == metadata.version("opencv-python-headless")
    assert v["GDAL"] and v["PROJ"] and v["python"].count(".") == 2
