"""Frames of a video file or of an ordered list of images, read lazily.

``FrameSource`` yields ``(index, name, rgb)`` one frame at a time (never the whole video):
``index`` is the frame's position in the video / list, ``name`` is ``"<video file>#<index:06d>"``
for a video and the image file name for a list. ``step`` keeps every n-th frame, ``max_frames``
stops after that many. Bad input is an ``InputError`` naming the file.
"""

from __future__ import annotations

import glob
import logging
import os
import struct
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from georeg.io.errors import ConfigError, InputError

log = logging.getLogger(__name__)

IMAGE_SUFFIXES = {".png", ".jpg", ".jpeg", ".tif", ".tiff", ".bmp", ".webp", ".ppm", ".pgm"}
VIDEO_HINT = "a video OpenCV can decode (e.g. MP4 / H.264 or mp4v)"


def frame_images(images: Any) -> list[str]:
    """``images``: a list of paths and/or globs, or one glob; sorted within each glob."""
    items = [images] if isinstance(images, str) else list(images or [])
    out: list[str] = []
    for it in items:
        hits = sorted(glob.glob(it)) if any(ch in it for ch in "*?[") else [it]
        out.extend(hits)
    return out


def jpeg_cut_short(path: str | Path) -> bool:
    """True for a JPEG whose data ends before its end-of-image marker (OpenCV decodes such a file
    without an error, the missing part grey). Reads the last bytes; only a file without the
    marker there is decoded in full (PIL) to tell a cut file from one with trailing bytes."""
    with open(path, "rb") as f:
        if f.read(2) != b"\xff\xd8":
            return False  # not a JPEG
        f.seek(0, os.SEEK_END)
        f.seek(max(0, f.tell() - 64))
        tail = f.read().rstrip(b"\x00\r\n ")
    if tail.endswith(b"\xff\xd9"):
        return False
    from PIL import Image

    try:
        with Image.open(path) as im:
            im.load()
    except OSError:
        return True
    return False


def read_frame(path: str | Path) -> np.ndarray:
    """One frame image as RGB uint8; ``InputError`` naming the file when OpenCV cannot read it
    or when it is a JPEG cut short."""
    if Path(path).is_file() and jpeg_cut_short(path):
        raise InputError(path, "JPEG data is truncated (the image ends early)",
                         "copy or export the frame again")  # fmt: skip
    img = cv2.imread(str(path), cv2.IMREAD_COLOR)
    if img is None:
        raise InputError(path, "cannot read the frame image", "PNG/JPEG/TIFF readable by OpenCV")
    return cv2.cvtColor(img, cv2.COLOR_BGR2RGB)


def video_name(path: str | Path, index: int) -> str:
    """The frame name of frame ``index`` of a video: ``"<file name>#<index:06d>"``."""
    return f"{Path(path).name}#{int(index):06d}"


