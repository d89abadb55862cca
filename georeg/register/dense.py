"""Area-based cross-spectral search: CFOG channels correlated by FFT over rotations.

The query (brought to the map's feature GSD) and a map window are turned into oriented-gradient
channels (georeg.register.tiepoints.cfog, which do not depend on which band made them), both are
shrunk so that the query is at most ``max_side`` pixels, and the query is correlated with the
window by FFT at every rotation step. The peak is judged against the distribution of every other
rotation and offset: a robust z-score (median / MAD of all scores) turned into an a-contrario
number of false alarms with a Gaussian tail, counted over all rotations and offsets.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import cv2
import numpy as np
import scipy.fft as sfft
from scipy.stats import norm

from georeg.register.tiepoints import cfog


@dataclass
class DenseResult:
    """Best rotation and offset: ``S`` maps query px (col, row) to map window px (col, row)."""

    S: np.ndarray  # 3 x 3 similarity, query px -> map window px
    angle_deg: float
    score: float  # mean channel correlation per valid query pixel at the peak
    z: float  # robust z-score of the peak among all rotations and offsets
    log10_nfa: float  # log10(tests) + log10 P(Z > z)
    second_ratio: float  # peak / best score at another rotation (> 20 deg away) or offset
    tests: int
    others: list[tuple[np.ndarray, float, float]] | None = None  # further peaks: (S, angle, score)


def _shrink(img: np.ndarray, valid: np.ndarray, f: float) -> tuple[np.ndarray, np.ndarray]:
    if abs(f - 1.0) < 1e-6:
        return img.astype(np.float32), valid
    size = (max(1, round(img.shape[1] * f)), max(1, round(img.shape[0] * f)))
    interp = cv2.INTER_AREA if f < 1 else cv2.INTER_LINEAR
    out = cv2.resize(img.astype(np.float32), size, interpolation=interp)
    m = cv2.resize(valid.astype(np.uint8), size, interpolation=cv2.INTER_NEAREST) > 0
    return out, m


def _inner(valid: np.ndarray, margin: int = 4) -> np.ndarray:
    """``valid`` eroded by ``margin`` px: where the channels owe nothing to a nodata border."""
    k = np.ones((2 * margin + 1, 2 * margin + 1), np.uint8)
    return cv2.erode(valid.astype(np.uint8), k, borderValue=0) > 0


def _rfft2_small(a: np.ndarray, P: int, Q: int) -> np.ndarray:
    """``rfft2(a, s=(P, Q))`` over the last two axes of a small ``a`` (C, h, w) zero-padded to
    P x Q: the row transforms of the h non-zero rows only, then the column transforms."""
    r = sfft.rfft(a, n=Q, axis=-1)
    return sfft.fft(r, n=P, axis=-2)


def _scale(f: float) -> np.ndarray:
    """Pixel-centre scaling by f as a 3 x 3 matrix: u' = (u + 0.5) f - 0.5."""
    return np.array([[f, 0, 0.5 * f - 0.5], [0, f, 0.5 * f - 0.5], [0, 0, 1.0]])


@dataclass
class Surface:
    """The correlation of a query with a map window over rotations (``dense_search``'s first
    step): ``scores[k, dy, dx]`` = mean channel correlation per valid query pixel at rotation
    ``angles[k]`` and offset (dy, dx) of the shrunk canvas (-inf = not searched)."""

    scores: np.ndarray  # (rotations, oy, ox) float32
    angles: np.ndarray
    mats: list[np.ndarray]  # per rotation: shrunk query px -> canvas px (3 x 3)
    s: float  # shrink factor of query (at the map GSD) and window
    pd: int  # padding of the shrunk window
    factor: float  # query GSD / map GSD

    def to_window(self, k: int, dy: int, dx: int) -> np.ndarray:
        """3 x 3 similarity query px (col, row) -> map window px of rotation k, offset (dy, dx)."""
        # query px -> shrunken query -> canvas -> shrunken map (+ offset) -> map window px
        T = np.array([[1.0, 0, dx - self.pd], [0, 1.0, dy - self.pd], [0, 0, 1]])
        return (np.linalg.inv(_scale(self.s)) @ T @ self.mats[k] @ _scale(self.s)
                @ _scale(self.factor))  # fmt: skip

    query_shape: tuple[int, int] = (0, 0)  # shrunk query (rows, cols)


