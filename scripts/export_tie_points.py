"""Rule export_tie_points: a SWIR registration's tie points as a GeoPackage table."""

from georeg.export.tie_points import export_tie_points
from georeg.io.scripting import run


def main(smk):
    export_tie_points(smk.input.registration, smk.input.geolocation, smk.output[0])


run(snakemake, main)  # noqa: F821
