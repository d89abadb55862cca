"""Rule products: elevation, fused product, segmentation, footprint, spectral point cloud."""

from georeg.io.scripting import run
from georeg.products.make import make_products


def main(smk):
    mosaics = {k: smk.input[k] for k in ("dsm", "dtm", "ndsm")}
    make_products(smk.input.registration, smk.input.geolocation, smk.input.image[0], smk.input.ortho,
                  mosaics, list(smk.input.points), smk.output[0], dict(smk.params.products),
                  smk.input.grid, smk.wildcards.name, smk.input.labels[0] if smk.input.labels else None,
                  smk.params.map_heights)  # fmt: skip


run(snakemake, main)  # noqa: F821
