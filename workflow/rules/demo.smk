# Demo stage: the deterministic synthetic scene every other stage is tested on (no download).
# georeg/demo/ writes everything under results/demo/; see docs/DEMO_SCENE.md.

DEMO = "results/demo"


rule demo_scene:
    output:
        orthophoto=f"{DEMO}/orthophoto.tif",
        lidar=expand(f"{DEMO}/lidar/tile_{{i}}.laz", i=range(config["demo"]["lidar_tiles"])),
        dsm=f"{DEMO}/truth/dsm.tif",
        dtm=f"{DEMO}/truth/dtm.tif",
        ndsm=f"{DEMO}/truth/ndsm.tif",
        labels=f"{DEMO}/truth/labels.tif",
        classes=f"{DEMO}/truth/classes.json",
        outliers=f"{DEMO}/truth/outliers.npy",
        demo_hdr=f"{DEMO}/queries/demo.hdr",
        demo_bil=f"{DEMO}/queries/demo.bil",
        demo_truth=f"{DEMO}/queries/demo_truth.tif",
        demo_labels=f"{DEMO}/queries/demo_labels.tif",
        demo_ndsm=f"{DEMO}/queries/demo_ndsm.tif",
        outside_hdr=f"{DEMO}/queries/outside.hdr",
        outside_bil=f"{DEMO}/queries/outside.bil",
        outside_truth=f"{DEMO}/queries/outside_truth.tif",
        outside_labels=f"{DEMO}/queries/outside_labels.tif",
        outside_ndsm=f"{DEMO}/queries/outside_ndsm.tif",
        scene=f"{DEMO}/scene.json",
    params:
        conf=config["demo"],
    log:
        "logs/demo/demo_scene.log",
    benchmark:
        "benchmarks/demo/demo_scene.tsv"
    threads: 1
    script:
        "../../scripts/demo_scene.py"
