"""Input/output at the bottom of the library: rasters, query cubes, video frames, atomic writes, errors."""
