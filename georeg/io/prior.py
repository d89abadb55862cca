"""An optional approximate location (``queries.<name>.prior``, ``frames.<set>.prior``): parsed,
checked and turned into a box in the map CRS, shared by the register and frames stages.

Without it a search is GPS-free (the whole map); with it the search keeps to the prior's box.

Forms (``crs``: ``map``, the default, or ``lonlat``):

* ``{"centre": [x, y], "radius_m": r}``: the square of half side r metres around the centre;
* ``{"box": [x0, y0, x1, y1]}``: a box (lon/lat: ``[lon0, lat0, lon1, lat1]``).

A plain sequence of four numbers is taken as map bounds (the library's own form).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import Any

Bounds = tuple[float, float, float, float]
CRS_CHOICES = ("map", "lonlat")


def _numbers(v: Any, n: int, what: str) -> list[float]:
    if not isinstance(v, Sequence) or isinstance(v, str) or len(v) != n:
        raise ValueError(f"{what} must be a list of {n} numbers, got {v!r}")
    try:
        out = [float(x) for x in v]
    except (TypeError, ValueError):
        raise ValueError(f"{what} must be a list of {n} numbers, got {v!r}") from None
    if not all(math.isfinite(x) for x in out):
        raise ValueError(f"{what} must be finite, got {v!r}")
    return out


def check_prior(prior: Any) -> dict[str, Any] | None:
    """The prior as a dict with ``crs`` set; raises ValueError naming what is wrong."""
    if prior is None:
        return None
    if not isinstance(prior, dict):
        return {"box": _numbers(prior, 4, "prior"), "crs": "map"}
    crs = prior.get("crs", "map")
    if crs not in CRS_CHOICES:
        raise ValueError(f"prior.crs must be one of {CRS_CHOICES}, got {crs!r}")
    unknown = set(prior) - {"centre", "radius_m", "box", "crs"}
    if unknown:
        raise ValueError(f"prior: unknown key(s) {sorted(unknown)} (centre + radius_m, or box)")
    if ("box" in prior) == ("centre" in prior):
        raise ValueError("prior needs either centre + radius_m or box")
    out: dict[str, Any] = {"crs": crs}
    if "box" in prior:
        b = _numbers(prior["box"], 4, "prior.box")
        if not (b[0] < b[2] and b[1] < b[3]):
            raise ValueError(f"prior.box must be [x0, y0, x1, y1] with x0 < x1, y0 < y1, got {b}")
        out["box"] = b
    else:
        out["centre"] = _numbers(prior["centre"], 2, "prior.centre")
        r = prior.get("radius_m")
        if not isinstance(r, (int, float)) or isinstance(r, bool) or not r > 0:
            raise ValueError(f"prior.radius_m must be a positive number of metres, got {r!r}")
        out["radius_m"] = float(r)
    if crs == "lonlat":
        pts = [out["box"][:2], out["box"][2:]] if "box" in out else [out["centre"]]
        for lon, lat in pts:
            if not (-180.0 <= lon <= 180.0 and -90.0 <= lat <= 90.0):
                raise ValueError(f"prior ({crs}): lon {lon}, lat {lat} out of range")
    return out


def _metres_per_unit(crs: Any) -> float:
    if crs is not None and crs.is_projected and crs.axis_info:
        return float(crs.axis_info[0].unit_conversion_factor)
    return 1.0


def prior_bounds(prior: Any, crs_wkt: str | None, where: str | None = None,
                 key: str = "queries.<name>.prior") -> Bounds | None:
    """The prior's box in the map CRS (None: no prior). ``crs_wkt``: the map's CRS (needed for
    ``lonlat`` and for radii on a map in feet). ``where``: a file to name in the error (the
    error is then ``georeg.io.errors.InputError``, else ValueError); ``key``: the config key
    named in its hint."""
    try:
        p = check_prior(prior)
        if p is None:
            return None
        crs = None
        if crs_wkt:
            from pyproj import CRS

            crs = CRS.from_user_input(crs_wkt)
        if p["crs"] == "lonlat":
            if crs is None:
                raise ValueError("prior in lonlat but the map has no CRS")
            from pyproj import Transformer

            tr = Transformer.from_crs("EPSG:4326", crs, always_xy=True)
            if "box" in p:
                b = tr.transform_bounds(*p["box"], densify_pts=21)
                return (float(b[0]), float(b[1]), float(b[2]), float(b[3]))
            cx, cy = tr.transform(*p["centre"])
        elif "box" in p:
            return tuple(p["box"])  # type: ignore[return-value]
        else:
            cx, cy = p["centre"]
        r = p["radius_m"] / _metres_per_unit(crs)
        return (float(cx) - r, float(cy) - r, float(cx) + r, float(cy) + r)
    except ValueError as exc:
        if where is None:
            raise
        from georeg.io.errors import InputError

        raise InputError(where, str(exc), f"see config/README.md, {key}") from None


def prior_record(prior: Any, bounds: Bounds | None) -> dict[str, Any] | None:
    """What a record (registration.json, poses.json) keeps of the prior: as given and its box
    in the map CRS."""
    if bounds is None:
        return None
    given = prior if isinstance(prior, dict) else list(prior)
    return {"given": given, "bounds": [float(v) for v in bounds]}
