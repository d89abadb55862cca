# Frame geo-localisation (issue 9): each frame set -> coarse location by the map index ->
# render-match-PnP against the textured map -> MI + gradient refinement -> poses and overlays.
# Params: the set's own entry and `frame_loc` (without demo_frames), so editing the demo views
# reruns only the demo frames and what reads them.

FRAME_SETS = sorted(config.get("frames") or {})
FRAME_LOC = {k: v for k, v in (config.get("frame_loc") or {}).items() if k != "demo_frames"}


wildcard_constraints:
    fset="|".join(re.escape(s) for s in FRAME_SETS) or "(?!)",


def frame_set_images(wildcards):
    from georeg.frame_localize import frame_images

    return frame_images(config["frames"][wildcards.fset].get("images"))


def frame_set_truth(wildcards):
    truth = config["frames"][wildcards.fset].get("truth")
    return [truth] if truth else []


def frame_set_laz(wildcards):
    if FRAME_LOC.get("render_source") != "points":
        return []
    return expand("results/map/tiles/{tile}/points.laz", tile=index_tile_ids())


rule localize_frames:
    input:
        images=frame_set_images,
        index=f"{INDEX_DIR}/meta.json",
        ortho="results/map/mosaic/ortho.vrt",
        dsm="results/map/mosaic/dsm.vrt",
        laz=frame_set_laz,
        truth=frame_set_truth,
    output:
        poses="results/frames/{fset}/poses.json",
        geojson="results/frames/{fset}/cameras.geojson",
        kml="results/frames/{fset}/cameras.kml",
        overlays=directory("results/frames/{fset}/overlays"),
    params:
        frames=lambda wc: config["frames"][wc.fset],
        frame_loc=FRAME_LOC,
    log:
        "logs/frames/{fset}.log",
    threads: 1
    resources:
        mem_mb=3000,
    script:
        "../../scripts/localize_frames.py"


TARGETS.append(expand("results/frames/{fset}/poses.json", fset=FRAME_SETS))
