"""Point clouds through PDAL: readers, the user's filter pipeline, SMRF ground.

Used when ``map.lidar_backend`` resolves to ``pdal`` (``auto``: when the ``pdal`` Python package
imports). Files are read by the reader PDAL infers from the name (LAS/LAZ/COPC, EPT, PLY, ... what
libpdal was built with), cropped to a tile while streaming, and reprojected to the map CRS with
the same CRS and unit rules as the laspy path (:mod:`georeg.map.lidar`). The filter stages of
``map.pdal_pipeline`` then run on the tile's points in **local metric coordinates**: X and Y in
metres east and north of the grown tile's lower-left corner, Z in metres (so ``filters.range``
limits on Z, ``filters.outlier`` distances and ``filters.smrf`` cells are metres whatever the
file's units). When the filtered points hold no ground class (2), ``map.pdal_ground`` (default
``filters.smrf``) classifies them.

Bad pipelines (JSON that does not parse, a stage PDAL does not know, a stage that fails on a file)
raise :class:`~georeg.io.errors.ConfigError` / :class:`~georeg.io.errors.InputError` naming the
stage and the file.
"""

from __future__ import annotations

import dataclasses
import difflib
import functools
import json
import logging
import os
import tempfile
from collections.abc import Iterator, Sequence
from pathlib import Path
from typing import Any

import laspy
import numpy as np
import pyproj
from pyproj import CRS as PCRS

from georeg.io.errors import ConfigError, InputError
from georeg.map import lidar

log = logging.getLogger(__name__)

BACKENDS = ("auto", "pdal", "laspy")
GROUND = 2
OUTLIER_CLASS = 7
#: ``map.pdal_ground`` default: PDAL's simple morphological filter with its own defaults
DEFAULT_GROUND: dict[str, Any] = {"type": "filters.smrf"}
#: dimensions handed to the filter stages and read back (missing ones default to 0)
DIMS = (
    ("X", np.float64),
    ("Y", np.float64),
    ("Z", np.float64),
    ("Classification", np.uint8),
    ("ReturnNumber", np.uint8),
    ("NumberOfReturns", np.uint8),
    ("Intensity", np.uint16),
)
_POINT_FIELDS = ("classification", "return_number", "number_of_returns", "intensity")
#: points of each file run through the pipeline by :func:`dry_run` (input check)
DRY_RUN_POINTS = 5000


@functools.lru_cache(maxsize=1)
def import_error() -> str | None:
    """None when ``import pdal`` works, else why it does not (package missing, libpdal not found)."""
    try:
        import pdal  # noqa: F401
    except Exception as exc:  # ImportError, or OSError when libpdal cannot be loaded
        return f"{type(exc).__name__}: {exc}"
    return None


def available() -> bool:
    """True when the ``pdal`` Python bindings import (libpdal found)."""
    return import_error() is None


def resolve_backend(choice: str = "auto") -> str:
    """``pdal`` or ``laspy`` for ``map.lidar_backend`` (``auto``: pdal when it imports)."""
    if choice not in BACKENDS:
        raise ConfigError(f"map.lidar_backend must be one of {BACKENDS}, got {choice!r}")
    if choice == "auto":
        return "pdal" if available() else "laspy"
    if choice == "pdal" and not available():
        raise ConfigError(
            f"map.lidar_backend: pdal, but the pdal Python package does not import "
            f"({import_error()}): run .ci/install-pdal (README, 'PDAL'), or set auto or laspy"
        )
    return choice


def default_pipeline(outlier: dict[str, Any] | None = None) -> list[dict[str, Any]]:
    """The pipeline of ``map_prep.outlier``: PDAL's statistical outlier filter, outliers dropped.

    open3d counts the point itself (distance 0) among its ``nb_neighbors``, PDAL does not: with
    ``mean_k = nb_neighbors - 1`` every mean distance is open3d's times nb/(nb - 1), and so are
    the global mean and standard deviation, so the same points are removed.
    """
    o = outlier or {}
    if not o.get("enabled", True):
        return []
    return [
        {
            "type": "filters.outlier",
            "method": "statistical",
            "mean_k": max(1, int(o.get("nb_neighbors", 8)) - 1),
            "multiplier": float(o.get("std_ratio", 3.0)),
        },
        {"type": "filters.range", "limits": f"Classification![{OUTLIER_CLASS}:{OUTLIER_CLASS}]"},
    ]


