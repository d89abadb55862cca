"""georeg: register airborne imagery to a geo-referenced map without GPS."""

from georeg.io.errors import GeoregError, InputError

__all__ = ["GeoregError", "InputError"]
__version__ = "0.1.0"
