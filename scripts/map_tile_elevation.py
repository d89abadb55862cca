"""Rule map_tile_elevation: DSM/DTM/nDSM/density and textured points of one tile (LiDAR or DEM)."""

from georeg.io.scripting import run
from georeg.map.elevation import make_elevation_tile


def main(smk):
    lidar = list(smk.input.source) if smk.params.source == "lidar" else []
    dem = smk.input.source[0] if smk.params.source == "dem" else None
    outputs = {k: smk.output[k] for k in ("dsm", "dtm", "ndsm", "density", "points")}
    chunk = smk.config["map_prep"]["lidar_chunk_points"]  # memory only: not in params
    settings = smk.params.settings
    make_elevation_tile(
        smk.input.ortho, outputs, lidar, dem, settings.get("lidar_crs"), settings, chunk
    )


run(snakemake, main)  # noqa: F821
