"""Errors that reach the user as one clear line naming the file and the problem."""

from __future__ import annotations

from pathlib import Path


class GeoregError(Exception):
    """Base class: an error the workflow reports as one line, without a traceback."""


class FileError(GeoregError):
    """An error about one file: ``<file>: <what is wrong> (<what to do>)``."""

    def __init__(self, path: str | Path | None, problem: str, hint: str = "") -> None:
        self.path = str(path) if path is not None else None
        self.problem = problem
        self.hint = hint
        where = f"{self.path}: " if self.path else ""
        tail = f" ({hint})" if hint else ""
        super().__init__(f"{where}{problem}{tail}")


class ConfigError(GeoregError):
    """A configuration value that cannot work (beyond what the JSON schema checks)."""


class InputError(FileError):
    """A bad input file: names the file, says what is wrong and what to do."""


class OutputError(FileError):
    """An output that could not be written (e.g. the disk is full): names the file."""