def _stage_list(spec: Any, where: str) -> list[Any]:
    if isinstance(spec, str):
        text, src = spec, where
        if not spec.lstrip().startswith(("[", "{")):
            p = Path(spec)
            if not p.is_file():
                raise ConfigError(f"{where}: {spec}: pipeline file not found (or not JSON text)")
            text, src = p.read_text(), str(p)
        try:
            spec = json.loads(text)
        except json.JSONDecodeError as exc:
            raise ConfigError(f"{src}: the PDAL pipeline JSON does not parse ({exc})") from exc
        where = src
    if isinstance(spec, dict):
        spec = spec.get("pipeline", [spec] if "type" in spec else None)
    if not isinstance(spec, list):
        raise ConfigError(f"{where}: a PDAL pipeline must be a list of stages, got {spec!r}")
    return spec


def resolve_pipeline(
    spec: Any, outlier: dict[str, Any] | None = None, where: str = "map.pdal_pipeline"
) -> list[dict[str, Any]]:
    """The filter stages of ``map.pdal_pipeline`` as a list of dicts (null: the default one).

    ``spec``: null, a list of stages (dicts with ``type``, or stage names), or a string: JSON text
    or the path of a JSON file (a list, or PDAL's ``{"pipeline": [...]}``). Readers and writers
    are refused (georeg reads map.lidar and rasterises the result itself).
    """
    if spec is None:
        return default_pipeline(outlier)
    stages = []
    for i, st in enumerate(_stage_list(spec, where), 1):
        st = {"type": st} if isinstance(st, str) else st
        if not isinstance(st, dict) or not isinstance(st.get("type"), str):
            raise ConfigError(f"{where}: stage {i} ({st!r}) needs a 'type' (e.g. filters.range)")
        kind = st["type"]
        if not kind.startswith("filters."):
            raise ConfigError(
                f"{where}: stage {i} '{kind}': only filters.* stages go here (georeg reads "
                "every map.lidar file itself and rasterises the result)"
            )
        if "inputs" in st or "tag" in st:
            st = {k: v for k, v in st.items() if k not in ("inputs", "tag")}
        stages.append(dict(st))
    return stages


def resolve_ground(spec: Any) -> dict[str, Any] | None:
    """``map.pdal_ground``: the stage run when no point is ground class; null = none."""
    if spec is None or spec is False:
        return None
    if isinstance(spec, str):
        spec = {"type": spec}
    return resolve_pipeline([spec], where="map.pdal_ground")[0]


@functools.lru_cache(maxsize=1)
def known_stages() -> frozenset[str]:
    """Names of the stages libpdal offers (its plugins included)."""
    import pdal.libpdalpython as lib

    return frozenset(d["name"] for d in lib.getDrivers())


def check_stages(stages: Sequence[dict[str, Any]], where: str = "map.pdal_pipeline") -> None:
    """ConfigError naming the first stage libpdal does not know (with the closest names)."""
    known = known_stages()
    for i, st in enumerate(stages, 1):
        if st["type"] not in known:
            near = difflib.get_close_matches(st["type"], sorted(known), n=3)
            hint = f"; did you mean {', '.join(near)}?" if near else ""
            raise ConfigError(
                f"{where}: stage {i} '{st['type']}' is not a stage of this libpdal{hint}"
            )


# ---------------------------------------------------------------------------- reading


def reader_stage(path: str | os.PathLike, **options: Any) -> dict[str, Any]:
    """The reader PDAL infers from the file name; InputError when there is none."""
    import pdal.libpdalpython as lib

    kind = lib.infer_reader_driver(str(path))
    if not kind:
        raise InputError(path, "PDAL has no reader for this file type", "LAS/LAZ/COPC/EPT/PLY...")
    return {"type": kind, "filename": str(path), **options}


def scan(path: str | os.PathLike, lidar_crs: str | None = None) -> lidar.LasInfo:
    """Header facts of any PDAL-readable point cloud (PDAL's quick info), CRS resolved."""
    import pdal

    p = Path(path)
    if not p.exists():
        raise InputError(p, "file not found", "check map.lidar in the config")
    try:
        qi = pdal.Pipeline(json.dumps([reader_stage(p)])).quickinfo
    except InputError:
        raise
    except Exception as exc:
        raise InputError(p, f"PDAL cannot read it ({exc})", "truncated or corrupt?") from exc
    info = next(iter(qi.values()), {}) if isinstance(qi, dict) else {}
    n = int(info.get("num_points", 0) or 0)
    if n == 0:
        raise InputError(p, "point cloud is empty (0 points)", "remove it from map.lidar")
    wkt = (info.get("srs") or {}).get("wkt") or ""
    if wkt:
        crs = PCRS.from_wkt(wkt)
        src = "file"
    elif lidar_crs:
        try:
            crs = PCRS.from_user_input(lidar_crs)
        except pyproj.exceptions.CRSError as exc:
            raise InputError(p, f"map.lidar_crs {lidar_crs!r} is not a CRS ({exc})") from exc
        src = "map.lidar_crs"
    else:
        raise InputError(
            p, "point cloud has no CRS", 'set map.lidar_crs (e.g. "EPSG:2994") to its CRS'
        )
    horiz, vert = lidar.split_crs(crs)
    z_to_m = (
        float(vert.axis_info[0].unit_conversion_factor)
        if vert is not None
        else lidar.horizontal_unit_m(horiz)
    )
    b = info.get("bounds") or {}
    bounds = tuple(float(b.get(k, 0.0)) for k in ("minx", "miny", "maxx", "maxy"))
    log.info("%s: PDAL %s, CRS from %s: %s; z unit %.10g m", p, next(iter(qi)), src, horiz.name, z_to_m)
    return lidar.LasInfo(str(p), n, horiz, vert, z_to_m, bounds, -1)  # type: ignore[arg-type]


