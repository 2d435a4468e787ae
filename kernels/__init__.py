"""Warp kernels of neurogf_warp (installed as ``neurogf_warp.kernels``)."""
