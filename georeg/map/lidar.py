"""LAS/LAZ reading: CRS and unit handling, chunked streaming, outlier removal, textured LAZ.

Coordinates leave this module as ``x, y`` in the map CRS (its own horizontal units) and ``z`` in
metres. The vertical unit is taken, in this order, from a compound CRS's vertical part, the
GeoTIFF ``VerticalUnitsGeoKey``/``VerticalCSTypeGeoKey``, or the horizontal CRS's axis unit (the
LAS convention when no vertical CRS is given: a file in US survey feet has heights in US survey
feet). Files without a CRS need ``map.lidar_crs``.
"""

from __future__ import annotations

import logging
import math
import os
from collections.abc import Iterator, Sequence
from dataclasses import dataclass
from pathlib import Path

import laspy
import lazrs
import numpy as np
import pyproj
from pyproj import CRS as PCRS
from pyproj import Transformer

from georeg.io.atomic import atomic_path
from georeg.io.errors import InputError

log = logging.getLogger(__name__)

Bounds = tuple[float, float, float, float]

#: EPSG unit codes of GeoTIFF VerticalUnitsGeoKey -> metres per unit
_UNIT_CODES = {9001: 1.0, 9002: 0.3048, 9003: 1200.0 / 3937.0}
_VERTICAL_UNITS_KEY = 4099
_VERTICAL_CS_KEY = 4096

#: a vertical CRS in metres with an unknown datum, for outputs whose source had none
_VERT_M_WKT = (
    'VERTCRS["unknown height (m)",VDATUM["unknown"],CS[vertical,1],'
    'AXIS["gravity-related height (H)",up,LENGTHUNIT["metre",1]]]'
)


@dataclass
class LasInfo:
    """Header facts of one LAS/LAZ file, with its CRS resolved."""

    path: str
    point_count: int
    crs: PCRS  # horizontal CRS of the file
    vertical: PCRS | None  # vertical CRS when the file gives one
    z_to_m: float  # metres per file z unit
    bounds: Bounds  # header bounds in the file CRS
    point_format: int


#: the LASzip VLR (compression parameters) of a LAZ file
_LASZIP_RECORD_ID = 22204


def _fail(path: str | os.PathLike, exc: BaseException, what: str = "cannot read") -> InputError:
    return InputError(
        path, f"{what} LAS/LAZ ({type(exc).__name__}: {exc})", "truncated or corrupt?"
    )


def _geokey_vertical(header: laspy.LasHeader) -> tuple[float | None, PCRS | None]:
    """(metres per unit, vertical CRS) from GeoTIFF keys, or (None, None)."""
    for vlr in header.vlrs:
        if isinstance(vlr, laspy.vlrs.known.GeoKeyDirectoryVlr):
            keys = {k.id: k.value_offset for k in vlr.geo_keys}
            vcrs = None
            if _VERTICAL_CS_KEY in keys and 1024 <= keys[_VERTICAL_CS_KEY] <= 32766:
                try:
                    vcrs = PCRS.from_epsg(keys[_VERTICAL_CS_KEY])
                except pyproj.exceptions.CRSError:
                    vcrs = None
            unit = _UNIT_CODES.get(keys.get(_VERTICAL_UNITS_KEY, -1))
            if unit is None and vcrs is not None:
                unit = vcrs.axis_info[0].unit_conversion_factor
            return unit, vcrs
    return None, None


def split_crs(crs: PCRS) -> tuple[PCRS, PCRS | None]:
    """(horizontal, vertical or None) parts of a CRS (compound or 3D projected/geographic)."""
    if crs.is_compound:
        subs = crs.sub_crs_list
        vert = next((s for s in subs if s.is_vertical), None)
        horiz = next(s for s in subs if not s.is_vertical)
        return horiz, vert
    if len(crs.axis_info) == 3 and not crs.is_geocentric:
        return crs.to_2d(), None
    return crs, None


def horizontal_unit_m(crs: PCRS) -> float:
    """Metres per horizontal unit (1 for geographic CRSs: heights are then metres)."""
    if crs.is_geographic:
        return 1.0
    return float(crs.axis_info[0].unit_conversion_factor)


