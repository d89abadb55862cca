"""Shared helpers: config loading (user map/queries replace the demo's), validation, targets."""

import copy
import re
from pathlib import Path

from snakemake.utils import validate


def _replace_user_sections(config):
    """A user's --configfile/--config `map`, `queries`, `frames` replace the defaults wholesale.

    Snakemake deep-merges command-line config into the Snakefile's `configfile:` default, so a
    user's file would otherwise inherit the demo's LiDAR list and the demo queries.
    """
    user = workflow.config_settings.overwrite_config or {}
    for key in ("map", "queries", "frames"):
        if key in user:
            config[key] = copy.deepcopy(user[key])


_replace_user_sections(config)
validate(config, schema="../schemas/config.schema.yaml")

QUERIES = sorted(config["queries"])


wildcard_constraints:
    name="|".join(re.escape(q) for q in QUERIES) or "(?!)",
TARGETS = []  # each stage file appends its final outputs (paths or input functions)


def all_inputs(wildcards):
    """Everything `rule all` asks for: the union of what each stage registered."""
    out = []
    for t in TARGETS:
        t = t(wildcards) if callable(t) else t
        out.extend([t] if isinstance(t, str) else t)
    return out


def orthophoto_paths():
    ortho = config["map"]["orthophoto"]
    return [ortho] if isinstance(ortho, str) else list(ortho)


def lidar_paths():
    return list(config["map"].get("lidar") or [])
