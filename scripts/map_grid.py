"""Rule map_grid (checkpoint): the tile grid over the union of the orthophotos."""

from georeg.io.scripting import run
from georeg.map.grid import write_grid


def main(smk):
    p = smk.params
    write_grid(smk.output[0], list(smk.input.ortho), p.tile_size_px, p.tile_overlap_px, p.crs)


run(snakemake, main)  # noqa: F821
