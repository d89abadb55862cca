"""Issue 13 through the real ``snakemake`` command: bad inputs, SIGKILL + rerun, repeatability,
two runs in one checkout (``--directory``), paths with spaces and non-ASCII characters.

One module fixture starts three workflows from this checkout at the same time, each in its own
``--directory``: A and B the small demo (tests/data/slurm_small.yaml: one map tile, a 96 x 128
query; + its ``outside`` query and two constant ones) with the same seed,
C a map-only run on a synthetic orthophoto + LiDAR under a path with spaces and accents. B is
SIGKILLed (whole process group, as a crash would) in the middle of ``map_tile_elevation``, then
rerun; A runs uninterrupted. The library-level matrix is test_reliability.py; the table of all
cases is docs/RELIABILITY.md.
"""

from __future__ import annotations

import hashlib
import json
import os
import signal
import subprocess
import sys
import time
from importlib import metadata
from pathlib import Path

import numpy as np
import pytest
import yaml
from digests import gpkg_digest, las_digest
from test_map_synthetic import make_las, make_ortho, scene_points
from test_query_io import write_envi

REPO = Path(__file__).resolve().parents[1]
# the small scene of the Slurm test (one map tile): every check here is about the workflow's
# files, not the registration, and A and B run it whole, three times in all (config/test.yaml's
# 2 x 2 tiles and 300 x 360 queries: a setup of 227 s alone, 321 s in CI; this scene 190; 267 s)
SMALL_CONFIG = REPO / "tests" / "data" / "slurm_small.yaml"
pytestmark = pytest.mark.slow

#: JSON keys that hold wall-clock times (differ between runs by nature)
TIMING_KEYS = {"seconds", "timings_s", "build_seconds", "rank_s"}
#: files that print wall-clock times (the report page and its summary table)
TIMED_FILES = {"results/report/index.html", "results/report/summary.csv"}
CACHE = "results/cache/"  # what the register sources keep between queries: not a product


def smk_cmd(workdir: Path, cfg: Path, *args: str) -> list[str]:
    return [
        sys.executable, "-m", "snakemake", "-s", str(REPO / "Snakefile"), "-d", str(workdir),
        "--configfile", str(cfg), *args,
    ]  # fmt: skip


def smk(workdir: Path, cfg: Path, *args: str) -> subprocess.CompletedProcess:
    return subprocess.run(
        smk_cmd(workdir, cfg, *args), capture_output=True, text=True, timeout=600, cwd=workdir
    )


def _timing(key: str) -> bool:
    return key in TIMING_KEYS or key.endswith("_s") or key.startswith("seconds_")


def _strip(obj):
    """JSON without timing keys; floats to 6 significant digits (a multi-threaded k-means
    objective differs in the 7th: a diagnostic, the centroids themselves are byte-identical)."""
    if isinstance(obj, dict):
        return {k: _strip(v) for k, v in obj.items() if not _timing(k)}
    if isinstance(obj, list):
        return [_strip(v) for v in obj]
    if isinstance(obj, float):
        return float(f"{obj:.6g}")
    return obj


def fingerprint(path: Path) -> str:
    """Hash of a product; JSON without its timing keys; a GeoPackage by its tables' rows (its
    ``gpkg_contents.last_change`` is the time of writing, as the standard asks); a LAS/LAZ file
    without its header's creation date (the day of writing)."""
    if path.suffix == ".json":
        data = _strip(json.loads(path.read_text()))
        return hashlib.sha256(json.dumps(data, sort_keys=True).encode()).hexdigest()
    if path.suffix == ".gpkg":
        return gpkg_digest(path)
    if path.suffix in (".las", ".laz"):
        return las_digest(path)
    return hashlib.sha256(path.read_bytes()).hexdigest()


def products(work: Path) -> dict[str, str]:
    out = {}
    for p in sorted((work / "results").rglob("*")):
        rel = str(p.relative_to(work))
        if p.is_file() and rel not in TIMED_FILES and not rel.startswith(CACHE):
            out[rel] = fingerprint(p)
    return out


