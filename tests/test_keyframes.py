"""Keyframe selection (issue 10) on synthetic sequences whose motion is known exactly."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from georeg.trajectory.keyframes import keyframe_stats, select_keyframes

W, H = 200, 150


def _texture(seed: int, w: int, h: int = H) -> np.ndarray:
    noise = np.random.default_rng(seed).normal(0, 1, (h, w)).astype(np.float32)
    t = cv2.GaussianBlur(noise, (0, 0), 2.0)
    return cv2.normalize(t, None, 0, 255, cv2.NORM_MINMAX).astype(np.uint8)


def _pan(n: int, v: int = 4, seed: int = 1):
    """Frame i: the window of a texture ``v * i`` px to the right (the scene moves left)."""
    tex = _texture(seed, W + v * n)
    for i in range(n):
        yield i, np.ascontiguousarray(tex[:, v * i : v * i + W])


def test_overlap_rule_triggers_where_features_leave_the_view():
    conf = {"min_overlap": 0.65, "max_baseline_px": 1e6, "min_baseline_px": 0, "max_gap": 1000}
    keys = keyframe_stats(_pan(60), conf)
    idx = [k.index for k in keys]
    assert idx[0] == 0 and idx[-1] == 59 and np.all(np.diff(idx) > 0)
    # features spread over x in [10, 190): 35 % of them have left the view after ~73 px (frame 18)
    gaps = np.diff(idx)[:-1]
    assert len(gaps) >= 2 and np.all((gaps >= 16) & (gaps <= 20)), idx
    assert all(k.reason == "overlap" for k in keys[1:-1])
    assert all(0.5 < k.overlap < 0.65 for k in keys[1:-1])
    # the baseline is the known displacement
    assert all(k.baseline_px == pytest.approx(4 * k.gap, abs=0.5) for k in keys[1:])


def test_baseline_rule_and_min_baseline():
    conf = {"min_overlap": 0.0, "max_baseline_px": 22.0, "min_baseline_px": 0}
    keys = keyframe_stats(_pan(40), conf)
    assert [k.index for k in keys] == [0, 6, 12, 18, 24, 30, 36, 39]  # 24 px > 22 px
    assert {k.reason for k in keys[1:-1]} == {"baseline"} and keys[-1].reason == "last"
    # a static noisy scene: no overlap/baseline keyframe below min_baseline, only max_gap
    tex = _texture(2, W)
    rng = np.random.default_rng(0)
    still = ((i, cv2.add(tex, rng.integers(0, 6, tex.shape, dtype=np.uint8))) for i in range(35))
    keys = keyframe_stats(still, {"min_overlap": 0.999, "min_baseline_px": 3.0, "max_gap": 10})
    assert [k.index for k in keys] == [0, 10, 20, 30, 34]
    assert [k.reason for k in keys] == ["first", "gap", "gap", "gap", "last"]


def test_lost_tracking_starts_a_keyframe_below_min_baseline():
    a, b = _texture(3, W), _texture(4, W)
    frames = [(i, a) for i in range(10)] + [(i, b) for i in range(10, 20)]
    keys = keyframe_stats(
        iter(frames), {"min_baseline_px": 50.0, "max_baseline_px": 60.0, "max_gap": 100}
    )
    assert [(k.index, k.reason) for k in keys] == [(0, "first"), (10, "lost"), (19, "last")]


def test_indices_are_kept_and_must_increase():
    frames = [(i * 5, f) for i, (_, f) in enumerate(_pan(20))]  # every 5th frame of a video
    idx = select_keyframes(frames, {"max_baseline_px": 20.0})
    assert idx[0] == 0 and idx[-1] == 95 and all(i % 5 == 0 for i in idx)
    assert select_keyframes([(7, frames[0][1])]) == [7]
    assert select_keyframes([]) == []
    with pytest.raises(ValueError, match="increase"):
        select_keyframes([(3, frames[0][1]), (3, frames[1][1])])


def test_stream_yields_each_keyframe_before_the_next_frame_is_read():
    """iter_keyframes: a keyframe comes out while its frame is the latest one read (the
    trajectory writes it then, without a second pass over the video)."""
    from georeg.trajectory.keyframes import iter_keyframes

    pulled: list[int] = []

    def frames():
        for i, g in _pan(60):
            pulled.append(i)
            yield i, g

    conf = {"min_overlap": 0.65, "max_baseline_px": 1e6, "min_baseline_px": 0, "max_gap": 1000}
    streamed = []
    for k in iter_keyframes(frames(), conf):
        assert k.index == pulled[-1]
        streamed.append(k.index)
    assert streamed == [k.index for k in keyframe_stats(_pan(60), conf)]
    assert streamed[-1] == 59
