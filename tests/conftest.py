"""Shared test set-up: Warp on the CPU, quiet, one kernel cache per pytest-xdist worker."""
import os
from pathlib import Path

import pytest

worker = os.environ.get("PYTEST_XDIST_WORKER")
if worker and "WARP_CACHE_PATH" not in os.environ:
    os.environ["WARP_CACHE_PATH"] = os.path.join(os.path.expanduser("~/.cache/warp-tests"), worker)

import warp as wp  # noqa: E402

wp.config.log_level = wp.LOG_WARNING
wp.config.quiet = True  # accepted and ignored by 1.19; keeps newer versions quiet
wp.init()

SHARED = Path(__file__).resolve().parents[1].parent / "shared"


def shared_path(*parts) -> Path:
    """A file under ../shared. Missing data fails under CI (CI=true) and skips, with the reason, elsewhere."""
    p = SHARED.joinpath(*parts)
    if not p.exists():
        msg = f"shared test data not found: {p} (the tests expect the shared/ folder beside the checkout)"
        if os.environ.get("CI"):
            pytest.fail(msg)
        pytest.skip(msg)
    return p
