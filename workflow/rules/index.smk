# Feature index (issue 4): SIFT features per map tile -> k-means visual words -> nearest word of
# every feature, per tile (parallel over tiles) -> the map index (a merge).
# Params hold only the `features:` / `vocabulary:` sections, so changing the matching settings
# (`register:`) reruns nothing here, while changing detector settings re-extracts every tile.

INDEX_DIR = "results/index/map"
# keep in sync with georeg.index.map_index.INDEX_ARRAYS (tests/test_index.py checks it)
INDEX_ARRAYS = [
    "xy", "z", "ndsm", "scale", "angle", "response", "desc", "tile", "word",
    "tile_offsets", "tile_bounds", "centroids", "ivf_offsets", "ivf_ids", "df", "idf",
    "wt_offsets", "wt_tile", "wt_count", "tile_norm",
]


rule tile_features:
    input:
        grid="results/map/grid.json",
        ortho="results/map/tiles/{tile}/ortho.tif",
        dsm="results/map/tiles/{tile}/dsm.tif",
        ndsm="results/map/tiles/{tile}/ndsm.tif",
    output:
        directory("results/index/features/{tile}"),
    params:
        features=config["features"],
    wildcard_constraints:
        tile=r"r\d+_c\d+",
    log:
        "logs/index/tile_features/{tile}.log",
    benchmark:
        "benchmarks/index/tile_features/{tile}.tsv"
    priority: 10
    threads: 1
    resources:
        mem_mb=2000,
    script:
        "../../scripts/index_tile_features.py"


rule vocabulary:
    input:
        features=index_feature_dirs,
    output:
        centroids="results/index/vocabulary/centroids.npy",
        meta="results/index/vocabulary/meta.json",
    params:
        vocabulary=config["vocabulary"],
        seed=index_vocabulary_seed(),
    log:
        "logs/index/vocabulary.log",
    benchmark:
        "benchmarks/index/vocabulary.tsv"
    priority: 10
    threads: index_vocabulary_threads
    resources:
        mem_mb=4000,
    script:
        "../../scripts/index_vocabulary.py"


rule word_quantizer:
    input:
        centroids="results/index/vocabulary/centroids.npy",
    output:
        "results/index/vocabulary/quantizer.faiss",
    params:
        ef_search=config["vocabulary"].get("ef_search", 64),
    log:
        "logs/index/word_quantizer.log",
    benchmark:
        "benchmarks/index/word_quantizer.tsv"
    priority: 10
    threads: 1
    resources:
        mem_mb=2000,
    script:
        "../../scripts/index_word_quantizer.py"


rule tile_words:
    input:
        features="results/index/features/{tile}",
        centroids="results/index/vocabulary/centroids.npy",
        quantizer="results/index/vocabulary/quantizer.faiss",
    output:
        "results/index/words/{tile}.npy",
    wildcard_constraints:
        tile=r"r\d+_c\d+",
    log:
        "logs/index/tile_words/{tile}.log",
    benchmark:
        "benchmarks/index/tile_words/{tile}.tsv"
    priority: 10
    threads: 1
    resources:
        mem_mb=1000,
    script:
        "../../scripts/index_tile_words.py"


rule build_index:
    input:
        grid="results/map/grid.json",
        centroids="results/index/vocabulary/centroids.npy",
        features=index_feature_dirs,
        words=index_word_files,
        quantizer="results/index/vocabulary/quantizer.faiss",
    output:
        meta=f"{INDEX_DIR}/meta.json",
        arrays=expand(f"{INDEX_DIR}/{{name}}.npy", name=INDEX_ARRAYS),
        quantizer=f"{INDEX_DIR}/quantizer.faiss",
    log:
        "logs/index/build_index.log",
    benchmark:
        "benchmarks/index/build_index.tsv"
    priority: 10
    threads: 1
    resources:
        mem_mb=4000,
    script:
        "../../scripts/index_build.py"


TARGETS.append(f"{INDEX_DIR}/meta.json")
