# Frame geo-localisation (issue 9): each frame set -> coarse location by the map index ->
# render-match-PnP against the textured map -> MI + gradient refinement -> poses and overlays.
# Params: the set's own entry and `frame_loc` (without demo_frames), so editing the demo views
# reruns only the demo frames and what reads them.

from georeg.io.video import frame_images

FRAME_LOC = {k: v for k, v in (config.get("frame_loc") or {}).items() if k != "demo_frames"}


rule localize_frames:
    input:
        images=lambda wc: frame_images(config["frames"][wc.fset].get("images")),
        index=f"{INDEX_DIR}/meta.json",
        ortho="results/map/mosaic/ortho.vrt",
        dsm=frame_dsm,
        laz=lambda wc: frame_laz_inputs(),
        truth=lambda wc: frame_set_truth(wc.fset),
        feature_maps=lambda wc: frame_set_feature_maps(wc.fset),
    output:
        poses="results/frames/{fset}/poses.json",
        geojson="results/frames/{fset}/cameras.geojson",
        kml="results/frames/{fset}/cameras.kml",
        overlays=directory("results/frames/{fset}/overlays"),
    params:
        frames=lambda wc: config["frames"][wc.fset],
        frame_loc=FRAME_LOC,
        ground_z=config["map"].get("ground_z", 0.0),
    wildcard_constraints:
        fset="|".join(re.escape(s) for s in IMAGE_SETS) or "(?!)",
    log:
        "logs/frames/{fset}.log",
    benchmark:
        "benchmarks/frames/localize_frames/{fset}.tsv"
    threads: 1
    resources:
        mem_mb=3000,
    script:
        "../../scripts/frames_localize.py"


TARGETS.append(expand("results/frames/{fset}/poses.json", fset=IMAGE_SETS))


# Maps that grow (issue 33): a set with write_feature_map writes feature_map.laz, the feature
# maps it used plus its own geo-registered points (a new file; inputs are never overwritten).
GROW_SETS = [s for s in FRAME_SETS if config["frames"][s].get("write_feature_map")]


rule grow_feature_map:
    input:
        poses="results/frames/{gset}/poses.json",
        images=lambda wc: [] if wc.gset in SFM_SETS else frame_images(config["frames"][wc.gset].get("images")),
        own=lambda wc: [f"results/frames/{wc.gset}/sfm_points.laz"] if wc.gset in SFM_SETS else [],
        used=lambda wc: frame_set_feature_maps(wc.gset),
        ortho="results/map/mosaic/ortho.vrt",
        dsm=frame_dsm,
    output:
        laz="results/frames/{gset}/feature_map.laz",
        descriptors="results/frames/{gset}/feature_map_descriptors.npy",
    params:
        conf=(config.get("frame_loc") or {}).get("feature_map") or {},
        ground_z=config["map"].get("ground_z", 0.0),
        video=lambda wc: wc.gset in SFM_SETS,
    wildcard_constraints:
        gset="|".join(re.escape(s) for s in GROW_SETS) or "(?!)",
    log:
        "logs/frames/grow_{gset}.log",
    threads: 1
    resources:
        mem_mb=2000,
    script:
        "../../scripts/frames_grow_feature_map.py"


TARGETS.append(expand("results/frames/{gset}/feature_map.laz", gset=GROW_SETS))
