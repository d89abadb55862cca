# Query registration (issue 5): query band -> one search job per along-track part -> fused
# registration + per-pixel geolocation. Params hold only what each rule uses, so changing the
# matching settings (`register:`) reruns the searches and the fusion, never the band extraction.

REG_PARTS = list(range(int(config["register"]["parts"])))
REG_SEED = config["seed"] if config["register"].get("seed") is None else config["register"]["seed"]
REG_INDEX_META = "results/index/map/meta.json"
REG_GRID = "results/map/grid.json"
REG_DSM = "results/map/mosaic/dsm.vrt"
REG_HAS_ELEVATION = bool(config["map"].get("lidar") or config["map"].get("dem"))  # else the DSM is nodata


rule query_band:
    input:
        reg_image_files,
    output:
        band="results/queries/{name}/band.tif",
        meta="results/queries/{name}/band.json",
    params:
        query=reg_query,
        percentiles=config["register"]["stretch_percentiles"],
    log:
        "logs/register/query_band/{name}.log",
    benchmark:
        "benchmarks/register/query_band/{name}.tsv"
    threads: 1
    resources:
        mem_mb=2000,
    script:
        "../../scripts/register_query_band.py"


rule search_part:
    input:
        band="results/queries/{name}/band.tif",
        meta="results/queries/{name}/band.json",
        index=REG_INDEX_META,
        grid=REG_GRID,
        ortho="results/map/mosaic/ortho.vrt",
    output:
        "results/queries/{name}/parts/part_{part}.json",
    params:
        register=config["register"],
        seed=REG_SEED,
    wildcard_constraints:
        part=r"\d+",
    log:
        "logs/register/search_part/{name}_{part}.log",
    benchmark:
        "benchmarks/register/search_part/{name}_{part}.tsv"
    priority: 20
    threads: 1
    resources:
        mem_mb=3000,
    script:
        "../../scripts/register_search_part.py"


rule fuse_parts:
    input:
        band="results/queries/{name}/band.tif",
        meta="results/queries/{name}/band.json",
        parts=expand("results/queries/{{name}}/parts/part_{part}.json", part=REG_PARTS),
        index=REG_INDEX_META,
        grid=REG_GRID,
        dsm=REG_DSM,
        ortho="results/map/mosaic/ortho.vrt",
        truth=reg_truth,
    output:
        registration="results/queries/{name}/registration_global.json",
        geolocation="results/queries/{name}/geolocation_global.tif",
    params:
        register=config["register"],
        seed=REG_SEED,
        cache_dir="results/cache/register",  # map features the sources keep between queries
        elevation=REG_HAS_ELEVATION,  # the elevation source reads the DSM
    log:
        "logs/register/fuse_parts/{name}.log",
    benchmark:
        "benchmarks/register/fuse_parts/{name}.tsv"
    priority: 20
    threads: 1
    resources:
        mem_mb=3000,
    script:
        "../../scripts/register_fuse_parts.py"


# Sub-pixel local refinement (issue 12): tie points against the orthophoto rendered through the
# global mapping, a per-line / polynomial / TPS model -> the final registration.json and
# geolocation.tif that products and the report consume. Only `refine:` keys are params, so tuning
# them never reruns the search or the fusion. Disabled: the global files are passed through.
rule refine_registration:
    input:
        band="results/queries/{name}/band.tif",
        registration="results/queries/{name}/registration_global.json",
        geolocation="results/queries/{name}/geolocation_global.tif",
        ortho="results/map/mosaic/ortho.vrt",
        dsm=REG_DSM,
        truth=reg_truth,
    output:
        registration="results/queries/{name}/registration.json",
        geolocation="results/queries/{name}/geolocation.tif",
    params:
        refine=config["refine"],
    log:
        "logs/register/refine_registration/{name}.log",
    benchmark:
        "benchmarks/register/refine_registration/{name}.tsv"
    priority: 20
    threads: 1
    resources:
        mem_mb=3000,
    script:
        "../../scripts/register_refine.py"


# geolocation.tif is always written (all NaN when the query is not found)
TARGETS.append(expand("results/queries/{name}/registration.json", name=QUERIES))
TARGETS.append(expand("results/queries/{name}/geolocation.tif", name=QUERIES))
