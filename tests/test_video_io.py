"""Frame sources (issue 10): videos and image lists read lazily; bad input names the file."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from georeg.io.errors import InputError
from georeg.io.video import FrameSource


def _frame(i: int, w: int = 64, h: int = 48) -> np.ndarray:
    """Frame ``i``: a flat grey of level 20 + 10 i (survives compression)."""
    return np.full((h, w, 3), 20 + 10 * i, np.uint8)


def _video(path, n: int = 12, fps: float = 5.0, size=(64, 48)):
    vw = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"mp4v"), fps, size)
    assert vw.isOpened()
    for i in range(n):
        vw.write(_frame(i, *size))
    vw.release()
    return path


def test_video_frames_step_max_and_names(tmp_path):
    src = FrameSource(_video(tmp_path / "clip.mp4"))
    assert (len(src), src.fps, src.width, src.height) == (12, 5.0, 64, 48)
    got = list(src)
    assert [i for i, _, _ in got] == list(range(12))
    assert got[3][1] == "clip.mp4#000003"
    for i, _, rgb in got:
        assert rgb.shape == (48, 64, 3) and rgb.dtype == np.uint8
        assert abs(float(rgb.mean()) - (20 + 10 * i)) < 4  # the right frame, in order
    sub = FrameSource(tmp_path / "clip.mp4", step=3, max_frames=3)
    assert len(sub) == 3
    got = [(i, n, float(rgb.mean())) for i, n, rgb in sub]
    assert [i for i, _, _ in got] == [0, 3, 6]
    assert [n for _, n, _ in got] == ["clip.mp4#000000", "clip.mp4#000003", "clip.mp4#000006"]
    assert all(abs(m - (20 + 10 * i)) < 4 for i, _, m in got)
    gray = list(FrameSource(tmp_path / "clip.mp4", step=5).gray())
    assert [i for i, _ in gray] == [0, 5, 10] and gray[0][1].ndim == 2


def test_video_is_read_lazily(tmp_path):
    src = FrameSource(_video(tmp_path / "clip.mp4"))
    it = iter(src)
    i, _, _ = next(it)  # a generator: one frame decoded, not the whole video
    assert i == 0 and not isinstance(it, list)
    it.close()


def test_image_list_and_glob(tmp_path):
    for i in range(5):
        cv2.imwrite(str(tmp_path / f"f_{i:02d}.png"), _frame(i))
    src = FrameSource(str(tmp_path / "f_*.png"), step=2, fps=2.0)
    assert (len(src), src.fps, src.width) == (3, 2.0, 64)
    got = [(i, n, int(rgb[0, 0, 0])) for i, n, rgb in src]
    assert got == [(0, "f_00.png", 20), (2, "f_02.png", 40), (4, "f_04.png", 60)]
    listed = FrameSource([tmp_path / "f_03.png", tmp_path / "f_01.png"])
    assert [n for _, n, _ in listed] == ["f_03.png", "f_01.png"] and listed.fps is None
    conf = {"images": [str(tmp_path / "f_*.png")], "max_frames": 2}
    assert len(FrameSource.from_config(conf)) == 2


def _raises_naming(path, fn, words: str):
    with pytest.raises(InputError) as e:
        fn()
    assert str(path) in str(e.value) and words in str(e.value)


def test_bad_videos_name_the_file(tmp_path):
    missing = tmp_path / "none.mp4"
    _raises_naming(missing, lambda: FrameSource(missing), "not found")
    text = tmp_path / "notes.mp4"
    text.write_text("not a video\n" * 100)
    _raises_naming(text, lambda: FrameSource(text), "video")
    empty = _video(tmp_path / "empty.mp4", n=0)
    _raises_naming(empty, lambda: FrameSource(empty), "video")


def test_bad_images_name_the_file(tmp_path):
    cv2.imwrite(str(tmp_path / "a.png"), _frame(0))
    bad = tmp_path / "b.png"
    bad.write_bytes(b"\x89PNG garbage")
    _raises_naming(bad, lambda: list(FrameSource([tmp_path / "a.png", bad])), "cannot read")
    big = tmp_path / "c.png"
    cv2.imwrite(str(big), _frame(1, 80, 48))
    _raises_naming(big, lambda: list(FrameSource([tmp_path / "a.png", big])), "one size")
    _raises_naming(tmp_path / "d.png", lambda: FrameSource([tmp_path / "d.png"]), "not found")
    pattern = str(tmp_path / "none_*.png")
    _raises_naming(pattern, lambda: FrameSource(pattern), "no frame images")


def _textured_video(path, n: int = 40, fps: float = 10.0):
    """Frame i: a 320 x 240 crop of one textured image, shifted 4 px per frame (each frame is
    told from the others by its content)."""
    rng = np.random.default_rng(0)
    base = cv2.GaussianBlur((rng.random((240, 480, 3)) * 255).astype(np.uint8), (0, 0), 3)
    frames = [np.ascontiguousarray(base[:, 4 * i : 4 * i + 320]) for i in range(n)]
    vw = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"mp4v"), fps, (320, 240))
    for f in frames:
        vw.write(f)
    vw.release()
    return path, frames


def corrupt_video(path, dst, start: float, stop: float) -> None:
    """Overwrite the fraction [start, stop) of the video's frame data (the mdat box, before the
    moov index at the end) with random bytes."""
    data = path.read_bytes()
    m0, m1 = data.find(b"mdat") + 4, data.find(b"moov") - 4
    a, b = m0 + int((m1 - m0) * start), m0 + int((m1 - m0) * stop)
    junk = np.random.default_rng(1).integers(0, 256, b - a, dtype=np.uint8).tobytes()
    dst.write_bytes(data[:a] + junk + data[b:])


@pytest.mark.parametrize("start,stop", [(0.4, 0.5), (0.75, 1.0)])
def test_corrupt_frames_are_left_out_and_the_good_ones_read(tmp_path, start, stop):
    """Corrupt frames in the middle or at the end: every decodable frame is yielded under its
    true index (its content says which it is), the others are listed in ``unreadable``."""
    path, frames = _textured_video(tmp_path / "clip.mp4")
    bad = tmp_path / "bad.mp4"
    corrupt_video(path, bad, start, stop)
    src = FrameSource(bad)
    got = {i: rgb for i, _, rgb in src}
    assert src.unreadable and not set(got) & set(src.unreadable)
    assert sorted([*got, *src.unreadable]) == list(range(40))
    lo, hi = min(src.unreadable), max(src.unreadable)
    assert 40 * start - 6 <= lo and hi <= 40 * stop + 12, src.unreadable
    assert max(got) > hi or stop == 1.0  # frames after a corrupt stretch are read again
    for i, rgb in got.items():  # each frame is the one its index says
        err = [np.abs(cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR).astype(int) - f).mean() for f in frames]
        assert int(np.argmin(err)) == i, (i, int(np.argmin(err)))
    # the intact video: nothing unreadable
    src = FrameSource(path)
    assert len(list(src)) == 40 and src.unreadable == []