def resolve_crs(
    path: str | os.PathLike, header: laspy.LasHeader, lidar_crs: str | None
) -> tuple[PCRS, PCRS | None, float]:
    """(horizontal CRS, vertical CRS or None, metres per z unit) of a LAS file.

    ``lidar_crs`` is used only for files without a CRS; none at all -> InputError naming the file.
    """
    try:
        crs = header.parse_crs()
    except Exception as exc:  # laspy/pyproj raise various types on bad VLRs
        log.warning("%s: CRS VLR not understood (%s)", path, exc)
        crs = None
    source = "header"
    if crs is None:
        if not lidar_crs:
            raise InputError(
                path,
                "LAS/LAZ file has no CRS",
                'set map.lidar_crs (e.g. "EPSG:2994") to the CRS the coordinates are in',
            )
        try:
            crs = PCRS.from_user_input(lidar_crs)
        except pyproj.exceptions.CRSError as exc:
            raise InputError(path, f"map.lidar_crs {lidar_crs!r} is not a CRS ({exc})") from exc
        source = "map.lidar_crs"
    horiz, vert = split_crs(crs)
    if vert is not None:
        z_to_m = float(vert.axis_info[0].unit_conversion_factor)
        zsrc = f"vertical CRS {vert.name}"
    else:
        unit, vcrs = _geokey_vertical(header) if source == "header" else (None, None)
        if unit is not None:
            z_to_m, vert, zsrc = unit, vcrs, "VerticalUnitsGeoKey"
        else:
            z_to_m, zsrc = horizontal_unit_m(horiz), "horizontal axis unit"
    log.info(
        "%s: CRS from %s: %s; z unit %.10g m (from %s)", path, source, horiz.name, z_to_m, zsrc
    )
    return horiz, vert, z_to_m


def scan(path: str | os.PathLike, lidar_crs: str | None = None) -> LasInfo:
    """Read only the header of a LAS/LAZ file; missing, corrupt, empty or CRS-less -> InputError."""
    p = Path(path)
    if not p.exists():
        raise InputError(p, "file not found", "check map.lidar in the config")
    try:
        with laspy.open(p) as reader:
            header = reader.header
    except Exception as exc:
        raise _fail(p, exc) from exc
    if header.point_count == 0:
        raise InputError(p, "point cloud is empty (0 points)", "remove it from map.lidar")
    _check_length(p, header)
    horiz, vert, z_to_m = resolve_crs(p, header, lidar_crs)
    mins, maxs = header.mins, header.maxs
    return LasInfo(
        str(p),
        int(header.point_count),
        horiz,
        vert,
        z_to_m,
        (float(mins[0]), float(mins[1]), float(maxs[0]), float(maxs[1])),
        header.point_format.id,
    )


def _check_length(path: Path, header: laspy.LasHeader) -> None:
    """InputError when the file is shorter than its header says: cut in its records (VLRs), its
    points, its LAZ chunk table or its extended records (a header read alone does not notice)."""
    size = path.stat().st_size
    start = int(header.offset_to_point_data)
    need = start + int(header.point_count) * int(header.point_format.size)
    what = f"its points need {need}"
    if start > size:
        need, what = start, f"its header and records need {start}"
    elif header.are_points_compressed:
        need, what = start, ""
        try:  # LAZ: an 8-byte offset to the chunk table (at the end), then the chunks
            vlr = next(v for v in header.vlrs if v.record_id == _LASZIP_RECORD_ID)
            with open(path, "rb") as f:
                f.seek(start)
                table = lazrs.read_chunk_table(f, lazrs.LazVlr(vlr.record_data))
            if table:
                need = start + 8 + sum(int(n) for _, n in table)
                what = f"its {len(table)} compressed chunk(s) end at byte {need}"
        except StopIteration:
            pass  # no LASzip record: laspy reports it when reading
        except Exception:  # noqa: BLE001 (lazrs raises its own type on a short read)
            need, what = size + 1, "its chunk table (the last bytes) is cut"
    if int(getattr(header, "number_of_evlrs", 0) or 0) > 0:
        evlr_end = int(header.start_of_first_evlr) + 60  # one EVLR header: 60 bytes
        if evlr_end > need:
            need, what = evlr_end, f"its extended records start at byte {evlr_end - 60}"
    if size < need:
        raise InputError(path, f"file is truncated: {size} bytes, {what}",
                         "copy or export it again")  # fmt: skip


