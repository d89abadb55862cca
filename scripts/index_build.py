"""Rule build_index: concatenate tile features and their words, write the inverted files."""

from pathlib import Path

from georeg.index.map_index import build_from_grid
from georeg.io.scripting import run


def main(smk):
    out_dir = Path(smk.output.meta).parent
    i = smk.input
    build_from_grid(
        i.grid, i.features, i.centroids, out_dir, word_files=i.words, quantizer_file=i.quantizer
    )


run(snakemake, main)  # noqa: F821
