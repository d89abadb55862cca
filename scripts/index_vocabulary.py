"""Rule vocabulary: k-means visual words over a seeded sample of all tiles' descriptors."""

from pathlib import Path

from georeg.index.vocabulary import build_vocabulary
from georeg.io.scripting import run


def main(smk):
    out_dir = Path(smk.output.centroids).parent
    build_vocabulary(
        smk.input.features, out_dir, smk.params.vocabulary, smk.params.seed, smk.threads
    )


run(snakemake, main)  # noqa: F821
