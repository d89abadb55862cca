"""Write outputs under a temporary name and rename on success: never a half-written file."""

from __future__ import annotations

import contextlib
import errno
import glob
import json
import math
import os
import shutil
from collections.abc import Iterator
from pathlib import Path
from typing import Any

from georeg.io.errors import GeoregError, OutputError


def _tmp_name(path: Path) -> Path:
    # keep the suffix so that drivers that look at it (GTiff, LAZ, PNG) still work
    return path.with_name(f".{path.stem}.tmp-{os.getpid()}{path.suffix}")


def _remove_stale(path: Path) -> None:
    """Delete temporaries of ``path`` left by a killed writer (SIGKILL, node failure).

    Only those whose process is gone: a concurrent writer of the same path keeps its own.
    """
    for old in path.parent.glob(f".{glob.escape(path.stem)}.tmp-*{glob.escape(path.suffix)}"):
        pid = old.name[len(path.stem) + 6 :].removesuffix(path.suffix)
        if not pid.isdigit() or int(pid) == os.getpid():
            continue
        try:
            os.kill(int(pid), 0)
            continue  # still running
        except ProcessLookupError:
            pass
        except PermissionError:
            continue  # alive, another user's
        if old.is_dir():
            shutil.rmtree(old, ignore_errors=True)
        else:
            with contextlib.suppress(FileNotFoundError):
                old.unlink()


@contextlib.contextmanager
def atomic_path(path: str | os.PathLike) -> Iterator[Path]:
    """Yield a temporary path beside ``path``; rename it onto ``path`` if the block succeeds.

    On any exception the temporary file is removed and ``path`` is left untouched.
    """
    final = Path(path)
    final.parent.mkdir(parents=True, exist_ok=True)
    _remove_stale(final)
    tmp = _tmp_name(final)
    try:
        yield tmp
        os.replace(tmp, final)
    except BaseException as exc:
        if tmp.is_dir():
            shutil.rmtree(tmp, ignore_errors=True)
        else:
            with contextlib.suppress(FileNotFoundError):
                tmp.unlink()
        if disk_full(exc):
            free = shutil.disk_usage(final.parent).free / 1e6
            raise OutputError(final, f"no space left on the device while writing it ({free:.1f} "
                              "MB free now)", "free space there, then run again") from exc  # fmt: skip
        raise


def disk_full(exc: BaseException) -> bool:
    """Whether ``exc`` (or what caused it) is ENOSPC: an OSError, or a GDAL / LAZ error whose
    message says so. An error already naming its file (GeoregError) is not wrapped again."""
    seen = 0
    while exc is not None and seen < 8 and not isinstance(exc, GeoregError):
        if isinstance(exc, OSError) and exc.errno == errno.ENOSPC:
            return True
        if "no space left on device" in str(exc).lower():
            return True
        exc, seen = exc.__cause__ or exc.__context__, seen + 1
    return False


def write_json(path: str | os.PathLike, data: Any, indent: int = 2) -> None:
    """Write ``data`` as indented JSON, atomically; a NaN or infinite number is written as null
    (strict JSON, RFC 8259: Python's ``NaN`` token breaks jq, browsers' ``JSON.parse`` and GDAL)."""
    with atomic_path(path) as tmp:
        tmp.write_text(json.dumps(finite(data), indent=indent, allow_nan=False) + "\n")


def finite(obj: Any) -> Any:
    """``obj`` with NumPy values as Python ones and NaN / infinite floats as None (JSON null)."""
    if isinstance(obj, dict):
        return {k: finite(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [finite(v) for v in obj]
    if isinstance(obj, float):
        return obj if math.isfinite(obj) else None
    if isinstance(obj, (str, int, bool)) or obj is None:
        return obj
    return finite(_json_default(obj))


def write_text(path: str | os.PathLike, text: str) -> None:
    """Write text atomically."""
    with atomic_path(path) as tmp:
        tmp.write_text(text)


def _json_default(obj: Any) -> Any:
    import numpy as np

    if isinstance(obj, np.generic):
        return obj.item()
    if isinstance(obj, np.ndarray):
        return obj.tolist()
    if isinstance(obj, Path):
        return str(obj)
    raise TypeError(f"not JSON serialisable: {type(obj).__name__}")
