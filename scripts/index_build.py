"""Rule build_index: concatenate tile features, assign visual words, write the inverted files."""

from pathlib import Path

from georeg.index import build_from_grid
from georeg.scripting import run


def main(smk):
    out_dir = Path(smk.output.meta).parent
    build_from_grid(smk.input.grid, smk.input.features, smk.input.centroids, out_dir)


run(snakemake, main)  # noqa: F821