def bounds_in(info: LasInfo, dst: PCRS) -> Bounds:
    """Header bounds of a file in CRS ``dst`` (densified edges)."""
    if info.crs == dst:
        return info.bounds
    tr = Transformer.from_crs(info.crs, dst, always_xy=True)
    return tr.transform_bounds(*info.bounds, densify_pts=21)


def overlaps(a: Bounds, b: Bounds) -> bool:
    return a[0] < b[2] and b[0] < a[2] and a[1] < b[3] and b[1] < a[3]


@dataclass
class Points:
    """Point attributes as flat arrays; x, y in the map CRS, z in metres."""

    x: np.ndarray
    y: np.ndarray
    z: np.ndarray
    classification: np.ndarray
    return_number: np.ndarray
    number_of_returns: np.ndarray
    intensity: np.ndarray

    def __len__(self) -> int:
        return int(self.x.size)

    def take(self, keep: np.ndarray) -> Points:
        return Points(*(getattr(self, f)[keep] for f in _FIELDS))

    @staticmethod
    def concat(parts: Sequence[Points]) -> Points:
        if not parts:
            return Points.empty()
        return Points(*(np.concatenate([getattr(p, f) for p in parts]) for f in _FIELDS))

    @staticmethod
    def empty() -> Points:
        f8, u1, u2 = np.empty(0, np.float64), np.empty(0, np.uint8), np.empty(0, np.uint16)
        return Points(f8, f8.copy(), f8.copy(), u1, u1.copy(), u1.copy(), u2)


_FIELDS = ("x", "y", "z", "classification", "return_number", "number_of_returns", "intensity")


def in_bounds(pts: Points, x: np.ndarray, y: np.ndarray, bounds: tuple | None) -> Points:
    """The points whose map-CRS x/y fall in ``bounds`` (left/top edges in, right/bottom out, so
    neighbouring tiles never share a point); all of them without bounds."""
    if bounds is None:
        return pts
    return pts.take((x >= bounds[0]) & (x < bounds[2]) & (y > bounds[1]) & (y <= bounds[3]))


def bounds_in_file_crs(bounds: tuple, map_crs, file_crs) -> tuple:
    """A map-CRS box in a point file's CRS, padded by 1 % (the points are pre-selected with it
    before their x/y are reprojected)."""
    if file_crs == map_crs:
        return tuple(bounds)
    back = Transformer.from_crs(map_crs, file_crs, always_xy=True)
    b = back.transform_bounds(*bounds, densify_pts=21)
    pad = 0.01 * max(b[2] - b[0], b[3] - b[1])
    return (b[0] - pad, b[1] - pad, b[2] + pad, b[3] + pad)


def iter_chunks(
    info: LasInfo,
    map_crs: PCRS,
    bounds: Bounds | None = None,
    chunk_points: int = 1_000_000,
) -> Iterator[Points]:
    """Stream a file in chunks, keep points inside ``bounds`` (map CRS), yield them in map CRS.

    Points are pre-selected in the file's CRS with the (densified, slightly grown) bounds, so
    only the kept points are reprojected. Memory ~ one chunk.
    """
    same = info.crs == map_crs
    tr = None if same else Transformer.from_crs(info.crs, map_crs, always_xy=True)
    pre = None if bounds is None else bounds_in_file_crs(bounds, map_crs, info.crs)
    seen = 0
    try:
        with laspy.open(info.path) as reader:
            for chunk in reader.chunk_iterator(chunk_points):
                n = len(chunk)
                if n == 0:
                    break
                seen += n
                x, y = np.asarray(chunk.x), np.asarray(chunk.y)
                if pre is not None:
                    sel = (x >= pre[0]) & (x <= pre[2]) & (y >= pre[1]) & (y <= pre[3])
                    if not sel.any():
                        continue
                    chunk = chunk[sel]
                    x, y = np.asarray(chunk.x), np.asarray(chunk.y)
                if tr is not None:
                    x, y = tr.transform(x, y)
                    x, y = np.asarray(x), np.asarray(y)
                pts = Points(
                    x,
                    y,
                    np.asarray(chunk.z, dtype=np.float64) * info.z_to_m,
                    np.asarray(chunk.classification, dtype=np.uint8),
                    np.asarray(chunk.return_number, dtype=np.uint8),
                    np.asarray(chunk.number_of_returns, dtype=np.uint8),
                    np.asarray(chunk.intensity, dtype=np.uint16),
                )
                pts = in_bounds(pts, x, y, bounds)
                if len(pts):
                    yield pts
    except InputError:
        raise
    except Exception as exc:  # lazrs / laspy / numpy errors on damaged data
        raise _fail(info.path, exc) from exc
    if seen < info.point_count:
        raise InputError(
            info.path,
            f"only {seen} of the {info.point_count} points in the header could be read",
            "truncated or corrupt?",
        )


