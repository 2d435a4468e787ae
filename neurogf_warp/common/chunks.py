"""Long CPU launches in chunks, so that Ctrl-C takes effect within about a second: a CPU launch of Warp runs to
its end before Python sees the signal (4M SDF points: minutes), and KeyboardInterrupt is raised between two chunks.
Every stage that runs long row-wise CPU work (surface snapping, the queries, the generalizable encoder) uses it."""
from __future__ import annotations

import time

import warp as wp

__all__ = ["in_chunks", "CPU_CHUNK_SECONDS", "CPU_FIRST_CHUNK", "CPU_CHUNK_ALIGN", "CPU_MAX_CHUNK"]

# seconds a chunk aims at (CUDA launches return at once and are never chunked)
CPU_CHUNK_SECONDS = 0.5
CPU_FIRST_CHUNK = 1024  # points of the first chunk (the next ones are sized from its time); a multiple of ALIGN
CPU_CHUNK_ALIGN = 256  # chunk sizes are multiples of this (whole tensor-core tiles; every point is independent)
CPU_MAX_CHUNK = 1 << 22


def in_chunks(device, n: int, run, first: int | None = None, align: int = CPU_CHUNK_ALIGN):
    """Call ``run(lo, hi)`` over [0, n): once on a CUDA device, in consecutive chunks on the CPU, each sized so that
    it takes about ``CPU_CHUNK_SECONDS`` (from the time of the previous one), so that Ctrl-C stops a long query
    within about that time. ``run`` must compute each row from its own inputs only (then the result is the same,
    bit for bit, as one launch over all rows). ``first``: the first chunk's size (default ``CPU_FIRST_CHUNK``);
    ``align``: later chunks are multiples of it. Returns the number of chunks run."""
    if n <= 0:
        return 0
    if not wp.get_device(device).is_cpu:
        run(0, n)
        return 1
    size, lo, count = max(1, first or CPU_FIRST_CHUNK), 0, 0
    while lo < n:
        hi = min(n, lo + size)
        t0 = time.perf_counter()
        run(lo, hi)
        count += 1
        dt = max(time.perf_counter() - t0, 1e-6)
        grow = min(4.0, max(0.25, CPU_CHUNK_SECONDS / dt))  # at most 4x either way: one slow chunk is no trend
        size = int(min(CPU_MAX_CHUNK, max(align, (size * grow) // align * align)))
        lo = hi
    return count