def _field(arr: np.ndarray, name: str, dtype: Any) -> np.ndarray:
    names = arr.dtype.names or ()
    if name in names:
        return np.asarray(arr[name]).astype(dtype, copy=False)
    return np.zeros(arr.shape[0], dtype)


def _crop_writer(info: lidar.LasInfo, filename: str) -> dict[str, Any]:
    """``writers.las`` for the cropped stream: LAS 1.4 format 6 (8-bit classes, 4-bit returns),
    1e-7 degree (~1 cm) or 1/1000 of the file's unit, offset at the header's lower-left."""
    scale = 1e-7 if info.crs.is_geographic else 1e-3
    return {
        "type": "writers.las",
        "filename": filename,
        "minor_version": 4,
        "dataformat_id": 6,
        "scale_x": scale,
        "scale_y": scale,
        "scale_z": 1e-3,
        "offset_x": float(info.bounds[0]),
        "offset_y": float(info.bounds[1]),
        "offset_z": 0.0,
    }


def iter_chunks(
    info: lidar.LasInfo,
    map_crs: PCRS,
    bounds: lidar.Bounds | None = None,
    chunk_points: int = 1_000_000,
) -> Iterator[lidar.Points]:
    """PDAL's twin of :func:`georeg.map.lidar.iter_chunks`: stream, crop, reproject, metres.

    PDAL streams the file through the crop to ``bounds`` (grown a little, in the file's CRS) into
    a temporary LAS file, which laspy then reads chunk by chunk, so memory stays ~ one chunk.
    Not ``Pipeline.iterator``: in python-pdal 3.5.5 its reader thread hands over the end of the
    stream without taking the lock, and the consumer can wait for ever (seen in CI; a loop of
    small reads reproduces it).
    """
    import pdal

    stages = [reader_stage(info.path)]
    if bounds is not None:
        pre = lidar.bounds_in_file_crs(bounds, map_crs, info.crs)
        stages.append({"type": "filters.crop", "bounds": f"([{pre[0]!r},{pre[2]!r}],[{pre[1]!r},{pre[3]!r}])"})
    with tempfile.TemporaryDirectory(prefix="georeg-pdal-") as tmp:
        out = os.path.join(tmp, "crop.las")
        stages.append(_crop_writer(info, out))
        try:
            pipe = pdal.Pipeline(json.dumps(stages))
            if pipe.streamable:
                pipe.execute_streaming(chunk_size=int(chunk_points))
            else:  # a reader without stream mode: PDAL holds the file's points
                pipe.execute()
            with laspy.open(out) as f:
                n = int(f.header.point_count)
        except InputError:
            raise
        except Exception as exc:  # PDAL raises RuntimeError with the stage's message
            raise InputError(info.path, f"PDAL cannot read it ({exc})", "truncated or corrupt?") from exc
        if n:
            crop = dataclasses.replace(info, path=out, point_count=n)
            yield from lidar.iter_chunks(crop, map_crs, bounds, chunk_points)


def read_points(
    infos: Sequence[lidar.LasInfo],
    map_crs: PCRS,
    bounds: lidar.Bounds,
    chunk_points: int = 1_000_000,
) -> lidar.Points:
    """All points of ``infos`` inside ``bounds`` (map CRS), read through PDAL."""
    parts = []
    for info in infos:
        if lidar.overlaps(lidar.bounds_in(info, map_crs), bounds):
            parts.extend(iter_chunks(info, map_crs, bounds, chunk_points))
    return lidar.Points.concat(parts)


# ---------------------------------------------------------------------------- filtering


def to_array(pts: lidar.Points, origin: tuple[float, float], scale: tuple[float, float]) -> np.ndarray:
    """Structured array of :data:`DIMS`; X/Y in metres from ``origin`` (map units x ``scale``)."""
    arr = np.empty(len(pts), dtype=[(n, t) for n, t in DIMS])
    arr["X"] = (pts.x - origin[0]) * scale[0]
    arr["Y"] = (pts.y - origin[1]) * scale[1]
    arr["Z"] = pts.z
    for (name, _), f in zip(DIMS[3:], _POINT_FIELDS, strict=True):
        arr[name] = getattr(pts, f)
    return arr


