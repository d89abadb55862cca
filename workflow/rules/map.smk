# Map preparation (issue 3): orthophotos + LiDAR (or a DEM) -> a tiled, aligned, elevation-aware map.
# `map_grid` is a checkpoint: the tile list is known only once the orthophotos have been read.
# Each rule gets only the params it uses, so a changed LiDAR setting reruns the elevation tiles,
# their mosaics and the overview, never the orthophoto tiles (see docs/ARCHITECTURE.md "map").

MAP_ELEV_LAYERS = ["dsm", "dtm", "ndsm", "density"]
MAP_MOSAIC_LAYERS = ["ortho"] + MAP_ELEV_LAYERS

# Headers in, a JSON or a VRT out (a second each, even for a county): on a cluster they run in the
# submitting snakemake, not through the queue (each queued job costs ~10 s of start-up and polls)
localrules:
    map_grid,
    map_mosaic,


checkpoint map_grid:
    input:
        ortho=orthophoto_paths(),
    output:
        "results/map/grid.json",
    params:
        tile_size_px=config["map_prep"]["tile_size_px"],
        tile_overlap_px=config["map_prep"]["tile_overlap_px"],
        crs=config["map"].get("crs"),
    log:
        "logs/map/map_grid.log",
    benchmark:
        "benchmarks/map/map_grid.tsv"
    threads: 1
    resources:
        mem_mb=1000,
    script:
        "../../scripts/map_grid.py"


rule map_tile_ortho:
    input:
        grid="results/map/grid.json",
        ortho=orthophoto_paths(),
    output:
        "results/map/tiles/{tile}/ortho.tif",
    params:
        resampling=config["map_prep"]["ortho_resampling"],
    wildcard_constraints:
        tile=r"r\d+_c\d+",
    log:
        "logs/map/map_tile_ortho/{tile}.log",
    benchmark:
        "benchmarks/map/map_tile_ortho/{tile}.tsv"
    priority: 10
    threads: 1
    resources:
        mem_mb=1000,
    script:
        "../../scripts/map_tile_ortho.py"


rule map_tile_elevation:
    input:
        ortho="results/map/tiles/{tile}/ortho.tif",
        source=map_elevation_inputs,
    output:
        dsm="results/map/tiles/{tile}/dsm.tif",
        dtm="results/map/tiles/{tile}/dtm.tif",
        ndsm="results/map/tiles/{tile}/ndsm.tif",
        density="results/map/tiles/{tile}/density.tif",
        points="results/map/tiles/{tile}/points.laz",
    params:
        source=map_elevation_source(),
        settings=map_elevation_params(),
        # memory only, deliberately not a rerun trigger: read from config in the script
    wildcard_constraints:
        tile=r"r\d+_c\d+",
    log:
        "logs/map/map_tile_elevation/{tile}.log",
    benchmark:
        "benchmarks/map/map_tile_elevation/{tile}.tsv"
    priority: 10
    threads: 1
    resources:
        mem_mb=3000,
    script:
        "../../scripts/map_tile_elevation.py"


rule map_mosaic:
    input:
        grid="results/map/grid.json",
        tiles=map_layer_tiles,
    output:
        "results/map/mosaic/{layer}.vrt",
    wildcard_constraints:
        layer="|".join(MAP_MOSAIC_LAYERS),
    log:
        "logs/map/map_mosaic/{layer}.log",
    benchmark:
        "benchmarks/map/map_mosaic/{layer}.tsv"
    priority: 20  # cheap, and the products need the mosaics
    threads: 1
    script:
        "../../scripts/map_mosaic.py"


rule map_overview:
    input:
        grid="results/map/grid.json",
        ortho="results/map/mosaic/ortho.vrt",
        dsm="results/map/mosaic/dsm.vrt",
    output:
        report("results/map/overview.png", caption="../report/overview.rst", category="map"),
    log:
        "logs/map/map_overview.log",
    benchmark:
        "benchmarks/map/map_overview.tsv"
    threads: 1
    resources:
        mem_mb=1500,
    script:
        "../../scripts/map_overview.py"


TARGETS.append(map_targets)