def demo_config(work: Path) -> Path:
    """The small demo plus its `outside` query (nothing to register it), a query of one constant
    value and an all-zero float query (no features at all)."""
    (work / "inputs").mkdir(parents=True)
    cube = np.full((5, 120, 100), 500, np.uint16)
    write_envi(
        work / "inputs" / "flat", cube, "bil",
        extra="wavelength units = nm\nwavelength = {900, 1100, 1200, 1500, 1700}\n",
    )  # fmt: skip
    write_envi(
        work / "inputs" / "zero", np.zeros((5, 120, 100), np.float32), "bil",
        extra="wavelength units = nm\nwavelength = {900, 1100, 1200, 1500, 1700}\n",
    )  # fmt: skip
    cfg = yaml.safe_load(SMALL_CONFIG.read_text())
    demo = cfg["queries"]["demo"]
    cfg["queries"]["outside"] = {
        **demo, "image": "results/demo/queries/outside.hdr",
        "truth": "results/demo/queries/outside_truth.tif",
    }  # fmt: skip
    cfg["queries"]["flat"] = {"image": "inputs/flat.hdr", "band": "1200nm", "gsd_m": 0.8}
    cfg["queries"]["zero"] = {"image": "inputs/zero.hdr", "band": "1200nm", "gsd_m": 0.8}
    p = work / "config.yaml"
    p.write_text(yaml.safe_dump(cfg))
    return p


def map_config(work: Path) -> Path:
    """A different config: map only, synthetic, every path with spaces and accents."""
    d = work / "entrées ü"
    d.mkdir(parents=True)
    ortho = make_ortho(d / "ortho été.tif")
    las = make_las(d / "nuage ß.laz", scene_points(density=0.5))
    cfg = {
        "map": {"orthophoto": str(ortho.relative_to(work)), "lidar": [str(las.relative_to(work))]},
        "queries": {},
        "map_prep": {"tile_size_px": 128, "tile_overlap_px": 16},
    }
    p = work / "ma config.yaml"
    p.write_text(yaml.safe_dump(cfg, allow_unicode=True))
    return p


def _tail(path: Path, n: int = 4000) -> str:
    return path.read_text(errors="replace")[-n:] if path.exists() else f"({path} missing)"


def _ps() -> str:
    """The machine's busiest processes (a hung run says what it waits on, and what loads it)."""
    try:
        return subprocess.run(["ps", "-eo", "pid,ppid,stat,etime,time,pcpu,args", "--sort=-pcpu"],
                              capture_output=True, text=True, timeout=10).stdout[:4000]  # fmt: skip
    except (OSError, subprocess.SubprocessError) as e:
        return f"(ps failed: {e})"


