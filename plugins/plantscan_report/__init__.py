"""plantscan exporters: HTML report, PLY/OBJ/GLB meshes, CSV/Parquet traits, COLMAP cameras."""
