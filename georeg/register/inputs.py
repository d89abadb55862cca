"""Every input of a run checked before any rule starts: all problems in one message.

The workflow calls :func:`check_inputs` right after the JSON-schema validation of the config, so a
wrong path, an unreadable file, a missing CRS, a geographic map CRS or a query band the cube does
not have stops the run before any job, with one line per problem naming its file or config key.
Only headers and metadata are read (no pixels; no points, except that with the PDAL backend the
first few thousand points of each point cloud go through ``map.pdal_pipeline`` so that a failing
stage stops the run here), so the check costs well under a second per input. What needs pixels (an all-nodata band, a corrupt block) is still reported by the rule
that reads them, with the same kind of message.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import pyproj

from georeg.io.errors import GeoregError
from georeg.io.prior import check_prior, prior_bounds
from georeg.io.query import open_query
from georeg.io.raster import open_raster
from georeg.io.video import frame_images, jpeg_cut_short
from georeg.map import pdal_points
from georeg.register.band import parse_band_spec, resolve_band
from georeg.register.rift import learned_import_error, learned_missing

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
        self.map_box: tuple[str, tuple[float, ...]] | None = None  # (CRS wkt, bounds) of the map
        self.prefix = Path(generated).as_posix().rstrip("/") + "/" if generated else None

    def made(self, path: Any) -> bool:
        return bool(self.prefix) and Path(str(path)).as_posix().startswith(self.prefix)

    def add(self, line: str) -> None:
        self.problems.append(line)

    def lidar(self, m: Mapping[str, Any], outlier: Mapping[str, Any] | None) -> None:
        """Point-cloud headers; with PDAL also the pipeline (parsed, stages known) and a dry run
        of it on the first points of each file, so a stage that fails stops the run here."""
        files = list(m.get("lidar") or [])
        try:
            backend = pdal_points.resolve_backend(m.get("lidar_backend", "auto")) if files else "laspy"
            stages = ground = None
            if backend == "pdal":
                stages = pdal_points.resolve_pipeline(m.get("pdal_pipeline"), dict(outlier or {}))
                ground = pdal_points.resolve_ground(
                    m.get("pdal_ground", pdal_points.DEFAULT_GROUND)
                )
                pdal_points.check_stages(stages)
                if ground is not None:
                    pdal_points.check_stages([ground], "map.pdal_ground")
        except GeoregError as exc:
            self.add(str(exc))
            return
        for path in files:
            if self.made(path):
                continue
            try:
                pdal_points.scan_any(path, m.get("lidar_crs"), backend)
                if stages is not None:
                    pdal_points.dry_run(path, stages, ground, m.get("lidar_crs"))
            except GeoregError as exc:
                self.add(f"map.lidar: {exc}")

    def map(self, m: Mapping[str, Any], outlier: Mapping[str, Any] | None = None) -> None:
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
                    if ds.crs is not None and (
                        map_crs is None or pyproj.CRS(ds.crs.to_wkt()) == pyproj.CRS(map_crs)
                    ):
                        self._grow_map_box(ds.crs.to_wkt(), tuple(ds.bounds))
                    if not map_crs and not ds.crs.is_projected:
                        lon, lat = _centre_lonlat(ds)
                        self.add(
                            f"{path}: the orthophoto's CRS ({ds.crs.to_string()}) is geographic; "
                            f"the map needs a projected CRS: set map.crs, e.g. {utm_hint(lon, lat)}"
                        )
            except GeoregError as exc:
                self.add(f"map.orthophoto: {exc}")
        self.lidar(m, outlier)
        if m.get("dem") and not self.made(m["dem"]):
            try:
                with open_raster(m["dem"]):
                    pass
            except GeoregError as exc:
                self.add(f"map.dem: {exc}")

    def _grow_map_box(self, crs: str, b: tuple[float, ...]) -> None:
        if self.map_box is None:
            self.map_box = (crs, b)
        elif self.map_box[0] == crs:
            o = self.map_box[1]
            self.map_box = (crs, (min(o[0], b[0]), min(o[1], b[1]), max(o[2], b[2]), max(o[3], b[3])))

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
            if q.get("prior") is not None:
                self.prior(key, q["prior"])

    def prior(self, key: str, prior: Any) -> None:
        """A query's location prior: well formed, and overlapping the map (when it is known)."""
        try:
            check_prior(prior)
        except ValueError as exc:
            self.add(f"{key}.{exc}" if str(exc).startswith("prior") else f"{key}.prior: {exc}")
            return
        if self.map_box is None:
            return
        crs, box = self.map_box
        try:
            b = prior_bounds(prior, crs)
        except ValueError as exc:
            self.add(f"{key}.prior: {exc}")
            return
        if b is None or b[0] > box[2] or b[2] < box[0] or b[1] > box[3] or b[3] < box[1]:
            self.add(f"{key}.prior: {b} does not overlap the map ({box}, {crs[:40]}...)")

    def learned(self, learned: Mapping[str, Any]) -> None:
        """``register.learned.enabled: true`` needs ALIKED (``.ci/install-learned``)."""
        if learned.get("enabled") is True and (why := learned_import_error()):
            self.add(learned_missing(why))

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
                        elif jpeg_cut_short(p):
                            self.add(f"{key}.images: {p}: JPEG data is truncated")
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
    c.map(config.get("map") or {}, (config.get("map_prep") or {}).get("outlier"))
    c.queries(config.get("queries") or {})
    c.frames(config.get("frames") or {})
    c.learned((config.get("register") or {}).get("learned") or {})
    return c.problems
