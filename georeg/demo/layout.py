"""Synthetic city layout: terrain, street grid, blocks and the objects in them (vector form).

The layout is resolution-free: rectangles (surfaces, buildings, cars), circles (trees) and
analytic terrain, in map coordinates (EPSG:32611 metres). ``raster.rasterize`` paints it on any
grid. Objects carry an epoch mask (1: orthophoto/LiDAR time, 2: query time) for scene changes.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from georeg.demo import classes as C
from georeg.demo import spectra as S

EPOCH_MAP, EPOCH_QUERY, EPOCH_BOTH = 1, 2, 3
KIND_SURFACE, KIND_BUILDING, KIND_ROOFTOP, KIND_CAR = 0, 1, 2, 3
SIDEWALK_M = 3.0
RECT_FIELDS = (
    "x0", "y0", "x1", "y1", "layer", "label", "mat", "c1", "c2", "h", "ridge_h", "ridge",
    "shape", "kind", "base", "bid", "epoch",
)  # fmt: skip
TREE_FIELDS = ("cx", "cy", "r", "h", "hb", "c1", "c2", "epoch")
BLOCK_TYPES = ("downtown", "residential", "commercial", "industrial", "park", "parking", "vacant")


@dataclass
class Terrain:
    """Smooth ground elevation (m): a base plus a few long-wavelength cosines."""

    base: float
    kx: np.ndarray
    ky: np.ndarray
    amp: np.ndarray
    phase: np.ndarray

    @classmethod
    def random(cls, rng: np.random.Generator) -> Terrain:
        n = 6
        wavelength = rng.uniform(900.0, 4000.0, n)
        theta = rng.uniform(0, np.pi, n)
        amp = rng.uniform(1.5, 4.0, n)
        return cls(
            base=float(rng.uniform(92.0, 98.0)),
            kx=2 * np.pi * np.cos(theta) / wavelength,
            ky=2 * np.pi * np.sin(theta) / wavelength,
            amp=amp,
            phase=rng.uniform(0, 2 * np.pi, n),
        )

    def __call__(self, x: np.ndarray, y: np.ndarray) -> np.ndarray:
        """Elevation at map coordinates (broadcasting x and y)."""
        x = np.asarray(x, dtype=np.float64) - 384000.0
        y = np.asarray(y, dtype=np.float64) - 3768000.0
        z = np.full(np.broadcast(x, y).shape, self.base)
        for kx, ky, a, p in zip(self.kx, self.ky, self.amp, self.phase, strict=True):
            z += a * np.cos(kx * x + ky * y + p)
        return z


@dataclass
class Streets:
    """Axis-aligned street grid: [start, end) intervals of N-S (x) and E-W (y) streets."""

    x: np.ndarray  # (n, 2) x intervals of north-south streets
    y: np.ndarray  # (m, 2) y intervals of east-west streets
    x_age: np.ndarray  # asphalt ageing per street (c2)
    y_age: np.ndarray
    diag_point: np.ndarray  # a point on the diagonal avenue
    diag_dir: np.ndarray  # its unit direction
    diag_width: float

    def diag_distance(self, x: np.ndarray, y: np.ndarray) -> np.ndarray:
        """Signed distance (m) from the diagonal avenue's centre line."""
        nx, ny = -self.diag_dir[1], self.diag_dir[0]
        return (x - self.diag_point[0]) * nx + (y - self.diag_point[1]) * ny


