"""The index coarse search of frames (georeg.frames.coarse.coarse_index) on maps padded with
other imagery (georeg.demo.padmap), and the location prior (georeg.io.prior).

Synthetic: a textured map at 1 m padded with other textures (3 x 3 blocks of 512 px), a nadir
frame rendered from it (rotated, 1.2 m GSD) found by the index search within a few metres, its
budget recorded, a prior that excludes it finds nothing, a frame of a texture not on the map is
``not_found``. Real (skips without ../shared): the odm drone frames inside a 9 Mpx map of other
real imagery, within one map GSD (0.2 m); an ngi frame (elsewhere) ``not_found``.
"""

from __future__ import annotations

import json
from pathlib import Path

import cv2
import numpy as np
import pytest
import rasterio
from affine import Affine

from georeg.demo.padmap import build
from georeg.frames.coarse import coarse_index
from georeg.frames.localize import MapSources, localize_frame, localize_image, set_prior
from georeg.io.errors import InputError
from georeg.io.prior import check_prior, prior_bounds

REPO = Path(__file__).resolve().parents[1]
DATA = REPO.parent / "shared" / "data"
CRS = rasterio.crs.CRS.from_epsg(32633).to_wkt()
SIDE = 512
FX, W, H = 250.0, 320, 240


def texture(seed: int, side: int = SIDE) -> np.ndarray:
    """Random rectangles and discs of random colours on a noisy ground, lightly blurred."""
    rng = np.random.default_rng(seed)
    img = (rng.normal(120, 12, (side, side, 3))).clip(0, 255).astype(np.uint8)
    for _ in range(side * side // 900):
        col = tuple(int(v) for v in rng.integers(0, 256, 3))
        x, y = (int(v) for v in rng.integers(0, side, 2))
        if rng.random() < 0.5:
            w, h = (int(v) for v in rng.integers(4, 30, 2))
            cv2.rectangle(img, (x, y), (x + w, y + h), col, -1)
        else:
            cv2.circle(img, (x, y), int(rng.integers(3, 15)), col, -1)
    return cv2.GaussianBlur(img, (3, 3), 0.8)


def make_case(d: Path, seed: int = 1, z: float = 100.0) -> Path:
    """A one-block case dir (map_ortho.tif, elevation.tif, case.json) at 1 m, EPSG:32633."""
    d.mkdir(parents=True, exist_ok=True)
    tr = Affine(1.0, 0, 500_000.0, 0, -1.0, 5_000_000.0)
    prof = {"driver": "GTiff", "width": SIDE, "height": SIDE, "crs": CRS, "transform": tr}
    with rasterio.open(d / "map_ortho.tif", "w", count=3, dtype="uint8", nodata=0, **prof) as o:
        o.write(np.moveaxis(np.maximum(texture(seed), 1), -1, 0))
    with rasterio.open(d / "elevation.tif", "w", count=1, dtype="float32", **prof) as o:
        o.write(np.full((1, SIDE, SIDE), z, np.float32))
    (d / "case.json").write_text(json.dumps({"crs_wkt": CRS}))
    return d


def nadir_frame(ortho: str, centre: tuple[float, float], gsd: float, heading_deg: float, z: float):
    """A nadir frame of the map ``ortho`` (W x H, fx ``FX``) over ``centre`` at ``gsd``, turned by
    ``heading_deg``: (gray, K, R, C)."""
    t = np.radians(heading_deg)
    R0 = np.array([[1.0, 0, 0], [0, -1, 0], [0, 0, -1]])
    Rz = np.array([[np.cos(t), -np.sin(t), 0], [np.sin(t), np.cos(t), 0], [0, 0, 1]])
    R = Rz @ R0
    C = np.array([centre[0], centre[1], z + gsd * FX])
    K = np.array([[FX, 0, (W - 1) / 2], [0, FX, (H - 1) / 2], [0, 0, 1]])
    with rasterio.open(ortho) as s:
        img, inv = np.moveaxis(s.read([1, 2, 3]), 0, -1), ~s.transform
    world = np.array([[centre[0] + dx, centre[1] + dy, z] for dx in (-300, 300) for dy in (-300, 300)])
    cam = (R @ (world - C).T).T
    uv = (K @ cam.T).T
    uv = uv[:, :2] / uv[:, 2:]
    px = np.array([inv @ (x, y) for x, y, _ in world]) - 0.5  # pixel-centre convention
    Hm = cv2.findHomography(px.astype(np.float32), uv.astype(np.float32))[0]
    frame = cv2.warpPerspective(img, Hm, (W, H), flags=cv2.INTER_AREA)
    return cv2.cvtColor(frame, cv2.COLOR_RGB2GRAY), K, R, C


@pytest.fixture(scope="module")
def synth(tmp_path_factory):
    root = tmp_path_factory.mktemp("padsynth")
    case = make_case(root / "case")
    pads = [texture(100 + i) for i in range(6)]
    man = build(case, None, 3, root / "map", seed=0, vocab_k=64, sample=20_000, pads=pads, block=SIDE)
    return root, man


def test_padmap_layout(synth):
    root, man = synth
    assert man["blocks_per_side"] == 3 and list(man["case_blocks"]) == [1, 1]
    with rasterio.open(root / "map" / "ortho.vrt") as s, rasterio.open(root / "case" / "map_ortho.tif") as c:
        assert s.width == 3 * SIDE
        # the case keeps its pixels and coordinates inside the padded map
        win = rasterio.windows.from_bounds(*c.bounds, s.transform)
        assert np.array_equal(s.read(window=win), c.read())


def test_index_coarse_finds_the_frame(synth):
    root, _ = synth
    maps = MapSources(root / "map" / "index", root / "map" / "ortho.vrt", root / "map" / "dsm.vrt")
    with rasterio.open(root / "case" / "map_ortho.tif") as c:
        cx, cy = (c.bounds.left + c.bounds.right) / 2, (c.bounds.bottom + c.bounds.top) / 2
    gray, K, R, C = nadir_frame(str(root / "map" / "ortho.vrt"), (cx + 20, cy - 30), 1.2, 30.0, 100.0)
    co = coarse_index(gray, K, maps.index, maps.gsd, {"max_regions": 4})
    assert co.ok, co.reason
    assert np.hypot(*(co.C[:2] - C[:2])) < 5.0
    b = co.budget
    assert b["mode"] == "index" and 1 <= b["regions_searched"] <= 2 * 4 and b["pnp_tests"] >= 1
    assert b["regions_budget"] == 4 and b["window_m"] == pytest.approx(1.5 * np.hypot(W, H), rel=1e-3)
    # a prior box away from the frame: no region there holds it
    far = (cx + 800, cy - 1000, cx + 1200, cy - 700)
    co2 = coarse_index(gray, K, maps.index, maps.gsd, {"max_regions": 4}, prior=far)
    assert not co2.ok or np.hypot(*(co2.C[:2] - C[:2])) > 50
    assert co2.budget["prior"] == list(far)
    # a prior around it: found, fewer regions ranked
    near = (cx - 100, cy - 100, cx + 100, cy + 100)
    co3 = coarse_index(gray, K, maps.index, maps.gsd, {"max_regions": 4}, prior=near)
    assert co3.ok and np.hypot(*(co3.C[:2] - C[:2])) < 5.0
    assert co3.budget["regions_ranked"] < b["regions_ranked"] or b["regions_ranked"] <= 4


def test_localize_on_padded_map_and_elsewhere(synth, tmp_path):
    root, _ = synth
    maps = MapSources(root / "map" / "index", root / "map" / "ortho.vrt", root / "map" / "dsm.vrt")
    conf = {"direct": {"whole_map_first_px": 0, "whole_map_px": 0}, "search": {"enabled": False},
            "render_after_direct": False, "refine": {"enabled": False},
            "coarse": {"index_min_px": 0}}  # the index search on this small map  # fmt: skip
    with rasterio.open(root / "case" / "map_ortho.tif") as c:
        cx, cy = (c.bounds.left + c.bounds.right) / 2, (c.bounds.bottom + c.bounds.top) / 2
    gray, K, R, C = nadir_frame(str(root / "map" / "ortho.vrt"), (cx - 10, cy + 15), 1.0, -50.0, 100.0)
    cam = {"fx": FX, "fy": FX, "cx": K[0, 2], "cy": K[1, 2]}
    rec, _ = localize_image(cv2.cvtColor(gray, cv2.COLOR_GRAY2RGB), "f.png", cam, maps, conf)
    assert rec["status"] == "registered", rec.get("reason")
    assert np.linalg.norm(np.asarray(rec["camera_center_xyz"]) - C) < 1.0  # one map GSD
    assert rec["coarse"]["budget"]["mode"] == "index"
    # a frame of a texture that is not on the map
    other = make_case(tmp_path / "other", seed=999)
    g2, *_ = nadir_frame(str(other / "map_ortho.tif"), (500_256.0, 4_999_744.0), 1.0, 0.0, 100.0)
    rec2, _ = localize_image(cv2.cvtColor(g2, cv2.COLOR_GRAY2RGB), "g.png", cam, maps, conf)
    assert rec2["status"] == "not_found"
    # bounded: pnp_per_window (3) x max_regions (16) x 2 stages (nadir, then the tilts)
    assert rec2["coarse"]["budget"]["pnp_tests"] <= 3 * 16 * 2


def test_prior_parsing_and_record(synth):
    root, _ = synth
    assert prior_bounds({"centre": [10, 20], "radius_m": 5}, CRS) == (5.0, 15.0, 15.0, 25.0)
    assert prior_bounds({"box": [1, 2, 3, 4]}, CRS) == (1, 2, 3, 4)
    b = prior_bounds({"centre": [15.0, 45.1], "radius_m": 1000, "crs": "lonlat"}, CRS)
    assert b[2] - b[0] == pytest.approx(2000, abs=1e-6) and 400_000 < b[0] < 600_000
    ft = rasterio.crs.CRS.from_epsg(2913).to_wkt()  # Oregon North, international feet
    b = prior_bounds({"centre": [0, 0], "radius_m": 0.3048}, ft)
    assert b[2] == pytest.approx(1.0, rel=1e-3)
    for bad in ({"centre": [1, 2]}, {"box": [3, 2, 1, 4]}, {"box": [0, 0, 1, 1], "crs": "utm"},
                {"centre": [200, 0], "radius_m": 5, "crs": "lonlat"}, {"centre": [1, 2], "radius_m": -1}):  # fmt: skip
        with pytest.raises(ValueError):
            check_prior(bad)
    maps = MapSources(root / "map" / "index", root / "map" / "ortho.vrt", root / "map" / "dsm.vrt")
    with pytest.raises(InputError, match="frames.s1.prior"):
        set_prior(maps, {"box": [1, 2]}, "s1")
    rec = set_prior(maps, {"centre": [500_256.0, 4_999_744.0], "radius_m": 100}, "s1")
    assert rec["bounds"] == [500_156.0, 4_999_644.0, 500_356.0, 4_999_844.0]
    assert maps.prior_box == tuple(rec["bounds"])


# ------------------------------------------------------------------------------------ real data

@pytest.mark.shared
@pytest.mark.slow
@pytest.mark.skipif(not (DATA / "frames_dev").is_dir(), reason="../shared/data is absent")
def test_real_odm_frames_in_padded_map(tmp_path):
    case = DATA / "frames_dev" / "odm"
    man = build(case, DATA, 3, tmp_path / "map", seed=0)
    assert man["mpx"] > 9
    maps = MapSources(tmp_path / "map" / "index", tmp_path / "map" / "ortho.vrt", tmp_path / "map" / "dsm.vrt")
    for fid in ("0136", "0142"):
        truth = json.loads((case / "truth" / f"{fid}.json").read_text())
        cam = {k: truth["intrinsics"][k] for k in ("fx", "fy", "cx", "cy")}
        cam["dist"] = truth["intrinsics"]["dist"]
        rec, _ = localize_frame(str(case / "queries" / f"{fid}.png"), cam, maps,
                                {"coarse": {"index_min_px": 0}})  # a 9 Mpx map
        assert rec["status"] == "registered", rec.get("reason")
        assert rec["coarse"]["budget"]["mode"] == "index"
        err = np.linalg.norm(np.asarray(rec["camera_center_xyz"]) - truth["camera_center_xyz"])
        assert err < 0.2, (fid, err)  # one map GSD
    ngi = DATA / "frames_dev" / "ngi"
    truth = json.loads((ngi / "truth" / "0182.json").read_text())
    cam = {k: truth["intrinsics"][k] for k in ("fx", "fy", "cx", "cy")}
    rec, _ = localize_frame(str(ngi / "queries" / "0182.png"), cam, maps, {"coarse": {"index_min_px": 0}})
    assert rec["status"] == "not_found"


def test_input_check_names_a_bad_frames_prior(tmp_path):
    from georeg.register.inputs import check_inputs

    img = tmp_path / "f.png"
    cv2.imwrite(str(img), np.zeros((100, 100, 3), np.uint8))
    bad = check_inputs({"frames": {"s": {"images": [str(img)], "prior": {"centre": [1, 2]}}}}, None)
    assert any(p.startswith("frames.s.prior") and "radius_m" in p for p in bad), bad
    ok = check_inputs({"frames": {"s": {"images": [str(img)], "prior": {"box": [0, 0, 1, 1]}}}}, None)
    assert not any("prior" in p for p in ok), ok
