"""Rule report_map: the map view results/report/map.html and its folder results/report/map/."""

from georeg.io.scripting import run
from georeg.report.map_view import run_map_view


def main(smk):
    run_map_view(
        smk.output.html,
        smk.output.folder,
        smk.input.grid,
        smk.input.ortho,
        list(smk.params.queries),
        list(smk.input.registration),
        list(smk.input.evaluation),
        list(smk.input.band),
        list(smk.input.geolocation),
        list(smk.params.query_truth),
        list(smk.params.frame_sets),
        list(smk.input.frames),
        list(smk.params.frame_truth),
        list(smk.params.video_sets),
        dict(smk.params.sizes),
    )


run(snakemake, main)  # noqa: F821
