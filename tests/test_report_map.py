"""The map view (results/report/map.html), built from a synthetic run in tmp and from real data.

The fixture writes what the workflow would (grid.json, the orthophoto, per query band.tif,
registration.json, geolocation.tif, evaluation.json, truth; per frame set poses.json, truth.json
and, for the video, trajectory.json) and builds the map view with the library; the geolocation of
the registered query bends away from its homography (a smooth along-track wobble, as the local
refinement delivers), so the drawn query must follow the geolocation to land on the map. The
browser tests drive headless Chromium over the DevTools protocol (tests/chromium_cdp.py).
"""

from __future__ import annotations

import hashlib
import json
import re
import warnings
from html.parser import HTMLParser
from pathlib import Path

import cv2
import numpy as np
import pytest
import rasterio
from chromium_cdp import CHROMIUM, HeadlessChromium
from rasterio.crs import CRS
from rasterio.transform import Affine

from georeg.register.geolocation import write_geolocation
from georeg.report.map_data import (
    MapFrame,
    look_end,
    lookup_residual,
    query_lookup,
    warp_query,
)
from georeg.report.map_view import FrameSetSource, QuerySource, write_map_view

MAP_T = Affine(0.5, 0, 500_000.0, 0, -0.5, 4_100_400.0)  # 1200 x 800 px at 0.5 m
MW, MH = 1200, 800
QW, QH = 220, 300
WOBBLE_M = 4.0  # amplitude of the geolocation's along-track wobble away from H (8 map px)
LEAFLET_SHA256 = "db49d009c841f5ca34a888c96511ae936fd9f5533e90d8b2c4d57596f4e5641a"


def _write(path: Path, data: np.ndarray, **kw) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    prof = {"driver": "GTiff", "width": data.shape[-1], "height": data.shape[-2]}
    prof.update(count=1 if data.ndim == 2 else data.shape[0], dtype=str(data.dtype), **kw)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        with rasterio.open(path, "w", **prof) as ds:
            ds.write(data if data.ndim == 3 else data[None])


def _map_rgb(rng: np.random.Generator) -> np.ndarray:
    """(3, MH, MW) uint8: smooth terrain, bright roofs, dark roads."""
    base = cv2.GaussianBlur(rng.random((MH, MW)).astype(np.float32), (0, 0), 8)
    base = (base - base.min()) / (np.ptp(base) + 1e-9) * 110 + 70
    for _ in range(260):
        x, y = rng.integers(0, MW - 30, 2)
        w, h = rng.integers(8, 30, 2)
        base[y : y + h, x : x + w] = rng.choice([35.0, 225.0])
    base[:, 600:612] = 40.0
    return np.stack([base * 0.85 + 10, base, base * 0.7 + 30]).clip(0, 255).astype(np.uint8)


def _h(x0: float, y0: float, angle_deg: float, gsd: float = 0.8) -> np.ndarray:
    """Query pixel centre (col, row) -> map x, y: rotated, GSD metres per query pixel."""
    a = np.deg2rad(angle_deg)
    return np.array([[gsd * np.cos(a), gsd * np.sin(a), x0],
                     [gsd * np.sin(a), -gsd * np.cos(a), y0], [0, 0, 1.0]])  # fmt: skip


def _geo_xy(H: np.ndarray, wobble: float) -> tuple[np.ndarray, np.ndarray]:
    """Map x, y of every query pixel: H plus a cross-track wobble varying along the rows."""
    c, r = np.meshgrid(np.arange(QW, dtype=float), np.arange(QH, dtype=float))
    p = np.stack([c, r, np.ones_like(c)], -1) @ H.T
    x, y = p[..., 0] / p[..., 2], p[..., 1] / p[..., 2]
    return x + wobble * np.sin(r / QH * 2 * np.pi), y


