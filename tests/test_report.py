"""The report: figures and the self-contained HTML page, built from a synthetic run in tmp.

The fixture writes what the registration stage would (registration.json, parts, band.tif,
geolocation.tif, truth) for two queries, one registered and one not found, on a small synthetic
map, then runs the report's library functions; no Snakemake run is needed.
"""

from __future__ import annotations

import base64
import json
import re
import shutil
import subprocess
import warnings
from html.parser import HTMLParser
from pathlib import Path

import cv2
import numpy as np
import pytest
import rasterio
from rasterio.crs import CRS
from rasterio.transform import Affine

from georeg.register.geolocation import map_xy, write_geolocation
from georeg.report.evaluation import run_evaluate_query
from georeg.report.figures import load_query_data, make_query_figures
from georeg.report.html import (
    level_text,
    parse_timings,
    pooled_text,
    query_seconds,
    run_report,
    sources_text,
)

PNG_MAGIC = b"\x89PNG\r\n\x1a\n"
CHROMIUM = Path("/usr/bin/chromium")
MAP_T = Affine(1.0, 0, 400_000.0, 0, -1.0, 5_000_600.0)  # 600 x 600 px at 1 m
QW, QH = 160, 200


def _map_image(rng: np.random.Generator) -> np.ndarray:
    """A textured RGB map: smooth noise plus bright 'roofs' and dark 'roads'."""
    base = cv2.GaussianBlur(rng.random((600, 600)).astype(np.float32), (0, 0), 6)
    base = (base - base.min()) / (np.ptp(base) + 1e-9) * 120 + 60
    for _ in range(140):
        x, y = rng.integers(0, 580, 2)
        w, h = rng.integers(6, 24, 2)
        base[y : y + h, x : x + w] = rng.choice([30.0, 220.0])
    rgb = np.stack([base, base * 0.9 + 10, base * 0.8 + 20]).clip(0, 255).astype(np.uint8)
    return rgb


def _h_true(x0: float, y0: float, angle: float) -> np.ndarray:
    a = np.deg2rad(angle)
    g = 0.8
    return np.array(
        [[g * np.cos(a), -g * np.sin(a), x0], [-g * np.sin(a), -g * np.cos(a), y0], [0, 0, 1.0]]
    )


def _write(path: Path, data: np.ndarray, **kw) -> None:
    prof = {"driver": "GTiff", "width": data.shape[-1], "height": data.shape[-2]}
    prof.update(count=1 if data.ndim == 2 else data.shape[0], dtype=str(data.dtype), **kw)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        with rasterio.open(path, "w", **prof) as ds:
            ds.write(data if data.ndim == 3 else data[None])


def _band_from_map(gray: np.ndarray, H: np.ndarray) -> np.ndarray:
    """The query band a sensor with query->map homography H would see (0 outside the map)."""
    to_px = np.array([[1, 0, -MAP_T.c - 0.5], [0, -1, MAP_T.f - 0.5], [0, 0, 1.0]])
    A = to_px @ H  # query px -> map px (1 m pixels)
    b = cv2.warpPerspective(
        gray, A, (QW, QH), flags=cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP, borderValue=0
    )
    return np.clip(b, 1, 255).astype(np.uint8) * (b > 0)


def _candidates(centres: list[tuple[float, float]], winner: int | None) -> list[dict]:
    out = []
    for i, (x, y) in enumerate(centres):
        out.append(
            {
                "bounds": [x - 150, y - 150, x + 150, y + 150],
                "centre": [x, y],
                "score": 0.9 - 0.1 * i,
                "rank": i,
                "inliers": 30 if i == winner else 3 + i,
                "accepted": i == winner,
            }
        )
    return out


