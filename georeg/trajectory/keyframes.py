"""Keyframes of a video by visual overlap and baseline, streaming.

Good features (Shi-Tomasi) of the last keyframe are tracked frame to frame (pyramidal Lucas-Kanade,
kept only if tracking back lands within ``fb_max_px``). A frame becomes the next keyframe when
the fraction of the keyframe's features still tracked (the visual overlap) drops below
``min_overlap`` or their median displacement (the baseline, pixels) exceeds ``max_baseline_px``,
but not before ``min_baseline_px`` unless tracking is lost (fewer than ``lost_fraction`` of the
features, or ``min_tracked``), nor later than ``max_gap`` frames. The first and the last frame are
keyframes. Only the previous frame is held: memory does not grow with the video.
"""

from __future__ import annotations

import logging
from collections.abc import Iterable, Iterator
from dataclasses import asdict, dataclass
from typing import Any

import cv2
import numpy as np

from georeg.io.errors import ConfigError

log = logging.getLogger(__name__)

DEFAULTS: dict[str, Any] = {
    "min_overlap": 0.65,  # fraction of the keyframe's features still tracked
    "max_baseline_px": None,  # median displacement since the keyframe; None: 3 % of the diagonal
    "min_baseline_px": None,  # no keyframe below this unless tracking is lost; None: 1 %
    "max_gap": 30,  # frames (of those given) between keyframes at most
    "max_features": 500,
    "quality": 0.01,  # goodFeaturesToTrack quality level
    "min_distance_px": None,  # between features; None: half the spacing of max_features on a grid
    "win_px": 21,  # Lucas-Kanade window
    "levels": 3,  # pyramid levels above the base
    "fb_max_px": 1.0,  # forward-backward tracking error bound
    "lost_fraction": 0.2,  # tracking lost below this fraction of the features ...
    "min_tracked": 15,  # ... or below this many
    "track_width": 960,  # wider frames are tracked downscaled (thresholds stay in frame pixels)
}


@dataclass(frozen=True)
class Keyframe:
    index: int  # frame index
    reason: str  # first | overlap | baseline | lost | gap | last
    features: int  # features detected on this keyframe
    overlap: float  # fraction of the previous keyframe's features tracked into this one
    baseline_px: float  # their median displacement (frame pixels)
    gap: int  # frames since the previous keyframe

    def as_dict(self) -> dict[str, Any]:
        return asdict(self)


def _conf(conf: dict | None, width: int, height: int) -> dict[str, Any]:
    c = {**DEFAULTS, **(conf or {})}
    diag = float(np.hypot(width, height))
    if c["max_baseline_px"] is None:
        c["max_baseline_px"] = 0.03 * diag
    if c["min_baseline_px"] is None:
        c["min_baseline_px"] = 0.01 * diag
    if not 0 <= float(c["min_overlap"]) < 1 or int(c["max_gap"]) < 1:
        raise ConfigError(
            f"keyframes: need 0 <= min_overlap < 1 and max_gap >= 1, got {c['min_overlap']}, "
            f"{c['max_gap']}"
        )
    if float(c["min_baseline_px"]) > float(c["max_baseline_px"]):
        raise ConfigError("keyframes: min_baseline_px > max_baseline_px")
    return c


