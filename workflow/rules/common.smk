"""Shared helpers: config loading (user map/queries replace the demo's), validation, targets,
and every stage's input functions (kept here so that the stage files hold only rules).
"""

import copy
import sys
import json
import re
from pathlib import Path

from snakemake.logging import logger
from snakemake.utils import validate


DATA_SECTIONS = ("map", "queries", "frames")


def _replace_user_sections(config):
    """A user's data sections (`map`, `queries`, `frames`) replace the demo's wholesale.

    Snakemake deep-merges command-line config into the Snakefile's `configfile:` default, so a
    user's file would otherwise inherit the demo's LiDAR list, queries and frames. Once the user
    gives any data section, the ones they leave out are empty rather than the demo's.
    """
    user = workflow.config_settings.overwrite_config or {}
    if any(key in user for key in DATA_SECTIONS):
        for key in DATA_SECTIONS:
            config[key] = copy.deepcopy(user.get(key, {}))


_replace_user_sections(config)
validate(config, schema="../schemas/config.schema.yaml")


def _check_inputs(config):
    """Every input file opened (headers only) before any rule runs; all problems in one message.
    Paths under results/ are made by the workflow (the demo) and checked by their rules."""
    from georeg.register.inputs import check_inputs

    problems = check_inputs(config, generated="results")
    if problems:
        lines = "\n".join(f"  - {p}" for p in problems)
        logger.error(f"{len(problems)} problem(s) with the inputs, nothing was started:\n{lines}")
        sys.exit(1)
    m = config["map"]
    if not (m.get("lidar") or m.get("dem")):
        logger.warning(
            "map without elevation (neither map.lidar nor map.dem): registration, cube and "
            "footprint run as usual; heights are nodata and the products that need them "
            "(points_spectra.laz, the segmentation) are skipped (products.json says which)"
        )


# once, in the snakemake a user starts; not again in every cluster job (a Slurm job's snakemake
# parses this file too: a county's thousands of headers would be read by each of its jobs)
if workflow.is_main_process:
    _check_inputs(config)

QUERIES = sorted(config["queries"])
FRAME_SETS = sorted(config.get("frames") or {})  # frame geo-localisation sets (frames, report)
# sets with a `video` (or `trajectory: true`) are trajectories (rule trajectory), the others
# independent frames (rule localize_frames); both write results/frames/{set}/poses.json
VIDEO_SETS = [s for s in FRAME_SETS if config["frames"][s].get("video")
              or config["frames"][s].get("trajectory")]  # fmt: skip
# sets with `collection: true` are unordered photo collections (rule collection, issue 33)
COLLECTION_SETS = [s for s in FRAME_SETS if config["frames"][s].get("collection")]
for _s in COLLECTION_SETS:
    if _s in VIDEO_SETS:
        raise ValueError(f"frames.{_s}: `collection: true` and a video / `trajectory: true` exclude "
                         "each other (a collection is unordered photos)")  # fmt: skip
# sets whose SfM points (sfm_points.laz + descriptors) are their feature map and export points
SFM_SETS = VIDEO_SETS + COLLECTION_SETS
IMAGE_SETS = [s for s in FRAME_SETS if s not in SFM_SETS]


def query_name_pattern():
    """Wildcard constraint for {name}: exactly the configured queries (nothing else matches)."""
    return "|".join(re.escape(q) for q in QUERIES) or "(?!)"


TARGETS = []  # each stage file appends its final outputs (paths or input functions)


def all_inputs(wildcards):
    """Everything the default target asks for: the union of what each stage registered."""
    out = []
    for t in TARGETS:
        t = t(wildcards) if callable(t) else t
        out.extend([t] if isinstance(t, str) else t)
    return out


def orthophoto_paths():
    ortho = config["map"]["orthophoto"]
    return [ortho] if isinstance(ortho, str) else list(ortho)


def lidar_paths():
    return list(config["map"].get("lidar") or [])


# ----------------------------------------------------------------- map stage


