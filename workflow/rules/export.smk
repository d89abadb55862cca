# Exports (issue 33): every frame set -> ODM gcp_list.txt and geo.txt, a COLMAP text model (local
# metric frame, georef.json beside it); every registered SWIR query -> its tie points as a
# GeoPackage table beside the footprint GeoJSON / KML. Params: the `export` keys only.

EXPORT = dict(config.get("export") or {})


rule export_frames:
    input:
        poses="results/frames/{eset}/poses.json",
        ortho="results/map/mosaic/ortho.vrt",
        dsm=frame_dsm,
        sfm=lambda wc: [f"results/frames/{wc.eset}/sfm_points.laz"] if wc.eset in SFM_SETS else [],
    output:
        gcp="results/frames/{eset}/export/gcp_list.txt",
        geo="results/frames/{eset}/export/geo.txt",
        cameras="results/frames/{eset}/export/colmap/cameras.txt",
        images="results/frames/{eset}/export/colmap/images.txt",
        points="results/frames/{eset}/export/colmap/points3D.txt",
        georef="results/frames/{eset}/export/colmap/georef.json",
        info="results/frames/{eset}/export/export.json",
    params:
        export=EXPORT,
        ground_z=config["map"].get("ground_z", 0.0),
    wildcard_constraints:
        eset="|".join(re.escape(s) for s in FRAME_SETS) or "(?!)",
    log:
        "logs/export/frames_{eset}.log",
    threads: 1
    resources:
        mem_mb=2000,
    script:
        "../../scripts/export_frames.py"


if EXPORT.get("enabled", True):
    TARGETS.append(expand("results/frames/{eset}/export/export.json", eset=FRAME_SETS))


rule export_tie_points:
    input:
        registration="results/queries/{name}/registration.json",
        geolocation="results/queries/{name}/geolocation.tif",
    output:
        "results/products/{name}/tie_points.gpkg",
    log:
        "logs/export/tie_points_{name}.log",
    threads: 1
    resources:
        mem_mb=1000,
    script:
        "../../scripts/export_tie_points.py"


if EXPORT.get("enabled", True):
    TARGETS.append(expand("results/products/{name}/tie_points.gpkg", name=QUERIES))
