"""Stage 2, ground truth: exact-grade geodesic distances and paths on a mesh (Warp solver, worker processes)."""
