"""Work split over ranks: which of a list of jobs (shapes, meshes) each rank of a torch.distributed run takes.

Jobs are given to ranks largest first, each to the rank with the least work so far (the longest-processing-time
rule), by a size that stands for their cost (a mesh file's bytes: ~linear in its vertices and faces). With
``i % world`` the collection's six families, drawn in turn, fell on the same ranks every time (two ranks: one got
the capsules, the largest shapes). The split depends only on the sizes and the world size, so every rank
computes the same one without talking to the others, and a run resumed with another world size splits again.
"""
from __future__ import annotations

import os

import numpy as np

__all__ = ["balanced_shard", "file_sizes"]


def balanced_shard(sizes, world: int, rank: int) -> list[int]:
    """Indices (ascending) of the jobs rank ``rank`` of ``world`` takes; ``sizes`` (n,) job costs (any unit)."""
    if world < 1 or not 0 <= rank < world:
        raise ValueError(f"rank {rank} is not in a world of {world}")
    sizes = np.asarray(sizes, dtype=np.float64).reshape(-1)
    load = np.zeros(world)
    mine = []
    for i in np.lexsort((np.arange(len(sizes)), -sizes)):  # largest first, ties by index: the same on every rank
        r = int(np.argmin(load))
        load[r] += sizes[i]
        if r == rank:
            mine.append(int(i))
    return sorted(mine)


def file_sizes(paths) -> np.ndarray:
    """(n,) bytes of each file (0 where it cannot be read: it then counts as the smallest job)."""
    out = []
    for p in paths:
        try:
            out.append(os.path.getsize(p))
        except OSError:
            out.append(0)
    return np.asarray(out, dtype=np.float64)
