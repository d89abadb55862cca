"""Rule word_quantizer: the vocabulary's nearest-word structure (flat or HNSW), built once."""

from georeg.index.map_index import save_word_quantizer
from georeg.io.scripting import run


def main(smk):
    save_word_quantizer(smk.input.centroids, smk.output[0], ef_search=int(smk.params.ef_search))


run(snakemake, main)  # noqa: F821
