"""The glue every ``scripts/*.py`` uses: logging to the rule's log, one-line errors, exit codes."""

from __future__ import annotations

import logging
import sys
import time
from collections.abc import Callable
from typing import Any

from georeg.io.errors import GeoregError

log = logging.getLogger("georeg")


def setup_logging(log_path: str | None = None, level: int = logging.INFO) -> None:
    """Log to stderr and, when given, to the rule's log file."""
    handlers: list[logging.Handler] = [logging.StreamHandler(sys.stderr)]
    if log_path:
        handlers.append(logging.FileHandler(log_path, mode="w"))
    logging.basicConfig(
        level=level,
        format="%(asctime)s %(levelname)s %(name)s: %(message)s",
        handlers=handlers,
        force=True,
    )


def run(snakemake: Any, main: Callable[[Any], object]) -> None:
    """Run ``main(snakemake)`` with logging set up; report a GeoregError as one line and exit 1."""
    log_path = None
    try:
        log_path = str(snakemake.log[0]) if len(snakemake.log) else None
    except (AttributeError, IndexError, TypeError):
        log_path = None
    setup_logging(log_path)
    rule = getattr(snakemake, "rule", "georeg")
    t0 = time.perf_counter()
    try:
        main(snakemake)
    except GeoregError as exc:
        log.error("%s", exc)
        print(f"georeg error in rule {rule}: {exc}", file=sys.stderr)
        sys.exit(1)
    log.info("rule %s done in %.1f s", rule, time.perf_counter() - t0)
