"""Rule refine_registration: sub-pixel local refinement; write registration.json + geolocation.tif."""

from georeg.io.scripting import run
from georeg.register.refine import run_refine


def main(smk):
    run_refine(
        smk.input.band,
        smk.input.registration,
        smk.input.geolocation,
        smk.input.ortho,
        smk.input.dsm,
        smk.input.truth[0] if smk.input.truth else None,
        dict(smk.params.refine),
        smk.output.registration,
        smk.output.geolocation,
    )


run(snakemake, main)  # noqa: F821