def from_array(arr: np.ndarray, origin: tuple[float, float], scale: tuple[float, float]) -> lidar.Points:
    """Inverse of :func:`to_array` (dimensions a stage dropped come back as 0)."""
    return lidar.Points(
        _field(arr, "X", np.float64) / scale[0] + origin[0],
        _field(arr, "Y", np.float64) / scale[1] + origin[1],
        _field(arr, "Z", np.float64),
        *(_field(arr, d, t) for d, t in DIMS[3:]),
    )


def _execute(stages: Sequence[dict[str, Any]], arr: np.ndarray) -> np.ndarray:
    import pdal

    pipe = pdal.Pipeline(json.dumps(list(stages)), arrays=[arr])
    pipe.execute()
    out = [a for a in pipe.arrays if a.shape[0]]
    return np.concatenate(out) if out else arr[:0]


def run_stages(
    arr: np.ndarray,
    stages: Sequence[dict[str, Any]],
    files: Sequence[str],
    where: str = "map.pdal_pipeline",
) -> np.ndarray:
    """Run the filter stages on ``arr``; a failure names the first failing stage and the files."""
    if not stages or arr.shape[0] == 0:
        return arr
    try:
        return _execute(stages, arr)
    except Exception as exc:
        # find the stage: run them one by one (only on this failure path)
        cur, bad, msg = arr, len(stages), str(exc)
        for i, st in enumerate(stages, 1):
            try:
                cur = _execute([st], cur)
            except Exception as e:  # noqa: BLE001 - reported below
                bad, msg = i, str(e)
                break
        st = stages[bad - 1]["type"]
        raise InputError(
            ", ".join(files) or None,
            f"PDAL stage {bad} '{st}' of {where} failed on this point cloud: {msg.strip()}",
            f"fix or remove stage '{st}' in {where}",
        ) from exc


def filter_points(
    pts: lidar.Points,
    stages: Sequence[dict[str, Any]],
    ground: dict[str, Any] | None,
    origin: tuple[float, float],
    scale: tuple[float, float],
    files: Sequence[str] = (),
) -> lidar.Points:
    """The pipeline's stages on ``pts`` (local metric coordinates), then ground when none is.

    Returns the filtered points in map coordinates, with the ground class the stages (or the
    ground stage) set.
    """
    if not len(pts):
        return pts
    n0 = len(pts)
    arr = run_stages(to_array(pts, origin, scale), stages, files)
    log.info(
        "PDAL pipeline %s: %d of %d points kept",
        [s["type"] for s in stages] or "(empty)",
        arr.shape[0],
        n0,
    )
    if ground is not None and arr.shape[0] and not (arr["Classification"] == GROUND).any():
        arr = run_stages(arr, [ground], files, where="map.pdal_ground")
        log.info(
            "no ground class: %s classified %d of %d points as ground",
            ground["type"],
            int((arr["Classification"] == GROUND).sum()),
            arr.shape[0],
        )
    return from_array(arr, origin, scale)


def dry_run(
    path: str | os.PathLike,
    stages: Sequence[dict[str, Any]],
    ground: dict[str, Any] | None,
    lidar_crs: str | None = None,
    n: int = DRY_RUN_POINTS,
) -> None:
    """Run the pipeline on the first ``n`` points of a file (input check): InputError if it fails."""
    import pdal

    info = scan_any(path, lidar_crs, "pdal")
    try:
        pipe = pdal.Pipeline(json.dumps([reader_stage(info.path, count=int(n))]))
        pipe.execute()
        arr = np.concatenate(pipe.arrays)
    except Exception as exc:
        raise InputError(path, f"PDAL cannot read it ({exc})", "truncated or corrupt?") from exc
    scale = (lidar.horizontal_unit_m(info.crs),) * 2
    pts = lidar.Points(
        _field(arr, "X", np.float64),
        _field(arr, "Y", np.float64),
        _field(arr, "Z", np.float64) * info.z_to_m,
        *(_field(arr, d, t) for d, t in DIMS[3:]),
    )
    origin = (float(pts.x.min()), float(pts.y.min())) if len(pts) else (0.0, 0.0)
    filter_points(pts, stages, ground, origin, scale, [str(path)])


def is_las(path: str | os.PathLike) -> bool:
    return str(path).lower().endswith((".las", ".laz"))


def scan_any(path: str | os.PathLike, lidar_crs: str | None = None, backend: str = "laspy") -> lidar.LasInfo:
    """Header facts of a ``map.lidar`` file: LAS/LAZ by laspy's header reader (both backends, so
    CRS and unit rules are the same), other formats by PDAL (the pdal backend only)."""
    if is_las(path) or backend != "pdal":
        return lidar.scan(path, lidar_crs)
    return scan(path, lidar_crs)
