"""Training data on the device: the dataset's arrays flattened for uniform sampling, and the SDF pool.

``obtain_dataset`` returns the dataset a run trains on: the one passed in, else the run folder's cached
copy when it was built for the same mesh and settings, else a fresh build (then cached).
"""
from __future__ import annotations

import os

import numpy as np
import torch

from neurogf_warp.common.checks import say
from neurogf_warp.dataset.build import Dataset, build_dataset, sample_sdf_points, sdf_truth
from neurogf_warp.mesh.mesh import Mesh

__all__ = ["TrainingData", "make_sdf_pool", "obtain_dataset", "warp_device"]


class TrainingData:
    """A dataset's arrays as device tensors; distance rows and paths flattened so that one ``randint`` draws a
    (source, target) pair uniformly.

    gd[k] : (n, 7) rows for k in global, local1, local2; pg : (Kg, 128, 3), pl : (Kl, 32, 3) paths;
    vertices : (V, 3); test_src : (T,) long; test_dist : (T, V); surface_points : (n, 3) numpy;
    full_dist : (K, V) whole distance rows (K = 0 unless the dataset kept them).
    """

    def __init__(self, ds: Dataset, device):
        t = lambda a, dt=torch.float32: torch.as_tensor(np.asarray(a), dtype=dt, device=device)  # noqa: E731
        self.gd = {k: t(getattr(ds, f"gd_{k}")).reshape(-1, 7) for k in ("global", "local1", "local2")}
        self.pg = t(ds.path_global)
        self.pl = t(ds.path_local)
        self.vertices = t(ds.vertices)
        self.faces = np.asarray(ds.faces)
        self.landmarks_solved = None  # landmarks a ``landmarks=K`` network's rows solve (None: K; set by the run)
        self.landmark_rows = None  # its (points, distances) lookup table, made once per run (``landmark_table``)
        self.full_dist = t(ds.full_dist)  # (K, V) whole rows of the first distance sources (landmark features)
        self.full_src = np.asarray(ds.full_src, np.int64)  # (K,) their vertices
        self.solve_k = int((ds.meta.get("settings") or {}).get("k", 3))  # Steiner points per edge of those rows
        self.test_src = torch.as_tensor(np.asarray(ds.test_src), dtype=torch.long, device=device)
        self.test_dist = t(ds.test_dist)
        self.surface_points = np.asarray(ds.surface_points, dtype=np.float32)
        for k, v in list(self.gd.items()) + [("path_global", self.pg), ("path_local", self.pl)]:
            if len(v) == 0:
                raise ValueError(f"the dataset has no {k} samples: the mesh is too small to sample from, or the "
                                 "solver could trace none of its paths (see the dataset's meta: dropped_paths)")


def make_sdf_pool(mesh: Mesh, surface_points, n: int, seed: int, device):
    """n SDF samples (§3 thirds) with ground truth, computed once: (n, 3), (n,) tensors on the device."""
    rng = np.random.default_rng([seed, 3])
    pts = np.asarray(sample_sdf_points(rng, surface_points, n), dtype=np.float32)
    sdf = np.asarray(sdf_truth(mesh, pts, device=warp_device(device)), dtype=np.float32)
    return torch.as_tensor(pts, device=device), torch.as_tensor(sdf, device=device)


def warp_device(device) -> str:
    """The Warp device name of a torch device ("cpu" or "cuda:N")."""
    d = torch.device(device)
    return "cpu" if d.type == "cpu" else f"cuda:{d.index or 0}"


def obtain_dataset(mesh: Mesh, dataset, cache: str | None, settings, seed: int, device, progress: bool,
                   time_limit_s: float | None = None, partial_ok: bool = False, devices=None) -> Dataset:
    """The dataset to train on.

    dataset : a Dataset, a dataset file, or None: the ``cache`` file when it was built for this mesh with these
        ``settings`` and ``seed``, else a fresh build with them (written to ``cache``).
    time_limit_s : seconds a fresh build may take in all (``build_dataset``: fewer sources and paths then)
    partial_ok : reuse a cached dataset that a time limit cut short (a run being continued trains on the data it
        started with); otherwise such a cache is rebuilt, since this call may have more time for it
    devices : GPUs that share a fresh build's distance sources (``build_dataset``)
    """
    if isinstance(dataset, Dataset):
        return _checked(dataset, mesh, "the given dataset")
    if dataset is not None:
        return _checked(Dataset.load(dataset), mesh, f"dataset {dataset}")
    want = settings.recipe(seed)
    if cache is not None and os.path.exists(cache):
        try:
            ds = Dataset.load(cache)
            if ds.fingerprint == mesh.fingerprint and _recipe_of(ds) == want and \
                    (partial_ok or ds.meta.get("complete", True)):
                say(progress, f"reusing dataset {cache}")
                return ds
            say(progress, f"dataset cache {cache} was built for another mesh, other settings or less time; "
                           "rebuilding it")
        except (ValueError, OSError) as e:  # an unreadable cache is rebuilt, never trusted
            say(True, f"dataset cache {cache} is unreadable ({e}); rebuilding it")
    say(progress, "building the training dataset" + (f" -> {cache}" if cache else ""))
    return build_dataset(mesh, cache, settings, seed=seed, device=warp_device(device), progress=progress,
                         time_limit_s=time_limit_s, devices=devices)


def _checked(ds: Dataset, mesh: Mesh, what: str) -> Dataset:
    if ds.fingerprint is not None and ds.fingerprint != mesh.fingerprint:
        raise ValueError(f"{what} was built for a different mesh (fingerprint {ds.fingerprint[:12]}...)")
    return ds


def _recipe_of(ds: Dataset) -> dict:
    """The settings a dataset was asked for, as recorded in its meta (``requested``)."""
    return ds.meta.get("requested") or {}