def map_tile_ids():
    """Tile ids of the map grid (after the map_grid checkpoint has run)."""
    with open(checkpoints.map_grid.get().output[0]) as f:
        return sorted(json.load(f)["tiles"])



def map_elevation_source():
    """'lidar' when map.lidar lists files, else 'dem' when map.dem is set, else 'none'."""
    if lidar_paths():
        return "lidar"
    return "dem" if config["map"].get("dem") else "none"



def map_elevation_params():
    """Only the map_prep keys that change the elevation result of the active source."""
    mp = config["map_prep"]
    if map_elevation_source() == "lidar":
        keys = ["point_margin_m", "drop_classes", "outlier", "dsm_fill_max_m", "dtm_fill", "dtm_window_m"]
        out = {k: mp[k] for k in keys}
        out["lidar_crs"] = config["map"].get("lidar_crs")
        out.update(map_pdal_params())
        return out
    if map_elevation_source() == "dem":
        return {"dem_resampling": mp["dem_resampling"]}
    return {}



def map_pdal_params():
    """The point-cloud backend and, for PDAL, its resolved pipeline and ground stage: a change
    reruns the elevation tiles only (nothing when laspy reads, so runs without PDAL are as before)."""
    from georeg.map import pdal_points

    m = config["map"]
    if pdal_points.resolve_backend(m["lidar_backend"]) != "pdal":
        return {}
    return {
        "backend": "pdal",
        "pdal_pipeline": pdal_points.resolve_pipeline(m["pdal_pipeline"], config["map_prep"]["outlier"]),
        "pdal_ground": pdal_points.resolve_ground(m["pdal_ground"]),
    }


def map_elevation_inputs(wildcards):
    src = map_elevation_source()
    if src == "lidar":
        return lidar_paths()
    return [config["map"]["dem"]] if src == "dem" else []



def map_layer_tiles(wildcards):
    return expand("results/map/tiles/{tile}/{layer}.tif", tile=map_tile_ids(), layer=wildcards.layer)



def map_targets(wildcards):
    """Final outputs of the map stage: per-tile rasters and points, mosaics, overview."""
    tiles = map_tile_ids()
    out = expand(
        "results/map/tiles/{tile}/{name}",
        tile=tiles,
        name=["ortho.tif"] + [f"{l}.tif" for l in MAP_ELEV_LAYERS] + ["points.laz"],
    )
    out += expand("results/map/mosaic/{layer}.vrt", layer=MAP_MOSAIC_LAYERS)
    out.append("results/map/overview.png")
    return out



# ----------------------------------------------------------------- index stage


def index_tile_ids():
    """Tile ids of the map grid (after the map_grid checkpoint has run)."""
    with open(checkpoints.map_grid.get().output[0]) as f:
        return sorted(json.load(f)["tiles"])



def index_feature_dirs(wildcards):
    return expand("results/index/features/{tile}", tile=index_tile_ids())



def index_word_files(wildcards):
    return expand("results/index/words/{tile}.npy", tile=index_tile_ids())



#: maps with fewer tiles train their vocabulary on one core: the demo's 9 tiles take 1.9 CPU-s,
#: and asking for every core made the job wait 34 s for a running 1-core job to finish
VOCABULARY_PARALLEL_TILES = 16


def index_vocabulary_threads(wildcards):
    """Every core given with --cores for a large map, 1 for a small one (or without --cores:
    `snakemake --report` has none, and `workflow.cores` raises there)."""
    cores = workflow.resource_settings.cores or 1
    return cores if len(index_tile_ids()) >= VOCABULARY_PARALLEL_TILES else 1


def index_vocabulary_seed():
    seed = config["vocabulary"].get("seed")
    return config["seed"] if seed is None else seed



# ----------------------------------------------------------------- register stage


def reg_query(wildcards):
    return config["queries"][wildcards.name]



def reg_image_files(wildcards):
    """The query image, plus the ENVI data file next to a header (so a changed cube reruns)."""
    from georeg.io.errors import InputError
    from georeg.io.query import find_envi_data

    image = Path(reg_query(wildcards)["image"])
    files = [str(image)]
    if image.suffix.lower() == ".hdr" and image.exists():
        try:
            files.append(str(find_envi_data(image)))
        except InputError:
            pass  # no data file: the rule's script reports it as one line, not a DAG traceback
    return files



