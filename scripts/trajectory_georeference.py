"""Rule trajectory: geo-reference every frame of one video (or ordered image list)."""

from pathlib import Path

from georeg.frames.localize import MapSources
from georeg.io.scripting import run
from georeg.trajectory.pipeline import georeference_video


def main(smk):
    fl = dict(smk.params.frame_loc)
    maps = MapSources(Path(smk.input.index).parent, smk.input.ortho,
                      smk.input.dsm[0] if smk.input.dsm else None, list(smk.input.laz),
                      dense_coarse=bool(fl.get("dense_coarse", True)),
                      ground_z=float(smk.params.ground_z))  # fmt: skip
    if smk.input.feature_maps:  # earlier sets' feature maps: the anchors try them first
        from georeg.frames.feature_map import load_feature_maps

        maps.feature_map = load_feature_maps(list(smk.input.feature_maps), maps.crs_wkt, maps.bounds(),
                                             fl.get("feature_map"))  # fmt: skip
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
