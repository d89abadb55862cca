"""The workflow end to end on the tiny demo (config/test.yaml), and its configuration contract."""

from __future__ import annotations

import json
import re
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import rasterio
from rasterio.transform import from_origin

from georeg.register.geolocation import evaluate

REPO = Path(__file__).resolve().parents[1]
TEST_CONFIG = REPO / "config" / "test.yaml"


def snakemake(workdir: Path, *args: str, timeout: int = 1500) -> subprocess.CompletedProcess:
    cmd = [sys.executable, "-m", "snakemake", "-s", str(REPO / "Snakefile"), "-d", str(workdir)]
    return subprocess.run(
        cmd + list(args), capture_output=True, text=True, timeout=timeout, cwd=workdir
    )


@pytest.fixture(scope="module")
def demo_run(tmp_path_factory) -> Path:
    """`snakemake --cores 2` (rule all) on the tiny demo, once for the module."""
    work = tmp_path_factory.mktemp("demo_run")
    proc = snakemake(work, "--cores", "2", "--configfile", str(TEST_CONFIG))
    assert proc.returncode == 0, proc.stderr[-4000:]
    return work


@pytest.mark.slow
def test_demo_query_registered_to_a_pixel(demo_run):
    reg = json.loads((demo_run / "results/queries/demo/registration.json").read_text())
    assert reg["status"] == "registered"
    # the tiny demo query (300 x 360 px, about 500 features) is too small to split: part 0
    # searched it whole, the part 1 job stayed idle, and registration.json says why
    assert reg["split"]["parts"] == 1 and "whole query" in reg["split"]["reason"]
    assert reg["split"]["idle_part_jobs"] == [1] and len(reg["parts"]) == 1
    assert reg["parts"][0]["rows"] == [0, reg["height"]]
    assert all((demo_run / f"results/queries/demo/parts/part_{i}.json").exists() for i in (0, 1))
    # `bands: auto` (the default): the demo cube's 1200 nm band pooled with its 2200 nm band
    nm = [b["wavelength_nm"] for b in reg["pooled_bands"]]
    # the tiny demo cube has 40 bands 41 nm apart
    assert len(nm) == 2 and abs(nm[0] - 1200) < 30 and abs(nm[1] - 2200) < 30
    with rasterio.open(demo_run / "results/queries/demo/band.tif") as src:
        assert src.count == 2
    # independent check against the dense truth, through the written geolocation raster
    with rasterio.open(demo_run / "results/queries/demo/geolocation.tif") as src:
        geo = src.read()
    with rasterio.open(demo_run / "results/demo/queries/demo_truth.tif") as src:
        truth = src.read()
    err = np.hypot(geo[0] - truth[0], geo[1] - truth[1])
    assert np.median(err) < 1.0  # map pixels are 1 m
    assert np.isfinite(geo[2]).mean() > 0.99  # every pixel got an elevation
    # geolocation.tif holds the locally refined geometry (issue 12); the homography is the
    # global one, evaluated in evaluation_global
    stats = evaluate(np.array(reg["homography"]), demo_run / "results/demo/queries/demo_truth.tif", 1.0)
    assert reg["evaluation_global"]["m"]["median"] == pytest.approx(stats["m"]["median"], rel=1e-6)
    assert reg["evaluation"]["m"]["median"] == pytest.approx(np.median(err), rel=1e-3)
    assert reg["refine"]["model"] != "homography"
    assert np.median(err) < stats["m"]["median"]
    # the map has LiDAR: the fused registration was checked against the DSM and agrees with it
    assert reg["lidar_check"]["mode"] == "record"
    assert reg["lidar_check"]["outcome"] == "agrees", reg["lidar_check"]


@pytest.mark.slow
def test_outside_query_not_found(demo_run):
    reg = json.loads((demo_run / "results/queries/outside/registration.json").read_text())
    assert reg["status"] == "not_found"
    assert reg["reason"]
    manifest = json.loads((demo_run / "results/products/outside/products.json").read_text())
    assert manifest["status"] == "not_found"


