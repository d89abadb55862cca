"""Rule localize_frames: geo-localise every frame of one set against the map."""

from pathlib import Path

from georeg.frames.localize import localize_set
from georeg.io.scripting import run


def main(smk):
    fs = dict(smk.params.frames)
    localize_set(
        list(smk.input.images),
        fs.get("camera"),
        Path(smk.input.index).parent,
        smk.input.ortho,
        smk.input.dsm[0] if smk.input.dsm else None,
        list(smk.input.laz),
        dict(smk.params.frame_loc),
        Path(smk.output.poses).parent,
        smk.input.truth[0] if smk.input.truth else None,
        ground_z=float(smk.params.ground_z),
        feature_maps=list(smk.input.feature_maps),
        prior=fs.get("prior"),
        set_name=smk.wildcards.fset,
    )


run(snakemake, main)  # noqa: F821
