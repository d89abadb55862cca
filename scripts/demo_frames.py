"""Rule demo_frames: render the demo drone frames and their truth poses."""

from pathlib import Path

from georeg.demo.frames import generate_frames
from georeg.io.scripting import run


def main(smk):
    conf = dict(smk.params.demo_frames)
    generate_frames(
        smk.input.scene, Path(smk.output.truth).parent, conf.get("views"), int(conf.get("seed", 9))
    )


run(snakemake, main)  # noqa: F821