@pytest.mark.slow
def test_products_and_overview_written(demo_run):
    manifest = json.loads((demo_run / "results/products/demo/products.json").read_text())
    assert manifest["status"] == "registered"
    assert (demo_run / "results/map/overview.png").stat().st_size > 10_000
    with rasterio.open(demo_run / "results/map/mosaic/dsm.vrt") as src:
        assert src.crs.to_epsg() == 32611


@pytest.mark.slow
def test_map_view_of_the_run(demo_run, tmp_path):
    """results/report/map.html: linked from index.html, the query drawn where it registered, and
    (with Chromium) rendered with its layers and no console error."""
    import re

    import cv2

    report = demo_run / "results/report"
    assert 'href="map.html"' in (report / "index.html").read_text()
    page = (report / "map.html").read_text()
    data = json.loads(re.search(r'id="map-data">(.*?)</script>', page, re.S)[1])
    drawn = {q["name"]: q for q in data["queries"]}
    assert drawn["demo"]["status"] == "registered" and drawn["demo"]["overlay"]
    assert drawn["outside"]["status"] == "not_found" and drawn["outside"]["overlay"] is None
    assert (report / drawn["demo"]["overlay"]["src"]).is_file()
    kinds = [f["properties"]["kind"] for f in data["features"]["features"]]
    assert kinds.count("query_footprint") == 1 and kinds.count("query_truth") == 2
    if not Path("/usr/bin/chromium").exists():
        pytest.skip("/usr/bin/chromium is absent")
    from chromium_cdp import HeadlessChromium

    with HeadlessChromium(tmp_path / "profile", 1200, 800) as b:
        b.open((report / "map.html").resolve().as_uri())
        b.wait_for("document.body.dataset.ready === '1' && document.body.dataset.ortho === 'loaded'")
        shot = cv2.imdecode(np.frombuffer(b.screenshot(), np.uint8), cv2.IMREAD_COLOR)
        assert shot.std() > 25
        assert b.evaluate("document.querySelectorAll('path.georeg-query_footprint').length") == 1
        assert b.evaluate("document.querySelectorAll('img.georeg-query-image').length") == 1
        assert b.errors() == []


@pytest.mark.slow
def test_second_run_has_nothing_to_do(demo_run):
    proc = snakemake(demo_run, "-n", "--cores", "2", "--configfile", str(TEST_CONFIG))
    assert proc.returncode == 0, proc.stderr[-2000:]
    assert "Nothing to be done" in proc.stdout + proc.stderr


@pytest.mark.slow
def test_changed_matching_parameter_reruns_registration_only(demo_run, tmp_path):
    extra = tmp_path / "ratio.yaml"
    extra.write_text("register:\n  ratio: 0.75\n")
    proc = snakemake(
        demo_run, "-n", "--cores", "2", "--configfile", str(TEST_CONFIG), str(extra)
    )
    out = proc.stdout + proc.stderr
    assert proc.returncode == 0, out[-2000:]
    assert "search_part" in out
    for rule in (
        "demo_scene", "map_tile_ortho", "tile_features", "vocabulary", "word_quantizer",
        "tile_words", "build_index",
    ):  # fmt: skip
        assert f"rule {rule}:" not in out and f"\n{rule} " not in out, rule



@pytest.mark.slow
def test_snakemake_report_without_cores_has_figures_and_captions(demo_run):
    """`snakemake --report report.zip` as the Snakemake docs show it (no --cores) after a run:
    the zip holds every report figure, and every figure's caption is in the report."""
    import zipfile

    proc = snakemake(demo_run, "--report", "report.zip", "--configfile", str(TEST_CONFIG))
    assert proc.returncode == 0, (proc.stdout + proc.stderr)[-3000:]
    with zipfile.ZipFile(demo_run / "report.zip") as z:
        names = z.namelist()
        text = "".join(z.read(n).decode("utf-8", "replace") for n in names
                       if n.endswith((".html", ".js")))  # fmt: skip
    figures = sorted((demo_run / "results/report/figures/demo").glob("*.png"))
    assert figures and (demo_run / "results/map/overview.png").exists()
    for fig in [*figures, demo_run / "results/map/overview.png"]:
        assert any(n.endswith(fig.name) for n in names), (fig.name, names[:20])
    for rst in ("overview", "query_figures", "index_html", "summary"):
        caption = (REPO / "workflow" / "report" / f"{rst}.rst").read_text()
        assert f'"caption": "<p>{" ".join(caption.split()[:3])}' in text, rst  # rendered in
    # every report() output of the workflow has a caption
    calls = [c for f in sorted((REPO / "workflow" / "rules").glob("*.smk"))
             for c in report_calls(f.read_text())]  # fmt: skip
    assert len(calls) >= 4 and all("caption=" in c for c in calls), calls


