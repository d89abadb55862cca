"""Rule search_part: search the map for one along-track part of the query."""

from georeg.io.scripting import run
from georeg.register.search import run_search_part


def main(smk):
    run_search_part(
        smk.input.band,
        smk.input.meta,
        smk.input.index,
        smk.input.grid,
        int(smk.wildcards.part),
        dict(smk.params.register),
        int(smk.params.seed),
        smk.output[0],
        smk.input.ortho,
    )


run(snakemake, main)  # noqa: F821
