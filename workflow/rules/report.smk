# Evaluation and the report (issue 7): per-query evaluation.json against the truth, per-query
# figures, the self-contained results/report/index.html (queries, and the frame sets' poses.json
# with their overlays when `frames` has sets), and Snakemake's own report
# (`snakemake --report report.html`, captions in workflow/report/). Params hold only the
# `report:` keys each rule uses: changing them never reruns a registration.

REP = config["report"]
REP_GRID = "results/map/grid.json"
REP_PARTS = list(range(int(config["register"]["parts"])))
REP_BENCH = "results/benchmark/summary.csv"


rule evaluate_query:
    input:
        registration="results/queries/{name}/registration.json",
        geolocation="results/queries/{name}/geolocation.tif",
        grid=REP_GRID,
        truth=rep_optional("truth"),
        labels=rep_optional("labels"),
        products=rep_products,
    output:
        "results/queries/{name}/evaluation.json",
    params:
        bound={k: REP[k] for k in ("success_error_px", "success_stat", "min_inside_fraction")},
    log:
        "logs/report/evaluate_query/{name}.log",
    benchmark:
        "benchmarks/report/evaluate_query/{name}.tsv"
    priority: 20
    threads: 1
    resources:
        mem_mb=1500,
    script:
        "../../scripts/report_evaluate_query.py"


rule report_figures:
    input:
        registration="results/queries/{name}/registration.json",
        evaluation="results/queries/{name}/evaluation.json",
        geolocation="results/queries/{name}/geolocation.tif",
        band="results/queries/{name}/band.tif",
        parts=expand("results/queries/{{name}}/parts/part_{part}.json", part=REP_PARTS),
        grid=REP_GRID,
        ortho="results/map/mosaic/ortho.vrt",
        ndsm="results/map/mosaic/ndsm.vrt",
        truth=rep_optional("truth"),
        labels=rep_optional("labels"),
        products=rep_products,
    output:
        report(
            directory("results/report/figures/{name}"),
            patterns=["{figure}.png"],
            caption="../report/query_figures.rst",
            category="queries",
            subcategory="{name}",
            labels={"query": "{name}", "figure": "{figure}"},
        ),
    params:
        figures={
            k: REP[k] for k in ("figure_dpi", "checker_squares", "max_inlier_lines")
        },
    log:
        "logs/report/report_figures/{name}.log",
    benchmark:
        "benchmarks/report/report_figures/{name}.tsv"
    priority: 20
    threads: 1
    resources:
        mem_mb=2000,
    script:
        "../../scripts/report_figures.py"


# The map view (issue 30): results/report/map.html + its folder results/report/map/ (Leaflet
# bundled from georeg/report/static, the decimated orthophoto, each registered query's band in
# the map frame), linked from index.html; opens from the file system, loads nothing remote.
rule report_map:
    input:
        grid=REP_GRID,
        ortho="results/map/mosaic/ortho.vrt",
        registration=expand("results/queries/{name}/registration.json", name=QUERIES),
        evaluation=expand("results/queries/{name}/evaluation.json", name=QUERIES),
        band=expand("results/queries/{name}/band.tif", name=QUERIES),
        geolocation=expand("results/queries/{name}/geolocation.tif", name=QUERIES),
        truth=[t for q in QUERIES if (t := (config["queries"][q] or {}).get("truth"))],
        frames=expand("results/frames/{fset}/poses.json", fset=FRAME_SETS),
        trajectories=expand("results/frames/{fset}/trajectory.json", fset=VIDEO_SETS),
    output:
        html="results/report/map.html",
        folder=directory("results/report/map"),
    params:
        queries=QUERIES,
        query_truth=[(config["queries"][q] or {}).get("truth") for q in QUERIES],
        frame_sets=FRAME_SETS,
        video_sets=VIDEO_SETS,
        frame_truth=[(config["frames"][s] or {}).get("truth") for s in FRAME_SETS],
        sizes={k: REP[k] for k in ("map_max_px", "map_query_px")},
    log:
        "logs/report/report_map.log",
    threads: 1
    resources:
        mem_mb=1500,
    script:
        "../../scripts/report_map.py"


rule report_html:
    input:
        map_view="results/report/map.html",
        registration=expand("results/queries/{name}/registration.json", name=QUERIES),
        evaluation=expand("results/queries/{name}/evaluation.json", name=QUERIES),
        figures=expand("results/report/figures/{name}", name=QUERIES),
        overview="results/map/overview.png",
        benchmark=rep_benchmark,
        frames=expand("results/frames/{fset}/poses.json", fset=FRAME_SETS),
    output:
        html=report(
            "results/report/index.html",
            caption="../report/index_html.rst",
            category="report",
            labels={"file": "index.html"},
        ),
        summary=report(
            "results/report/summary.csv",
            caption="../report/summary.rst",
            category="report",
            labels={"file": "summary.csv"},
        ),
    params:
        queries=QUERIES,
        frame_sets=FRAME_SETS,
        frame_truth=[(config["frames"][s] or {}).get("truth") for s in FRAME_SETS],
        config=config,
        logs=["logs", "benchmarks"],
    log:
        "logs/report/report_html.log",
    benchmark:
        "benchmarks/report/report_html.tsv"
    threads: 1
    resources:
        mem_mb=1500,
    script:
        "../../scripts/report_html.py"


TARGETS.append("results/report/index.html")