@pytest.fixture(scope="module")
def runs(tmp_path_factory):
    root = tmp_path_factory.mktemp("reliability")
    a, b, c = root / "run A", root / "run B", root / "run C é ü"
    cfg_a, cfg_b, cfg_c = demo_config(a), demo_config(b), map_config(c)
    log = {k: open(root / f"{k}.log", "w") for k in "abc"}  # noqa: SIM115
    pa = subprocess.Popen(
        smk_cmd(a, cfg_a, "--cores", "1"), cwd=a, stdout=log["a"], stderr=log["a"]
    )
    pc = subprocess.Popen(
        smk_cmd(c, cfg_c, "--cores", "1", "results/map/overview.png"), cwd=c,
        stdout=log["c"], stderr=log["c"],
    )  # fmt: skip
    pb = subprocess.Popen(
        smk_cmd(b, cfg_b, "--cores", "1"), cwd=b, stdout=log["b"], stderr=log["b"],
        start_new_session=True,
    )  # fmt: skip
    # SIGKILL B (snakemake and its job) once a map_tile_elevation job is reading LiDAR
    t0, killed_in = time.time(), None
    while time.time() - t0 < 400 and pb.poll() is None:
        logs = list((b / "logs" / "map" / "map_tile_elevation").glob("*.log"))
        started = [p for p in logs if "CRS from header" in p.read_text()]
        if started:
            time.sleep(0.5)
            killed_in = started[0].stem
            os.killpg(pb.pid, signal.SIGKILL)
            break
        time.sleep(0.1)
    pb.wait()
    left = {
        str(p.relative_to(b)): p.read_bytes() for p in (b / "results").rglob("*") if p.is_file()
    }
    for k, p in (("a", pa), ("c", pc)):
        try:
            p.wait(timeout=900)
        except subprocess.TimeoutExpired:
            for q in (pa, pc):
                q.kill()
            for f in log.values():
                f.close()
            pytest.fail(f"run {k.upper()} still running after 900 s; its log ends:\n"
                        + _tail(root / f"{k}.log") + "\nprocesses:\n" + _ps())  # fmt: skip
    for f in log.values():
        f.close()
    # rerun B: after a crash Snakemake's lock stays, so --unlock first; the killed job reruns
    unlock = smk(b, cfg_b, "--unlock", "--cores", "1")
    rerun = smk(b, cfg_b, "--cores", "2", "--rerun-incomplete")
    return {
        "root": root, "a": a, "b": b, "c": c, "codes": (pa.returncode, pc.returncode),
        "killed_in": killed_in, "left": left, "unlock": unlock, "rerun": rerun,
    }  # fmt: skip


def test_concurrent_runs_in_one_checkout_do_not_clobber(runs):
    assert runs["codes"] == (0, 0), (runs["root"] / "a.log").read_text()[-3000:] + (
        runs["root"] / "c.log"
    ).read_text()[-3000:]
    assert (runs["c"] / "results/map/overview.png").exists()
    assert not (runs["c"] / "results/demo").exists()  # C has only its own (map-only) products
    assert not (runs["a"] / "entrées ü").exists()
    # with --directory nothing lands in the checkout (no run but these has a query "flat")
    assert not (REPO / "results" / "queries" / "flat").exists()
    for w in ("a", "c"):
        assert not list(runs[w].glob("results/**/.*.tmp-*")), w


def test_paths_with_spaces_and_non_ascii_run(runs):
    vrt = (runs["c"] / "results/map/mosaic/ortho.vrt").read_text()
    assert "ortho été.tif" not in vrt  # VRT points at the tiles, relative, not at the source
    import rasterio

    with rasterio.open(runs["c"] / "results/map/mosaic/dsm.vrt") as v:
        assert v.read(1, masked=True).count() > 0


def test_sigkill_mid_rule_leaves_no_plausible_partial_file(runs):
    assert runs["killed_in"], "map_tile_elevation never started in run B"
    a = runs["a"]
    for rel, data in runs["left"].items():
        name = Path(rel).name
        if name.startswith("."):
            continue  # a hidden temporary (.name.tmp-PID.ext): never taken for a product
        assert (a / rel).exists(), rel
        if rel.endswith(".json"):
            assert _strip(json.loads(data)) == _strip(json.loads((a / rel).read_text())), rel
        else:
            assert data == (a / rel).read_bytes(), f"{rel} left partial by the kill"


def test_rerun_after_kill_completes_identically(runs):
    assert runs["unlock"].returncode == 0, runs["unlock"].stderr[-2000:]
    assert runs["rerun"].returncode == 0, runs["rerun"].stderr[-3000:]
    pa, pb = products(runs["a"]), products(runs["b"])
    assert pa.keys() == pb.keys()
    differ = [k for k in pa if pa[k] != pb[k]]
    assert not differ, differ  # same seed: same registration, products, figures, LAZ
    assert not list(runs["b"].glob("results/**/.*.tmp-*"))  # stale temporaries cleaned


