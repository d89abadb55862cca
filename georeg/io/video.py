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
        want = self.indices()
        if not want:
            return
        cap = cv2.VideoCapture(str(self.video))
        if not cap.isOpened():
            raise InputError(self.video, "not a readable video", VIDEO_HINT)
        try:
            i, k = 0, 0
            while k < len(want):
                if i == want[k]:
                    ok, img = cap.read()
                    if not ok or img is None:
                        break
                    self._check_size(img, self.video, f"frame {i}")
                    yield i, video_name(self.video, i), cv2.cvtColor(img, cv2.COLOR_BGR2RGB)
                    k += 1
                elif not cap.grab():
                    break
                i += 1
            if k < len(want):
                log.warning("%s: ends after %d frames (container says %d)", self.video, i,
                            self.n_total)  # fmt: skip
        finally:
            cap.release()

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
