"""Warp kernels on meshes: closest points."""