class FrameSource:
    """A video file, or an ordered list of images (paths and/or globs), as a lazy frame iterable.

    ``fps``: the video's rate (the configured ``fps`` if the container has none); for images the
    configured ``fps`` or None. ``len()`` is the number of frames the iteration yields (for a video
    from the container's frame count: a truncated file yields fewer, with a warning).
    """

    def __init__(self, source: str | Path | list | tuple, step: int = 1,
                 max_frames: int | None = None, fps: float | None = None) -> None:  # fmt: skip
        if int(step) < 1:
            raise ConfigError(f"frames: step must be >= 1, got {step}")
        if max_frames is not None and int(max_frames) < 1:
            raise ConfigError(f"frames: max_frames must be >= 1 or null, got {max_frames}")
        self.step = int(step)
        self.max_frames = None if max_frames is None else int(max_frames)
        self.video: Path | None = None
        self.images: list[str] = []
        #: frames of the last iteration that could not be decoded (a video's corrupt frames)
        self.unreadable: list[int] = []
        if isinstance(source, (str, Path)) and _is_video(str(source)):
            self.video = Path(source)
            self._open_video(fps)
        else:
            self._open_images(source, fps)

    @classmethod
    def from_config(cls, conf: dict[str, Any]) -> FrameSource:
        """From a frame set's configuration: ``video`` or ``images``, ``step``, ``max_frames``,
        ``fps``."""
        src = conf.get("video") or conf.get("images")
        if not src:
            raise ConfigError("frames: a frame set needs 'video' or 'images'")
        return cls(src, int(conf.get("step") or 1), conf.get("max_frames"), conf.get("fps"))

    # ------------------------------------------------------------------------------ opening

    def _open_video(self, fps: float | None) -> None:
        p = self.video
        if not p.is_file():
            raise InputError(p, "video file not found", "check frames.<set>.video")
        cap = cv2.VideoCapture(str(p))
        try:
            if not cap.isOpened():
                raise InputError(p, "not a readable video (or one without frames)", VIDEO_HINT)
            ok, img = cap.read()
            if not ok or img is None:
                raise InputError(p, "the video has no readable frame", VIDEO_HINT)
            self.height, self.width = img.shape[:2]
            self.n_total = int(cap.get(cv2.CAP_PROP_FRAME_COUNT) or 0)
            if self.n_total < 1:  # no count in the container: count the frames once
                self.n_total = 1
                while cap.grab():
                    self.n_total += 1
            rate = float(cap.get(cv2.CAP_PROP_FPS) or 0.0)
        finally:
            cap.release()
        self.fps = rate if rate > 0 else (float(fps) if fps else None)

    def _open_images(self, source: Any, fps: float | None) -> None:
        self.images = frame_images([str(s) for s in source] if isinstance(source, (list, tuple))
                                   else str(source))  # fmt: skip
        if not self.images:
            raise InputError(str(source), "no frame images match", "a list of image paths or globs")
        for p in self.images:
            if not Path(p).is_file():
                raise InputError(p, "frame image not found")
        first = read_frame(self.images[0])
        self.height, self.width = first.shape[:2]
        self.n_total = len(self.images)
        self.fps = float(fps) if fps else None

    # ------------------------------------------------------------------------------ reading

    def indices(self) -> range:
        """The frame indices the iteration yields."""
        r = range(0, self.n_total, self.step)
        return r if self.max_frames is None else r[: self.max_frames]

    def __len__(self) -> int:
        return len(self.indices())

    def __iter__(self) -> Iterator[tuple[int, str, np.ndarray]]:
        return self._iter_video() if self.video is not None else self._iter_images()

    def gray(self) -> Iterator[tuple[int, np.ndarray]]:
        """``(index, gray uint8)`` of the same frames (the input of ``select_keyframes``)."""
        for i, _, rgb in self:
            yield i, cv2.cvtColor(rgb, cv2.COLOR_RGB2GRAY)

    def _check_size(self, img: np.ndarray, path: str | Path, what: str) -> None:
        if img.shape[:2] != (self.height, self.width):
            raise InputError(path, f"{what} is {img.shape[1]} x {img.shape[0]}, the first frame "
                             f"{self.width} x {self.height}", "all frames must have one size")  # fmt: skip

    def _iter_video(self) -> Iterator[tuple[int, str, np.ndarray]]:
        """Decode frame after frame; a frame the decoder cannot return (corrupt data, a cut file)
        is skipped and its index kept in ``unreadable`` (the frames after it are still read)."""
        self.unreadable = []
        want = self.indices()
        if not want:
            return
        wanted, last = set(want), want[-1]
        cap = cv2.VideoCapture(str(self.video))
        if not cap.isOpened():
            raise InputError(self.video, "not a readable video", VIDEO_HINT)
        try:
            keys = mp4_key_frames(self.video)  # None: not an MP4/MOV, or no index of them
            # pos: the index of the next decoded frame; broken: a frame since the last key frame
            # failed, so the frames predicted from it are wrong too (the decoder conceals them)
            pos, failed, just_failed, broken = 0, 0, False, False
            while pos <= last and failed <= self.n_total:
                if not cap.grab():
                    self.unreadable += [pos] if pos in wanted else []
                    pos, failed, just_failed, broken = pos + 1, failed + 1, True, True
                    continue
                i = self._index_after_failures(cap, pos) if just_failed else pos
                just_failed = False
                self.unreadable += [j for j in range(pos, i) if j in wanted]
                pos = i + 1
                broken = broken and keys is not None and i not in keys
                if broken or i not in wanted:
                    self.unreadable += [i] if broken and i in wanted else []
                    continue
                ok, img = cap.retrieve()
                if not ok or img is None:
                    self.unreadable.append(i)
                    continue
                self._check_size(img, self.video, f"frame {i}")
                yield i, video_name(self.video, i), cv2.cvtColor(img, cv2.COLOR_BGR2RGB)
            self.unreadable += [j for j in want if j >= pos]
            if self.unreadable:
                log.warning("%s: %d frame(s) could not be decoded and are left out: %s",
                            self.video, len(self.unreadable), _ranges(self.unreadable))  # fmt: skip
        finally:
            cap.release()

    def _index_after_failures(self, cap: cv2.VideoCapture, pos: int) -> int:
        """The index of the frame just decoded after unreadable ones: from its time stamp when
        that is later than the count of read attempts (one failed read can skip several)."""
        if not self.fps:
            return pos
        t = cap.get(cv2.CAP_PROP_POS_MSEC)
        i = int(round(t * self.fps / 1000.0)) if t and t > 0 else pos
        return i if pos <= i < self.n_total else pos

    def _iter_images(self) -> Iterator[tuple[int, str, np.ndarray]]:
        for i in self.indices():
            p = self.images[i]
            img = read_frame(p)
            self._check_size(img, p, "the image")
            yield i, Path(p).name, img


