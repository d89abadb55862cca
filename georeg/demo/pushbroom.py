"""Pushbroom SWIR query: flight geometry with attitude jitter and the cube, rendered by line blocks.

Geometry: lines are acquired along the heading (line 0 first), samples run across track towards the
LEFT of the flight direction, so the image is a proper rotation of the map (never a mirror image).
Per line, smooth roll / pitch / yaw jitter moves the line across / along track by a fraction of a
pixel up to ~1.5 px.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from georeg.demo import envi
from georeg.demo import spectra as S
from georeg.demo.illumination import direct_and_sky
from georeg.demo.layout import EPOCH_QUERY, Layout
from georeg.demo.raster import Grid, Texture, rasterize
from georeg.io.atomic import atomic_path

SUBSAMPLES = ((-0.25, -0.25), (-0.25, 0.25), (0.25, -0.25), (0.25, 0.25))  # (along, across) px
JITTER_PAD_PX = 3.0


def smooth_series(rng: np.random.Generator, n: int, amplitude: float) -> np.ndarray:
    """A smooth random series of ``n`` values within about +-``amplitude``."""
    t = np.arange(n, dtype=np.float64)
    out = np.zeros(n)
    for _ in range(3):
        period = rng.uniform(60.0, 700.0)
        out += rng.uniform(0.3, 1.0) * np.sin(2 * np.pi * t / period + rng.uniform(0, 2 * np.pi))
    return amplitude * out / max(np.abs(out).max(), 1e-9)


@dataclass
class Flight:
    """Where each query pixel looks: centre, heading, ground sampling and per-line jitter."""

    centre: tuple[float, float]
    heading_deg: float
    gsd: float
    samples: int
    lines: int
    along_px: np.ndarray  # (lines,) pitch: along-track offset
    across_px: np.ndarray  # (lines,) roll: across-track offset
    yaw: np.ndarray  # (lines,) yaw: along-track offset per pixel off nadir

    @classmethod
    def random(cls, rng: np.random.Generator, centre: tuple[float, float], heading_deg: float, gsd: float,
               samples: int, lines: int) -> Flight:  # fmt: skip
        return cls(
            centre=centre,
            heading_deg=heading_deg,
            gsd=gsd,
            samples=samples,
            lines=lines,
            along_px=smooth_series(rng, lines, 0.9),
            across_px=smooth_series(rng, lines, 1.4),
            yaw=smooth_series(rng, lines, 1.0 / max(samples / 2, 1)),
        )

    def axes(self) -> tuple[np.ndarray, np.ndarray]:
        """Unit vectors (east, north) of the along-track and across-track (left) directions."""
        th = np.radians(self.heading_deg)
        return np.array([np.sin(th), np.cos(th)]), np.array([-np.cos(th), np.sin(th)])

    def coords(
        self, l0: int, l1: int, da: float = 0.0, dc: float = 0.0
    ) -> tuple[np.ndarray, np.ndarray]:
        """Map (x, y) of lines l0..l1-1, all samples, at sub-pixel offset (da, dc) from the centre."""
        line = np.arange(l0, l1, dtype=np.float64)[:, None]
        samp = np.arange(self.samples, dtype=np.float64)[None, :]
        c = samp + 0.5 + dc + self.across_px[l0:l1, None] - self.samples / 2
        a = (
            line
            + 0.5
            + da
            + self.along_px[l0:l1, None]
            + self.yaw[l0:l1, None] * c
            - self.lines / 2
        )
        u, v = self.axes()
        x = self.centre[0] + self.gsd * (a * u[0] + c * v[0])
        y = self.centre[1] + self.gsd * (a * u[1] + c * v[1])
        return x, y

    def corners(self) -> np.ndarray:
        """Nominal (jitter-free) footprint corners (4, 2): first line left/right, last line right/left."""
        u, v = self.axes()
        ha, hc = self.lines * self.gsd / 2, self.samples * self.gsd / 2
        pts = [(-ha, -hc), (-ha, hc), (ha, hc), (ha, -hc)]
        return np.array([np.array(self.centre) + a * u + c * v for a, c in pts])

    def half_extent(self, pad_px: float = JITTER_PAD_PX) -> tuple[float, float]:
        """Half width / height (m) of the footprint's bounding box including jitter."""
        th = np.radians(self.heading_deg)
        ha, hc = (self.lines / 2 + pad_px) * self.gsd, (self.samples / 2 + pad_px) * self.gsd
        return ha * abs(np.sin(th)) + hc * abs(np.cos(th)), ha * abs(np.cos(th)) + hc * abs(
            np.sin(th)
        )

    def bbox(self, pad_px: float = JITTER_PAD_PX) -> tuple[float, float, float, float]:
        hx, hy = self.half_extent(pad_px)
        return (self.centre[0] - hx, self.centre[1] - hy, self.centre[0] + hx, self.centre[1] + hy)

    def to_json(self) -> dict:
        return {
            "centre": list(self.centre),
            "heading_deg": self.heading_deg,
            "gsd_m": self.gsd,
            "samples": self.samples,
            "lines": self.lines,
            "corners": self.corners().tolist(),
            "corner_order": "line0/sample0, line0/last sample, last line/last sample, last line/sample0",
            "samples_direction": "left of the flight direction (image is a rotation of the map, no mirror)",
            "jitter_max_px": {
                "along": float(np.abs(self.along_px).max()),
                "across": float(np.abs(self.across_px).max()),
                "yaw_edge": float(np.abs(self.yaw).max() * self.samples / 2),
            },
        }


