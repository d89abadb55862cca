"""Rule tile_features: SIFT features of one map tile with map x, y and DSM/nDSM z."""

import cv2

from georeg.index.features import extract_tile_from_grid
from georeg.io.scripting import run


def main(smk):
    cv2.setNumThreads(smk.threads)
    i = smk.input
    extract_tile_from_grid(
        i.grid, smk.wildcards.tile, i.ortho, i.dsm, i.ndsm, smk.params.features, smk.output[0]
    )


run(snakemake, main)  # noqa: F821
