"""Rule export_frames: ODM and COLMAP exports of one registered frame set."""

from pathlib import Path

import rasterio

from georeg.export.frame_set import export_frame_set
from georeg.io.scripting import run


def main(smk):
    with rasterio.open(smk.input.ortho) as ds:
        crs_wkt = ds.crs.to_wkt()
    export_frame_set(
        smk.input.poses,
        Path(smk.output.info).parent,
        crs_wkt,
        ortho=smk.input.ortho,
        dsm=smk.input.dsm[0] if smk.input.dsm else None,
        sfm_laz=smk.input.sfm[0] if smk.input.sfm else None,
        ground_z=float(smk.params.ground_z),
        conf={k: v for k, v in dict(smk.params.export).items() if k != "enabled"},
    )


run(snakemake, main)  # noqa: F821