def test_repeatable_registration_and_versions_in_report(runs):
    a, b = runs["a"], runs["b"]
    for name in ("demo", "outside"):
        ra = json.loads((a / f"results/queries/{name}/registration.json").read_text())
        rb = json.loads((b / f"results/queries/{name}/registration.json").read_text())
        assert _strip(ra) == _strip(rb)
        assert ra["software"]["opencv-python-headless"] == metadata.version("opencv-python-headless")
    html = (a / "results/report/index.html").read_text()
    assert "software versions" in html
    for pkg in ("numpy", "opencv-python-headless", "faiss-cpu", "GDAL", "PROJ", "snakemake"):
        assert f">{pkg}<" in html, pkg


@pytest.mark.parametrize("name", ["flat", "zero"])
def test_constant_query_is_not_found_with_reason(runs, name):
    reg = json.loads((runs["a"] / f"results/queries/{name}/registration.json").read_text())
    assert reg["status"] == "not_found"
    assert reg["reason"]
    prod = json.loads((runs["a"] / f"results/products/{name}/products.json").read_text())
    assert prod["status"] == "not_found" and prod["files"] == {}


# ---------------------------------------------------------------- bad inputs, one line each


def _expect_failure(
    proc, path: str, problem: str, missing: list[Path], before_run: bool = False
) -> None:
    """One line naming the file and the problem, no traceback, none of ``missing`` written.

    ``before_run``: the input check of the config (headers only) finds it, so the run stops in a
    list of problems before any job starts; otherwise the rule that reads the pixels reports it.
    """
    err = proc.stderr
    assert proc.returncode != 0
    line = f"{path}: {problem}"
    if before_run:
        assert "problem(s) with the inputs, nothing was started" in err, err[-3000:]
        hits = [ln for ln in err.splitlines() if ln.startswith("  - ") and line in ln]
        assert "Select jobs to execute" not in err, err[-3000:]
    else:
        hits = [ln for ln in err.splitlines() if ln.startswith("georeg error in rule") and line in ln]
    assert hits, err[-3000:]
    assert "Traceback" not in err, err[-3000:]
    for m in missing:
        assert not m.exists(), m


def _map_case(tmp: Path, ortho: Path, lidar: list[Path], target: str):
    cfg = {
        "map": {"orthophoto": ortho.name, "lidar": [p.name for p in lidar]},
        "queries": {},
        "map_prep": {"tile_size_px": 256, "tile_overlap_px": 16},
    }
    p = tmp / "c.yaml"
    p.write_text(yaml.safe_dump(cfg))
    return smk(tmp, p, "--cores", "1", target)


