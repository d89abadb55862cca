# Frame geo-localisation (issue 9): each frame set -> coarse location by the map index ->
# render-match-PnP against the textured map -> MI + gradient refinement -> poses and overlays.
# Params: the set's own entry and `frame_loc` (without demo_frames), so editing the demo views
# reruns only the demo frames and what reads them.

from georeg.io.video import frame_images

FRAME_LOC = {k: v for k, v in (config.get("frame_loc") or {}).items() if k != "demo_frames"}


def feature_map_laz(name):
    """The feature map a frame set writes: feature_map.laz (write_feature_map), else a trajectory
    set's sfm_points.laz; a path (not a set name) is itself."""
    fs = (config.get("frames") or {}).get(name)
    if fs is None:
        return name
    if fs.get("write_feature_map"):
        return f"results/frames/{name}/feature_map.laz"
    if name in VIDEO_SETS:
        return f"results/frames/{name}/sfm_points.laz"
    raise ValueError(f"frames: feature map {name!r} is an image set without write_feature_map: "
                     "it writes no feature map")


def frame_set_feature_maps(fset):
    """The feature maps frame set ``fset`` uses (frames.<set>.feature_maps)."""
    return [feature_map_laz(f) for f in config["frames"][fset].get("feature_maps") or []]


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
    threads: 1
    resources:
        mem_mb=3000,
    script:
        "../../scripts/frames_localize.py"


TARGETS.append(expand("results/frames/{fset}/poses.json", fset=IMAGE_SETS))
