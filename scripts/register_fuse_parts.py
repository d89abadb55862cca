"""Rule fuse_parts: fuse the parts into one registration; write geolocation.tif."""

from georeg.io.scripting import run
from georeg.register.fuse import run_fuse_parts


def main(smk):
    run_fuse_parts(
        smk.input.band,
        smk.input.meta,
        list(smk.input.parts),
        smk.input.index,
        smk.input.grid,
        smk.input.dsm,
        smk.input.truth[0] if smk.input.truth else None,
        dict(smk.params.register),
        int(smk.params.seed),
        smk.output.registration,
        smk.output.geolocation,
        smk.input.ortho,
        smk.params.cache_dir,
        bool(smk.params.elevation),
    )


run(snakemake, main)  # noqa: F821
