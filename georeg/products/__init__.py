"""Products of a registered query: cube, elevation, fused raster, point cloud, segmentation, footprint."""
