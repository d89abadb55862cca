"""Shared fixtures: where the repository and the public data live; every test runs in a
temporary working directory (never the checkout's results/, logs/ or .snakemake/)."""

from __future__ import annotations

import os
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
SHARED_DATA = REPO.parent / "shared" / "data"

# The Slurm executor plugin asks `scontrol show config` for MinJobAge when snakemake starts, even
# for a local run. Where the Slurm client is installed but no controller answers (a machine after
# tests/test_slurm.py stopped its cluster), every `snakemake` the tests start waits ~10 s for it.
# An empty Slurm configuration makes scontrol fail at once; test_slurm.py takes the real one back.
NO_SLURM_CONF = "/dev/null"
os.environ.setdefault("SLURM_CONF", NO_SLURM_CONF)


def pytest_report_header(config):
    """The numerical libraries that differ from constraints.txt (the versions the suite last passed
    with): a real-data test at its margin can fail on another OpenCV (5.1: three did)."""
    from georeg.io.versions import library_versions, untested

    other = untested(library_versions())
    if not other:
        return "georeg: the libraries' versions as in constraints.txt"
    return "georeg: NOT the tested versions (constraints.txt): " + other


def pytest_collection_modifyitems(config, items):
    """Long files first: the Slurm test (it mostly waits for the queue), then files with a `slow`
    test, then the rest, each file's tests in their order. With `--dist loadfile` and
    `--no-loadscope-reorder` (pyproject.toml) the two workers take whole files in this order, so
    the long waits overlap with work and the many short files fill the end (xdist's own order, by
    number of tests, started the one-test Slurm file last: 7 of the suite's 34 minutes)."""

    def rank(item) -> int:
        return 0 if item.get_closest_marker("slurm") else 1 if item.get_closest_marker("slow") else 2

    first: dict[str, int] = {}
    for item in items:
        f = item.nodeid.split("::", 1)[0]
        first[f] = min(first.get(f, 2), rank(item))
    items.sort(key=lambda item: first[item.nodeid.split("::", 1)[0]])


@pytest.fixture(scope="session", autouse=True)
def _session_cwd(tmp_path_factory):
    """Module and session fixtures run in a fresh directory, not where pytest was started: a
    relative path such as ``results/demo/orthophoto.tif`` never finds what a run of the workflow
    in the checkout left there (the README's two commands pass in either order)."""
    old = Path.cwd()
    os.chdir(tmp_path_factory.mktemp("cwd"))
    yield
    os.chdir(old)


@pytest.fixture(autouse=True)
def _test_cwd(tmp_path, monkeypatch):
    """Each test runs in its own temporary directory (its ``tmp_path``)."""
    monkeypatch.chdir(tmp_path)


@pytest.fixture(scope="session")
def repo() -> Path:
    return REPO


@pytest.fixture(scope="session")
def shared_data() -> Path:
    """../shared/data beside the repository; tests that need it skip cleanly when absent."""
    if not SHARED_DATA.is_dir():
        pytest.skip("../shared/data is absent")
    return SHARED_DATA


@pytest.fixture(scope="session")
def small_demo_map(tmp_path_factory):
    """A 640 m demo city (seed 7) with a one-tile map and its index, built once per session:
    (dir, scene paths, tile dir, tile layer paths). Frames and video tests add their own files
    in their own sub-directories."""
    import json

    import numpy as np

    from georeg.demo import generate_scene
    from georeg.index.features import extract_tile_from_grid
    from georeg.index.map_index import MapIndex
    from georeg.index.vocabulary import build_vocabulary
    from georeg.map.elevation import LAYERS, make_elevation_tile
    from georeg.map.grid import make_ortho_tile, write_grid

    tmp = tmp_path_factory.mktemp("small_demo_map")
    conf = {"seed": 7, "size_m": 640, "margin_m": 320, "lidar_tiles": 1,
            "query": {"samples": 64, "lines": 64, "bands": 8}}  # fmt: skip
    paths = generate_scene(conf, tmp / "demo")
    write_grid(tmp / "grid.json", [paths["orthophoto"]], 1024, 64)
    tile = "r000_c000"
    tdir = tmp / "tiles" / tile
    make_ortho_tile(tmp / "grid.json", tile, tdir / "ortho.tif")
    outs = {k: str(tdir / f"{k}.tif") for k in LAYERS} | {"points": str(tdir / "points.laz")}
    make_elevation_tile(str(tdir / "ortho.tif"), outs, [paths["lidar_0"]])
    fdir = tmp / "features" / tile
    extract_tile_from_grid(tmp / "grid.json", tile, tdir / "ortho.tif", outs["dsm"], outs["ndsm"],
                           {"rootsift": True, "max_features_per_mpx": 8000}, fdir)  # fmt: skip
    build_vocabulary([fdir], tmp / "vocab", {"k": 200, "sample_size": 50000}, 42)
    crs = json.loads((tmp / "grid.json").read_text()).get("crs")
    MapIndex.build([fdir], [tile], np.load(tmp / "vocab" / "centroids.npy"), tmp / "index",
                   crs_wkt=crs)  # fmt: skip
    return tmp, paths, tdir, outs
