"""Exports for photogrammetry and GIS tools: ODM gcp_list.txt / geo.txt, a COLMAP text model,
tie points as a GeoPackage table."""
