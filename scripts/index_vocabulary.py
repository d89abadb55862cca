"""Rule vocabulary: k-means visual words over a seeded sample of all tiles' descriptors."""

from pathlib import Path

from georeg.scripting import run
from georeg.vocabulary import build_vocabulary


def main(smk):
    out_dir = Path(smk.output.centroids).parent
    build_vocabulary(
        smk.input.features, out_dir, smk.params.vocabulary, smk.params.seed, smk.threads
    )


run(snakemake, main)  # noqa: F821
