"""Rule trajectory: geo-reference every frame of one video (or ordered image list)."""

from pathlib import Path

from georeg.frames.localize import open_map_sources
from georeg.io.scripting import run
from georeg.trajectory.pipeline import georeference_video


def main(smk):
    fl = dict(smk.params.frame_loc)
    maps = open_map_sources(Path(smk.input.index).parent, smk.input.ortho,
                            smk.input.dsm[0] if smk.input.dsm else None, list(smk.input.laz), fl,
                            float(smk.params.ground_z), list(smk.input.feature_maps))  # fmt: skip
    georeference_video(
        dict(smk.params.frames),
        maps,
        fl,
        dict(smk.params.trajectory),
        Path(smk.output.poses).parent,
        None,
        smk.input.truth[0] if smk.input.truth else None,
    )


run(snakemake, main)  # noqa: F821
