"""Map preparation: the tile grid, orthophoto tiles, LiDAR/DEM elevation, mosaics and overview."""
