"""The report's frames section, from synthetic poses.json files (no localisation run).

Set "drone": 4 frames (2 registered with known errors, 1 missed, 1 correctly not found) and their
800 x 600 overlays: one row per frame, the mean row, thumbnails. Set "video": 120 entries with
frame indices, keyframes and a truth file: statistics, one path plot, at most 6 overlays.
"""

from __future__ import annotations

import base64
import json
from html.parser import HTMLParser
from pathlib import Path

import cv2
import numpy as np
import pytest

from georeg.report.frames_html import MAX_VIDEO_OVERLAYS, THUMB_WIDTH, _truth_centres
from georeg.report.html import build_report

ERR_A = {"horizontal_m": 1.0, "vertical_m": 0.5, "position_m": 1.118, "rotation_deg": 0.2}
ERR_D = {"horizontal_m": 3.0, "vertical_m": 0.1, "position_m": 3.002, "rotation_deg": 0.6}
PNP_A = {"horizontal_m": 2.0, "vertical_m": 1.5, "position_m": 2.5, "rotation_deg": 1.0}
PNP_D = {"horizontal_m": 4.0, "vertical_m": 0.5, "position_m": 4.03, "rotation_deg": 0.4}


def _entry(name: str, status: str, expected: str, pnp=None, final=None, **kw) -> dict:
    ev = {"expected": expected}
    if pnp:
        ev["pnp"] = pnp
    if final:
        ev["final"] = final
    reg = status == "registered"
    return {"image": f"frames/{name}.png", "status": status,
            "camera_center_xyz": [100.0, 200.0, 150.0] if reg else None,
            "R_world_to_cam": np.eye(3).tolist() if reg else None, "inliers": 40 if reg else 5,
            "reprojection_px": 1.25 if reg else None, "timings_s": {"total_s": 12.5},
            "evaluation": ev, **kw}  # fmt: skip


def _overlay(path: Path, w: int, h: int, seed: int) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    img = np.random.default_rng(seed).integers(0, 255, (h, w, 3), np.uint8)
    cv2.imwrite(str(path), cv2.GaussianBlur(img, (0, 0), 3))


def _truth_path(n: int) -> np.ndarray:
    t = np.linspace(0, np.pi, n)
    return np.c_[500 + 200 * np.cos(t), 800 + 200 * np.sin(t), np.full(n, 150.0)]


@pytest.fixture(scope="module")
def page(tmp_path_factory) -> tuple[Path, str, dict]:
    root = tmp_path_factory.mktemp("report_frames")
    drone = root / "frames" / "drone"
    poses = [_entry("a", "registered", "registered", PNP_A, ERR_A, path="direct 2D-3D",
                    verification={"score": 321, "candidates": []}),
             _entry("b", "not_found", "registered"),
             _entry("c", "not_found", "not_found"),
             _entry("d", "registered", "registered", PNP_D, ERR_D)]  # fmt: skip
    drone.mkdir(parents=True)
    (drone / "poses.json").write_text(json.dumps(poses))
    for i, p in enumerate(poses):
        _overlay(drone / "overlays" / f"{Path(p['image']).stem}.png", 800, 600, i)
    video = root / "frames" / "video"
    video.mkdir(parents=True)
    n = 120
    truth = _truth_path(n)
    rng = np.random.default_rng(0)
    vposes, errs = [], []
    for i in range(n):
        if i % 15 == 7:  # 8 entries not registered
            vposes.append({**_entry(f"v{i}", "not_found", "registered"), "frame": i})
            continue
        e = {"horizontal_m": float(rng.uniform(0, 3)), "vertical_m": float(rng.uniform(0, 1)),
             "rotation_deg": float(rng.uniform(0, 2))}  # fmt: skip
        e["position_m"] = float(np.hypot(e["horizontal_m"], e["vertical_m"]))
        errs.append(e)
        rec = _entry(f"v{i}", "registered", "registered", e, e, frame=i, keyframe=i % 10 == 0)
        rec["image"] = f"flight.mp4#{i}"
        rec["camera_center_xyz"] = (truth[i] + [e["horizontal_m"], 0, 0]).tolist()
        if i % 30 == 0:  # keyframes 0, 30, 60, 90 were tried alone: two registered
            alone = i % 60 == 0
            rec["single_frame"] = {"status": "registered" if alone else "not_found",
                                   "located_by_sequence_only": not alone}  # fmt: skip
        vposes.append(rec)
    (video / "poses.json").write_text(json.dumps(vposes))
    vtruth = [{"image": f"flight.mp4#{i}", "frame": i, "camera_center_xyz": truth[i].tolist()}
              for i in range(n)]  # fmt: skip
    (video / "truth.json").write_text(json.dumps(vtruth))
    for i in range(n):
        _overlay(video / "overlays" / f"flight_{i:05d}.png", 160, 120, i)
    sets = {"drone": {"poses": drone / "poses.json", "truth": None},
            "video": {"poses": video / "poses.json", "truth": video / "truth.json"}}  # fmt: skip
    out = root / "index.html"
    build_report([], {"frames": {}}, out, log_roots=[], frame_sets=sets)
    return root, out.read_text(), {"errs": errs, "vposes": vposes, "truth": vtruth}


