"""Rule map_mosaic: a hand-written GDAL VRT of one layer over all tiles (tile cores)."""

from georeg.io.scripting import run
from georeg.map.grid import write_mosaic


def main(smk):
    write_mosaic(smk.input.grid, smk.wildcards.layer, list(smk.input.tiles), smk.output[0])


run(snakemake, main)  # noqa: F821
