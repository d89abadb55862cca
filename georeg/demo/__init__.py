"""Deterministic synthetic demo scene: orthophoto, LiDAR, SWIR pushbroom queries and ground truth."""

from georeg.demo.scene import generate_scene, output_paths

__all__ = ["generate_scene", "output_paths"]
