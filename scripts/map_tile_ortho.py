"""Rule map_tile_ortho: one orthophoto tile as a COG, mosaicked from the overlapping sources."""

from georeg.io.scripting import run
from georeg.map.grid import make_ortho_tile


def main(smk):
    make_ortho_tile(smk.input.grid, smk.wildcards.tile, smk.output[0], smk.params.resampling)


run(snakemake, main)  # noqa: F821
