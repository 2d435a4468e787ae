"""Named training presets, and the choice of one by device and mesh size.

``default`` is the GPU recipe measured on bunny and fandisk (benchmarks/RESULTS.md); ``paper`` is the
published network and recipe; ``cpu`` fits a CPU run of a few minutes; ``cpu_small`` is a seconds-long
smoke run for tests (its models are not meant to be accurate). Each preset is a set of changes to the
``TrainConfig`` defaults (= ``default``).
"""
from __future__ import annotations

from .config import TrainConfig

__all__ = ["PRESETS", "preset", "choose_preset", "describe"]

_SMALL_BATCHES = dict(batch_sdf=2048, batch_g=4096, batch_l1=512, batch_l2=1024, batch_paths_g=128,
                      batch_paths_l=128, batch_surf=16, batch_querier=2048, sdf_pool=20000)

PRESETS = {
    "default": {},
    "paper": dict(fourier=0, euclid=False, path_residual=False, path_width=1, path_window=False, dist_loss="l1",
                  refine_dist_steps=0, refine_path_lr=1e-3, ratios={"refine_path": 0.1}),
    "cpu": dict(_SMALL_BATCHES, D=64, batch_surf=32, batch_querier=4096, sdf_pool=100000, val_every=500,
                n_sources=64, n_path_sources=16, n_path_global=64, n_path_local=32, n_global=4096, n_local2=512,
                n_surface=30000),
    "cpu_small": dict(_SMALL_BATCHES, D=64, val_every=100, log_every=20, n_sources=64, n_global=256,
                      n_local1=8, n_local2=32, n_path_sources=16, n_path_global=16, n_path_local=16, n_test=2,
                      n_surface=30000, n_spread=2000),
}

DESCRIPTIONS = {
    "default": "the GPU recipe (D=256, 65K pairs and 4K paths per step, 2,048 sources)",
    "paper": "the published network and recipe (no Fourier inputs, |p - q| term or residual paths; L1 losses)",
    "cpu": "a CPU run of a few minutes (D=64, small batches, a small dataset)",
    "cpu_small": "a seconds-long CPU smoke run for tests (tiny data; not accurate)",
}


def preset(name: str = "default", **changes) -> TrainConfig:
    """The ``TrainConfig`` of preset ``name``, with ``changes`` (flat or dotted setting names) applied.

    Raises ValueError for an unknown preset, naming the known ones.
    """
    if name not in PRESETS:
        raise ValueError(f"unknown preset {name!r}; known: {', '.join(PRESETS)}")
    cfg = TrainConfig().set(**PRESETS[name])
    cfg.preset = name
    return cfg.set(**changes) if changes else cfg


def choose_preset(device: str, n_vertices: int) -> str:
    """The preset for a device ("cpu", "cuda", "cuda:1", ...) and a mesh of ``n_vertices``: the GPU recipe on a
    GPU, ``cpu`` on the CPU."""
    return "cpu" if str(device).startswith("cpu") else "default"


def describe() -> str:
    """One line per preset, for help texts."""
    return "\n".join(f"{k}: {v}" for k, v in DESCRIPTIONS.items())