class _Frames(HTMLParser):
    """Cells with data-key of the frames tables (by set), images and overlay figures by section."""

    def __init__(self) -> None:
        super().__init__()
        self.rows: dict[str, list[dict[str, str]]] = {}
        self.classes: dict[str, list[str]] = {}
        self.summary: dict[str, dict[str, str]] = {}
        self.images: dict[str, list[str]] = {}
        self._set, self._table, self._fig = "", "", ""

    def handle_starttag(self, tag: str, attrs: list[tuple[str, str | None]]) -> None:
        a = dict(attrs)
        if tag == "section" and (a.get("id") or "").startswith("frames-"):
            self._set = (a["id"] or "")[len("frames-") :]
        if tag == "table":
            self._table = a.get("class") or ""
        if tag == "tr" and self._table == "frames":
            self.rows.setdefault(self._set, []).append({})
        if tag in ("td", "th") and a.get("data-key"):
            key, val = a["data-key"] or "", a.get("data-value") or ""
            if self._table == "frames" and self.rows.get(self._set):
                self.rows[self._set][-1][key] = val
                if key == "status":
                    self.classes.setdefault(self._set, []).append(a.get("class") or "")
            elif self._table == "frames-summary":
                self.summary.setdefault(self._set, {})[key] = val
        if tag == "figure":
            self._fig = a.get("class") or ""
        if tag == "img" and self._set:
            self.images.setdefault(f"{self._set}/{self._fig}", []).append(a.get("src") or "")

    def handle_endtag(self, tag: str) -> None:
        if tag == "table":
            self._table = ""
        if tag == "section":
            self._set = ""


def _parse(text: str) -> _Frames:
    p = _Frames()
    p.feed(text)
    return p


def _num(v: str):
    return json.loads(v) if v else None


def test_frame_rows_and_mean_equal_the_json(page) -> None:
    root, text, _ = page
    p = _parse(text)
    rows = [r for r in p.rows["drone"] if r]
    assert [r["frame"] for r in rows] == ["a", "b", "c", "d", "mean"]
    saved = json.loads((root / "frames/drone/poses.json").read_text())
    for r, s in zip(rows[:4], saved, strict=True):
        assert r["status"] == s["status"]
        assert _num(r["inliers"]) == s["inliers"]
        assert _num(r["reprojection_px"]) == s["reprojection_px"]
        assert _num(r["seconds"]) == 12.5
        assert r["path"] == (s.get("path") or "")
        assert _num(r["verification_score"]) == (s.get("verification") or {}).get("score")
        for key in ("pnp", "final"):
            e = s["evaluation"].get(key) or {}
            for k in ("horizontal_m", "vertical_m", "rotation_deg"):
                assert _num(r[f"{key}_{k}"]) == e.get(k)
    mean = rows[-1]
    # means over a and d, by hand
    assert _num(mean["final_horizontal_m"]) == pytest.approx(2.0)
    assert _num(mean["final_vertical_m"]) == pytest.approx(0.3)
    assert _num(mean["final_rotation_deg"]) == pytest.approx(0.4)
    assert _num(mean["pnp_horizontal_m"]) == pytest.approx(3.0)
    assert _num(mean["pnp_vertical_m"]) == pytest.approx(1.0)
    assert _num(mean["pnp_rotation_deg"]) == pytest.approx(0.7)
    # b was expected registered: the only red status
    assert p.classes["drone"] == ["ok", "bad", "ok", "ok"]
    assert "registered (registered)" in text and "not_found (registered)" in text


def test_overlay_thumbnails_are_small_jpegs(page) -> None:
    _, text, _ = page
    imgs = _parse(text).images["drone/overlay"]
    assert len(imgs) == 4
    for src in imgs:
        assert src.startswith("data:image/jpeg;base64,")
        raw = np.frombuffer(base64.b64decode(src.split(",", 1)[1]), np.uint8)
        img = cv2.imdecode(raw, cv2.IMREAD_COLOR)
        assert img.shape[:2] == (270, THUMB_WIDTH)  # 800 x 600 downscaled, aspect kept