class _Tracker:
    """The features of one keyframe, tracked frame to frame (all in tracking pixels)."""

    def __init__(self, gray: np.ndarray, c: dict, scale: float) -> None:
        h, w = gray.shape
        md = c["min_distance_px"]
        md = 0.5 * np.sqrt(w * h / c["max_features"]) if md is None else float(md) * scale
        mask = np.zeros_like(gray)
        b = max(2, int(c["win_px"]) // 2)
        mask[b : h - b, b : w - b] = 255
        pts = cv2.goodFeaturesToTrack(gray, int(c["max_features"]), float(c["quality"]),
                                      max(1.0, float(md)), mask=mask, blockSize=7)  # fmt: skip
        self.key = np.zeros((0, 2), np.float32) if pts is None else pts.reshape(-1, 2)
        self.cur = self.key.copy()
        self.alive = np.ones(len(self.key), bool)
        self.lk = {"winSize": (int(c["win_px"]),) * 2, "maxLevel": int(c["levels"]),
                   "criteria": (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 30, 0.01)}  # fmt: skip
        self.fb_max = float(c["fb_max_px"]) * scale

    def track(self, prev: np.ndarray, gray: np.ndarray) -> None:
        idx = np.flatnonzero(self.alive)
        if idx.size == 0:
            return
        p0 = self.cur[idx].reshape(-1, 1, 2)
        p1, st1, _ = cv2.calcOpticalFlowPyrLK(prev, gray, p0, None, **self.lk)
        p0b, st2, _ = cv2.calcOpticalFlowPyrLK(gray, prev, p1, None, **self.lk)
        h, w = gray.shape
        p1 = p1.reshape(-1, 2)
        ok = (st1.ravel() == 1) & (st2.ravel() == 1)
        ok &= np.linalg.norm(p0b.reshape(-1, 2) - p0.reshape(-1, 2), axis=1) < self.fb_max
        ok &= (p1[:, 0] >= 0) & (p1[:, 0] <= w - 1) & (p1[:, 1] >= 0) & (p1[:, 1] <= h - 1)
        self.cur[idx[ok]] = p1[ok]
        self.alive[idx[~ok]] = False

    def overlap(self) -> float:
        return float(self.alive.mean()) if len(self.alive) else 0.0

    def baseline(self) -> float:
        if not self.alive.any():
            return float("inf")
        return float(np.median(np.linalg.norm(self.cur[self.alive] - self.key[self.alive], axis=1)))


def keyframe_stats(
    frames: Iterable[tuple[int, np.ndarray]], conf: dict | None = None
) -> list[Keyframe]:
    """The keyframes of ``frames`` (``(index, gray uint8)``, increasing indices), with why each
    was chosen and its overlap and baseline to the previous one."""
    return list(iter_keyframes(frames, conf))


def iter_keyframes(
    frames: Iterable[tuple[int, np.ndarray]], conf: dict | None = None
) -> Iterator[Keyframe]:
    """``keyframe_stats`` as a stream: each keyframe is yielded as soon as it is decided, before
    the next frame is pulled from ``frames`` (the last frame after the end), so a caller can keep
    just the current frame and act on it."""
    keys: list[Keyframe] = []
    prev = tr = c = None
    scale, gap, last, seen = 1.0, 0, None, 0
    for index, gray in frames:
        seen += 1
        if gray.ndim != 2:
            raise ValueError(f"keyframes: frame {index} is not a gray image (shape {gray.shape})")
        if last is not None and index <= last[0]:
            raise ValueError(f"keyframes: frame indices must increase ({last[0]} then {index})")
        if c is None:
            c = _conf(conf, gray.shape[1], gray.shape[0])
            scale = min(1.0, float(c["track_width"]) / gray.shape[1])
        g = gray if scale == 1.0 else cv2.resize(gray, None, fx=scale, fy=scale,
                                                 interpolation=cv2.INTER_AREA)  # fmt: skip
        reason = None
        if tr is None:
            reason, ov, base = "first", 1.0, 0.0
        else:
            gap += 1
            tr.track(prev, g)
            ov, base = tr.overlap(), tr.baseline() / scale
            n = int(tr.alive.sum())
            lost = len(tr.key) >= c["min_tracked"] and (
                n < c["min_tracked"] or ov < c["lost_fraction"]
            )
            moved = base >= c["min_baseline_px"]
            if lost:
                reason = "lost"
            elif moved and ov < c["min_overlap"]:
                reason = "overlap"
            elif moved and base > c["max_baseline_px"]:
                reason = "baseline"
            elif gap >= c["max_gap"]:
                reason = "gap"
        if reason is not None:
            tr = _Tracker(g, c, scale)
            keys.append(Keyframe(int(index), reason, len(tr.key), ov, base, gap))
            yield keys[-1]
            log.debug("keyframe %d (%s): overlap %.2f, baseline %.1f px, %d features", index,
                      reason, ov, base, len(tr.key))  # fmt: skip
            gap = 0
        prev, last = g, (int(index), ov, base, gap)
    if last is not None and keys[-1].index != last[0]:
        keys.append(Keyframe(last[0], "last", 0, last[1], last[2], last[3]))
        yield keys[-1]
    reasons = {r: sum(k.reason == r for k in keys) for r in dict.fromkeys(k.reason for k in keys)}
    log.info("keyframes: %d of %d frames (%s)", len(keys), seen,
             ", ".join(f"{r} {n}" for r, n in reasons.items()))  # fmt: skip


def select_keyframes(
    frames: Iterable[tuple[int, np.ndarray]], conf: dict | None = None
) -> list[int]:
    """Indices of the keyframes of ``frames`` (``(index, gray uint8)``): see the module doc."""
    return [k.index for k in keyframe_stats(frames, conf)]