def reg_truth(wildcards):
    truth = reg_query(wildcards).get("truth")
    return [truth] if truth else []



# ----------------------------------------------------------------- products stage


def prod_image_files(wildcards):
    """The query image, plus the ENVI data file next to a header (so a changed cube reruns)."""
    from georeg.io.query import find_envi_data

    image = Path(config["queries"][wildcards.name]["image"])
    files = [str(image)]
    if image.suffix.lower() == ".hdr" and image.exists():
        files.append(str(find_envi_data(image)))
    return files



def prod_point_tiles(wildcards):
    """Filtered map points of every tile (known after the map_grid checkpoint)."""
    if not config["products"]["points"]["enabled"] or map_elevation_source() == "none":
        return []
    return expand("results/map/tiles/{tile}/points.laz", tile=map_tile_ids())



def prod_labels(wildcards):
    labels = config["queries"][wildcards.name].get("labels")
    return [labels] if labels else []



# ----------------------------------------------------------------- report stage


def rep_query(wildcards):
    return config["queries"][wildcards.name]



def rep_optional(key):
    """Input function: the query's `truth` / `labels` file as a one-item list, or nothing."""

    def f(wildcards):
        v = rep_query(wildcards).get(key)
        return [v] if v else []

    return f



def rep_products_defined():
    """True when the products stage (rule `products`, products.json) is part of the workflow.
    Checked by the name of the rule: its outputs carry the global {name} constraint."""
    return any(r.name == "products" for r in workflow.rules)



def rep_products(wildcards):
    """The products manifest (segmentation), when `report.segmentation` and the stage exists."""
    if not REP["segmentation"] or not rep_products_defined():
        return []
    return [f"results/products/{wildcards.name}/products.json"]



def rep_benchmark(wildcards):
    """results/benchmark/summary.csv when `python benchmarks/run.py` wrote it (then a newer one
    rebuilds the page); the benchmark is not a rule: it measures the library, minutes long."""
    return [REP_BENCH] if Path(REP_BENCH).exists() else []




# ----------------------------------------------------------------- frames and trajectories


def frame_set_media(fset):
    """The set's video file, or its ordered image list (paths and globs expanded)."""
    from georeg.io.video import frame_images

    fs = config["frames"][fset]
    return [fs["video"]] if fs.get("video") else frame_images(fs.get("images"))


def frame_set_truth(fset):
    """The set's truth.json as a one-item list, or nothing."""
    t = config["frames"][fset].get("truth")
    return [t] if t else []


def frame_dsm(wildcards):
    """The DSM mosaic frames take their 3-D points from; none for a map without elevation (the
    frames then use the flat ground map.ground_z)."""
    return [] if map_elevation_source() == "none" else ["results/map/mosaic/dsm.vrt"]


def frame_laz_inputs():
    """The tiles' textured points.laz when frames are rendered from points, else nothing."""
    if (config.get("frame_loc") or {}).get("render_source") == "points":
        return expand("results/map/tiles/{tile}/points.laz", tile=index_tile_ids())
    return []


def feature_map_laz(name):
    """The feature map a frame set writes: feature_map.laz (write_feature_map), else a trajectory
    set's sfm_points.laz; a path (not a set name) is itself."""
    fs = (config.get("frames") or {}).get(name)
    if fs is None:
        return name
    if fs.get("write_feature_map"):
        return f"results/frames/{name}/feature_map.laz"
    if name in SFM_SETS:
        return f"results/frames/{name}/sfm_points.laz"
    raise ValueError(f"frames: feature map {name!r} is an image set without write_feature_map: "
                     "it writes no feature map")


def frame_set_feature_maps(fset):
    """The feature maps frame set ``fset`` uses (frames.<set>.feature_maps)."""
    return [feature_map_laz(f) for f in config["frames"][fset].get("feature_maps") or []]
