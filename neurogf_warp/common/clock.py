"""Where a time budget starts counting: the call, or the start of the process for a command-line run.

A user times ``neurogf-warp train ... --budget-seconds 120`` from pressing Enter to the prompt, so the imports
before the command runs and the exit after it count too; ``ngf.train(..., budget_seconds=120)`` from Python counts
from the call. The command line enters :func:`process_clock` around the command; budgeted calls then ask
:func:`budget_start` where their clock started. Light on purpose (no torch): the command line imports it first.
"""
from __future__ import annotations

import contextlib
import os
import time

__all__ = ["process_start", "process_clock", "budget_start", "EXIT_RESERVE_S"]

EXIT_RESERVE_S = 0.5  # a command-line budget ends this much before its time: the process still prints and exits
_STARTED: list = []  # perf_counter values of the process start while a command-line run is going on


def _started_ago(pid) -> float | None:
    """Seconds since process ``pid`` ("self" or a number) started, from /proc (Linux); None where unknown."""
    try:
        with open(f"/proc/{pid}/stat", "rb") as f:
            stat = f.read().decode("ascii", "replace")
        ticks = int(stat[stat.rindex(")") + 2:].split()[19])  # field 22, starttime, in clock ticks since boot
        since_boot = time.clock_gettime(time.CLOCK_BOOTTIME)
        ago = since_boot - ticks / os.sysconf("SC_CLK_TCK")
    except (OSError, ValueError, IndexError, AttributeError):
        return None
    return ago if 0.0 <= ago < 30 * 24 * 3600 else None


def process_start(launcher: bool = True) -> float | None:
    """The ``time.perf_counter()`` value at which this process started (None where the OS does not say). Under
    torchrun (``launcher``), the start of its launcher, the process the user started."""
    ago = None
    if launcher and "TORCHELASTIC_RUN_ID" in os.environ:
        ago = _started_ago(os.getppid())
    if ago is None:
        ago = _started_ago("self")
    return None if ago is None else time.perf_counter() - ago


@contextlib.contextmanager
def process_clock(active: bool = True):
    """Inside: budgets count from the process start (see the module docstring); ``active`` False: no change."""
    start = process_start() if active else None
    _STARTED.append(start)
    try:
        yield start
    finally:
        _STARTED.pop()


def budget_start(now: float) -> float:
    """Where the clock of a budgeted call that begins at ``now`` starts: ``now``, or inside :func:`process_clock`
    the process start, less ``EXIT_RESERVE_S`` for the exit after the call."""
    start = next((s for s in reversed(_STARTED) if s is not None), None)
    return now if start is None else min(now, start - EXIT_RESERVE_S)