@dataclass
class Layout:
    """Everything that exists in the synthetic world, in vector form."""

    extent: tuple[float, float, float, float]  # xmin, ymin, xmax, ymax
    terrain: Terrain
    streets: Streets
    block_type: np.ndarray  # (ny, nx) index into BLOCK_TYPES
    block_label: np.ndarray  # base class code of each block interior
    block_mat: np.ndarray
    block_c1: np.ndarray
    block_c2: np.ndarray
    rects: dict[str, np.ndarray]
    trees: dict[str, np.ndarray]
    centres: list[tuple[float, float]] = field(default_factory=list)

    def block_index(self, x: np.ndarray, y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Block column/row index of coordinates (clipped to the block arrays)."""
        i = np.searchsorted(self.streets.x[:, 0], x, side="right") - 1
        j = np.searchsorted(self.streets.y[:, 0], y, side="right") - 1
        ny, nx = self.block_type.shape
        return np.clip(j, 0, ny - 1), np.clip(i, 0, nx - 1)


class _Builder:
    """Collects rectangles and trees as columns (scalar or vectorised appends)."""

    def __init__(self) -> None:
        self.r: dict[str, list] = {f: [] for f in RECT_FIELDS}
        self.t: dict[str, list] = {f: [] for f in TREE_FIELDS}

    def rect(self, box, *, layer, label, mat, c1=0.0, c2=0.0, h=0.0, ridge_h=0.0, ridge=0,
             shape=0, kind=KIND_SURFACE, base=np.nan, bid=-1, epoch=EPOCH_BOTH) -> None:  # fmt: skip
        vals = dict(x0=box[0], y0=box[1], x1=box[2], y1=box[3], layer=layer, label=label, mat=mat,
                    c1=c1, c2=c2, h=h, ridge_h=ridge_h, ridge=ridge, shape=shape, kind=kind,
                    base=base, bid=bid, epoch=epoch)  # fmt: skip
        for k, v in vals.items():
            self.r[k].append(np.atleast_1d(np.asarray(v, dtype=np.float64)))

    def rects(self, x0, y0, x1, y1, **kw) -> None:
        """Vectorised append: x0..y1 arrays, other fields scalars or arrays of the same length."""
        n = len(x0)
        if n == 0:
            return
        defaults = dict(c1=0.0, c2=0.0, h=0.0, ridge_h=0.0, ridge=0, shape=0, kind=KIND_SURFACE,
                        base=np.nan, bid=-1, epoch=EPOCH_BOTH)  # fmt: skip
        defaults.update(kw)
        vals = dict(x0=x0, y0=y0, x1=x1, y1=y1, **defaults)
        for k in RECT_FIELDS:
            self.r[k].append(np.broadcast_to(np.asarray(vals[k], dtype=np.float64), (n,)).copy())

    def trees(self, cx, cy, r, h, hb, c1, c2, epoch=EPOCH_BOTH) -> None:
        n = len(cx)
        if n == 0:
            return
        vals = dict(cx=cx, cy=cy, r=r, h=h, hb=hb, c1=c1, c2=c2, epoch=epoch)
        for k in TREE_FIELDS:
            self.t[k].append(np.broadcast_to(np.asarray(vals[k], dtype=np.float64), (n,)).copy())

    def arrays(self) -> tuple[dict[str, np.ndarray], dict[str, np.ndarray]]:
        r = {k: np.concatenate(v) if v else np.zeros(0) for k, v in self.r.items()}
        t = {k: np.concatenate(v) if v else np.zeros(0) for k, v in self.t.items()}
        for k in ("layer", "label", "mat", "ridge", "shape", "kind", "bid", "epoch"):
            r[k] = r[k].astype(np.int32)
        t["epoch"] = t["epoch"].astype(np.int32)
        return r, t


def _street_intervals(
    rng: np.random.Generator, lo: float, hi: float
) -> tuple[np.ndarray, np.ndarray]:
    """Street [start, end) intervals from ``lo`` to ``hi``: irregular blocks, some wide avenues."""
    out, age = [], []
    x = lo - rng.uniform(20, 120)
    k = 0
    while x < hi + 150:
        major = k % int(rng.integers(3, 6)) == 0
        w = rng.uniform(22, 30) if major else rng.uniform(11, 16)
        out.append((x, x + w))
        age.append(rng.uniform(0.0, 1.0))
        x += w + rng.uniform(75, 175)
        k += 1
    return np.array(out), np.array(age)


def _cars_in_lot(
    b: _Builder, rng: np.random.Generator, box, occ_map: float, occ_query: float
) -> None:
    """Rows of parking stalls in ``box`` with cars at both epochs (some stay, some move/arrive)."""
    x0, y0, x1, y1 = box
    along_x = (x1 - x0) >= (y1 - y0)
    if not along_x:  # work in a frame where rows run along the first axis
        x0, y0, x1, y1 = y0, x0, y1, x1
    n_mod = int((y1 - y0 - 1.0) // 17.4)
    n_st = int((x1 - x0 - 1.0) // 2.7)
    if n_mod < 1 or n_st < 1:
        return
    row_y = np.concatenate(
        [y0 + 0.5 + np.arange(n_mod) * 17.4, y0 + 0.5 + np.arange(n_mod) * 17.4 + 12.2]
    )
    sx = x0 + 0.5 + np.arange(n_st) * 2.7
    gx, gy = np.meshgrid(sx, row_y)
    gx, gy = gx.ravel(), gy.ravel()
    n = gx.size
    m = rng.random(n) < occ_map
    stay = m & (rng.random(n) < 0.5)
    new = ~stay & (rng.random(n) < occ_query)
    for sel, epoch in ((stay, EPOCH_BOTH), (m & ~stay, EPOCH_MAP), (new, EPOCH_QUERY)):
        k = int(sel.sum())
        if k == 0:
            continue
        cx = gx[sel] + 1.35 + rng.uniform(-0.2, 0.2, k)
        cy = gy[sel] + 2.6 + rng.uniform(-0.3, 0.3, k)
        half_w, half_l = 0.9 + rng.uniform(-0.05, 0.1, k), 2.25 + rng.uniform(-0.3, 0.4, k)
        c1, c2 = _car_colours(rng, k)
        a0, a1, b0, b1 = cx - half_w, cx + half_w, cy - half_l, cy + half_l
        if not along_x:
            a0, b0, a1, b1 = b0, a0, b1, a1
        b.rects(a0, b0, a1, b1, layer=5, label=C.VEHICLE, mat=S.CAR, c1=c1, c2=c2, h=1.5,
                kind=KIND_CAR, epoch=epoch)  # fmt: skip


def _car_colours(rng: np.random.Generator, k: int) -> tuple[np.ndarray, np.ndarray]:
    """Brightness (white, silver, grey, black...) and red tint of ``k`` cars."""
    c1 = rng.choice([-0.6, -0.3, 0.0, 1.5, 3.5], size=k, p=[0.25, 0.15, 0.2, 0.2, 0.2])
    c1 = c1 + rng.normal(0, 0.1, k)
    c2 = (rng.random(k) < 0.12).astype(float)
    return c1, c2


def _trees_in(b: _Builder, rng: np.random.Generator, box, n: int, rmin: float, rmax: float,
              hmin: float, hmax: float) -> None:  # fmt: skip
    """``n`` trees with random crowns inside ``box``."""
    if n <= 0:
        return
    x0, y0, x1, y1 = box
    r = rng.uniform(rmin, rmax, n)
    h = np.maximum(rng.uniform(hmin, hmax, n), 2.2 * r)
    h = np.minimum(h, 20.0)
    b.trees(rng.uniform(x0, x1, n), rng.uniform(y0, y1, n), r, h, h * rng.uniform(0.25, 0.45, n),
            rng.normal(0, 0.12, n), rng.uniform(0, 1, n))  # fmt: skip


def _block_downtown(b, rng, box, u, terrain, bid):
    x0, y0, x1, y1 = box
    w, h = x1 - x0, y1 - y0
    along_x = w >= h
    n = int(rng.integers(1, 4))
    cuts = np.sort(rng.uniform(0.25, 0.75, n - 1)) if n > 1 else np.array([])
    edges = np.concatenate([[0.0], cuts, [1.0]])
    for a, c in zip(edges[:-1], edges[1:], strict=True):
        p = (x0 + a * w, y0, x0 + c * w, y1) if along_x else (x0, y0 + a * h, x1, y0 + c * h)
        pw, ph = p[2] - p[0], p[3] - p[1]
        if pw < 12 or ph < 12:
            continue
        roll = rng.random()
        if roll < 0.72:
            bid += 1
            inset = rng.uniform(2, 6)
            fp = (p[0] + inset, p[1] + inset, p[2] - inset, p[3] - inset)
            cx, cy = 0.5 * (fp[0] + fp[2]), 0.5 * (fp[1] + fp[3])
            base = float(terrain(cx, cy))
            height = float(np.clip(15 + 105 * u * rng.random() ** 0.8, 15, 120))
            roof = rng.choice(
                [S.ROOF_TAR, S.ROOF_COOL, S.ROOF_METAL, S.CONCRETE], p=[0.35, 0.3, 0.15, 0.2]
            )
            label = C.TALL_BUILDING if height >= 13 else C.HOUSE
            if rng.random() < 0.3 and height > 30:  # podium + tower
                b.rect(fp, layer=3, label=label, mat=roof, c1=rng.normal(0, 0.1), c2=rng.random(),
                       h=rng.uniform(8, 15), kind=KIND_BUILDING, base=base, bid=bid)  # fmt: skip
                fw, fh = fp[2] - fp[0], fp[3] - fp[1]
                tw, th = fw * rng.uniform(0.45, 0.7), fh * rng.uniform(0.45, 0.7)
                tx, ty = fp[0] + rng.uniform(0, fw - tw), fp[1] + rng.uniform(0, fh - th)
                fp = (tx, ty, tx + tw, ty + th)
                roof = rng.choice([S.ROOF_TAR, S.ROOF_COOL, S.ROOF_METAL])
            b.rect(fp, layer=3, label=label, mat=roof, c1=rng.normal(0, 0.1), c2=rng.random(),
                   h=height, kind=KIND_BUILDING, base=base, bid=bid)  # fmt: skip
            if rng.random() < 0.65:  # mechanical penthouse
                fw, fh = fp[2] - fp[0], fp[3] - fp[1]
                pw2, ph2 = fw * rng.uniform(0.2, 0.45), fh * rng.uniform(0.2, 0.45)
                px, py = (
                    fp[0] + rng.uniform(0.1, 0.9) * (fw - pw2),
                    fp[1] + rng.uniform(0.1, 0.9) * (fh - ph2),
                )
                b.rect((px, py, px + pw2, py + ph2), layer=4, label=label,
                       mat=rng.choice([S.ROOF_METAL, S.CONCRETE]), c1=rng.normal(0, 0.1),
                       h=height + rng.uniform(3, 8), kind=KIND_ROOFTOP, base=base, bid=bid)  # fmt: skip
        elif roll < 0.88:
            lot = (p[0] + 1, p[1] + 1, p[2] - 1, p[3] - 1)
            b.rect(
                lot, layer=1, label=C.PARKING, mat=S.ASPHALT, c1=rng.normal(0, 0.1), c2=rng.random()
            )
            _cars_in_lot(b, rng, lot, rng.uniform(0.4, 0.95), rng.uniform(0.3, 0.9))
        else:
            _trees_in(b, rng, p, int(pw * ph / 150), 2.5, 4.5, 6, 12)
    return bid


def _block_residential(b, rng, box, terrain, bid):
    x0, y0, x1, y1 = box
    w, h = x1 - x0, y1 - y0
    along_x = w >= h
    L, D = (w, h) if along_x else (h, w)  # frontage length, block depth

    def frame(a0, d0, a1, d1, south: bool):
        """Lot-frame (along, depth-from-street) -> map box for the south/west or north/east row."""
        if along_x:
            return (
                (x0 + a0, y0 + d0, x0 + a1, y0 + d1)
                if south
                else (x0 + a0, y1 - d1, x0 + a1, y1 - d0)
            )
        return (
            (x0 + d0, y0 + a0, x0 + d1, y0 + a1) if south else (x1 - d1, y0 + a0, x1 - d0, y0 + a1)
        )

    rows = (True, False) if D >= 40 else (True,)
    depth = D / len(rows)
    for south in rows:
        a = 0.0
        while a < L - 10:
            lw = min(rng.uniform(13, 22), L - a)
            lot = frame(a, 0, a + lw, depth, south)
            roll = rng.random()
            if roll < 0.55:  # individual lawn
                b.rect(
                    lot,
                    layer=1,
                    label=C.GRASS,
                    mat=S.GRASS,
                    c1=rng.normal(0, 0.12),
                    c2=rng.beta(1.5, 3),
                )
            elif roll < 0.68:
                b.rect(
                    lot,
                    layer=1,
                    label=C.BARE_SOIL,
                    mat=S.SOIL,
                    c1=rng.normal(0, 0.1),
                    c2=rng.random(),
                )
            hw = min(rng.uniform(8, 15), lw - 4)
            setback = rng.uniform(5, 9)
            hd = min(rng.uniform(10, 18), depth - setback - 4)
            if hw > 6 and hd > 6:
                bid += 1
                ha = a + rng.uniform(1.5, lw - hw - 1.5)
                house = frame(ha, setback, ha + hw, setback + hd, south)
                cx, cy = 0.5 * (house[0] + house[2]), 0.5 * (house[1] + house[3])
                storeys = 1 if rng.random() < 0.7 else 2
                eave = rng.uniform(2.8, 4.0) if storeys == 1 else rng.uniform(5.5, 6.5)
                gable = rng.random() < 0.72
                ridge_h = min(rng.uniform(1.2, 2.6), 9.0 - eave) if gable else 0.0
                bw, bh = house[2] - house[0], house[3] - house[1]
                roof = rng.choice([S.ROOF_TILE, S.ROOF_SHINGLE, S.ROOF_TAR, S.ROOF_COOL, S.ROOF_METAL],
                                  p=[0.35, 0.4, 0.1, 0.1, 0.05])  # fmt: skip
                if not gable and roof in (S.ROOF_TILE, S.ROOF_SHINGLE):
                    roof = S.ROOF_TAR
                b.rect(house, layer=3, label=C.HOUSE, mat=roof, c1=rng.normal(0, 0.12), c2=rng.random(),
                       h=eave, ridge_h=ridge_h, ridge=(1 if bw >= bh else 2) if gable else 0,
                       kind=KIND_BUILDING, base=float(terrain(cx, cy)), bid=bid)  # fmt: skip
                # driveway from the street to the house
                da = a + 0.5 if ha - a > lw - (ha - a + hw) else a + lw - 3.5
                b.rect(frame(da, 0, da + 3.0, setback + 2, south), layer=2, label=C.CONCRETE,
                       mat=S.CONCRETE, c1=rng.normal(0, 0.08), c2=rng.random() * 0.5)  # fmt: skip
                if rng.random() < 0.4:
                    c1, c2 = _car_colours(rng, 1)
                    car = frame(da + 0.6, 0.8, da + 2.4, 5.3, south)
                    b.rect(car, layer=5, label=C.VEHICLE, mat=S.CAR, c1=c1[0], c2=c2[0], h=1.5,
                           kind=KIND_CAR, epoch=int(rng.choice([1, 2, 3], p=[0.25, 0.25, 0.5])))  # fmt: skip
                back = depth - setback - hd
                if rng.random() < 0.18 and back > 7 and lw > 9:
                    pa = a + rng.uniform(1, lw - 8)
                    pd = setback + hd + rng.uniform(1.5, back - 5)
                    b.rect(
                        frame(pa, pd, pa + rng.uniform(5, 7.5), pd + rng.uniform(3.2, 4.2), south),
                        layer=2,
                        label=C.WATER,
                        mat=S.POOL,
                        c1=rng.normal(0, 0.08),
                        c2=rng.random(),
                    )
            nt = rng.poisson(1.3)
            _trees_in(b, rng, lot, nt, 1.8, 4.2, 5, 13)
            a += lw
    # street trees along the frontage
    nst = rng.poisson(L / 14)
    if nst:
        al = rng.uniform(2, L - 2, nst)
        side = rng.random(nst) < 0.5
        d = np.full(nst, 1.2)
        cx = np.where(along_x, x0 + al, np.where(side, x0 + d, x1 - d))
        cy = np.where(along_x, np.where(side, y0 + d, y1 - d), y0 + al)
        r = rng.uniform(2.2, 4.0, nst)
        hh = rng.uniform(6, 12, nst)
        b.trees(cx, cy, r, hh, hh * 0.35, rng.normal(0, 0.1, nst), rng.uniform(0, 1, nst))
    return bid


def _block_lowrise(b, rng, box, terrain, bid, industrial: bool):
    x0, y0, x1, y1 = box
    w, h = x1 - x0, y1 - y0
    n = int(rng.integers(1, 3 if industrial else 4))
    along_x = w >= h
    edges = np.concatenate([[0.0], np.sort(rng.uniform(0.3, 0.7, n - 1)), [1.0]])
    for a, c in zip(edges[:-1], edges[1:], strict=True):
        p = (x0 + a * w, y0, x0 + c * w, y1) if along_x else (x0, y0 + a * h, x1, y0 + c * h)
        pw, ph = p[2] - p[0], p[3] - p[1]
        fw, fh = pw * rng.uniform(0.5, 0.85), ph * rng.uniform(0.45, 0.8)
        fx, fy = (
            p[0] + rng.uniform(2, max(pw - fw - 2, 2.5)),
            p[1] + rng.uniform(2, max(ph - fh - 2, 2.5)),
        )
        fp = (fx, fy, min(fx + fw, p[2] - 2), min(fy + fh, p[3] - 2))
        if fp[2] - fp[0] < 8 or fp[3] - fp[1] < 8:
            continue
        bid += 1
        roof = rng.choice(
            [S.ROOF_METAL, S.ROOF_COOL, S.ROOF_TAR],
            p=[0.6, 0.25, 0.15] if industrial else [0.2, 0.4, 0.4],
        )
        base = float(terrain(0.5 * (fp[0] + fp[2]), 0.5 * (fp[1] + fp[3])))
        b.rect(fp, layer=3, label=C.HOUSE, mat=roof, c1=rng.normal(0, 0.1), c2=rng.random(),
               h=rng.uniform(6, 12.5), kind=KIND_BUILDING, base=base, bid=bid)  # fmt: skip
        # parking in the remaining strip of the parcel (the larger of the two sides)
        if along_x:
            lot = (
                (p[0] + 1, fp[3] + 2, p[2] - 1, p[3] - 1)
                if p[3] - fp[3] > fp[1] - p[1]
                else (p[0] + 1, p[1] + 1, p[2] - 1, fp[1] - 2)
            )
        else:
            lot = (
                (fp[2] + 2, p[1] + 1, p[2] - 1, p[3] - 1)
                if p[2] - fp[2] > fp[0] - p[0]
                else (p[0] + 1, p[1] + 1, fp[0] - 2, p[3] - 1)
            )
        if lot[2] - lot[0] > 8 and lot[3] - lot[1] > 8:
            _cars_in_lot(b, rng, lot, rng.uniform(0.2, 0.8), rng.uniform(0.2, 0.8))
    if not industrial:
        _trees_in(b, rng, box, rng.poisson(w * h / 1500), 2.0, 3.5, 5, 9)
    else:
        for _ in range(rng.poisson(1.0)):  # dirt storage yard
            sx, sy = rng.uniform(10, 30), rng.uniform(10, 30)
            px, py = rng.uniform(x0, max(x1 - sx, x0 + 1)), rng.uniform(y0, max(y1 - sy, y0 + 1))
            b.rect((px, py, min(px + sx, x1), min(py + sy, y1)), layer=1, label=C.BARE_SOIL,
                   mat=S.SOIL, c1=rng.normal(0, 0.1), c2=rng.random())  # fmt: skip
    return bid


def _block_park(b, rng, box):
    x0, y0, x1, y1 = box
    w, h = x1 - x0, y1 - y0
    if rng.random() < 0.5 and min(w, h) > 50:  # pond
        rx, ry = rng.uniform(8, min(30, w / 4)), rng.uniform(8, min(30, h / 4))
        cx, cy = rng.uniform(x0 + rx + 5, x1 - rx - 5), rng.uniform(y0 + ry + 5, y1 - ry - 5)
        b.rect((cx - rx, cy - ry, cx + rx, cy + ry), layer=2, label=C.WATER, mat=S.WATER,
               c1=rng.normal(0, 0.1), c2=rng.random(), shape=1)  # fmt: skip
    # concrete paths: one along each axis
    px, py = rng.uniform(x0 + 10, x1 - 10), rng.uniform(y0 + 10, y1 - 10)
    b.rect(
        (px - 1.5, y0, px + 1.5, y1),
        layer=1,
        label=C.CONCRETE,
        mat=S.CONCRETE,
        c1=rng.normal(0, 0.1),
    )
    b.rect(
        (x0, py - 1.5, x1, py + 1.5),
        layer=1,
        label=C.CONCRETE,
        mat=S.CONCRETE,
        c1=rng.normal(0, 0.1),
    )
    if rng.random() < 0.4:  # sports court / dry field
        sx, sy = rng.uniform(20, 40), rng.uniform(15, 30)
        qx, qy = rng.uniform(x0, max(x1 - sx, x0 + 1)), rng.uniform(y0, max(y1 - sy, y0 + 1))
        b.rect((qx, qy, min(qx + sx, x1), min(qy + sy, y1)), layer=1,
               label=C.BARE_SOIL if rng.random() < 0.5 else C.GRASS,
               mat=S.SOIL, c1=rng.normal(0, 0.1), c2=rng.random() * 0.5)  # fmt: skip
    # clustered trees
    n_clusters = max(1, int(w * h / 4000))
    for _ in range(n_clusters):
        cx, cy = rng.uniform(x0, x1), rng.uniform(y0, y1)
        k = rng.poisson(10)
        tx = np.clip(cx + rng.normal(0, 12, k), x0, x1)
        ty = np.clip(cy + rng.normal(0, 12, k), y0, y1)
        r = rng.uniform(2.5, 6.5, k)
        hh = np.clip(rng.uniform(8, 20, k), 2.2 * r, 20)
        b.trees(
            tx,
            ty,
            r,
            hh,
            hh * rng.uniform(0.2, 0.4, k),
            rng.normal(0, 0.12, k),
            rng.uniform(0, 1, k),
        )


def populate_block(b: _Builder, rng: np.random.Generator, box, name: str, u: float,
                   terrain: Terrain, bid: int) -> tuple[int, int, float, int]:  # fmt: skip
    """Fill one city block of type ``name``; returns (ground label, material, c2 scale, next id)."""
    if name == "downtown":
        return C.CONCRETE, S.CONCRETE, 0.4, _block_downtown(b, rng, box, u, terrain, bid)
    if name == "residential":
        return C.GRASS, S.GRASS, 0.6, _block_residential(b, rng, box, terrain, bid)
    if name in ("commercial", "industrial"):
        return C.PARKING, S.ASPHALT, 1.0, _block_lowrise(b, rng, box, terrain, bid,
                                                         name == "industrial")  # fmt: skip
    if name == "park":
        _block_park(b, rng, box)
        return C.GRASS, S.GRASS, 0.3, bid
    if name == "parking":
        _cars_in_lot(b, rng, (box[0] + 1, box[1] + 1, box[2] - 1, box[3] - 1),
                     rng.uniform(0.3, 0.95), rng.uniform(0.3, 0.95))  # fmt: skip
        _trees_in(b, rng, box, rng.poisson(4), 2.0, 3.5, 5, 9)
        return C.PARKING, S.ASPHALT, 1.0, bid
    # vacant
    _trees_in(b, rng, box, rng.poisson((box[2] - box[0]) * (box[3] - box[1]) / 1500),
              1.5, 3.0, 5, 7)  # fmt: skip
    if rng.random() < 0.5:
        b.rect((box[0], box[1], 0.5 * (box[0] + box[2]), box[3]), layer=1, label=C.GRASS,
               mat=S.GRASS, c1=rng.normal(0, 0.1), c2=rng.uniform(0.6, 1.0))  # fmt: skip
    return C.BARE_SOIL, S.SOIL, 1.0, bid


def drop_on_avenue(streets: Streets, rects: dict[str, np.ndarray],
                   trees: dict[str, np.ndarray]) -> tuple[dict, dict]:  # fmt: skip
    """The diagonal avenue cuts through blocks: drop what lies on it (large lots may stay)."""
    half = streets.diag_width / 2 + SIDEWALK_M
    cx, cy = 0.5 * (rects["x0"] + rects["x1"]), 0.5 * (rects["y0"] + rects["y1"])
    rad = 0.5 * np.hypot(rects["x1"] - rects["x0"], rects["y1"] - rects["y0"])
    keep = np.abs(streets.diag_distance(cx, cy)) > half + rad
    keep |= (rects["kind"] == KIND_SURFACE) & (rad > 25)
    keep_t = np.abs(streets.diag_distance(trees["cx"], trees["cy"])) > half + trees["r"]
    return {k: v[keep] for k, v in rects.items()}, {k: v[keep_t] for k, v in trees.items()}


def make_layout(rng: np.random.Generator, extent: tuple[float, float, float, float],
                map_centre: tuple[float, float], map_size: float) -> Layout:  # fmt: skip
    """Generate the city over ``extent`` (xmin, ymin, xmax, ymax), downtown near ``map_centre``."""
    xmin, ymin, xmax, ymax = extent
    terrain = Terrain.random(rng)
    sx, sx_age = _street_intervals(rng, xmin, xmax)
    sy, sy_age = _street_intervals(rng, ymin, ymax)
    ang = rng.uniform(np.radians(25), np.radians(65)) * rng.choice([-1, 1])
    diag_dir = np.array([np.cos(ang), np.sin(ang)])
    diag_pt = np.array(map_centre) + rng.uniform(-0.3, 0.3, 2) * map_size
    streets = Streets(sx, sy, sx_age, sy_age, diag_pt, diag_dir, float(rng.uniform(24, 32)))
    # urban centres: downtown near the map centre, secondary ones anywhere in the world
    centres = [
        (
            map_centre[0] + rng.uniform(-0.12, 0.12) * map_size,
            map_centre[1] + rng.uniform(-0.12, 0.12) * map_size,
            380.0,
            1.0,
        )
    ]
    for _ in range(3):
        centres.append(
            (
                rng.uniform(xmin, xmax),
                rng.uniform(ymin, ymax),
                rng.uniform(180, 300),
                rng.uniform(0.5, 0.8),
            )
        )
    nbx, nby = len(sx) - 1, len(sy) - 1
    btype = np.zeros((nby, nbx), np.int32)
    blabel = np.zeros((nby, nbx), np.uint8)
    bmat = np.zeros((nby, nbx), np.uint8)
    bc1 = rng.normal(0, 0.08, (nby, nbx))
    bc2 = rng.random((nby, nbx))
    b = _Builder()
    bid = 0
    others = np.array([0.52, 0.13, 0.07, 0.08, 0.10, 0.10])
    for j in range(nby):
        for i in range(nbx):
            box = (
                sx[i, 1] + SIDEWALK_M,
                sy[j, 1] + SIDEWALK_M,
                sx[i + 1, 0] - SIDEWALK_M,
                sy[j + 1, 0] - SIDEWALK_M,
            )
            cx, cy = 0.5 * (box[0] + box[2]), 0.5 * (box[1] + box[3])
            u = max(
                s * np.exp(-(((cx - ux) ** 2 + (cy - uy) ** 2) / r**2)) for ux, uy, r, s in centres
            )
            t = 0 if rng.random() < 0.9 * u else 1 + int(rng.choice(6, p=others / others.sum()))
            btype[j, i] = t
            blabel[j, i], bmat[j, i], c2_scale, bid = populate_block(
                b, rng, box, BLOCK_TYPES[t], u, terrain, bid
            )
            bc2[j, i] *= c2_scale
    rects, trees = drop_on_avenue(streets, *b.arrays())
    return Layout(extent, terrain, streets, btype, blabel, bmat, bc1, bc2, rects, trees,
                  [(c[0], c[1]) for c in centres])  # fmt: skip


def intersects(rects: dict[str, np.ndarray], box) -> np.ndarray:
    """Mask of rectangles whose bbox intersects ``box`` (x0, y0, x1, y1)."""
    return (
        (rects["x1"] > box[0])
        & (rects["x0"] < box[2])
        & (rects["y1"] > box[1])
        & (rects["y0"] < box[3])
    )


def tree_boxes(trees: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
    """Bounding boxes of tree crowns, in the rectangle field names."""
    return {
        "x0": trees["cx"] - trees["r"],
        "y0": trees["cy"] - trees["r"],
        "x1": trees["cx"] + trees["r"],
        "y1": trees["cy"] + trees["r"],
    }
