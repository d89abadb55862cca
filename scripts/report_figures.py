"""Rule report_figures: every figure of one query, plus figures.json (titles, captions)."""

from georeg.io.scripting import run
from georeg.report.figures import load_query_data, make_query_figures


def main(smk):
    q = load_query_data(
        smk.wildcards.name,
        smk.input.registration,
        smk.input.band,
        list(smk.input.parts),
        smk.input.ortho,
        ndsm=smk.input.ndsm,
        evaluation=smk.input.evaluation,
        truth=smk.input.truth[0] if smk.input.truth else None,
        geolocation=smk.input.geolocation,
        products=smk.input.products[0] if smk.input.products else None,
        labels=smk.input.labels[0] if smk.input.labels else None,
    )
    make_query_figures(q, smk.output[0], dict(smk.params.figures))


run(snakemake, main)  # noqa: F821
