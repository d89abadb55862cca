"""Rule report_html: the self-contained results/report/index.html and summary.csv."""

from georeg.io.scripting import run
from georeg.report.html import run_report


def main(smk):
    frame_sets = {
        name: {"poses": poses, "truth": truth}
        for name, poses, truth in zip(
            smk.params.frame_sets, smk.input.frames, smk.params.frame_truth, strict=True
        )
    }
    run_report(
        list(smk.params.queries),
        list(smk.input.registration),
        list(smk.input.evaluation),
        list(smk.input.figures),
        dict(smk.params.config),
        smk.output.html,
        smk.output.summary,
        log_roots=list(smk.params.logs),
        benchmark_csv=smk.input.benchmark[0] if smk.input.benchmark else None,
        overview_png=smk.input.overview,
        frame_sets=frame_sets,
        map_html=smk.input.map_view,
    )


run(snakemake, main)  # noqa: F821
