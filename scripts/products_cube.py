"""Rule products_cube: the query cube resampled onto a north-up map-CRS grid (COG + ENVI)."""

from georeg.io.scripting import run
from georeg.products.make import make_cube


def main(smk):
    make_cube(smk.input.registration, smk.input.geolocation, smk.input.image[0], smk.output[0],
              dict(smk.params.products), smk.input.ortho, smk.wildcards.name, smk.threads)  # fmt: skip


run(snakemake, main)  # noqa: F821
