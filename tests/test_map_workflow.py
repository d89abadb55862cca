"""End-to-end: the map stage through Snakemake on a tiny synthetic scene, and its rerun triggers.

Runs a minimal Snakefile (the repo's config, common.smk and map.smk only) with --directory in a
temporary folder, so nothing lands in the repo's results/.
"""

from __future__ import annotations

import re
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import rasterio
import yaml
from test_map_synthetic import GROUND_M, ROOF_M, make_scene

REPO = Path(__file__).resolve().parents[1]
pytestmark = pytest.mark.slow


def _snakefile(tmp: Path) -> Path:
    sf = tmp / "Snakefile"
    sf.write_text(
        f'configfile: "{REPO}/config/config.yaml"\n'
        f'include: "{REPO}/workflow/rules/common.smk"\n'
        f'include: "{REPO}/workflow/rules/map.smk"\n'
        "rule all:\n    input: all_inputs\n    default_target: True\n"
    )
    return sf


def _config(tmp: Path, ortho: Path, las: Path, std_ratio: float) -> Path:
    cfg = {
        "map": {"orthophoto": str(ortho), "lidar": [str(las)], "lidar_crs": None, "dem": None},
        "queries": {},
        "map_prep": {
            "tile_size_px": 128,
            "tile_overlap_px": 16,
            "outlier": {"nb_neighbors": 8, "std_ratio": std_ratio},
        },
    }
    p = tmp / f"cfg_{std_ratio}.yaml"
    p.write_text(yaml.safe_dump(cfg))
    return p


def _smk(tmp: Path, cfg: Path, *args: str) -> subprocess.CompletedProcess:
    cmd = [
        sys.executable,
        "-m",
        "snakemake",
        "-s",
        str(_snakefile(tmp)),
        "--directory",
        str(tmp),
        "--configfile",
        str(cfg),
        "--cores",
        "2",
        *args,
    ]
    return subprocess.run(cmd, capture_output=True, text=True, timeout=300)


def _planned_rules(out: str) -> dict[str, int]:
    """Rule -> job count from the job stats table of a dry run."""
    rules = {}
    for line in out.splitlines():
        m = re.match(r"^(map_\w+)\s+(\d+)\s*$", line.strip())
        if m:
            rules[m.group(1)] = int(m.group(2))
    return rules


def test_map_stage_end_to_end_and_param_rerun(tmp_path):
    ortho, las, _ = make_scene(tmp_path)
    cfg = _config(tmp_path, ortho, las, 3.0)
    r = _smk(tmp_path, cfg)
    assert r.returncode == 0, r.stderr[-3000:]
    res = tmp_path / "results" / "map"
    tiles = sorted(p.name for p in (res / "tiles").iterdir())
    assert tiles == ["r000_c000", "r000_c001", "r001_c000", "r001_c001"]
    for t in tiles:
        for name in ("ortho.tif", "dsm.tif", "dtm.tif", "ndsm.tif", "density.tif", "points.laz"):
            assert (res / "tiles" / t / name).stat().st_size > 0
    assert (res / "overview.png").stat().st_size > 10_000
    with rasterio.open(res / "mosaic" / "dsm.vrt") as v, rasterio.open(ortho) as o:
        assert v.shape == o.shape and v.transform == o.transform
        d = v.read(1, masked=True)
        assert d.max() == pytest.approx(ROOF_M, abs=0.3)
        assert np.ma.median(d) == pytest.approx(GROUND_M, abs=0.2)
    with rasterio.open(res / "mosaic" / "ortho.vrt") as v, rasterio.open(ortho) as o:
        assert np.array_equal(v.read(), o.read())

    # nothing to do with the same config
    r = _smk(tmp_path, cfg, "-n")
    assert r.returncode == 0, r.stderr[-3000:]
    assert _planned_rules(r.stdout + r.stderr) == {}

    # a changed outlier parameter reruns the elevation tiles and what reads them, not the ortho
    cfg2 = _config(tmp_path, ortho, las, 2.0)
    r = _smk(tmp_path, cfg2, "-n", "--rerun-triggers", "params", "mtime")
    assert r.returncode == 0, r.stderr[-3000:]
    planned = _planned_rules(r.stdout + r.stderr)
    assert planned.get("map_tile_elevation") == 4
    assert planned.get("map_overview") == 1
    assert planned.get("map_mosaic") == 4  # dsm, dtm, ndsm, density; not ortho
    assert "map_tile_ortho" not in planned and "map_grid" not in planned


def test_workflow_bad_lidar_fails_with_one_line_and_no_outputs(tmp_path):
    from test_map_synthetic import make_las, make_ortho, scene_points

    ortho = make_ortho(tmp_path / "ortho.tif")
    las = make_las(tmp_path / "nocrs.laz", scene_points(density=0.2), crs=None)
    cfg = _config(tmp_path, ortho, las, 3.0)
    r = _smk(tmp_path, cfg)
    assert r.returncode != 0
    assert "nocrs.laz: LAS/LAZ file has no CRS" in r.stderr
    assert not list((tmp_path / "results" / "map" / "tiles").glob("*/dsm.tif"))