def _is_video(source: str) -> bool:
    """A single path that is not an image nor a glob is taken as a video."""
    return (
        not any(ch in source for ch in "*?[") and Path(source).suffix.lower() not in IMAGE_SUFFIXES
    )


def _boxes(buf: bytes, start: int, end: int) -> Iterator[tuple[bytes, int, int]]:
    """(type, payload start, end) of the ISO-BMFF boxes in ``buf[start:end]``."""
    i = start
    while i + 8 <= end:
        size, typ = struct.unpack(">I4s", buf[i : i + 8])
        head = 8
        if size == 1:
            size, head = struct.unpack(">Q", buf[i + 8 : i + 16])[0], 16
        elif size == 0:
            size = end - i
        if size < head:
            return
        yield typ, i + head, min(i + size, end)
        i += size


def _find(buf: bytes, start: int, end: int, path: list[bytes]) -> Iterator[tuple[int, int]]:
    for typ, a, b in _boxes(buf, start, end):
        if typ == path[0]:
            yield from ([(a, b)] if len(path) == 1 else _find(buf, a, b, path[1:]))


def mp4_key_frames(path: str | Path) -> set[int] | None:
    """0-based indices of the key (sync) frames of an MP4/MOV's video track, from its ``stss``
    box; every frame when the track has none (all key frames); None when not an MP4/MOV."""
    try:
        with open(path, "rb") as f:
            end = f.seek(0, os.SEEK_END)
            pos, moov = 0, None
            while pos + 8 <= end and moov is None:  # top-level boxes: headers only
                f.seek(pos)
                size, typ = struct.unpack(">I4s", f.read(8))
                head = 8
                if size == 1:
                    size, head = struct.unpack(">Q", f.read(8))[0], 16
                elif size == 0:
                    size = end - pos
                if size < head:
                    return None
                if typ == b"moov":
                    f.seek(pos + head)
                    moov = f.read(size - head)
                pos += size
    except (OSError, struct.error):
        return None
    if moov is None:
        return None
    for a, b in _find(moov, 0, len(moov), [b"trak"]):
        hdlr = next(_find(moov, a, b, [b"mdia", b"hdlr"]), None)
        if hdlr is None or moov[hdlr[0] + 8 : hdlr[0] + 12] != b"vide":
            continue
        stbl = next(_find(moov, a, b, [b"mdia", b"minf", b"stbl"]), None)
        stss = next(_find(moov, *stbl, [b"stss"]), None) if stbl else None
        if stss is None:
            return None if stbl is None else _AllFrames()
        n = struct.unpack(">I", moov[stss[0] + 4 : stss[0] + 8])[0]
        return {k - 1 for k in struct.unpack(f">{n}I", moov[stss[0] + 8 : stss[0] + 8 + 4 * n])}
    return None


class _AllFrames(set):
    """Every frame is a key frame (a video track without an ``stss`` box)."""

    def __contains__(self, item: object) -> bool:
        return True


def _ranges(idx: list[int]) -> str:
    """``[3, 4, 5, 9]`` -> ``"3-5, 9"``."""
    runs: list[list[int]] = []
    for i in sorted(idx):
        if runs and i == runs[-1][1] + 1:
            runs[-1][1] = i
        else:
            runs.append([i, i])
    return ", ".join(str(a) if a == b else f"{a}-{b}" for a, b in runs)
