"""Rule collection: geo-reference an unordered photo collection (georeg.trajectory.collection)."""

from pathlib import Path

from georeg.frames.localize import MapSources, set_prior
from georeg.io.scripting import run
from georeg.trajectory.collection import georeference_collection


def main(smk):
    fl = dict(smk.params.frame_loc)
    fs = dict(smk.params.frames)
    maps = MapSources(Path(smk.input.index).parent, smk.input.ortho,
                      smk.input.dsm[0] if smk.input.dsm else None, list(smk.input.laz),
                      dense_coarse=bool(fl.get("dense_coarse", True)),
                      ground_z=float(smk.params.ground_z))  # fmt: skip
    if smk.input.feature_maps:  # earlier sets' feature maps: the single photos try them first
        from georeg.frames.feature_map import load_feature_maps

        maps.feature_map = load_feature_maps(list(smk.input.feature_maps), maps.crs_wkt, maps.bounds(),
                                             fl.get("feature_map"))  # fmt: skip
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
