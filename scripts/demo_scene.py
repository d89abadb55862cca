"""Snakemake script for rule demo_scene: generate the synthetic demo scene into results/demo/."""

from pathlib import Path

from georeg.demo import generate_scene
from georeg.io.scripting import run

run(snakemake, lambda sm: generate_scene(sm.params.conf, Path(sm.output.orthophoto).parent))  # noqa: F821