def read_points(
    infos: Sequence[LasInfo],
    map_crs: PCRS,
    bounds: Bounds,
    chunk_points: int = 1_000_000,
) -> Points:
    """All points of ``infos`` inside ``bounds`` (map CRS); files whose header misses it are skipped."""
    parts = []
    for info in infos:
        if not overlaps(bounds_in(info, map_crs), bounds):
            continue
        parts.extend(iter_chunks(info, map_crs, bounds, chunk_points))
    return Points.concat(parts)


def remove_outliers(xyz_m: np.ndarray, nb_neighbors: int = 8, std_ratio: float = 3.0) -> np.ndarray:
    """Boolean keep-mask from open3d statistical outlier removal on metric coordinates.

    A point goes when its mean distance to its ``nb_neighbors`` nearest neighbours exceeds the
    global mean by more than ``std_ratio`` standard deviations (isolated birds, low noise).
    """
    n = xyz_m.shape[0]
    keep = np.ones(n, dtype=bool)
    if n <= nb_neighbors:
        return keep
    import open3d as o3d  # heavy import: only when needed

    pcd = o3d.geometry.PointCloud(
        o3d.utility.Vector3dVector(np.ascontiguousarray(xyz_m, np.float64))
    )
    _, idx = pcd.remove_statistical_outlier(
        nb_neighbors=int(nb_neighbors), std_ratio=float(std_ratio)
    )
    keep[:] = False
    keep[np.asarray(idx, dtype=np.int64)] = True
    return keep


def output_crs(map_crs: PCRS) -> PCRS:
    """Compound CRS written into textured LAZ headers: map CRS horizontally, metres vertically."""
    horiz, vert = split_crs(map_crs)
    if vert is not None and abs(vert.axis_info[0].unit_conversion_factor - 1.0) < 1e-12:
        return map_crs
    return pyproj.crs.CompoundCRS(
        name=f"{horiz.name} + height (m)", components=[horiz, PCRS.from_wkt(_VERT_M_WKT)]
    )


def write_textured_laz(
    path: str | os.PathLike, pts: Points, rgb: np.ndarray, map_crs: PCRS
) -> None:
    """Write points (map CRS x/y, metres z) with RGB (uint8, n x 3) as LAS 1.4 point format 7."""
    header = laspy.LasHeader(point_format=7, version="1.4")
    unit = horizontal_unit_m(split_crs(map_crs)[0])
    xy_scale = 1e-7 if map_crs.is_geographic else 0.001 / unit
    header.scales = np.array([xy_scale, xy_scale, 0.001])
    if len(pts):
        header.offsets = np.array(
            [math.floor(pts.x.min()), math.floor(pts.y.min()), math.floor(pts.z.min())]
        )
    header.add_crs(output_crs(map_crs))
    las = laspy.LasData(header)
    las.x, las.y, las.z = pts.x, pts.y, pts.z
    las.classification = pts.classification
    las.return_number = np.clip(pts.return_number, 1, 15)
    las.number_of_returns = np.clip(pts.number_of_returns, 1, 15)
    las.intensity = pts.intensity
    rgb16 = rgb.astype(np.uint16) * 257
    las.red, las.green, las.blue = rgb16[:, 0], rgb16[:, 1], rgb16[:, 2]
    with atomic_path(path) as tmp:
        las.write(str(tmp))
