# Video trajectory geo-referencing (issue 10): a frame set with a `video` (or `trajectory: true`
# on an ordered image list) -> keyframes -> pycolmap SfM -> anchor keyframes registered by the
# single-frame method -> Sim(3) by structure projection -> ICP -> every frame located.
# Same outputs as rule localize_frames (poses.json, one entry per frame) plus the trajectory as
# CSV / GeoJSON / KML, the geo-registered 3-D feature map (LAZ + descriptors) and trajectory.json.


rule trajectory:
    input:
        video=lambda wc: frame_set_media(wc.vset),
        index=f"{INDEX_DIR}/meta.json",
        ortho="results/map/mosaic/ortho.vrt",
        dsm=frame_dsm,
        laz=lambda wc: frame_laz_inputs(),
        truth=lambda wc: frame_set_truth(wc.vset),
        feature_maps=lambda wc: frame_set_feature_maps(wc.vset),
    output:
        poses="results/frames/{vset}/poses.json",
        info="results/frames/{vset}/trajectory.json",
        csv="results/frames/{vset}/trajectory.csv",
        geojson="results/frames/{vset}/trajectory.geojson",
        kml="results/frames/{vset}/trajectory.kml",
        laz="results/frames/{vset}/sfm_points.laz",
        descriptors="results/frames/{vset}/sfm_points_descriptors.npy",
        overlays=directory("results/frames/{vset}/overlays"),
    params:
        frames=lambda wc: config["frames"][wc.vset],
        frame_loc=FRAME_LOC,
        trajectory={k: v for k, v in config["trajectory"].items() if k != "demo_video"},
        ground_z=config["map"].get("ground_z", 0.0),
    wildcard_constraints:
        vset="|".join(re.escape(s) for s in VIDEO_SETS) or "(?!)",
    log:
        "logs/frames/{vset}.log",
    benchmark:
        "benchmarks/trajectory/trajectory/{vset}.tsv"
    threads: 1
    resources:
        mem_mb=4000,
    script:
        "../../scripts/trajectory_georeference.py"


TARGETS.append(expand("results/frames/{vset}/poses.json", vset=VIDEO_SETS))


# Unordered photo collections (issue 33): a frame set with `collection: true` -> SfM of all photos
# (exhaustive pairs) -> the photos registered alone anchor a Sim(3) -> ICP -> every photo in the
# model posed by it, the others by the single-frame method (georeg.trajectory.collection).
# Same outputs as rule localize_frames, plus the geo-registered SfM points and collection.json.
COLLECTION = dict(config.get("collection") or {})


rule collection:
    input:
        images=lambda wc: frame_images(config["frames"][wc.cset].get("images")),
        index=f"{INDEX_DIR}/meta.json",
        ortho="results/map/mosaic/ortho.vrt",
        dsm=frame_dsm,
        laz=lambda wc: frame_laz_inputs(),
        truth=lambda wc: frame_set_truth(wc.cset),
        feature_maps=lambda wc: frame_set_feature_maps(wc.cset),
    output:
        poses="results/frames/{cset}/poses.json",
        info="results/frames/{cset}/collection.json",
        geojson="results/frames/{cset}/cameras.geojson",
        kml="results/frames/{cset}/cameras.kml",
        laz="results/frames/{cset}/sfm_points.laz",
        descriptors="results/frames/{cset}/sfm_points_descriptors.npy",
    params:
        frames=lambda wc: config["frames"][wc.cset],
        frame_loc=FRAME_LOC,
        collection=COLLECTION,
        ground_z=config["map"].get("ground_z", 0.0),
    wildcard_constraints:
        cset="|".join(re.escape(s) for s in COLLECTION_SETS) or "(?!)",
    log:
        "logs/frames/{cset}.log",
    benchmark:
        "benchmarks/trajectory/collection/{cset}.tsv"
    threads: 1
    resources:
        mem_mb=4000,
    script:
        "../../scripts/collection_georeference.py"


TARGETS.append(expand("results/frames/{cset}/poses.json", cset=COLLECTION_SETS))
