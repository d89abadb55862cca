"""Similarity transforms Sim(3): closed form (Umeyama), RANSAC, non-linear refinement.

``Sim3(s, R, t)`` maps ``X -> s R X + t`` (rows of an (N, 3) array). ``transform_pose`` carries a
camera (world -> camera rotation, centre) from the source frame (SfM) to the target frame (map).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.optimize import least_squares
from scipy.spatial.transform import Rotation


@dataclass(frozen=True)
class Sim3:
    s: float
    R: np.ndarray  # (3, 3)
    t: np.ndarray  # (3,)

    @classmethod
    def identity(cls) -> Sim3:
        return cls(1.0, np.eye(3), np.zeros(3))

    @classmethod
    def from_matrix(cls, M: np.ndarray) -> Sim3:
        """From a 4x4 [[sR, t], [0, 1]]."""
        A = np.asarray(M, float)[:3, :3]
        s = float(np.cbrt(np.linalg.det(A)))
        return cls(s, A / s, np.asarray(M, float)[:3, 3].copy())

    def apply(self, X: np.ndarray) -> np.ndarray:
        """(N, 3) or (3,) points -> s R X + t."""
        return self.s * np.asarray(X, float) @ self.R.T + self.t

    def inverse(self) -> Sim3:
        return Sim3(1.0 / self.s, self.R.T, -(self.R.T @ self.t) / self.s)

    def compose(self, other: Sim3) -> Sim3:
        """``self o other``: first ``other``, then ``self``."""
        return Sim3(self.s * other.s, self.R @ other.R, self.s * self.R @ other.t + self.t)

    def matrix(self) -> np.ndarray:
        M = np.eye(4)
        M[:3, :3] = self.s * self.R
        M[:3, 3] = self.t
        return M

    def rotation_deg(self) -> float:
        return float(np.degrees(np.linalg.norm(Rotation.from_matrix(self.R).as_rotvec())))


def _umeyama_batch(src: np.ndarray, dst: np.ndarray, with_scale: bool = True):
    """Batched Umeyama: (B, n, 3) x2 -> s (B,), R (B, 3, 3), t (B, 3), ok (B,)."""
    ms, md = src.mean(1), dst.mean(1)
    a, b = src - ms[:, None], dst - md[:, None]
    n = src.shape[1]
    cov = np.einsum("bni,bnj->bij", b, a) / n
    U, D, Vt = np.linalg.svd(cov)
    S = np.ones((len(src), 3))
    S[:, 2] = np.sign(np.linalg.det(U) * np.linalg.det(Vt))
    S[S[:, 2] == 0, 2] = 1.0
    R = U @ (S[:, :, None] * Vt)
    var = np.einsum("bni,bni->b", a, a) / n
    ok = (var > 1e-12) & (D[:, 1] > 1e-9 * np.maximum(D[:, 0], 1e-300))
    s = np.where(ok, (D * S).sum(1) / np.where(var > 0, var, 1.0), 1.0) if with_scale else np.ones(len(src))  # fmt: skip
    t = md - s[:, None] * np.einsum("bij,bj->bi", R, ms)
    return s, R, t, ok


def umeyama(src: np.ndarray, dst: np.ndarray, with_scale: bool = True) -> Sim3:
    """Least-squares Sim(3) (or rigid, ``with_scale=False``) with dst ~ s R src + t."""
    src, dst = np.asarray(src, float), np.asarray(dst, float)
    if src.shape != dst.shape or src.ndim != 2 or src.shape[1] != 3 or len(src) < 3:
        raise ValueError(f"umeyama: need two (N >= 3, 3) arrays, got {src.shape} and {dst.shape}")
    s, R, t, ok = _umeyama_batch(src[None], dst[None], with_scale)
    if not ok[0]:
        raise ValueError("umeyama: degenerate point set (coincident or collinear points)")
    return Sim3(float(s[0]), R[0], t[0])


def _residuals(sim: Sim3, src: np.ndarray, dst: np.ndarray) -> np.ndarray:
    return np.linalg.norm(sim.apply(src) - dst, axis=1)


def ransac_sim3(
    src: np.ndarray, dst: np.ndarray, threshold: float, max_iters: int = 2000, seed: int = 0,
    min_inliers: int = 6, confidence: float = 0.999, with_scale: bool = True,
    method: str = "pycolmap",
) -> tuple[Sim3, np.ndarray]:  # fmt: skip
    """Robust Sim(3) (rigid if not ``with_scale``) from 3-D/3-D correspondences.

    ``method``: "pycolmap" (COLMAP's LO-RANSAC, 2-7x faster, the default) or "numpy" (batched
    minimal 3-point samples, then least squares on the inliers). ``threshold``: inlier distance in
    ``dst`` units. Returns (Sim3, inlier mask); ValueError when fewer than ``min_inliers`` agree.
    """
    src, dst = np.asarray(src, float), np.asarray(dst, float)
    n = len(src)
    if src.shape != dst.shape or src.ndim != 2 or n < max(3, min_inliers):
        raise ValueError(f"ransac_sim3: {n} correspondences, need >= {max(3, min_inliers)}")
    if method == "pycolmap":
        best = _ransac_pycolmap(src, dst, threshold, max_iters, seed, confidence, with_scale)
        best_cnt = -1 if best is None else int((_residuals(best, src, dst) < threshold).sum())
    elif method == "numpy":
        best, best_cnt = _ransac_numpy(src, dst, threshold, max_iters, seed, confidence, with_scale)
    else:
        raise ValueError(f"ransac_sim3: unknown method {method!r} (pycolmap | numpy)")
    if best is None or best_cnt < min_inliers:
        raise ValueError(f"ransac_sim3: best model has {max(best_cnt, 0)} inliers of {n} within "
                         f"{threshold:g} (need {min_inliers})")  # fmt: skip
    mask = _residuals(best, src, dst) < threshold
    for _ in range(5):  # local optimisation: refit on the inliers until the set is stable
        try:
            sim = umeyama(src[mask], dst[mask], with_scale)
        except ValueError:
            break
        new = _residuals(sim, src, dst) < threshold
        if new.sum() < mask.sum():
            break
        best, stop = sim, np.array_equal(new, mask)
        mask = new
        if stop:
            break
    return best, mask


def _ransac_pycolmap(src, dst, threshold, max_iters, seed, confidence, with_scale) -> Sim3 | None:
    import pycolmap

    o = pycolmap.RANSACOptions()
    o.max_error = float(threshold)
    o.random_seed = int(seed)
    o.max_num_trials = int(max_iters)
    o.min_num_trials = min(o.min_num_trials, int(max_iters))
    o.confidence = float(confidence)
    o.num_threads = 1
    est = pycolmap.estimate_sim3d_robust if with_scale else pycolmap.estimate_rigid3d_robust
    r = est(src, dst, o)
    if r is None:
        return None
    T = r["tgt_from_src"]
    s = float(np.asarray(T.scale)) if with_scale else 1.0
    return Sim3(s, np.asarray(T.rotation.matrix(), float), np.asarray(T.translation, float))


def _ransac_numpy(src, dst, threshold, max_iters, seed, confidence, with_scale):
    """Batched minimal-sample RANSAC: (best Sim3 or None, its inlier count)."""
    n = len(src)
    rng = np.random.default_rng(seed)
    best_cnt, best = -1, None
    done, need = 0, max_iters
    batch = int(np.clip(4_000_000 // n, 16, 256))  # bounds the (batch, n, 3) residual array
    th2 = threshold**2
    while done < min(need, max_iters):
        b = min(batch, max_iters - done)
        idx = np.argsort(rng.random((b, n)), axis=1)[:, :3] if n <= 64 else _three(rng, b, n)
        s, R, t, ok = _umeyama_batch(src[idx], dst[idx], with_scale)
        s, R, t = s[ok], R[ok], t[ok]
        done += b
        if len(s) == 0:
            continue
        pred = s[:, None, None] * np.einsum("bij,nj->bni", R, src) + t[:, None]
        cnt = (((pred - dst[None]) ** 2).sum(2) < th2).sum(1)
        k = int(np.argmax(cnt))
        if cnt[k] > best_cnt:
            best_cnt, best = int(cnt[k]), Sim3(float(s[k]), R[k], t[k])
            w = best_cnt / n
            p_fail = max(1.0 - w**3, 1e-12)
            need = int(np.ceil(np.log(1 - confidence) / np.log(p_fail))) if p_fail < 1 else max_iters  # fmt: skip
    return best, best_cnt


def _three(rng: np.random.Generator, b: int, n: int) -> np.ndarray:
    """(b, 3) samples of three distinct indices in [0, n)."""
    i = rng.integers(0, n, b)
    j = rng.integers(0, n - 1, b)
    j += j >= i
    lo, hi = np.minimum(i, j), np.maximum(i, j)
    k = rng.integers(0, n - 2, b)
    k += k >= lo
    k += k >= hi
    return np.c_[i, j, k]


def refine_sim3(
    src: np.ndarray, dst: np.ndarray, sim: Sim3, loss: str = "huber", scale: float = 1.0,
    with_scale: bool = True, max_nfev: int = 100,
) -> Sim3:  # fmt: skip
    """Robust non-linear least squares of ||s R src + t - dst|| from ``sim``.

    Parameters: rotation increment (so(3), left), log-scale increment, translation (about the
    centroids). ``loss``/``scale``: scipy ``least_squares`` loss and its soft threshold (dst units).
    """
    src, dst = np.asarray(src, float), np.asarray(dst, float)
    if len(src) < 3:
        raise ValueError(f"refine_sim3: {len(src)} correspondences, need >= 3")
    ms, md = src.mean(0), dst.mean(0)
    a, b = src - ms, dst - md
    t0 = sim.apply(ms) - md  # translation in centred coordinates

    def unpack(x):
        R = Rotation.from_rotvec(x[:3]).as_matrix() @ sim.R
        s = sim.s * np.exp(x[3]) if with_scale else sim.s
        return s, R, t0 + x[4:7]

    def fun(x):
        s, R, t = unpack(x)
        return (s * a @ R.T + t - b).ravel()

    res = least_squares(fun, np.zeros(7), loss=loss, f_scale=scale, method="trf",
                        max_nfev=max_nfev, x_scale="jac")  # fmt: skip
    s, R, t = unpack(res.x)
    return Sim3(float(s), R, md + t - s * R @ ms)


def transform_pose(sim: Sim3, R_wc: np.ndarray, C: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Camera (world -> camera R, centre C) in the source frame -> the target frame.

    C' = s R C + t, R' = R_wc R^T. Accepts one pose ((3, 3), (3,)) or a stack ((M, 3, 3), (M, 3)).
    """
    R_wc, C = np.asarray(R_wc, float), np.asarray(C, float)
    return R_wc @ sim.R.T, sim.apply(C)
