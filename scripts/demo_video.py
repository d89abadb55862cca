"""Rule demo_video: render the demo drone video (MP4) and its per-frame truth poses."""

from pathlib import Path

from georeg.demo.video import generate_video
from georeg.io.errors import ConfigError
from georeg.io.scripting import run


def main(smk):
    conf = dict(smk.params.demo_video or {})
    seed = int(conf.pop("seed", 10))
    video, truth = Path(smk.output.video), Path(smk.output.truth)
    if video.parent != truth.parent:
        raise ConfigError(f"demo_video: {video} and {truth} must be in one directory")
    generate_video(smk.input.scene, video.parent, conf, seed, video.name, truth.name)


run(snakemake, main)  # noqa: F821
