"""Rule evaluate_query: evaluation.json of one query (error vs truth, outcome, parts)."""

from georeg.io.scripting import run
from georeg.report.evaluation import run_evaluate_query


def main(smk):
    run_evaluate_query(
        smk.input.registration,
        smk.input.geolocation,
        smk.input.truth[0] if smk.input.truth else None,
        smk.input.grid,
        dict(smk.params.bound),
        smk.output[0],
        labels=smk.input.labels[0] if smk.input.labels else None,
        products=smk.input.products[0] if smk.input.products else None,
    )


run(snakemake, main)  # noqa: F821
