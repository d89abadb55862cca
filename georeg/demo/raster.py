"""Paint the vector layout on a regular north-up grid: labels, materials, heights, texture."""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np
from affine import Affine

from georeg.demo import classes as C
from georeg.demo import spectra as S
from georeg.demo.layout import SIDEWALK_M, Layout, intersects, tree_boxes


@dataclass(frozen=True)
class Grid:
    """North-up grid: top-left corner (x0, y0), pixel size ``res`` (m), ``width`` x ``height``."""

    x0: float
    y0: float
    res: float
    width: int
    height: int

    @property
    def transform(self) -> Affine:
        return Affine(self.res, 0.0, self.x0, 0.0, -self.res, self.y0)

    @property
    def bounds(self) -> tuple[float, float, float, float]:
        return (self.x0, self.y0 - self.height * self.res, self.x0 + self.width * self.res, self.y0)

    def xs(self) -> np.ndarray:
        return self.x0 + (np.arange(self.width) + 0.5) * self.res

    def ys(self) -> np.ndarray:
        return self.y0 - (np.arange(self.height) + 0.5) * self.res

    def window(self, x0: float, y0: float, x1: float, y1: float) -> tuple[int, int, int, int]:
        """Row/col slice bounds of the pixels whose centres fall inside the box."""
        c0 = int(np.ceil((x0 - self.x0) / self.res - 0.5))
        c1 = int(np.ceil((x1 - self.x0) / self.res - 0.5))
        r0 = int(np.ceil((self.y0 - y1) / self.res - 0.5))
        r1 = int(np.ceil((self.y0 - y0) / self.res - 0.5))
        return max(r0, 0), min(r1, self.height), max(c0, 0), min(c1, self.width)

    def crop(self, r0: int, c0: int, height: int, width: int) -> Grid:
        return Grid(self.x0 + c0 * self.res, self.y0 - r0 * self.res, self.res, width, height)

    def to_pixel(self, x: np.ndarray, y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Fractional (col, row) of map coordinates, pixel centres at integers."""
        return (x - self.x0) / self.res - 0.5, (self.y0 - y) / self.res - 0.5


class Texture:
    """World-fixed multi-octave value noise (same surface texture seen by every sensor)."""

    SPACINGS = (40.0, 9.0, 2.0)
    WEIGHTS = (0.55, 0.45, 0.55)

    def __init__(self, rng: np.random.Generator, extent: tuple[float, float, float, float]) -> None:
        self.xmin, _, _, self.ymax = extent
        w, h = extent[2] - extent[0], extent[3] - extent[1]
        self.lattices = [
            rng.standard_normal((int(h / s) + 3, int(w / s) + 3), dtype=np.float32)
            for s in self.SPACINGS
        ]
        # independent fine-scale field for tree-crown clumping
        self.crown = rng.standard_normal((int(h / 0.9) + 3, int(w / 0.9) + 3), dtype=np.float32)

    def _sample(self, lat: np.ndarray, spacing: float, grid: Grid) -> np.ndarray:
        mx = ((grid.xs() - self.xmin) / spacing).astype(np.float32)
        my = ((self.ymax - grid.ys()) / spacing).astype(np.float32)
        mapx = np.broadcast_to(mx[None, :], (grid.height, grid.width))
        mapy = np.broadcast_to(my[:, None], (grid.height, grid.width))
        return cv2.remap(lat, np.ascontiguousarray(mapx), np.ascontiguousarray(mapy), cv2.INTER_CUBIC,
                         borderMode=cv2.BORDER_REFLECT)  # fmt: skip

    def field(self, grid: Grid) -> np.ndarray:
        """Unit-variance-ish texture on ``grid`` (float32)."""
        out = np.zeros((grid.height, grid.width), np.float32)
        for lat, s, wgt in zip(self.lattices, self.SPACINGS, self.WEIGHTS, strict=True):
            out += wgt * self._sample(lat, s, grid)
        return out

    def crown_field(self, grid: Grid) -> np.ndarray:
        return self._sample(self.crown, 0.9, grid)


@dataclass
class Surface:
    """Per-pixel scene state on a grid."""

    grid: Grid
    label: np.ndarray  # uint8 class code
    mat: np.ndarray  # uint8 material id
    c1: np.ndarray  # float32 brightness variation
    c2: np.ndarray  # float32 material parameter
    dsm: np.ndarray  # float32 surface elevation (m)
    dtm: np.ndarray  # float32 ground elevation (m)


def _street_masks(
    v: np.ndarray, intervals: np.ndarray, pad: float
) -> tuple[np.ndarray, np.ndarray]:
    """Index of the street containing each coordinate (or -1) after widening by ``pad``."""
    i = np.searchsorted(intervals[:, 0] - pad, v, side="right") - 1
    i = np.clip(i, 0, len(intervals) - 1)
    inside = (v >= intervals[i, 0] - pad) & (v < intervals[i, 1] + pad)
    return np.where(inside, i, -1), inside


def rasterize(layout: Layout, grid: Grid, epoch: int, texture: Texture) -> Surface:
    """Paint ``layout`` as it is at ``epoch`` (EPOCH_MAP or EPOCH_QUERY) on ``grid``."""
    xs, ys = grid.xs(), grid.ys()
    H, W = grid.height, grid.width
    dtm = layout.terrain(xs[None, :], ys[:, None]).astype(np.float32)
    st = layout.streets
    # block interiors
    bj, bi = layout.block_index(xs[None, :], ys[:, None])
    label = layout.block_label[bj, bi]
    mat = layout.block_mat[bj, bi]
    c1 = layout.block_c1[bj, bi].astype(np.float32)
    c2 = layout.block_c2[bj, bi].astype(np.float32)
    # sidewalks then streets
    _, swx = _street_masks(xs, st.x, SIDEWALK_M)
    _, swy = _street_masks(ys, st.y, SIDEWALK_M)
    sw = swx[None, :] | swy[:, None]
    label[sw], mat[sw] = C.CONCRETE, S.CONCRETE
    ix, rx = _street_masks(xs, st.x, 0.0)
    iy, ry = _street_masks(ys, st.y, 0.0)
    road_x = np.broadcast_to(rx[None, :], (H, W))
    road = road_x | ry[:, None]
    label[road], mat[road] = C.ROAD, S.ASPHALT
    age = np.where(
        road_x, st.x_age[np.maximum(ix, 0)][None, :], st.y_age[np.maximum(iy, 0)][:, None]
    )
    c2[road] = age[road]
    c1[sw | road] = 0.0
    r = layout.rects
    sel = np.flatnonzero(intersects(r, grid.bounds) & ((r["epoch"] & epoch) > 0))
    sel = sel[np.lexsort((sel, r["layer"][sel]))]
    dsm = dtm.copy()
    avenue_done = False
    for k in sel:
        if r["layer"][k] >= 3 and not avenue_done:
            _paint_avenue(layout, xs, ys, label, mat, c1, c2)
            avenue_done = True
        r0, r1, cc0, cc1 = grid.window(r["x0"][k], r["y0"][k], r["x1"][k], r["y1"][k])
        if r0 >= r1 or cc0 >= cc1:
            continue
        win = (slice(r0, r1), slice(cc0, cc1))
        m = np.ones((r1 - r0, cc1 - cc0), bool)
        if r["shape"][k] == 1:  # ellipse
            cx, cy = 0.5 * (r["x0"][k] + r["x1"][k]), 0.5 * (r["y0"][k] + r["y1"][k])
            ax, ay = 0.5 * (r["x1"][k] - r["x0"][k]), 0.5 * (r["y1"][k] - r["y0"][k])
            m = ((xs[cc0:cc1][None, :] - cx) / ax) ** 2 + ((ys[r0:r1][:, None] - cy) / ay) ** 2 < 1
        label[win][m], mat[win][m] = r["label"][k], r["mat"][k]
        c1[win][m], c2[win][m] = r["c1"][k], r["c2"][k]
        h = r["h"][k]
        if h > 0:
            base = r["base"][k] if np.isfinite(r["base"][k]) else dtm[win]
            z = base + h + _ridge(r, k, xs[cc0:cc1], ys[r0:r1])
            dsm[win] = np.where(m, z, dsm[win])
    if not avenue_done:
        _paint_avenue(layout, xs, ys, label, mat, c1, c2)
    _paint_trees(layout, grid, epoch, xs, ys, label, mat, c1, c2, dsm, dtm)
    # surface texture (world-fixed), tree crowns get an extra clumping term
    tex = texture.field(grid)
    c1 += S.TEXTURE_AMP[mat].astype(np.float32) * tex
    tree = label == C.TREE
    c1[tree] += 0.25 * texture.crown_field(grid)[tree]
    return Surface(grid, label, mat, c1, c2, dsm, dtm)


def _ridge(r: dict[str, np.ndarray], k: int, xs: np.ndarray, ys: np.ndarray) -> np.ndarray | float:
    """Extra height of a gable roof above its eaves (0 for flat roofs)."""
    if r["ridge"][k] == 0 or r["ridge_h"][k] <= 0:
        return 0.0
    if r["ridge"][k] == 1:  # ridge along x: height falls off in y
        c, half = 0.5 * (r["y0"][k] + r["y1"][k]), 0.5 * (r["y1"][k] - r["y0"][k])
        d = np.abs(ys[:, None] - c) / half + 0 * xs[None, :]
    else:
        c, half = 0.5 * (r["x0"][k] + r["x1"][k]), 0.5 * (r["x1"][k] - r["x0"][k])
        d = np.abs(xs[None, :] - c) / half + 0 * ys[:, None]
    return r["ridge_h"][k] * np.clip(1.0 - d, 0.0, 1.0)


def _paint_avenue(layout, xs, ys, label, mat, c1, c2) -> None:
    st = layout.streets
    d = np.abs(st.diag_distance(xs[None, :], ys[:, None]))
    sw = d < st.diag_width / 2 + SIDEWALK_M
    label[sw], mat[sw], c1[sw] = C.CONCRETE, S.CONCRETE, 0.0
    road = d < st.diag_width / 2
    label[road], mat[road], c2[road] = C.ROAD, S.ASPHALT, 0.15


def _paint_trees(layout, grid, epoch, xs, ys, label, mat, c1, c2, dsm, dtm) -> None:
    t = layout.trees
    sel = np.flatnonzero(intersects(tree_boxes(t), grid.bounds) & ((t["epoch"] & epoch) > 0))
    for k in sel:
        cx, cy, rad = t["cx"][k], t["cy"][k], t["r"][k]
        r0, r1, cc0, cc1 = grid.window(cx - rad, cy - rad, cx + rad, cy + rad)
        if r0 >= r1 or cc0 >= cc1:
            continue
        win = (slice(r0, r1), slice(cc0, cc1))
        q = ((xs[cc0:cc1][None, :] - cx) ** 2 + (ys[r0:r1][:, None] - cy) ** 2) / rad**2
        inside = q < 1
        z = dtm[win] + t["hb"][k] + (t["h"][k] - t["hb"][k]) * np.sqrt(np.clip(1 - q, 0, 1))
        m = inside & (z > dsm[win])
        dsm[win] = np.where(m, z, dsm[win])
        label[win][m], mat[win][m] = C.TREE, S.LEAF
        c1[win][m], c2[win][m] = t["c1"][k], t["c2"][k]
