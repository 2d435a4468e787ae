"""Warp's start, quiet unless asked: no banner, no "Module ... load" lines, no CUDA-driver warning on a GPU-less
machine. Library calls should print nothing their caller did not ask for.

Warp 1.19 prints its banner at ``wp.init()`` and a line per module load when ``wp.config.log_level`` is
``LOG_INFO`` (its default) or lower, and it has no ``quiet`` switch; the CUDA-driver warning comes from its
native library, straight to file descriptor 2, while it initializes. So, once per process, before Warp
initializes through this package: the log level goes to ``LOG_WARNING`` (unless the caller has already changed
it from Warp's default), and the driver warning is filtered out of what Warp writes during ``wp.init()``.

Get them back with the environment variable ``NEUROGF_WARP_VERBOSE=1`` (or the command line's ``--verbose``),
or set ``wp.config.log_level = wp.LOG_INFO`` yourself after importing this package.
"""
from __future__ import annotations

import contextlib
import os
import sys
import tempfile

__all__ = ["VERBOSE_ENV", "verbose_requested", "quiet_warp", "init_warp", "CUDA_WARNING"]

VERBOSE_ENV = "NEUROGF_WARP_VERBOSE"
CUDA_WARNING = "Warp CUDA warning: Could not find or load the NVIDIA CUDA driver. GPU execution will not be available."

_configured = False


def verbose_requested() -> bool:
    """True when ``NEUROGF_WARP_VERBOSE`` is set to anything but '' or '0'."""
    return os.environ.get(VERBOSE_ENV, "") not in ("", "0")


def quiet_warp(verbose: bool | None = None) -> None:
    """Set Warp's log level once: ``LOG_INFO`` when verbose (``verbose`` or the environment variable), else
    ``LOG_WARNING`` unless the caller already changed it from Warp's default. Later calls change nothing unless
    ``verbose`` is given explicitly (the command line's ``-v``)."""
    global _configured
    import warp as wp

    if verbose is None and _configured:
        return
    loud = verbose if verbose is not None else verbose_requested()
    if loud:
        wp.config.log_level = min(wp.config.log_level, wp.LOG_INFO)
    elif wp.config.log_level == wp.LOG_INFO:  # Warp's default: the caller has not chosen
        wp.config.log_level = wp.LOG_WARNING
    _configured = True


@contextlib.contextmanager
def _without_driver_warning():
    """Send file descriptor 2 to a temporary file while the block runs, then pass on all but the CUDA-driver
    warning (written by Warp's native library, which Python's sys.stderr does not see)."""
    try:
        sys.stderr.flush()
        saved = os.dup(2)
    except (OSError, ValueError):  # no usable stderr (closed, or replaced by an object without a descriptor)
        yield
        return
    with tempfile.TemporaryFile() as tmp:
        os.dup2(tmp.fileno(), 2)
        try:
            yield
        finally:
            sys.stderr.flush()
            os.dup2(saved, 2)
            os.close(saved)
            tmp.seek(0)
            rest = tmp.read().decode(errors="replace").replace(CUDA_WARNING, "")
            if rest.strip():
                sys.stderr.write(rest if rest.endswith("\n") else rest + "\n")


def init_warp(verbose: bool | None = None):
    """Import and initialize Warp quietly (see the module docstring); returns the ``warp`` module."""
    import warp as wp

    quiet_warp(verbose)
    if _warp_initialized(wp):
        return wp
    loud = verbose if verbose is not None else verbose_requested()
    with contextlib.nullcontext() if loud else _without_driver_warning():
        wp.init()
    return wp


def _warp_initialized(wp) -> bool:
    try:
        return wp._src.context.runtime is not None
    except AttributeError:  # another Warp layout: initializing twice is harmless, only not silenced
        return False
