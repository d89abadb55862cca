"""Rule grow_feature_map: the feature maps a set used plus its own points, as a new file."""

import rasterio

from georeg.frames.feature_map_grow import grow_feature_map
from georeg.io.scripting import run


def main(smk):
    with rasterio.open(smk.input.ortho) as ds:
        crs_wkt = ds.crs.to_wkt()
    grow_feature_map(
        smk.output.laz,
        crs_wkt,
        list(smk.input.used),
        own=list(smk.input.own),
        poses_json=None if smk.params.video else smk.input.poses,
        dsm=smk.input.dsm[0] if smk.input.dsm else None,
        ground_z=float(smk.params.ground_z),
        conf=dict(smk.params.conf),
    )


run(snakemake, main)  # noqa: F821
