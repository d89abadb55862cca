"""Rule map_mosaic: a hand-written GDAL VRT of one layer over all tiles (tile cores)."""

from georeg.mapgrid import write_mosaic
from georeg.scripting import run


def main(smk):
    write_mosaic(smk.input.grid, smk.wildcards.layer, list(smk.input.tiles), smk.output[0])


run(snakemake, main)  # noqa: F821
