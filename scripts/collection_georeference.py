"""Rule collection: geo-reference an unordered photo collection (georeg.trajectory.collection)."""

from pathlib import Path

from georeg.frames.localize import open_map_sources, set_prior
from georeg.io.scripting import run
from georeg.trajectory.collection import georeference_collection


def main(smk):
    fl = dict(smk.params.frame_loc)
    fs = dict(smk.params.frames)
    maps = open_map_sources(Path(smk.input.index).parent, smk.input.ortho,
                            smk.input.dsm[0] if smk.input.dsm else None, list(smk.input.laz), fl,
                            float(smk.params.ground_z), list(smk.input.feature_maps))  # fmt: skip
    set_prior(maps, fs.get("prior"), smk.wildcards.cset)
    georeference_collection(
        fs,
        maps,
        fl,
        dict(smk.params.collection),
        Path(smk.output.poses).parent,
        None,
        smk.input.truth[0] if smk.input.truth else None,
    )


run(snakemake, main)  # noqa: F821