def shrunk_query(q_u8: np.ndarray, factor: float,
                 max_side: int) -> tuple[np.ndarray, np.ndarray, float, int]:  # fmt: skip
    """The query as the correlation sees it: resampled to the map GSD (``factor`` = query GSD /
    map GSD), then shrunk by s so that it is at most ``max_side`` px. Returns (query, valid, s,
    D = the side of the canvas that holds it at any rotation; the map is padded by D // 2)."""
    q, qv = _shrink(q_u8, q_u8 > 0, factor)
    s = min(1.0, max_side / max(q.shape))
    q, qv = _shrink(q, qv, s)
    return q, qv, s, int(math.ceil(math.hypot(*q.shape))) + 2


def correlation_surface(
    q_u8: np.ndarray,
    factor: float,
    m_u8: np.ndarray,
    step_deg: float = 10.0,
    max_side: int = 96,
    orientations: int = 9,
    min_overlap: float = 0.9,
    centre_box: tuple[float, float, float, float] | None = None,
    angles: np.ndarray | None = None,
) -> Surface | None:
    """The CFOG correlation of the query (uint8, 0 = nodata; ``factor`` = query GSD / map GSD)
    with the map window ``m_u8`` (uint8, 0 = nodata) at every rotation step and offset (see
    ``dense_search``; ``angles`` in degrees instead of every ``step_deg``). None when nothing
    overlaps."""
    q, qv, s, D = shrunk_query(q_u8, factor, max_side)
    m, mv = _shrink(m_u8, m_u8 > 0, s)
    if qv.sum() < 64 or mv.sum() < 64:
        return None
    h, w = q.shape
    # the query may stick out of the window by up to half its rotated side
    pd = D // 2
    m = np.pad(m, pd)
    mv = np.pad(mv, pd)
    M = cfog(m, mv, orientations)
    M[:, ~_inner(mv)] = 0.0  # no nodata-border gradients: they would align with the query's
    # single precision, FFT sizes with small prime factors: the same linear correlation
    P, Q = sfft.next_fast_len(M.shape[1] + D, True), sfft.next_fast_len(M.shape[2] + D, True)
    FM = sfft.rfft2(M.astype(np.float32), s=(P, Q))
    FMv = sfft.rfft2(mv.astype(np.float32), s=(P, Q))
    # offsets (dy, dx) with the canvas inside the padded map: the map window starts at 0
    oy, ox = M.shape[1] - D + 1, M.shape[2] - D + 1
    if oy < 1 or ox < 1:
        return None
    angles = np.arange(0.0, 360.0, step_deg) if angles is None else np.asarray(angles, float)
    scores = np.full((len(angles), oy, ox), -np.inf, np.float32)
    allowed = np.ones((oy, ox), bool)
    if centre_box is not None:
        # offset (dy, dx) puts the query centre at window px ((d + (D - 1) / 2 - pd) + 0.5) / s - 0.5
        cc = (np.arange(ox) + (D - 1) / 2 - pd + 0.5) / s - 0.5
        cr = (np.arange(oy) + (D - 1) / 2 - pd + 0.5) / s - 0.5
        c0, r0, c1, r1 = centre_box
        allowed = ((cr >= r0) & (cr <= r1))[:, None] & ((cc >= c0) & (cc <= c1))[None, :]
    mats = []
    for k, a in enumerate(angles):
        A = cv2.getRotationMatrix2D(((w - 1) / 2, (h - 1) / 2), float(a), 1.0)
        A[:, 2] += ((D - 1) / 2 - (w - 1) / 2, (D - 1) / 2 - (h - 1) / 2)
        qr = cv2.warpAffine(q, A, (D, D), flags=cv2.INTER_LINEAR)
        vr = cv2.warpAffine(qv.astype(np.uint8), A, (D, D), flags=cv2.INTER_NEAREST) > 0
        C = cfog(qr, vr, orientations)
        vr = _inner(vr)
        C[:, ~vr] = 0.0
        n = float(vr.sum())
        C[:, vr] -= C[:, vr].mean(axis=1, keepdims=True)  # zero mean: chance offsets score ~0
        FQ = _rfft2_small(C.astype(np.float32), P, Q)
        corr = sfft.irfft2((FM * np.conj(FQ)).sum(0), s=(P, Q))[:oy, :ox]
        FV = _rfft2_small(vr.astype(np.float32)[None], P, Q)[0]
        cnt = sfft.irfft2(FMv * np.conj(FV), s=(P, Q))
        ok = (cnt[:oy, :ox] >= min_overlap * n) & allowed
        scores[k] = np.where(ok, corr / max(n, 1.0), -np.inf)
        mats.append(np.vstack([A, [0, 0, 1]]))
    return Surface(scores, angles, mats, s, pd, factor, (h, w))


