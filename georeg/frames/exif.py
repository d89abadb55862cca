"""Focal length of a frame from its EXIF tags (Pillow), for ``camera: null``.

In order: ``FocalLengthIn35mmFilm`` (fx = f35 / 36 mm x the image's long side, the 36 mm side of
a 35 mm frame), else ``FocalLength`` (mm) x ``FocalPlaneXResolution`` (sensor pixels per
``FocalPlaneResolutionUnit``: 2 inch, 3 cm, 4 mm, 5 um), rescaled when the image was resized
from the ``PixelXDimension`` it was taken at, else ``FocalLength`` / the sensor width of the
camera ``Model`` in ``SENSOR_WIDTH_MM`` (common drone cameras; the image's long side spans the
sensor's width) x the image's long side. The principal point is put at the image centre, no
distortion. None when the file has no such tags (then the focal length is searched).
"""

from __future__ import annotations

import logging
from pathlib import Path
from typing import Any

log = logging.getLogger(__name__)

EXIF_IFD = 0x8769
FOCAL_LENGTH = 37386
FOCAL_35MM = 41989
FOCAL_PLANE_XRES = 41486
FOCAL_PLANE_UNIT = 41488
PIXEL_X_DIMENSION = 40962
MAKE, MODEL = 0x010F, 0x0110

# Sensor width x height (mm) of common drone cameras by EXIF Model (manufacturers' data sheets:
# 1" = 13.2 x 8.8, 1/2.3" = 6.17 x 4.55, 1/2" = 6.4 x 4.8, 1/1.3" = 9.6 x 7.2, 4/3 = 17.3 x 13.0).
SENSOR_MM: dict[str, tuple[float, float]] = {
    "FC6310": (13.2, 8.8),  # DJI Phantom 4 Pro
    "FC6310R": (13.2, 8.8),  # DJI Phantom 4 RTK
    "FC6310S": (13.2, 8.8),  # DJI Phantom 4 Pro V2.0
    "FC6510": (13.2, 8.8),  # DJI Zenmuse X4S
    "FC3411": (13.2, 8.8),  # DJI Air 2S
    "L1D-20C": (13.2, 8.8),  # DJI Mavic 2 Pro (Hasselblad)
    "FC330": (6.17, 4.55),  # DJI Phantom 4
    "FC300X": (6.17, 4.55),  # DJI Phantom 3 Professional
    "FC300S": (6.17, 4.55),  # DJI Phantom 3 Advanced
    "FC350": (6.17, 4.55),  # DJI Inspire 1 (Zenmuse X3)
    "FC220": (6.17, 4.55),  # DJI Mavic Pro
    "FC2103": (6.17, 4.55),  # DJI Mavic Air
    "FC2204": (6.17, 4.55),  # DJI Mavic 2 Zoom
    "FC7203": (6.17, 4.55),  # DJI Mavic Mini
    "FC7303": (6.17, 4.55),  # DJI Mini 2
    "FC3170": (6.4, 4.8),  # DJI Mavic Air 2
    "FC3582": (9.6, 7.2),  # DJI Mini 3 Pro
    "FC6520": (17.3, 13.0),  # DJI Zenmuse X5S
    "L2D-20C": (17.3, 13.0),  # DJI Mavic 3 (Hasselblad)
    "M3E": (17.3, 13.0),  # DJI Mavic 3 Enterprise
    "FC6540": (23.5, 15.7),  # DJI Zenmuse X7
    "ZENMUSEP1": (35.9, 24.0),  # DJI Zenmuse P1
}
SENSOR_WIDTH_MM = {k: v[0] for k, v in SENSOR_MM.items()}


def sensor_width_mm(model: Any) -> float | None:
    """Sensor width (mm) of an EXIF camera ``Model`` in the drone table, else None (case, spaces
    and a trailing NUL ignored)."""
    if not isinstance(model, (str, bytes)):
        return None
    m = model.decode("ascii", "ignore") if isinstance(model, bytes) else model
    return SENSOR_WIDTH_MM.get(m.strip().strip("\x00").replace(" ", "").upper())


UNIT_MM = {2: 25.4, 3: 10.0, 4: 1.0, 5: 1e-3}  # FocalPlaneResolutionUnit -> mm


def _num(v: Any) -> float | None:
    """An EXIF number (int, IFDRational, (num, den) tuple) as a positive float, else None."""
    try:
        f = float(v[0]) / float(v[1]) if isinstance(v, tuple) else float(v)
    except (TypeError, ValueError, ZeroDivisionError, IndexError):
        return None
    return f if f > 0 and f == f and f != float("inf") else None


def exif_focal_px(path: str | Path) -> tuple[float, str] | None:
    """(fx in pixels of the image as stored, which tags gave it), or None."""
    from PIL import Image, UnidentifiedImageError

    try:
        with Image.open(path) as im:
            w, h = im.size
            exif = im.getexif()
            tags = {**dict(exif), **dict(exif.get_ifd(EXIF_IFD))}
    except (OSError, UnidentifiedImageError, SyntaxError) as exc:  # not an image / bad EXIF
        log.warning("no EXIF read from %s: %s", path, exc)
        return None
    f35 = _num(tags.get(FOCAL_35MM))
    if f35:
        return f35 / 36.0 * max(w, h), "FocalLengthIn35mmFilm"
    fmm, xres = _num(tags.get(FOCAL_LENGTH)), _num(tags.get(FOCAL_PLANE_XRES))
    unit = UNIT_MM.get(int(_num(tags.get(FOCAL_PLANE_UNIT)) or 2))
    if fmm and xres and unit:
        fx = fmm * xres / unit  # mm x (sensor px / unit) / (mm / unit)
        full_w = _num(tags.get(PIXEL_X_DIMENSION))
        if full_w and abs(full_w - w) > 1 and abs(full_w - h) > 1:
            fx *= w / full_w  # resized since it was taken
        return fx, "FocalLength x FocalPlaneXResolution"
    sw = sensor_width_mm(tags.get(MODEL))
    if fmm and sw:
        model = str(tags.get(MODEL)).strip().strip("\x00")
        return fmm / sw * max(w, h), f"FocalLength / sensor width of {model} ({sw} mm, drone table)"
    return None


def exif_camera(path: str | Path, width: int, height: int) -> dict[str, Any] | None:
    """A ``camera`` dict (pixels; centred principal point, no distortion, ``source: exif``)
    from the EXIF focal length of ``path``, or None."""
    got = exif_focal_px(path)
    if got is None:
        return None
    fx, tags = got
    log.info("%s: EXIF focal length %.1f px (%s)", Path(path).name, fx, tags)
    return {"fx": fx, "fy": fx, "cx": (width - 1) / 2, "cy": (height - 1) / 2,
            "dist": [0.0] * 5, "source": "exif", "exif_tags": tags}  # fmt: skip
