"""Warp kernels for pictures: ray casting."""
