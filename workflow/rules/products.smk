# Spectral-elevation products (issue 6): geo-referenced cube, per-pixel elevation, fused product,
# segmentation, footprint and the spectral point cloud of every query (docs/ARCHITECTURE.md
# "products"). Two rules so that a changed segmentation never recomputes the cube. The manifests
# (cube.json, products.json) are the only declared outputs: a not_found query gets a manifest that
# says so and no heavy file; a registered query's manifest lists every product file.

PROD_GEOLOC = "results/queries/{name}/geolocation.tif"
PROD_REG = "results/queries/{name}/registration.json"
PROD_MOSAICS = {k: f"results/map/mosaic/{k}.vrt" for k in ("dsm", "dtm", "ndsm")}
PROD_ORTHO = "results/map/mosaic/ortho.vrt"
PROD_GRID = "results/map/grid.json"
PROD_CUBE_KEYS = ("grid", "gsd_m", "resampling", "chunk_bands", "inverse_step_px", "envi_copy")
PROD_MAKE_KEYS = ("grid", "gsd_m", "chunk_bands", "inverse_step_px", "fused", "reflectance_scale", "points", "segmentation")


rule products_cube:
    input:
        registration=PROD_REG,
        geolocation=PROD_GEOLOC,
        image=prod_image_files,
        ortho=PROD_ORTHO,
    output:
        "results/products/{name}/cube.json",
    params:
        products={k: config["products"][k] for k in PROD_CUBE_KEYS},
    log:
        "logs/products/products_cube/{name}.log",
    benchmark:
        "benchmarks/products/products_cube/{name}.tsv"
    priority: 20
    threads: 1
    resources:
        mem_mb=1500,
    script:
        "../../scripts/products_cube.py"


rule products:
    input:
        registration=PROD_REG,
        geolocation=PROD_GEOLOC,
        image=prod_image_files,
        ortho=PROD_ORTHO,
        grid=PROD_GRID,
        points=prod_point_tiles,
        labels=prod_labels,
        **PROD_MOSAICS,
    output:
        "results/products/{name}/products.json",
    params:
        products={k: config["products"][k] for k in PROD_MAKE_KEYS},
        map_heights=map_elevation_source() != "none",
    log:
        "logs/products/products/{name}.log",
    benchmark:
        "benchmarks/products/products/{name}.tsv"
    priority: 20
    threads: 1
    resources:
        mem_mb=2000,
    script:
        "../../scripts/products_make.py"


TARGETS.append(expand("results/products/{name}/{manifest}.json", name=QUERIES, manifest=("cube", "products")))