def _band(gray: np.ndarray, x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """What the sensor saw: the map sampled at each pixel's geolocation (0 = outside the map)."""
    col = ((x - MAP_T.c) / MAP_T.a - 0.5).astype(np.float32)
    row = ((y - MAP_T.f) / MAP_T.e - 0.5).astype(np.float32)
    b = cv2.remap(gray, col, row, cv2.INTER_LINEAR, borderValue=0)
    return np.clip(b, 1, 255).astype(np.uint8) * (b > 0)


def _camera(C: list[float], heading_deg: float, off_nadir_deg: float) -> list[list[float]]:
    """R_world_to_cam of a camera looking along a heading (clockwise from north), tilted."""
    h, t = np.deg2rad(heading_deg), np.deg2rad(off_nadir_deg)
    fwd = np.array([np.sin(h), np.cos(h), 0.0])
    z = np.cos(t) * np.array([0, 0, -1.0]) + np.sin(t) * fwd  # optical axis
    x = np.cross(fwd, [0, 0, 1.0])
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    return np.stack([x, y, z]).tolist()


def _pose(image: str, C: list[float], heading: float, **kw) -> dict:
    R = _camera(C, heading, 30.0)
    axis = np.asarray(R[2])
    g = np.asarray(C) + (0 - C[2]) / axis[2] * axis
    fp = [[g[0] + dx, g[1] + dy] for dx, dy in ((-40, 30), (40, 30), (40, -30), (-40, -30))]
    return {"image": image, "status": "registered", "camera_center_xyz": C, "R_world_to_cam": R,
            "footprint_xy": fp, "inliers": 120, "reprojection_px": 0.9, **kw}  # fmt: skip


@pytest.fixture(scope="module")
def run_dir(tmp_path_factory: pytest.TempPathFactory) -> Path:
    root = tmp_path_factory.mktemp("map_view")
    rng = np.random.default_rng(11)
    rgb = _map_rgb(rng)
    crs = CRS.from_epsg(32611)
    _write(root / "map/ortho.tif", rgb, crs=crs, transform=MAP_T)
    (root / "map/grid.json").write_text(json.dumps(
        {"crs": crs.to_wkt(), "transform": list(MAP_T)[:6], "width": MW, "height": MH}))  # fmt: skip
    gray = cv2.cvtColor(np.moveaxis(rgb, 0, -1), cv2.COLOR_RGB2GRAY)
    queries = []
    for name, H, found in (("good", _h(500_110.0, 4_100_330.0, 25.0), True),
                           ("lost", _h(500_400.0, 4_100_200.0, -10.0), False)):  # fmt: skip
        q = root / "queries" / name
        x, y = _geo_xy(H, WOBBLE_M)
        _write(q / "band.tif", _band(gray, x, y), nodata=0)
        _write(q / "truth.tif", np.stack([x, y]))
        reg = {"status": "registered" if found else "not_found", "width": QW, "height": QH,
               "homography": H.tolist() if found else None, "inliers": 80 if found else 0,
               "matches": 130 if found else None, "candidates_tried": 4,
               "lidar_check": {"outcome": "agrees"} if found else None}  # fmt: skip
        if not found:
            reg["reason"] = "part 0: 4 candidate(s) tried, none accepted </script><b>x</b>"
        (q / "registration.json").write_text(json.dumps(reg))
        write_geolocation(q / "geolocation.tif", H if found else None, QW, QH, None,
                          crs.to_wkt(), xy=(x, y) if found else None)  # fmt: skip
        ev = ({"outcome": "success", "error": {"px": {"median": 0.31, "p90": 0.52, "max": 0.9},
                                               "m": {"median": 0.155, "p90": 0.26, "max": 0.45}}}
              if found else {"outcome": "missed"})  # fmt: skip
        (q / "evaluation.json").write_text(json.dumps(ev))
        queries.append(QuerySource(name, q / "registration.json", q / "evaluation.json",
                                   q / "band.tif", q / "geolocation.tif", q / "truth.tif"))  # fmt: skip
    drone = root / "frames/drone"
    drone.mkdir(parents=True)
    poses = [_pose("frames/nadir.png", [500_150.0, 4_100_100.0, 120.0], 40.0,
                   evaluation={"expected": "registered", "final": {"horizontal_m": 0.8,
                               "vertical_m": 0.3, "rotation_deg": 0.1}}),
             _pose("frames/oblique.png", [500_450.0, 4_100_300.0, 90.0], 200.0),
             {"image": "frames/outside.png", "status": "not_found", "reason": "no hypothesis verified",
              "inliers": 4, "evaluation": {"expected": "registered"}}]  # fmt: skip
    truth = [{"image": "frames/outside.png", "camera_center_xyz": [500_520.0, 4_100_060.0, 100.0]}]
    (drone / "poses.json").write_text(json.dumps(poses))
    (drone / "truth.json").write_text(json.dumps(truth))
    video = root / "frames/video"
    video.mkdir(parents=True)
    t = np.linspace(0, np.pi, 80)
    vposes, vtruth = [], []
    for i, a in enumerate(t):
        C = [500_300.0 + 160 * np.cos(a), 4_100_150.0 + 110 * np.sin(a), 100.0]
        vtruth.append({"frame": i, "camera_center_xyz": C})
        if i % 17 == 9:
            vposes.append({"image": f"flight.mp4#{i:06d}", "frame": i, "status": "not_found"})
            continue
        vposes.append(_pose(f"flight.mp4#{i:06d}", [C[0] + 0.6, C[1] - 0.4, C[2]],
                            float(np.rad2deg(-a)) % 360, frame=i, keyframe=i % 8 == 0,
                            source="sfm" if i % 8 == 0 else "tracking"))  # fmt: skip
    (video / "poses.json").write_text(json.dumps(vposes))
    (video / "truth.json").write_text(json.dumps(vtruth))
    stats = {"horizontal_m": {"mean": 0.8, "median": 0.72, "p90": 1.31, "max": 2.5}}
    (video / "trajectory.json").write_text(json.dumps(
        {"frames": 80, "icp": {"accepted": False, "reason": "gain 0.01 < min_gain 0.02"},
         "evaluation": {"after_icp": stats}}))  # fmt: skip
    sets = [FrameSetSource("drone", drone / "poses.json", drone / "truth.json"),
            FrameSetSource("video", video / "poses.json", video / "truth.json",
                           video / "trajectory.json")]  # fmt: skip
    write_map_view(root / "report/map.html", root / "report/map", root / "map/grid.json",
                   root / "map/ortho.tif", queries, sets)  # fmt: skip
    return root


def _data(run_dir: Path) -> dict:
    html = (run_dir / "report/map.html").read_text()
    m = re.search(r'<script type="application/json" id="map-data">(.*?)</script>', html, re.S)
    assert m, "no embedded data"
    return json.loads(m.group(1))


def _ncc(a: np.ndarray, b: np.ndarray) -> float:
    a, b = a - a.mean(), b - b.mean()
    return float((a * b).sum() / np.sqrt((a * a).sum() * (b * b).sum() + 1e-12))


def _ortho_gray(path: Path, channel: int | None = None) -> np.ndarray:
    """The orthophoto as float32 luminance (or one channel)."""
    with rasterio.open(path) as ds:
        rgb = ds.read()
    if channel is not None:
        return rgb[channel].astype(np.float32)
    return cv2.cvtColor(np.moveaxis(rgb, 0, -1), cv2.COLOR_RGB2GRAY).astype(np.float32)


def _ncc_under(gray: np.ndarray, rgba: np.ndarray, bounds: list[float],
               high_pass: bool = False) -> float:
    """Correlation of a drawn query image with the orthophoto under it (where it is opaque)."""
    c0, r0, c1, r1 = bounds
    h, w = rgba.shape[:2]
    mc, mr = np.meshgrid(c0 + (np.arange(w) + 0.5) * (c1 - c0) / w,
                         r0 + (np.arange(h) + 0.5) * (r1 - r0) / h)  # fmt: skip
    under = cv2.remap(gray, (mc - 0.5).astype(np.float32), (mr - 0.5).astype(np.float32),
                      cv2.INTER_LINEAR)  # fmt: skip
    drawn = rgba[..., 0].astype(np.float32)
    if high_pass:  # detail only (a smooth real orthophoto correlates with itself shifted)
        drawn, under = (a - cv2.GaussianBlur(a, (0, 0), 3) for a in (drawn, under))
    m = cv2.erode((rgba[..., 3] > 0).astype(np.uint8), np.ones((9, 9), np.uint8)) > 0
    assert m.sum() > 1000
    return _ncc(drawn[m].astype(float), under[m].astype(float))


def _overlay_vs_map(run_dir: Path, rgba: np.ndarray, bounds: list[float]) -> float:
    return _ncc_under(_ortho_gray(run_dir / "map/ortho.tif"), rgba, bounds)


def test_query_image_lands_on_the_map_through_its_geolocation(run_dir: Path) -> None:
    data = _data(run_dir)
    good = next(q for q in data["queries"] if q["name"] == "good")
    img = cv2.imread(str(run_dir / "report" / good["overlay"]["src"]), cv2.IMREAD_UNCHANGED)
    rgba = cv2.cvtColor(img, cv2.COLOR_BGRA2RGBA)
    assert _overlay_vs_map(run_dir, rgba, good["overlay"]["bounds"]) > 0.9
    # the homography alone (no geolocation) misses by the wobble: the geolocation is what is drawn
    frame = MapFrame.from_grid(run_dir / "map/grid.json")
    with rasterio.open(run_dir / "queries/good/band.tif") as ds:
        band = ds.read(1)
    reg = json.loads((run_dir / "queries/good/registration.json").read_text())
    h_only, b = warp_query(band, None, reg["homography"], frame)
    assert _overlay_vs_map(run_dir, h_only, b) < 0.75
    lost = next(q for q in data["queries"] if q["name"] == "lost")
    assert lost["overlay"] is None  # nothing registered, nothing drawn


def test_lookup_inverts_the_geolocation(run_dir: Path) -> None:
    """Each drawn pixel shows the query pixel whose geolocation lands on it (to 0.05 map px),
    where the homography alone is off by the wobble (8 map px)."""
    frame = MapFrame.from_grid(run_dir / "map/grid.json")
    H = _h(500_110.0, 4_100_330.0, 25.0)
    geo = _geo_xy(H, WOBBLE_M)
    fixed = lookup_residual(query_lookup((QH, QW), geo, H, frame))
    plain = lookup_residual(query_lookup((QH, QW), geo, H, frame, iterations=0))
    assert len(fixed) > 20_000 and np.median(fixed) < 0.05 and np.percentile(fixed, 99) < 0.2
    assert 4 < np.median(plain) < 8.5 and plain.max() > 7.5
    # a large query is decimated (every k-th pixel), still drawn at its place
    lk = query_lookup((QH, QW), geo, H, frame, max_px=60)
    assert lk.k == 3 and max(lk.qc.shape) <= 60
    assert np.median(lookup_residual(lk)) < 0.2


def test_features_are_in_map_pixels_with_status_and_errors(run_dir: Path) -> None:
    data = _data(run_dir)
    assert data["size"] == [MW, MH] and data["crs"]["name"] == "EPSG:32611"
    assert data["ortho"]["bounds"] == pytest.approx([0, 0, MW, MH])
    feats = data["features"]["features"]
    kinds = {f["properties"]["kind"] for f in feats}
    assert {"query_footprint", "query_truth", "camera", "frame_footprint", "look", "path",
            "truth_path", "truth_camera"} <= kinds  # fmt: skip
    # the registered query's footprint is its truth outline (same geolocation), in map pixels
    fp = next(f for f in feats if f["properties"]["kind"] == "query_footprint")
    tr = next(f for f in feats if f["properties"]["kind"] == "query_truth"
              and f["properties"]["name"] == "good")  # fmt: skip
    assert np.allclose(fp["geometry"]["coordinates"], tr["geometry"]["coordinates"], atol=0.02)
    x, y = _geo_xy(_h(500_110.0, 4_100_330.0, 25.0), WOBBLE_M)
    first = fp["geometry"]["coordinates"][0][0]
    assert first == pytest.approx([(x[0, 0] - MAP_T.c) / 0.5, (MAP_T.f - y[0, 0]) / 0.5], abs=0.02)
    info = dict(fp["properties"]["info"])
    assert info["status"] == "registered" and info["outcome"] == "success"
    assert info["error median"] == "0.31 px = 0.15 m" or info["error median"].startswith("0.31 px")
    # the query not found: no footprint, its truth outline carries the status and the reason
    lost = [f for f in feats if f["properties"]["name"] == "lost"]
    assert [f["properties"]["kind"] for f in lost] == ["query_truth"]
    assert dict(lost[0]["properties"]["info"])["reason"].startswith("part 0")
    cams = [f for f in feats if f["properties"]["kind"] == "camera" and f["properties"]["set"] == "drone"]
    assert [c["geometry"]["coordinates"] for c in cams] == [[300.0, 600.0], [900.0, 200.0]]
    outside = next(f for f in feats if f["properties"]["kind"] == "truth_camera"
                   and f["properties"]["set"] == "drone")  # fmt: skip
    assert outside["geometry"]["coordinates"] == [1040.0, 680.0]
    assert dict(outside["properties"]["info"])["status"] == "not_found"
    assert dict(cams[0]["properties"]["info"])["error horizontal / vertical"] == "0.80 m / 0.30 m"
    # the video: its path through the registered frames in order, keyframes and every 10th drawn
    path = next(f for f in feats if f["properties"]["kind"] == "path")
    assert len(path["geometry"]["coordinates"]) == 80 - len(range(9, 80, 17))
    info = dict(path["properties"]["info"])
    assert info["frames registered"] == f"{80 - len(range(9, 80, 17))} of 80"
    assert info["horizontal error (m) median / p90 / max"] == "0.72 / 1.31 / 2.50"
    assert info["ICP"] == "refused: gain 0.01 < min_gain 0.02"
    vcams = [f for f in feats if f["properties"]["kind"] == "camera" and f["properties"]["set"] == "video"]
    assert 10 <= len(vcams) <= 20


def test_look_direction_follows_the_optical_axis() -> None:
    for heading in (0.0, 90.0, 225.0):
        p = _pose("x.png", [100.0, 200.0, 150.0], heading)
        end = look_end(p)
        d = end - np.array([100.0, 200.0])
        assert np.rad2deg(np.arctan2(d[0], d[1])) % 360 == pytest.approx(heading, abs=1e-6)


class _Refs(HTMLParser):
    def __init__(self) -> None:
        super().__init__()
        self.refs: list[str] = []

    def handle_starttag(self, tag: str, attrs: list[tuple[str, str | None]]) -> None:
        a = dict(attrs)
        for k in ("src", "href"):
            if a.get(k) and tag in ("script", "link", "img"):
                self.refs.append(a[k] or "")


def test_page_loads_only_bundled_files(run_dir: Path) -> None:
    page = run_dir / "report/map.html"
    p = _Refs()
    p.feed(page.read_text())
    assert len(p.refs) == 4  # leaflet.css, mapview.css, leaflet.js, mapview.js
    for ref in p.refs:
        assert not re.match(r"(https?:)?//", ref), ref
        assert (page.parent / ref).is_file(), ref
    data = _data(run_dir)
    for src in [data["ortho"]["src"]] + [q["overlay"]["src"] for q in data["queries"] if q["overlay"]]:
        assert (page.parent / src).is_file()
    leaflet = (run_dir / "report/map/leaflet/leaflet.js").read_bytes()
    assert hashlib.sha256(leaflet).hexdigest() == LEAFLET_SHA256
    assert (run_dir / "report/map/leaflet/LICENSE").read_text().startswith("BSD 2-Clause")
    js = (run_dir / "report/map/mapview.js").read_text()
    assert not re.search(r"https?://", js)
    ortho = cv2.imread(str(run_dir / "report/map/ortho.jpg"))
    assert ortho.shape[:2] == (MH, MW) and ortho.std() > 20


def _colour_share(img: np.ndarray, rgb: tuple[int, int, int], tol: int = 40) -> float:
    d = np.abs(img[..., :3].astype(int) - np.array(rgb[::-1])).max(axis=2)
    return float((d <= tol).mean())


@pytest.mark.skipif(not CHROMIUM.exists(), reason="/usr/bin/chromium is absent")
def test_map_view_renders_toggles_and_clicks_in_chromium(run_dir: Path, tmp_path: Path) -> None:
    url = (run_dir / "report/map.html").resolve().as_uri()
    with HeadlessChromium(tmp_path / "profile", 1400, 900) as b:
        b.open(url)
        b.wait_for("document.body.dataset.ready === '1' && document.body.dataset.ortho === 'loaded'")
        b.wait_for("Array.from(document.querySelectorAll('img.georeg-query-image'))"
                   ".every(i => i.complete && i.naturalWidth > 0)")  # fmt: skip
        shot = cv2.imdecode(np.frombuffer(b.screenshot(), np.uint8), cv2.IMREAD_COLOR)
        (tmp_path / "shot.png").write_bytes(cv2.imencode(".png", shot)[1].tobytes())
        assert shot.shape[:2] == (900, 1400)
        mapbox = b.evaluate("(r => [r.left, r.top, r.width, r.height])"
                            "(document.getElementById('map').getBoundingClientRect())")  # fmt: skip
        x0, y0, w, h = (int(v) for v in mapbox)
        area = shot[y0 : y0 + h, x0 : x0 + w]
        assert area.std() > 25, "the map area is blank"
        assert len(np.unique(area.reshape(-1, 3) // 16, axis=0)) > 200  # orthophoto texture
        green = _colour_share(area, (0, 224, 0), 30)  # the registered query's footprint
        assert green > 2e-4
        n = "document.querySelectorAll('{}').length"
        assert b.evaluate(n.format("path.georeg-query_footprint")) == 1
        assert b.evaluate(n.format("path.georeg-camera")) >= 2 + 10
        assert b.evaluate(n.format("path.georeg-path")) == 1
        # layers toggle through the layer control's checkboxes
        toggle = ("(label => {{ const i = Array.from(document.querySelectorAll("
                  "'.leaflet-control-layers-overlays label')).find(l => l.textContent.trim() "
                  "=== label).querySelector('input'); i.click(); return i.checked; }})('{}')")  # fmt: skip
        assert b.evaluate(toggle.format("query footprints")) is False
        assert b.evaluate(n.format("path.georeg-query_footprint")) == 0
        off = cv2.imdecode(np.frombuffer(b.screenshot(), np.uint8), cv2.IMREAD_COLOR)
        assert _colour_share(off[y0 : y0 + h, x0 : x0 + w], (0, 224, 0), 30) < green / 3
        assert b.evaluate(toggle.format("query footprints")) is True
        assert b.evaluate(n.format("path.georeg-query_footprint")) == 1
        assert b.evaluate(toggle.format("query images")) is False
        assert b.evaluate(n.format("img.georeg-query-image")) == 0
        assert b.evaluate(toggle.format("query images")) is True
        assert b.evaluate(toggle.format("video trajectories")) is False
        assert b.evaluate(n.format("path.georeg-path")) == 0
        # the opacity slider and the swipe
        b.evaluate("(s => { s.value = 25; s.dispatchEvent(new Event('input')); })"
                   "(document.getElementById('query-slider'))")  # fmt: skip
        assert b.evaluate("document.querySelector('img.georeg-query-image').style.opacity") == "0.25"
        b.evaluate("document.querySelector('input[value=swipe]').click()")
        assert b.evaluate("document.querySelector('img.georeg-query-image').style.opacity") == "1"
        assert b.evaluate("georegMap.map.getPane('queryPane').style.clip").startswith("rect(")
        # a click on a camera shows its status and errors
        pt = b.evaluate("(l => { const p = georegMap.map.latLngToContainerPoint(l.getLatLng()); "
                        "return [p.x, p.y]; })(georegMap.byId['frame:drone:nadir'])")  # fmt: skip
        b.click(x0 + pt[0], y0 + pt[1])
        popup = b.wait_for("(p => p && p.textContent)(document.querySelector('.leaflet-popup-content'))")
        assert "nadir" in popup and "registered" in popup and "0.80 m / 0.30 m" in popup
        # the side list focuses a query and opens its popup
        b.evaluate("document.querySelector('#side a[data-id=\"query:lost\"]').click()")
        popup = b.wait_for("(p => p && p.textContent.includes('lost') && p.textContent)"
                           "(document.querySelector('.leaflet-popup-content'))")  # fmt: skip
        assert "not_found" in popup and "missed" in popup and "none accepted" in popup
        assert "</script><b>x</b>" in popup  # markup in the data is shown as text
        # the mouse position in the map CRS
        b.call("Input.dispatchMouseEvent", type="mouseMoved", x=x0 + w / 2, y=y0 + h / 2)
        assert "EPSG:32611" in b.evaluate("document.querySelector('.georeg-pos').textContent")
        assert b.errors() == []


# ----------------------------------------------------------------------------- real data


@pytest.fixture(scope="module")
def odm_view(shared_data: Path, tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, dict]:
    """The map view over the real ODM drone orthophoto (frames_dev/odm, 0.2 m): its two frames at
    their surveyed poses, and a query band cut from the real orthophoto through a known
    geolocation (H plus a wobble)."""
    case = shared_data / "frames_dev" / "odm"
    root = tmp_path_factory.mktemp("map_view_odm")
    with rasterio.open(case / "map_ortho.tif") as ds:
        rgb, T, crs = ds.read(), ds.transform, ds.crs
    (root / "grid.json").write_text(json.dumps({"crs": crs.to_wkt(), "transform": list(T)[:6],
                                                "width": rgb.shape[2], "height": rgb.shape[1]}))  # fmt: skip
    H = _h(T.c + 120.0, T.f - 60.0, -30.0, gsd=0.5)
    c, r = np.meshgrid(np.arange(QW, dtype=float), np.arange(QH, dtype=float))
    p = np.stack([c, r, np.ones_like(c)], -1) @ H.T
    x = p[..., 0] / p[..., 2] + 2.0 * np.sin(r / QH * 2 * np.pi)  # 10 map px of wobble
    y = p[..., 1] / p[..., 2]
    green = rgb[1]
    col = ((x - T.c) / T.a - 0.5).astype(np.float32)
    row = ((y - T.f) / T.e - 0.5).astype(np.float32)
    b = cv2.remap(green, col, row, cv2.INTER_LINEAR, borderValue=0)
    band = np.clip(b, 1, 255).astype(np.uint8) * (b > 0)  # 0 = nodata, as band.tif
    q = root / "q"
    _write(q / "band.tif", band, nodata=0)
    (q / "registration.json").write_text(json.dumps(
        {"status": "registered", "width": QW, "height": QH, "homography": H.tolist()}))  # fmt: skip
    write_geolocation(q / "geolocation.tif", H, QW, QH, None, crs.to_wkt(), xy=(x, y))
    truth = {t.stem: json.loads(t.read_text()) for t in sorted((case / "truth").glob("*.json"))}
    poses = [{"image": f"queries/{k}.png", "status": "registered", "inliers": 200,
              "camera_center_xyz": t["camera_center_xyz"], "R_world_to_cam": t["R_world_to_cam"],
              "footprint_xy": [v[:2] for v in t["footprint_xyz"]]} for k, t in truth.items()]  # fmt: skip
    (root / "poses.json").write_text(json.dumps(poses))
    write_map_view(root / "report/map.html", root / "report/map", root / "grid.json",
                   case / "map_ortho.tif",
                   [QuerySource("real", q / "registration.json", None, q / "band.tif",
                                q / "geolocation.tif")],
                   [FrameSetSource("odm", root / "poses.json")])  # fmt: skip
    return root, truth


@pytest.mark.shared
def test_real_orthophoto_query_and_surveyed_cameras(odm_view: tuple[Path, dict],
                                                    shared_data: Path) -> None:  # fmt: skip
    root, truth = odm_view
    data = _data(root)
    frame = MapFrame.from_grid(root / "grid.json")
    # the drawn query lies on the real orthophoto where its geolocation says, not where H says
    green = _ortho_gray(shared_data / "frames_dev/odm/map_ortho.tif", channel=1)
    q = data["queries"][0]
    img = cv2.imread(str(root / "report" / q["overlay"]["src"]), cv2.IMREAD_UNCHANGED)
    drawn = _ncc_under(green, cv2.cvtColor(img, cv2.COLOR_BGRA2RGBA), q["overlay"]["bounds"], True)
    with rasterio.open(root / "q/band.tif") as ds:
        band = ds.read(1)
    H = json.loads((root / "q/registration.json").read_text())["homography"]
    h_only, b = warp_query(band, None, H, frame)
    by_h = _ncc_under(green, h_only, b, True)
    assert drawn > 0.75 and by_h < 0.4  # measured 0.86 and 0.22
    # the surveyed cameras: at their centres, looking at the ground point of the image centre
    feats = data["features"]["features"]
    for name, t in truth.items():
        cam = next(f for f in feats if f["properties"]["kind"] == "camera"
                   and f["properties"]["name"] == name)  # fmt: skip
        centre = frame.to_px(t["camera_center_xyz"][:2])[0]
        assert cam["geometry"]["coordinates"] == pytest.approx(centre, abs=0.01)
        look = next(f for f in feats if f["properties"]["kind"] == "look"
                    and f["properties"]["name"] == name)  # fmt: skip
        a, e = np.asarray(look["geometry"]["coordinates"])
        g = frame.to_px(t["ground_point_of_image_centre"][:2])[0]
        ang = np.degrees(np.arctan2(*(e - a)[::-1]) - np.arctan2(*(g - a)[::-1]))
        assert abs((ang + 180) % 360 - 180) < 5, name


@pytest.mark.shared
@pytest.mark.skipif(not CHROMIUM.exists(), reason="/usr/bin/chromium is absent")
def test_real_map_view_renders_in_chromium(odm_view: tuple[Path, dict], tmp_path: Path) -> None:
    root, _ = odm_view
    with HeadlessChromium(tmp_path / "profile", 1400, 900) as b:
        b.open((root / "report/map.html").resolve().as_uri())
        b.wait_for("document.body.dataset.ready === '1' && document.body.dataset.ortho === 'loaded'")
        b.wait_for("Array.from(document.querySelectorAll('img.georeg-query-image'))"
                   ".every(i => i.complete && i.naturalWidth > 0)")  # fmt: skip
        shot = cv2.imdecode(np.frombuffer(b.screenshot(), np.uint8), cv2.IMREAD_COLOR)
        (tmp_path / "shot.png").write_bytes(cv2.imencode(".png", shot)[1].tobytes())
        x0, y0, w, h = (int(v) for v in b.evaluate(
            "(r => [r.left, r.top, r.width, r.height])"
            "(document.getElementById('map').getBoundingClientRect())"))  # fmt: skip
        area = shot[y0 : y0 + h, x0 : x0 + w]
        assert area.std() > 25 and len(np.unique(area.reshape(-1, 3) // 16, axis=0)) > 200
        assert b.evaluate("document.querySelectorAll('path.georeg-camera').length") == 2
        assert b.evaluate("document.querySelectorAll('path.georeg-frame_footprint').length") == 2
        assert b.errors() == []


def test_report_links_the_map_view(tmp_path: Path) -> None:
    from georeg.report.html import build_report

    out = tmp_path / "report" / "index.html"
    build_report([], {}, out, log_roots=[], map_html=tmp_path / "report" / "map.html")
    page = out.read_text()
    assert page.count('href="map.html"') == 2 and "<script" not in page
    build_report([], {}, out, log_roots=[])
    assert "map.html" not in out.read_text()


def test_bad_inputs_name_the_file_and_leave_no_output(run_dir: Path, tmp_path: Path) -> None:
    from georeg.io.errors import InputError

    bad = tmp_path / "ortho.tif"
    bad.write_bytes(b"II*\x00 not a tiff")
    out = tmp_path / "report"
    with pytest.raises(InputError, match="ortho.tif"):
        write_map_view(out / "map.html", out / "map", run_dir / "map/grid.json", bad, [])
    grid = tmp_path / "grid.json"
    grid.write_text("{}")
    with pytest.raises(InputError, match="grid.json"):
        write_map_view(out / "map.html", out / "map", grid, run_dir / "map/ortho.tif", [])
    assert not out.exists() or not any(out.iterdir())  # no half-written page or folder
