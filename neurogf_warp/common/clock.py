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

__all__ = ["process_start", "process_clock", "budget_start", "exit_reserve", "EXIT_RESERVE_S", "EXIT_SHARE"]

# A command-line budget ends before its time by what the process still needs to print and exit: at least
# EXIT_RESERVE_S, and EXIT_SHARE of its start-up time (the interpreter's teardown of torch and Warp follows their
# import: on a loaded 2-core machine `import torch` took 11.1 s and its exit 3.6 s, Warp's 4.4 s and 1.2 s).
EXIT_RESERVE_S = 0.5
EXIT_SHARE = 0.4
_STARTED: list = []  # innermost last: the process start (a perf_counter value), or None for "from the call"


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
    """Inside: budgets count from the process start (see the module docstring); ``active`` False: from each
    call again (e.g. a budget per mesh of a folder), until the block ends. The innermost block decides."""
    start = process_start() if active else None
    _STARTED.append(start)
    try:
        yield start
    finally:
        _STARTED.pop()


def budget_start(now: float) -> float:
    """Where the clock of a budgeted call that begins at ``now`` starts: ``now``, or inside :func:`process_clock`
    the process start, less :func:`exit_reserve` for the exit after the call."""
    start = _STARTED[-1] if _STARTED else None
    return now if start is None else min(now, start - exit_reserve(now - start))


def exit_reserve(startup_s: float) -> float:
    """Seconds kept for a process's exit after a start-up (imports) of ``startup_s`` seconds; 1.5 times that under
    torchrun, whose launcher exits (its own teardown) after the workers' (a 25 s two-rank gen-train on a loaded
    2-core machine ended 26.1 s after torchrun started with one share, 20.4 s with two)."""
    factor = 1.5 if "TORCHELASTIC_RUN_ID" in os.environ else 1.0
    return factor * max(EXIT_RESERVE_S, EXIT_SHARE * max(startup_s, 0.0))
