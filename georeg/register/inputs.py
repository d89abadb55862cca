"""Every input of a run checked before any rule starts: all problems in one message.

The workflow calls :func:`check_inputs` right after the JSON-schema validation of the config, so a
wrong path, an unreadable file, a missing CRS, a geographic map CRS or a query band the cube does
not have stops the run before any job, with one line per problem naming its file or config key.
Only headers and metadata are read (no pixels, no points), so the check costs well under a second
per input. What needs pixels (an all-nodata band, a corrupt block) is still reported by the rule
that reads them, with the same kind of message.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import pyproj

from georeg.io.errors import GeoregError
from georeg.io.query import open_query
from georeg.io.raster import open_raster
from georeg.io.video import frame_images
from georeg.map import lidar
from georeg.register.band import parse_band_spec, resolve_band

VIDEO_SUFFIXES = {".mp4", ".avi", ".mov", ".mkv", ".m4v", ".mpg", ".mpeg", ".webm"}


def utm_hint(lon: float, lat: float) -> str:
    """'EPSG:326zz (WGS 84 / UTM zone zzN)' for a point: the projected CRS to reproject to."""
    zone = int(math.floor((lon + 180.0) / 6.0)) % 60 + 1
    code = (32600 if lat >= 0 else 32700) + zone
    return f"EPSG:{code} (WGS 84 / UTM zone {zone}{'N' if lat >= 0 else 'S'})"


def _projected(crs: Any) -> bool:
    return pyproj.CRS.from_user_input(crs).is_projected


class _Checker:
    """Collects problems; paths under ``generated`` (made by the workflow's rules) are skipped."""

    def __init__(self, generated: str | None) -> None:
        self.problems: list[str] = []
        self.prefix = Path(generated).as_posix().rstrip("/") + "/" if generated else None

    def made(self, path: Any) -> bool:
        return bool(self.prefix) and Path(str(path)).as_posix().startswith(self.prefix)

    def add(self, line: str) -> None:
        self.problems.append(line)

    def map(self, m: Mapping[str, Any]) -> None:
        orthos = m.get("orthophoto")
        orthos = [orthos] if isinstance(orthos, str) else list(orthos or [])
        if not orthos:
            self.add("map.orthophoto: no orthophoto given")
        map_crs = m.get("crs")
        if map_crs:
            try:
                if not _projected(map_crs):
                    self.add(f"map.crs: {map_crs} is not a projected CRS (metres or feet needed)")
            except pyproj.exceptions.CRSError as exc:
                self.add(f"map.crs: {map_crs!r} is not a CRS ({exc})")
                map_crs = None
        for path in orthos:
            if self.made(path):
                continue
            try:
                with open_raster(path) as ds:
                    if not map_crs and not ds.crs.is_projected:
                        lon, lat = _centre_lonlat(ds)
                        self.add(
                            f"{path}: the orthophoto's CRS ({ds.crs.to_string()}) is geographic; "
                            f"the map needs a projected CRS: set map.crs, e.g. {utm_hint(lon, lat)}"
                        )
            except GeoregError as exc:
                self.add(f"map.orthophoto: {exc}")
        for path in m.get("lidar") or []:
            if self.made(path):
                continue
            try:
                lidar.scan(path, m.get("lidar_crs"))
            except GeoregError as exc:
                self.add(f"map.lidar: {exc}")
        if m.get("dem") and not self.made(m["dem"]):
            try:
                with open_raster(m["dem"]):
                    pass
            except GeoregError as exc:
                self.add(f"map.dem: {exc}")

    def queries(self, queries: Mapping[str, Any]) -> None:
        for name, q in sorted(queries.items()):
            key = f"queries.{name}"
            if not self.made(q["image"]):
                try:
                    cube = open_query(q["image"])
                    resolve_band(cube, parse_band_spec(q.get("band", "auto")))
                except GeoregError as exc:
                    self.add(f"{key}: {exc}")
            for opt in ("truth", "labels"):
                v = q.get(opt)
                if v and not self.made(v) and not Path(v).exists():
                    self.add(f"{key}.{opt}: {v}: file not found")

    def frames(self, frames: Mapping[str, Any]) -> None:
        from PIL import Image, UnidentifiedImageError

        for name, fs in sorted(frames.items()):
            key = f"frames.{name}"
            if fs.get("video"):
                v = Path(fs["video"])
                if not self.made(v) and (not v.is_file() or v.stat().st_size == 0):
                    self.add(f"{key}.video: {v}: file not found or empty")
                continue
            images = fs.get("images")
            items = [images] if isinstance(images, str) else list(images or [])
            if not items:
                self.add(f"{key}.images: no image given")
            for it in items:
                if self.made(it):
                    continue
                hits = frame_images([it])
                if not hits:
                    self.add(f"{key}.images: {it}: no file matches")
                for p in hits:
                    try:
                        with Image.open(p) as im:
                            w, h = im.size
                        if min(w, h) < 64:
                            self.add(f"{key}.images: {p}: {w} x {h} px, frames need >= 64 px")
                    except FileNotFoundError:
                        self.add(f"{key}.images: {p}: file not found")
                    except (UnidentifiedImageError, OSError) as exc:
                        self.add(f"{key}.images: {p}: not a readable image ({exc})")
            t = fs.get("truth")
            if t and not self.made(t) and not Path(t).exists():
                self.add(f"{key}.truth: {t}: file not found")
            if fs.get("prior") is not None:
                from georeg.io.prior import check_prior

                try:
                    check_prior(fs["prior"])
                except ValueError as exc:
                    self.add(f"{key}.prior: {exc}")


def _centre_lonlat(ds: Any) -> tuple[float, float]:
    b = ds.bounds
    tr = pyproj.Transformer.from_crs(ds.crs, "EPSG:4326", always_xy=True)
    return tr.transform((b.left + b.right) / 2, (b.bottom + b.top) / 2)


def check_inputs(config: Mapping[str, Any], generated: str | None = "results") -> list[str]:
    """Problems with the run's input files (map, queries, frames), one line each; [] when fine.

    Paths under ``generated`` (the workflow's own outputs, e.g. the demo scene in
    ``results/demo/``) are written by rules and not checked here.
    """
    c = _Checker(generated)
    c.map(config.get("map") or {})
    c.queries(config.get("queries") or {})
    c.frames(config.get("frames") or {})
    return c.problems
