"""Scene changes between the map epoch (orthophoto/LiDAR) and the query epoch ("months later")."""

from __future__ import annotations

import numpy as np

from georeg.demo import classes as C
from georeg.demo import spectra as S
from georeg.demo.layout import (
    EPOCH_BOTH,
    EPOCH_MAP,
    EPOCH_QUERY,
    KIND_BUILDING,
    KIND_CAR,
    KIND_ROOFTOP,
    SIDEWALK_M,
    Layout,
    intersects,
    tree_boxes,
)
from georeg.demo.pushbroom import Flight


def _inside(flight: Flight, x: np.ndarray, y: np.ndarray, margin: float) -> np.ndarray:
    """Points inside the nominal footprint of ``flight``, at least ``margin`` m from its edges."""
    u, v = flight.axes()
    dx, dy = np.asarray(x) - flight.centre[0], np.asarray(y) - flight.centre[1]
    a, c = dx * u[0] + dy * u[1], dx * v[0] + dy * v[1]
    ha, hc = flight.lines * flight.gsd / 2 - margin, flight.samples * flight.gsd / 2 - margin
    return (np.abs(a) < ha) & (np.abs(c) < hc)


def _box(r: dict[str, np.ndarray], k: int) -> list[float]:
    return [float(r["x0"][k]), float(r["y0"][k]), float(r["x1"][k]), float(r["y1"][k])]


def apply_changes(layout: Layout, rng: np.random.Generator, flight: Flight) -> list[dict]:
    """Cut trees and raise a new building inside the query footprint (in place); list the changes."""
    changes: list[dict] = []
    t = layout.trees
    cand = np.flatnonzero((t["epoch"] == EPOCH_BOTH) & _inside(flight, t["cx"], t["cy"], 10.0))
    n_cut = min(cand.size, max(3, int(0.08 * cand.size)))
    for k in np.sort(rng.choice(cand, n_cut, replace=False)) if n_cut else []:
        t["epoch"][k] = EPOCH_MAP
        changes.append({"kind": "tree_cut", "bbox": _box(tree_boxes(t), k)})
    # a new building on a block interior fully inside the footprint
    st = layout.streets
    xs0, xs1 = st.x[:-1, 1] + SIDEWALK_M, st.x[1:, 0] - SIDEWALK_M
    ys0, ys1 = st.y[:-1, 1] + SIDEWALK_M, st.y[1:, 0] - SIDEWALK_M
    bx0, by0 = np.meshgrid(xs0, ys0)
    bx1, by1 = np.meshgrid(xs1, ys1)
    ok = np.ones(bx0.shape, bool)
    for cx, cy in ((bx0, by0), (bx1, by0), (bx0, by1), (bx1, by1)):
        ok &= _inside(flight, cx, cy, 4.0)
    ok &= np.abs(
        st.diag_distance(0.5 * (bx0 + bx1), 0.5 * (by0 + by1))
    ) > st.diag_width + 0.5 * np.hypot(bx1 - bx0, by1 - by0)
    if ok.any():
        j, i = np.argwhere(ok)[rng.integers(ok.sum())]
        box = (bx0[j, i], by0[j, i], bx1[j, i], by1[j, i])
    else:  # tiny footprint: a small building near its centre
        half = min(flight.lines, flight.samples) * flight.gsd / 8
        box = (
            flight.centre[0] - half,
            flight.centre[1] - half,
            flight.centre[0] + half,
            flight.centre[1] + half,
        )
    w, h = box[2] - box[0], box[3] - box[1]
    fw, fh = w * rng.uniform(0.4, 0.7), h * rng.uniform(0.4, 0.7)
    fx, fy = box[0] + rng.uniform(0, w - fw), box[1] + rng.uniform(0, h - fh)
    fp = (fx, fy, fx + fw, fy + fh)
    r = layout.rects
    hit = (
        intersects(r, fp)
        & np.isin(r["kind"], (KIND_BUILDING, KIND_ROOFTOP, KIND_CAR))
        & ((r["epoch"] & EPOCH_QUERY) > 0)
    )
    for k in np.flatnonzero(hit):
        r["epoch"][k] &= EPOCH_MAP
        changes.append({"kind": "removed_for_construction", "bbox": _box(r, k)})
    thit = np.flatnonzero(intersects(tree_boxes(t), fp) & ((t["epoch"] & EPOCH_QUERY) > 0))
    for k in thit:
        t["epoch"][k] &= EPOCH_MAP
        changes.append({"kind": "tree_cut", "bbox": _box(tree_boxes(t), k)})
    height = float(rng.uniform(18.0, 45.0))
    bid = int(r["bid"].max(initial=0)) + 1
    new = {
        "x0": fp[0], "y0": fp[1], "x1": fp[2], "y1": fp[3], "layer": 3, "label": C.TALL_BUILDING,
        "mat": S.ROOF_COOL, "c1": 0.05, "c2": 0.1, "h": height, "ridge_h": 0.0, "ridge": 0, "shape": 0,
        "kind": KIND_BUILDING, "base": float(layout.terrain(0.5 * (fp[0] + fp[2]), 0.5 * (fp[1] + fp[3]))),
        "bid": bid, "epoch": EPOCH_QUERY,
    }  # fmt: skip
    for k, v in new.items():
        r[k] = np.append(r[k], np.asarray(v, dtype=r[k].dtype))
    changes.append(
        {"kind": "new_building", "bbox": [float(v) for v in fp], "height_m": height, "id": bid}
    )
    return changes


def car_changes(layout: Layout, boxes: list[tuple[float, float, float, float]]) -> list[dict]:
    """Cars present at only one epoch, inside any of ``boxes``."""
    r = layout.rects
    sel = (r["kind"] == KIND_CAR) & (r["epoch"] != EPOCH_BOTH) & (r["epoch"] > 0)
    near = np.zeros_like(sel)
    for b in boxes:
        near |= intersects(r, b)
    out = []
    for k in np.flatnonzero(sel & near):
        kind = "car_removed" if r["epoch"][k] == EPOCH_MAP else "car_added"
        out.append({"kind": kind, "bbox": _box(r, k)})
    return out
