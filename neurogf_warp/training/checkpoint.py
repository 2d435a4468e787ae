"""Where a run keeps its files, and its checkpoints: written atomically, read back with their format checked.

A run that writes ``spot.ngf`` keeps its work files in one folder beside it, ``spot.train/``: the checkpoint
(``checkpoint.pt``), the cached dataset (``dataset.npz``) and the training log (``log.json``).
"""
from __future__ import annotations

import copy
import sys

import numpy as np
import torch

from neurogf_warp.mesh.mesh import Mesh
from neurogf_warp.training.config import STAGES, TrainConfig
from neurogf_warp.training.run_folder import RunFiles, RunLock  # noqa: F401 - re-exported

__all__ = ["RunFiles", "RunLock", "save_checkpoint", "load_checkpoint", "save_model", "CKPT_VERSION", "finished"]

# 2: the refine_dist stage; 3: network options in the config; 4: nested config and the run's request
CKPT_VERSION = 4
READABLE = (3, 4)


def save_checkpoint(state: dict, path: str) -> bool:
    """Atomic write (tmp + os.replace); on failure the previous checkpoint stays, a warning is printed and
    False returned (training goes on)."""
    from neurogf_warp.common.files import atomic_write

    try:
        atomic_write(path, lambda f: torch.save(state, f))
        return True
    except Exception as e:  # noqa: BLE001 - a failed checkpoint must not end the run
        print(f"warning: could not save checkpoint {path} ({e}); the previous one is kept", file=sys.stderr)
        return False


def load_checkpoint(path: str) -> dict:
    """Read a training checkpoint; its ``config`` comes back as a TrainConfig. Raises ValueError for an unreadable
    file or another format."""
    try:
        ck = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as e:  # noqa: BLE001 - torch raises many kinds for a bad file
        raise ValueError(f"checkpoint {path} is unreadable ({e}); delete it to start over") from e
    if not isinstance(ck, dict) or "version" not in ck:
        raise ValueError(f"{path} is not a neurogf-warp training checkpoint")
    if ck["version"] not in READABLE:
        raise ValueError(f"{path} is a training checkpoint of format {ck['version']}; this version resumes formats "
                         f"{READABLE} only (its stages or network differ). Delete it, or start over with --force")
    ck["config"] = TrainConfig.from_dict(ck["config"])
    ck.setdefault("request", None)
    return ck


def finished(ck: dict) -> bool:
    """True when the checkpoint was written after the last stage."""
    return ck["stage"] >= len(STAGES)


def save_model(net, querier, mesh: Mesh, path: str, info: dict):
    """Write the final model file (``neurogf_warp.save``) from copies of the networks; returns the Model."""
    from neurogf_warp.model.files import save
    from neurogf_warp.model.model import Model

    net = copy.deepcopy(net).cpu().eval()
    model = Model(net=net, querier=copy.deepcopy(querier).cpu().eval(), mesh=mesh, center=mesh.center,
                  scale=mesh.scale, config=info, landmarks=mesh_landmarks(net, mesh))
    save(model, path)
    return model


def mesh_landmarks(net, mesh: Mesh):
    """A landmark network's table at the mesh's vertices (file numbering), taken from the rows it trained with;
    None for other networks. Every used vertex must have its exact row there (ground truth on the mesh itself)."""
    if not net.landmarks:
        return None
    x = mesh.normalize(mesh.vertices).astype(np.float32)
    used = np.zeros(mesh.n_input, bool)
    used[mesh.input_to_internal >= 0] = True
    rows, hit = net.landmark_table.match(torch.from_numpy(x))
    hit = hit.numpy()
    if not hit[used].all():
        raise ValueError(f"{int((~hit[used]).sum())} mesh vertices have no landmark row: a network with landmarks "
                         "needs its ground truth on the mesh itself, not on a proxy of it")
    out = net.landmark_table.table[rows].numpy().copy()
    out[~used] = np.nan
    return out
