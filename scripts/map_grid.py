"""Rule map_grid (checkpoint): the tile grid over the union of the orthophotos."""

from georeg.mapgrid import write_grid
from georeg.scripting import run


def main(smk):
    p = smk.params
    write_grid(smk.output[0], list(smk.input.ortho), p.tile_size_px, p.tile_overlap_px, p.crs)


run(snakemake, main)  # noqa: F821