def report_calls(text: str) -> list[str]:
    """The argument text of every ``report(...)`` call in a rule file."""
    out = []
    for m in re.finditer(r"\breport\(", text):
        depth, k = 1, m.end()
        while depth:
            depth += {"(": 1, ")": -1}.get(text[k], 0)
            k += 1
        out.append(text[m.end() : k - 1])
    return out


def _write_ortho(path: Path, crs: str | None = "EPSG:32633") -> None:
    rng = np.random.default_rng(0)
    data = rng.integers(0, 255, (3, 64, 64), dtype=np.uint8)
    with rasterio.open(
        path, "w", driver="GTiff", width=64, height=64, count=3, dtype="uint8",
        crs=crs, transform=from_origin(360000, 5800000, 1.0, 1.0),
    ) as dst:  # fmt: skip
        dst.write(data)


def test_user_config_replaces_demo_map_and_queries(tmp_path):
    """A user's map/queries replace the demo's wholesale: no demo LiDAR, no demo queries."""
    _write_ortho(tmp_path / "my ortho.tif")
    _write_ortho(tmp_path / "mine.tif")  # inputs are opened before the run: they must exist
    (tmp_path / "my.yaml").write_text(
        "map:\n  orthophoto: my ortho.tif\n"
        "queries:\n  mine:\n    image: mine.tif\n"
        "register:\n  ratio: 0.8\n"
    )
    my = str(tmp_path / "my.yaml")
    proc = snakemake(tmp_path, "-n", "--cores", "1", "--configfile", my)
    out = proc.stdout + proc.stderr
    assert proc.returncode == 0, out[-2000:]
    assert "demo_scene" not in out and "results/demo" not in out  # no demo LiDAR, no demo scene
    # the user's query is planned from the user's image...
    proc = snakemake(tmp_path, "results/queries/mine/band.tif", "-n", "--configfile", my)
    assert "mine.tif" in proc.stdout + proc.stderr  # planned
    # ...and the demo's queries are gone, not merged in
    for name in ("demo", "outside"):
        proc = snakemake(tmp_path, f"results/queries/{name}/band.tif", "-n", "--configfile", my)
        assert proc.returncode != 0, name


def test_schema_rejects_unknown_key_naming_it(tmp_path):
    (tmp_path / "bad.yaml").write_text("register:\n  ratoi: 0.8\n")
    proc = snakemake(tmp_path, "-n", "--cores", "1", "--configfile", str(tmp_path / "bad.yaml"))
    assert proc.returncode != 0
    assert "ratoi" in proc.stdout + proc.stderr


def test_schema_rejects_wrong_type_naming_it(tmp_path):
    (tmp_path / "bad.yaml").write_text("map_prep:\n  tile_size_px: big\n")
    proc = snakemake(tmp_path, "-n", "--cores", "1", "--configfile", str(tmp_path / "bad.yaml"))
    assert proc.returncode != 0
    assert "tile_size_px" in proc.stdout + proc.stderr or "'big'" in proc.stdout + proc.stderr


def test_lint_clean_but_for_conda_advice(tmp_path):
    """`snakemake --lint` finds nothing but its conda/container advice (no envs by design)."""
    proc = snakemake(tmp_path, "--lint", "--configfile", str(TEST_CONFIG))
    out = proc.stdout + proc.stderr
    titles = {ln.strip() for ln in out.splitlines() if ln.strip().startswith("* ")}
    assert titles, out[-2000:]  # the linter ran and printed its findings
    assert titles <= {"* Specify a conda environment or container for each rule.:"}, titles