@pytest.fixture(scope="module")
def run_dir(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A synthetic results/ tree with two queries, evaluated, drawn and reported."""
    root = tmp_path_factory.mktemp("report_run")
    rng = np.random.default_rng(3)
    rgb = _map_image(rng)
    crs = CRS.from_epsg(32633)
    (root / "map").mkdir()
    _write(root / "map/ortho.tif", rgb, crs=crs, transform=MAP_T)
    ndsm = cv2.GaussianBlur(rng.random((600, 600)).astype(np.float32), (0, 0), 4) * 30
    _write(root / "map/ndsm.tif", ndsm, crs=crs, transform=MAP_T, nodata=-9999.0)
    grid = {
        "crs": crs.to_wkt(),
        "transform": list(MAP_T)[:6],
        "width": 600,
        "height": 600,
        "tiles": {},
    }
    (root / "map/grid.json").write_text(json.dumps(grid))
    gray = cv2.cvtColor(np.moveaxis(rgb, 0, -1), cv2.COLOR_RGB2GRAY)
    queries = {
        "good": _h_true(400_150.0, 5_000_480.0, 20.0),
        "lost": _h_true(403_000.0, 5_003_000.0, -10.0),  # 3 km away: not on the map
    }
    for name, Ht in queries.items():
        q = root / "queries" / name
        (q / "parts").mkdir(parents=True)
        band = (
            _band_from_map(gray, Ht) if name == "good" else rng.integers(1, 255, (QH, QW), np.uint8)
        )
        _write(q / "band.tif", band, nodata=0)
        x, y = map_xy(Ht, QW, QH)
        _write(q / "truth.tif", np.stack([x, y]))
        found = name == "good"
        H = np.array([[1, 0, 0.6], [0, 1, -0.4], [0, 0, 1.0]]) @ Ht if found else None
        parts, reg_parts = [], []
        for i in range(2):
            r0, r1 = i * QH // 2, (i + 1) * QH // 2
            Hp = (np.array([[1, 0, 1.5 * (i + 1)], [0, 1, 0], [0, 0, 1.0]]) @ Ht) if found else None
            qxy = np.c_[rng.uniform(0, QW, 25), rng.uniform(r0, r1, 25)]
            p = {
                "part": i,
                "strategy": "index",
                "rows": [r0, r1],
                "candidates_available": 8,
                "candidates_tried": 3,
                "candidates": _candidates(
                    [(400_300.0, 5_000_300.0), (400_100.0, 5_000_450.0), (400_450.0, 5_000_150.0)],
                    1 if found else None,
                ),
                "accepted": found,
                "homography": None if Hp is None else Hp.tolist(),
                "inliers": 30 if found else 0,
                "seconds": 2.5 + i,
            }
            if found:
                p["inlier_query_xy"] = qxy.tolist()
                p["inlier_map_xy"] = np.c_[map_xy_pts(Ht, qxy)].tolist()
            parts.append(p)
            (q / "parts" / f"part_{i}.json").write_text(json.dumps(p))
            reg_parts.append(
                {
                    k: p[k]
                    for k in (
                        "part",
                        "rows",
                        "accepted",
                        "candidates_tried",
                        "inliers",
                        "homography",
                        "seconds",
                    )
                }
            )
        reg = {
            "status": "registered" if found else "not_found",
            "query": f"{name}.hdr",
            "band": {"index": 120, "wavelength_nm": 1201.5},
            "width": QW,
            "height": QH,
            "crs": crs.to_wkt(),
            "homography": None if H is None else H.tolist(),
            "inliers": 57 if found else 0,
            "matches": 80 if found else None,
            "residual_px": 0.9 if found else None,
            "log10_nfa": -40.2 if found else None,
            "strategy": "index",
            "acceptance": "nfa",
            "map_px_m": 1.0,
            "candidates_tried": 6,
            "lidar_check": {"outcome": "agrees", "coherent": 0.2} if found else None,
            "parts": reg_parts,
            "fuse": {"method": "fused"} if found else {"parts_accepted": []},
            "timings_s": {
                "query_band": 1.25,
                "search_parts": {"0": 2.5, "1": 3.5},
                "fuse_total": 4.0 if found else 0.5,
            },
        }
        if not found:
            reg["reason"] = "part 0: 3 candidate(s) tried, none accepted; part 1: 3 ..."
        (q / "registration.json").write_text(json.dumps(reg))
        products = labels = None
        if found:  # a products stage output: segmentation in query geometry + its manifest
            # georeg.products.segmentation classes: 4 = grass, 5 = road / bare; demo labels 5 -> 4, 1 -> 5
            seg = np.where(band > 128, 4, 5).astype(np.uint8) * (band > 0)
            seg[:20] = np.where(band[:20] > 0, 1, 0)  # some wrong pixels: "tall building"
            _write(q / "segmentation.tif", seg, nodata=0)
            with rasterio.open(q / "segmentation.tif", "r+") as ds:
                ds.write_colormap(
                    1, {1: (200, 40, 40, 255), 4: (130, 210, 90, 255), 5: (150, 150, 150, 255)}
                )
            _write(q / "labels.tif", np.where(band > 128, 5, 1).astype(np.uint8), nodata=0)
            (q / "products.json").write_text(
                json.dumps(
                    {
                        "status": "registered",
                        "files": {"segmentation": "segmentation.tif"},
                        "segmentation": {
                            "classes": {"1": "tall building", "4": "grass", "5": "road / bare"}
                        },
                    }
                )
            )
            products, labels = q / "products.json", q / "labels.tif"
        write_geolocation(q / "geolocation.tif", H, QW, QH, root / "map/ndsm.tif", crs.to_wkt())
        run_evaluate_query(
            q / "registration.json",
            q / "geolocation.tif",
            q / "truth.tif",
            root / "map/grid.json",
            {"success_error_px": 3.0},
            q / "evaluation.json",
            labels=labels,
            products=products,
        )
        data = load_query_data(
            name,
            q / "registration.json",
            q / "band.tif",
            sorted((q / "parts").glob("part_*.json")),
            root / "map/ortho.tif",
            ndsm=root / "map/ndsm.tif",
            evaluation=q / "evaluation.json",
            truth=q / "truth.tif",
            geolocation=q / "geolocation.tif",
            products=products,
            labels=labels,
        )
        make_query_figures(data, root / "figures" / name, {"figure_dpi": 50})
    logs = root / "logs" / "register" / "fuse_parts"
    logs.mkdir(parents=True)
    (logs / "good.log").write_text("x INFO georeg: rule fuse_parts done in 4.0 s\n")
    (logs / "lost.log").write_text("x INFO georeg: rule fuse_parts done in 0.5 s\n")
    bench = root / "benchmarks" / "map"
    bench.mkdir(parents=True)
    (bench / "map_grid.tsv").write_text("s\th:m:s\tmax_rss\n1.5\t0:00:01\t10\n")
    (root / "benchmark.csv").write_text("scenario,index_outcome\nrotation 30,success\n")
    names = sorted(queries)
    run_report(
        names,
        [str(root / "queries" / n / "registration.json") for n in names],
        [str(root / "queries" / n / "evaluation.json") for n in names],
        [str(root / "figures" / n) for n in names],
        {"report": {"success_error_px": 3.0}, "queries": {n: {} for n in names}},
        root / "report" / "index.html",
        root / "report" / "summary.csv",
        log_roots=[root / "logs", root / "benchmarks"],
        benchmark_csv=root / "benchmark.csv",
    )
    return root


def map_xy_pts(H: np.ndarray, pts: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    p = np.c_[pts, np.ones(len(pts))] @ H.T
    return p[:, 0] / p[:, 2], p[:, 1] / p[:, 2]


class _Page(HTMLParser):
    """Collects summary-table cells (data-key / data-value) and embedded images."""

    def __init__(self) -> None:
        super().__init__()
        self.rows: list[dict[str, str]] = []
        self.images: list[str] = []
        self.figures: list[str] = []
        self.external: list[str] = []
        self._in_summary = False

    def handle_starttag(self, tag: str, attrs: list[tuple[str, str | None]]) -> None:
        a = dict(attrs)
        if tag == "table":
            self._in_summary = a.get("id") == "summary"
        if self._in_summary and tag == "tr":
            self.rows.append({})
        if self._in_summary and tag == "td" and a.get("data-key") and self.rows:
            self.rows[-1][a["data-key"]] = a.get("data-value") or ""
        if tag == "img":
            self.images.append(a.get("src") or "")
        if tag == "figure" and a.get("data-file"):
            self.figures.append(a["data-file"] or "")
        for k in ("src", "href"):
            v = a.get(k) or ""
            if tag in ("link", "script", "img") and re.match(r"(https?:)?//", v):
                self.external.append(v)

    def handle_endtag(self, tag: str) -> None:
        if tag == "table":
            self._in_summary = False


def _page(run_dir: Path) -> _Page:
    p = _Page()
    p.feed((run_dir / "report" / "index.html").read_text())
    return p


def test_report_exists_and_is_self_contained(run_dir: Path) -> None:
    html = (run_dir / "report" / "index.html").read_text()
    assert html.startswith("<!DOCTYPE html>")
    page = _page(run_dir)
    assert not page.external, "the page must not load anything from the network"
    assert "<script" not in html
    assert "rotation 30" in html  # benchmark table included
    assert "fuse_parts" in html and "map_grid" in html  # timings from logs and benchmark files
    assert "success_error_px: 3.0" in html  # configuration dump


def test_every_figure_exists_and_is_a_png(run_dir: Path) -> None:
    page = _page(run_dir)
    assert len(page.images) == len(page.figures) > 0
    listed = []
    for name in ("good", "lost"):
        man = json.loads((run_dir / "figures" / name / "figures.json").read_text())
        for f in man["figures"]:
            p = run_dir / "figures" / name / f["file"]
            assert p.exists(), p
            assert p.read_bytes()[:8] == PNG_MAGIC
            img = cv2.imread(str(p))
            assert img is not None and img.shape[0] > 200 and img.shape[1] > 300
            assert img.std() > 5, f"{p} looks blank"
            listed.append(f["file"])
    assert sorted(listed) == sorted(page.figures)
    for src in page.images:
        assert src.startswith("data:image/png;base64,")
        assert base64.b64decode(src.split(",", 1)[1])[:8] == PNG_MAGIC
    keys_good = [
        f["key"] for f in json.loads((run_dir / "figures/good/figures.json").read_text())["figures"]
    ]
    keys = (
        "match",
        "checkerboard",
        "footprints",
        "search",
        "inliers",
        "ndsm",
        "error",
        "segmentation",
    )
    for k in keys:
        assert k in keys_good
    keys_lost = [
        f["key"] for f in json.loads((run_dir / "figures/lost/figures.json").read_text())["figures"]
    ]
    assert keys_lost[:2] == ["not_found", "search"]


def test_summary_numbers_equal_the_json(run_dir: Path) -> None:
    rows = {r["query"]: r for r in _page(run_dir).rows if r}
    assert set(rows) == {"good", "lost"}
    for name, row in rows.items():
        reg = json.loads((run_dir / "queries" / name / "registration.json").read_text())
        ev = json.loads((run_dir / "queries" / name / "evaluation.json").read_text())

        def val(key: str, row: dict[str, str] = row):
            return json.loads(row[key]) if row[key] else None

        assert row["status"] == reg["status"]
        assert row["outcome"] == ev["outcome"]
        assert val("inliers") == reg["inliers"]
        assert val("candidates_tried") == reg["candidates_tried"]
        err = ev.get("error") or {}
        assert val("error_median_px") == (err.get("px") or {}).get("median")
        assert val("error_p90_px") == (err.get("px") or {}).get("p90")
        assert val("error_max_px") == (err.get("px") or {}).get("max")
        assert val("error_median_m") == (err.get("m") or {}).get("median")
        assert val("error_p90_m") == (err.get("m") or {}).get("p90")
        assert val("time_s") == pytest.approx(query_seconds(reg))
        assert val("lidar_check") == (reg.get("lidar_check") or {}).get("outcome")
    assert rows["good"]["outcome"] == "success"
    assert json.loads(rows["good"]["error_median_px"]) == pytest.approx(0.72, abs=0.01)
    assert rows["lost"]["outcome"] == "correct_not_found"
    seg = json.loads((run_dir / "queries/good/evaluation.json").read_text())["segmentation"]
    assert 0.8 < seg["overall_accuracy"] < 1.0 and seg["classes"]["4"]["name"] == "grass"
    csv_text = (run_dir / "report" / "summary.csv").read_text().splitlines()
    assert csv_text[0].startswith("query,status,outcome") and len(csv_text) == 3


def test_parse_timings(run_dir: Path) -> None:
    found = parse_timings([run_dir / "logs", run_dir / "benchmarks"])
    rows = {(r["stage"], r["rule"]): r for r in found}
    assert rows[("register", "fuse_parts")]["jobs"] == 2
    assert rows[("register", "fuse_parts")]["total_s"] == pytest.approx(4.5)
    assert rows[("map", "map_grid")]["total_s"] == pytest.approx(1.5)
    assert rows[("map", "map_grid")]["source"] == "benchmark"


@pytest.mark.skipif(not CHROMIUM.exists(), reason="/usr/bin/chromium is absent")
def test_chromium_renders_without_console_errors(run_dir: Path, tmp_path: Path) -> None:
    shot = tmp_path / "shot.png"
    profile = tmp_path / "profile"
    cmd = [
        str(CHROMIUM),
        "--headless",
        "--no-sandbox",
        "--disable-gpu",
        "--disable-quic",
        "--no-first-run",
        "--disable-background-networking",
        "--disable-component-update",
        "--disable-sync",
        "--disable-dev-shm-usage",
        f"--user-data-dir={profile}",
        "--enable-logging=stderr",
        "--v=0",
        f"--screenshot={shot}",
        "--window-size=1200,3000",
        (run_dir / "report" / "index.html").resolve().as_uri(),
    ]
    res = subprocess.run(cmd, capture_output=True, text=True, timeout=120)
    log = res.stdout + res.stderr
    assert shot.exists(), f"no screenshot; chromium said:\n{log[-3000:]}"
    console = [ln for ln in log.splitlines() if "CONSOLE" in ln or "Uncaught" in ln]
    assert not [ln for ln in console if "ERROR" in ln or "Uncaught" in ln], console
    img = cv2.imread(str(shot))
    assert img is not None and img.shape[:2] == (3000, 1200)
    assert img.std() > 10, "the screenshot is blank"
    # the header bar (dark blue) and figures (not just white) are rendered
    assert (img.reshape(-1, 3) < 100).all(axis=1).mean() > 0.01
    shutil.rmtree(profile, ignore_errors=True)


def test_pooled_bands_text() -> None:
    pooled = [{"index": 39, "wavelength_nm": 1199.2}, {"index": 113, "wavelength_nm": 2200.0}]
    assert pooled_text(pooled) == "1199.2 nm (index 39), 2200.0 nm (index 113)"
    assert pooled_text([{"index": None, "wavelength_nm": None}]) == "mean"
    assert pooled_text([{"index": 0, "wavelength_nm": None}]) == "index 0"
    assert pooled_text(None) is None


def test_level_text() -> None:
    lv = {"gsd": 30.0, "width": 157, "height": 186, "features": 127, "seconds": 0.2}
    assert level_text(lv) == "orthophoto averaged to 30 map units: 157 x 186 px, 127 features"
    assert level_text({"gsd": 30.0, "reason": "too large"}) == "not used: too large"
    assert level_text(None) is None


def test_sources_text_names_each_source_and_why_rift_decided_nothing() -> None:
    reg = {"sources": [{"name": "features", "accepted": False, "candidates": 24},
                       {"name": "rift", "accepted": False, "candidates": 36}],
           "split": {"rift": {"ran": True, "accepted": False, "log10_nfa": -4.7,
                              "null_log10_nfa": -2.1, "matches": 23, "reason": "too close"}}}  # fmt: skip
    assert sources_text(reg) == (
        "features (24 tried); rift (36 tried): log10 NFA -4.7, other rotations' best -2.1, "
        "23 cells; too close"
    )
    reg["sources"][1]["accepted"], reg["split"]["rift"]["accepted"] = True, True
    assert sources_text(reg).endswith("rift (36 tried, accepted): log10 NFA -4.7, other rotations' best -2.1, 23 cells")
    assert sources_text({}) is None
    reg["split"]["rift"] |= {"gsd": 0.48, "gsd_guesses": [{"gsd": 1.1, "guess": 1.0}, {"gsd": 0.48, "guess": 0.5}]}
    assert sources_text(reg).endswith(
        "23 cells; GSD unknown: 1, 0.5 map units a pixel searched, this pose at 0.48")
    del reg["split"]["rift"]["gsd_guesses"]
    reg["second_pass"] = {"refused": "part 0's pose does not hold over the whole query",
                          "sources": ["small_windows", "cfog_null", "rift"]}  # fmt: skip
    assert sources_text(reg).endswith(
        "23 cells; second pass (small_windows, cfog_null, rift) after the verifier refused the "
        "first candidate: part 0's pose does not hold over the whole query"
    )
    reg["second_pass"]["elsewhere"] = {"distance_m": 16800.0, "side_m": 13000.0,
                                       "reason": "the second pass's candidate lies 16800 map units away"}  # fmt: skip
    assert sources_text(reg).endswith("whole query; not kept: the second pass's candidate lies 16800 map units away")


def test_sources_text_gives_the_elevation_source_its_decision() -> None:
    """The elevation source (rift against the DSM) is reported like rift: its NFA and cells."""
    reg = {"sources": [{"name": "features", "accepted": False, "candidates": 24},
                       {"name": "elevation", "accepted": True, "candidates": 36}],
           "split": {"elevation": {"ran": True, "accepted": True, "log10_nfa": -27.3,
                                   "null_log10_nfa": 6.3, "matches": 57}}}  # fmt: skip
    assert sources_text(reg) == (
        "features (24 tried); elevation (36 tried, accepted): log10 NFA -27.3, other rotations' "
        "best 6.3, 57 cells"
    )
