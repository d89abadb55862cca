"""Rule tile_words: the nearest visual word of every feature of one map tile."""

import faiss

from georeg.index.map_index import assign_tile_words
from georeg.io.scripting import run


def main(smk):
    faiss.omp_set_num_threads(smk.threads)
    i = smk.input
    assign_tile_words(i.features, i.centroids, smk.output[0], quantizer_path=i.quantizer)


run(snakemake, main)  # noqa: F821