def dense_search(
    q_u8: np.ndarray,
    factor: float,
    m_u8: np.ndarray,
    step_deg: float = 10.0,
    max_side: int = 96,
    orientations: int = 9,
    min_overlap: float = 0.9,
    centre_box: tuple[float, float, float, float] | None = None,
    n_peaks: int = 1,
    apart_px: float = 8.0,
) -> DenseResult | None:
    """Find the query (uint8, 0 = nodata; ``factor`` = query GSD / map GSD) in the map window
    ``m_u8`` (uint8, 0 = nodata) over rotations of ``step_deg``. None when nothing overlaps.
    ``centre_box`` = (col0, row0, col1, row1) in window px: only offsets that put the query's
    centre inside it are searched. ``n_peaks`` > 1: also the next best peaks in ``others``, each
    more than 20 deg or ``apart_px`` window px away from every peak taken before it."""
    sf = correlation_surface(q_u8, factor, m_u8, step_deg, max_side, orientations, min_overlap,
                             centre_box)  # fmt: skip
    if sf is None:
        return None
    scores, angles, s = sf.scores, sf.angles, sf.s
    oy, ox = scores.shape[1:]
    to_window = sf.to_window
    fin = np.isfinite(scores)
    if not fin.any():
        return None
    k, dy, dx = np.unravel_index(int(np.argmax(np.where(fin, scores, -np.inf))), scores.shape)
    peak = float(scores[k, dy, dx])
    vals = scores[fin].astype(np.float64)
    med = float(np.median(vals))
    mad = 1.4826 * float(np.median(np.abs(vals - med))) + 1e-12
    z = (peak - med) / mad
    # the best score elsewhere: other rotations (> 20 deg away) or offsets > 3 px away
    dang = np.abs((angles - angles[k] + 180.0) % 360.0 - 180.0)
    other = scores.copy()
    near = dang <= 20.0
    yy, xx = np.ogrid[:oy, :ox]
    disc = (yy - dy) ** 2 + (xx - dx) ** 2 <= 9
    other[near] = np.where(disc[None], -np.inf, other[near])
    second = float(np.max(np.where(np.isfinite(other), other, -np.inf)))
    tests = int(fin.sum())
    log_nfa = math.log10(tests) + float(norm.logsf(z)) / math.log(10.0)

    others = []
    rest = np.where(fin, scores, -np.inf)
    ki, yi, xi = k, dy, dx
    r2 = max(1.0, apart_px * s) ** 2
    for _ in range(max(0, int(n_peaks) - 1)):
        da = np.abs((angles - angles[ki] + 180.0) % 360.0 - 180.0) <= 20.0
        rest[da] = np.where(((yy - yi) ** 2 + (xx - xi) ** 2 <= r2)[None], -np.inf, rest[da])
        ki, yi, xi = np.unravel_index(int(np.argmax(rest)), rest.shape)
        if not np.isfinite(rest[ki, yi, xi]):
            break
        others.append((to_window(ki, yi, xi), float(angles[ki]), float(rest[ki, yi, xi])))
    return DenseResult(to_window(k, dy, dx), float(angles[k]), peak, float(z), log_nfa,
                       peak / second if second > 0 else math.inf, tests, others)  # fmt: skip


def window_u8(gray: np.ndarray, levels: tuple[float, float] | None = None) -> np.ndarray:
    """A float map window (NaN = nodata) stretched to uint8 1..255, 0 = nodata: its own 1 and
    99 percentiles to 1 and 255, or the given ``levels`` (lo, hi; e.g. a whole map's, for one
    tile of it)."""
    ok = np.isfinite(gray)
    out = np.zeros(gray.shape, np.uint8)
    if ok.sum() < 16:
        return out
    lo, hi = np.percentile(gray[ok], [1.0, 99.0]) if levels is None else levels
    out[ok] = np.round(np.clip((gray[ok] - lo) / max(hi - lo, 1e-6), 0, 1) * 254 + 1).astype(
        np.uint8
    )
    return out