def test_video_set_gets_statistics_plot_and_few_overlays(page) -> None:
    _, text, data = page
    p = _parse(text)
    assert "video" not in p.rows  # no per-frame table
    s = {k: _num(v) for k, v in p.summary["video"].items()}
    errs = data["errs"]
    assert s["entries"] == 120 and s["registered"] == len(errs) == 112
    assert s["status_wrong"] == 8 and s["keyframes"] == 12
    assert (s["single_tried"], s["single_registered"], s["sequence_only"]) == (4, 2, 2)
    pos = [e["position_m"] for e in errs]
    rot = [e["rotation_deg"] for e in errs]
    assert s["final_n"] == 112
    assert s["final_position_m_mean"] == pytest.approx(np.mean(pos))
    assert s["final_position_m_p90"] == pytest.approx(np.percentile(pos, 90))
    assert s["final_rotation_deg_mean"] == pytest.approx(np.mean(rot))
    assert s["final_rotation_deg_p90"] == pytest.approx(np.percentile(rot, 90))
    plots = p.images["video/path-plot"]
    assert len(plots) == 1 and plots[0].startswith("data:image/png;base64,")
    plot = cv2.imdecode(
        np.frombuffer(base64.b64decode(plots[0].split(",", 1)[1]), np.uint8), cv2.IMREAD_COLOR
    )
    assert plot.shape[1] <= 500 and plot.std() > 5
    assert len(p.images["video/overlay"]) == MAX_VIDEO_OVERLAYS
    assert len(text) < 600_000  # 120 overlays on disk, 6 thumbnails + 1 plot in the page


def test_truth_path_from_the_truth_file_by_frame_index(page) -> None:
    _, _, data = page
    tc = _truth_centres(data["vposes"], data["truth"])
    assert all(c is not None for c in tc)
    assert np.allclose(tc[37], data["truth"][37]["camera_center_xyz"])


def test_no_frame_sets_no_section(tmp_path: Path) -> None:
    build_report([], {}, tmp_path / "index.html", log_roots=[])
    text = (tmp_path / "index.html").read_text()
    assert 'id="frames"' not in text and "frame set" not in text


def test_flat_ground_is_said_above_the_table(tmp_path: Path) -> None:
    """Poses localised without elevation carry a warning; the set's section repeats it, counted."""
    from georeg.frames.localize import FLAT_GROUND_WARNING
    from georeg.report.frames_html import set_section

    ground = {"source": "flat (no DSM given)", "z": 0.0, "warning": FLAT_GROUND_WARNING}
    poses = [_entry("a", "registered", "registered", PNP_A, ERR_A, ground=ground),
             _entry("b", "not_found", "not_found", ground=ground), _entry("c", "not_found", "not_found")]  # fmt: skip
    (tmp_path / "poses.json").write_text(json.dumps(poses))
    text = set_section("drone", tmp_path / "poses.json")
    assert 'data-key="flat_ground" data-value="2"' in text and "2 of 3 entries" in text
    (tmp_path / "poses.json").write_text(json.dumps(poses[2:]))
    assert "flat_ground" not in set_section("drone", tmp_path / "poses.json")


def test_feature_map_service_is_said_above_the_table(tmp_path: Path) -> None:
    """Frames tried against a feature map: the section says which it served and how many fell back."""
    from georeg.report.frames_html import set_section

    fm = {"sources": ["sfm_points.laz"], "map_points": 1234}
    poses = [_entry("a", "registered", "registered", PNP_A, ERR_A, path="feature map 2D-3D",
                    feature_map={**fm, "used": True}),
             _entry("b", "registered", "registered", PNP_A, ERR_A, path="direct 2D-3D",
                    feature_map={**fm, "used": False, "fallback": "map-only path: 3 PnP inliers"}),
             _entry("c", "not_found", "not_found")]  # fmt: skip
    (tmp_path / "poses.json").write_text(json.dumps(poses))
    text = set_section("later", tmp_path / "poses.json")
    assert 'data-key="feature_map_served" data-value="1"' in text
    assert "served 1 of 2 frames tried (a.png)" in text and "1234 points" in text
    (tmp_path / "poses.json").write_text(json.dumps(poses[2:]))
    assert "feature_map_served" not in set_section("later", tmp_path / "poses.json")