def test_workflow_truncated_orthophoto(tmp_path):
    import rasterio
    from rasterio.transform import from_origin

    o = tmp_path / "trunc ortho.tif"
    with rasterio.open(
        o, "w", driver="GTiff", width=400, height=400, count=3, dtype="uint8",
        crs="EPSG:32611", transform=from_origin(500000, 3760000, 1, 1), compress="deflate",
        tiled=True,
    ) as ds:  # fmt: skip
        ds.write(np.random.default_rng(0).integers(0, 255, (3, 400, 400), dtype=np.uint8))
    o.write_bytes(o.read_bytes()[: o.stat().st_size // 2])
    tile = "results/map/tiles/r001_c001/ortho.tif"  # its blocks lie in the missing half
    r = _map_case(tmp_path, o, [], tile)
    _expect_failure(r, o.name, "", [tmp_path / tile])
    assert "truncated or corrupt" in r.stderr


def test_workflow_orthophoto_without_crs(tmp_path):
    o = make_ortho(tmp_path / "ortho.tif", crs=None)
    r = _map_case(tmp_path, o, [], "results/map/grid.json")
    _expect_failure(
        r, "ortho.tif", "raster has no CRS", [tmp_path / "results/map/grid.json"], before_run=True
    )


def test_workflow_laz_with_zero_points(tmp_path):
    o = make_ortho(tmp_path / "ortho.tif")
    empty = make_las(tmp_path / "empty.laz", {k: v[:0] for k, v in scene_points(0.01).items()})
    r = _map_case(tmp_path, o, [empty], "results/map/tiles/r000_c000/dsm.tif")
    tile = tmp_path / "results/map/tiles/r000_c000"
    _expect_failure(
        r, "empty.laz", "point cloud is empty (0 points)",
        [tile / f"{n}.tif" for n in ("dsm", "dtm", "ndsm", "density")] + [tile / "points.laz"],
        before_run=True,
    )  # fmt: skip


def test_workflow_laz_truncated_in_the_middle(tmp_path):
    """Issue 30: half a LAZ is refused by the input check, before any job starts."""
    o = make_ortho(tmp_path / "ortho.tif")
    good = make_las(tmp_path / "full.laz", scene_points(density=0.5))
    cut = tmp_path / "cut.laz"
    cut.write_bytes(good.read_bytes()[: good.stat().st_size // 2])
    r = _map_case(tmp_path, o, [cut], "results/map/tiles/r000_c000/dsm.tif")
    tile = tmp_path / "results/map/tiles/r000_c000"
    _expect_failure(
        r, "cut.laz", "file is truncated", [tile / "dsm.tif", tile / "points.laz"], before_run=True
    )

def test_workflow_bad_query_cubes(tmp_path):
    """Six bad cubes and a missing orthophoto: all listed in one message before any job starts."""
    rng = np.random.default_rng(0)
    cube = rng.integers(1, 1000, (5, 40, 30)).astype(np.uint16)
    wl = "wavelength units = nm\nwavelength = {900, 1100, 1200, 1500, 1700}\n"
    write_envi(tmp_path / "short cube", cube, "bil", extra=wl)
    short = tmp_path / "short cube.bil"
    short.write_bytes(short.read_bytes()[:-64])
    write_envi(tmp_path / "gz", cube, "bsq", extra=wl + "file compression = 1\n")
    gz = tmp_path / "gz.bil"
    gz.write_bytes(__import__("gzip").compress(gz.read_bytes()))
    write_envi(tmp_path / "nowl", cube, "bil")
    write_envi(tmp_path / "swir", cube, "bil", extra=wl)
    (tmp_path / "nodata.hdr").write_text("ENVI\nsamples = 3\nlines = 3\nbands = 1\ndata type = 1\n")
    queries = {
        "short": ("short cube.hdr", "1200nm", "short cube.bil", "data file is"),
        "gz": ("gz.hdr", "1200nm", "gz.hdr", "the data file is gzip-compressed"),
        "nowl": ("nowl.hdr", "1200nm", "nowl.hdr", "cannot select 1200 nm: the image has no wavelengths"),
        "far": ("swir.hdr", "2400nm", "swir.hdr", "wavelength 2400 nm is outside the cube"),
        "idx": ("swir.hdr", 9, "swir.hdr", "band index 9 does not exist"),
        "nodata": ("nodata.hdr", 0, "nodata.hdr", "no ENVI data file next to the header"),
    }  # fmt: skip
    cfg = {
        "map": {"orthophoto": "none.tif"},
        "queries": {k: {"image": v[0], "band": v[1], "gsd_m": 0.8} for k, v in queries.items()},
    }
    p = tmp_path / "q.yaml"
    p.write_text(yaml.safe_dump(cfg))
    targets = [f"results/queries/{k}/band.tif" for k in queries]
    r = smk(tmp_path, p, "--cores", "1", "-k", *targets)
    for k, (_, _, path, problem) in queries.items():
        _expect_failure(
            r, path, problem,
            [tmp_path / f"results/queries/{k}/band.tif", tmp_path / f"results/queries/{k}/band.json"],
            before_run=True,
        )  # fmt: skip
    assert "map.orthophoto: none.tif: file not found" in r.stderr  # every problem in one list
