"""Rule map_overview: quicklook PNG (orthophoto + tile grid, hillshaded DSM)."""

from georeg.io.scripting import run
from georeg.map.overview import make_overview


def main(smk):
    make_overview(smk.input.grid, smk.input.ortho, smk.input.dsm, smk.output[0])


run(snakemake, main)  # noqa: F821
