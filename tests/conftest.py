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


@pytest.fixture(scope="session")
def ellipsoid():
    """A 642-vertex ellipsoid (icosphere(3) scaled 1 x 0.8 x 0.6): the training tests' mesh."""
    import numpy as np
    import trimesh

    from neurogf_warp.mesh.mesh import load_mesh

    tm = trimesh.creation.icosphere(subdivisions=3)
    tm.vertices *= np.array([1.0, 0.8, 0.6])
    return load_mesh(tm)


@pytest.fixture(scope="session")
def tiny_dataset(ellipsoid):
    """The ``cpu_small`` preset's dataset of the ellipsoid (a few seconds on 2 cores)."""
    from neurogf_warp.dataset.build import build_dataset
    from neurogf_warp.training import preset

    return build_dataset(ellipsoid, None, preset("cpu_small").data, device="cpu", progress=False)


@pytest.fixture(scope="module")
def one_thread():
    """Tiny batches: one torch thread avoids OpenMP spin-waits, several times faster on a busy 2-core box."""
    import torch

    n = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(n)


@pytest.fixture(scope="session")
def trained(tmp_path_factory, ellipsoid, tiny_dataset):
    """(Model, model path): the ellipsoid trained for 300 joint steps with the ``cpu_small`` preset (one thread)."""
    import torch

    from neurogf_warp.training import preset, train

    out = tmp_path_factory.mktemp("trained") / "m.ngf"
    n = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        cfg = preset("cpu_small", querier_steps=30, epochs=3, iters_per_epoch=100)
        model = train(ellipsoid, out, config=cfg, dataset=tiny_dataset, device="cpu", progress=False)
    finally:
        torch.set_num_threads(n)
    return model, out


@pytest.fixture
def ctrl_c_raises():
    """SIGINT raises KeyboardInterrupt during the test, as in a terminal, even where the test runner was started
    with SIGINT ignored (a background job of a non-interactive shell inherits SIG_IGN); restored afterwards."""
    import signal

    before = signal.signal(signal.SIGINT, signal.default_int_handler)
    yield
    signal.signal(signal.SIGINT, before)


# Fixtures that train or build something for many seconds: a test that uses one is slow (out of the quick run).
SLOW_FIXTURES = {"trained"}


@pytest.hookimpl(tryfirst=True)  # before pytest's own -m selection, which then sees these marks
def pytest_collection_modifyitems(config, items):
    """Marks from what a test needs: ``slow`` for the fixtures above, ``gpu`` for a test parametrized on a CUDA
    device; ``gpu`` tests are skipped where Warp finds no CUDA device."""
    cuda = wp.get_cuda_device_count() > 0
    for item in items:
        if SLOW_FIXTURES.intersection(getattr(item, "fixturenames", ())):
            item.add_marker(pytest.mark.slow)
        params = getattr(getattr(item, "callspec", None), "params", {})
        if any(isinstance(v, str) and v.startswith("cuda") for v in params.values()):
            item.add_marker(pytest.mark.gpu)
        if not cuda and item.get_closest_marker("gpu"):
            item.add_marker(pytest.mark.skip(reason="needs a CUDA device"))