def fine_grid(flight: Flight, sun: S.Sun, max_height: float, res: float) -> Grid:
    """Grid covering the footprint plus the up-sun strip whose objects can cast shadows into it."""
    x0, y0, x1, y1 = flight.bbox()
    reach = max_height / np.tan(np.radians(sun.elevation_deg)) + 5.0
    s = sun.vector()
    ux, uy = s[:2] / np.hypot(s[0], s[1])  # horizontal direction towards the sun
    x0, x1 = x0 - 5 + min(ux, 0) * reach, x1 + 5 + max(ux, 0) * reach
    y0, y1 = y0 - 5 + min(uy, 0) * reach, y1 + 5 + max(uy, 0) * reach
    x0, y1 = np.floor(x0 / res) * res, np.ceil(y1 / res) * res
    return Grid(
        float(x0), float(y1), res, int(np.ceil((x1 - x0) / res)), int(np.ceil((y1 - y0) / res))
    )


@dataclass
class QueryProducts:
    truth: np.ndarray  # (2, lines, samples) float64 map x, y of pixel centres
    labels: np.ndarray  # (lines, samples) uint8
    ndsm: np.ndarray  # (lines, samples) float32


def render_query(layout: Layout, texture: Texture, flight: Flight, sun: S.Sun, bands: int,
                 header_path: Path, rng: np.random.Generator, description: str) -> QueryProducts:  # fmt: skip
    """Render the query cube to ENVI (int16 reflectance x 10000, BIL) and return its truth."""
    res = flight.gsd / 2
    max_h = float(max(np.max(layout.rects["h"] + layout.rects["ridge_h"], initial=0.0), 20.0)) + 2.0
    grid = fine_grid(flight, sun, max_h, res)
    surf = rasterize(layout, grid, EPOCH_QUERY, texture)
    direct, sky = direct_and_sky(surf.dsm, surf.label, res, sun)
    wl, fwhm = S.wavelengths(bands)
    M, V = S.swir_library(wl)
    d = S.diffuse_ratio(wl, sun.elevation_deg)
    lib = np.concatenate([M / (1 + d), V / (1 + d), M * d / (1 + d), V * d / (1 + d)]).astype(
        np.float32
    )
    nm = S.N_MATERIALS
    mat, c1, c2 = surf.mat.ravel(), surf.c1.ravel(), surf.c2.ravel()
    direct, sky = direct.ravel(), sky.ravel()
    ndsm_f = (surf.dsm - surf.dtm).ravel()
    label_f = surf.label.ravel()
    sigma = S.noise_sigma(wl).astype(np.float32)
    gain = (1.0 + 0.004 * rng.standard_normal((flight.samples, bands))).astype(
        np.float32
    )  # detector striping
    L, Sm = flight.lines, flight.samples
    truth = np.empty((2, L, Sm))
    labels = np.empty((L, Sm), np.uint8)
    ndsm = np.empty((L, Sm), np.float32)
    step = max(1, int(6e6 // (Sm * bands)))

    def flat_index(x: np.ndarray, y: np.ndarray) -> np.ndarray:
        col, row = grid.to_pixel(x, y)
        col = np.clip(np.rint(col), 0, grid.width - 1).astype(np.int64)
        row = np.clip(np.rint(row), 0, grid.height - 1).astype(np.int64)
        return (row * grid.width + col).ravel()

    data = envi.data_path(header_path)
    with atomic_path(data) as tmp, open(tmp, "wb") as fh:
        for l0 in range(0, L, step):
            l1 = min(L, l0 + step)
            n = (l1 - l0) * Sm
            x, y = flight.coords(l0, l1)
            truth[0, l0:l1], truth[1, l0:l1] = x, y
            idx = flat_index(x, y)
            labels[l0:l1] = label_f[idx].reshape(l1 - l0, Sm)
            ndsm[l0:l1] = ndsm_f[idx].reshape(l1 - l0, Sm)
            coef = np.zeros((n, 4 * nm), np.float32)
            rows = np.arange(n)
            for da, dc in SUBSAMPLES:
                k = flat_index(*flight.coords(l0, l1, da, dc))
                m = mat[k].astype(np.int64)
                b1, b2 = (1.0 + c1[k]) / 4, c2[k] / 4
                coef[rows, m] += direct[k] * b1
                coef[rows, nm + m] += direct[k] * b2
                coef[rows, 2 * nm + m] += sky[k] * b1
                coef[rows, 3 * nm + m] += sky[k] * b2
            refl = (coef @ lib).reshape(l1 - l0, Sm, bands) * gain
            noise = rng.standard_normal(refl.shape, dtype=np.float32)
            refl += noise * sigma * (0.6 + 0.4 * np.sqrt(np.clip(refl, 0, None) / 0.3))
            dn = np.clip(np.rint(refl * 10000.0), -32000, 32000).astype(np.int16)
            envi.write_bil_block(fh, dn, np.int16)
    extra = {
        "reflectance scale factor": "10000",
        "data units": "reflectance x 10000 (int16)",
    }
    hdr = envi.envi_header(Sm, L, bands, np.dtype(np.int16), wl, fwhm, description, extra)
    with atomic_path(header_path) as tmp:
        tmp.write_text(hdr)
    return QueryProducts(truth, labels, ndsm)
