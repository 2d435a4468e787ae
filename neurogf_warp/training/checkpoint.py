"""Where a run keeps its files, and its checkpoints: written atomically, read back with their format checked.

A run that writes ``spot.ngf`` keeps its work files in one folder beside it, ``spot.train/``: the checkpoint
(``checkpoint.pt``), the cached dataset (``dataset.npz``) and the training log (``log.json``).
"""
from __future__ import annotations

import copy
import glob
import os
import sys
import tempfile
import time
from dataclasses import dataclass

import torch

from neurogf_warp.common.checks import InputError
from neurogf_warp.mesh.mesh import Mesh
from neurogf_warp.training.config import STAGES, TrainConfig

__all__ = ["RunFiles", "RunLock", "save_checkpoint", "load_checkpoint", "save_model", "CKPT_VERSION", "finished"]

# 2: the refine_dist stage; 3: network options in the config; 4: nested config and the run's request
CKPT_VERSION = 4
READABLE = (3, 4)


@dataclass(frozen=True)
class RunFiles:
    """The files of one training run: the model and, in ``folder``, its checkpoint, dataset and log."""

    model: str
    folder: str

    @classmethod
    def for_model(cls, model_path) -> "RunFiles":
        model = os.path.abspath(os.fspath(model_path))
        return cls(model, os.path.splitext(model)[0] + ".train")

    @property
    def checkpoint(self) -> str:
        return os.path.join(self.folder, "checkpoint.pt")

    @property
    def dataset(self) -> str:
        return os.path.join(self.folder, "dataset.npz")

    @property
    def log(self) -> str:
        return os.path.join(self.folder, "log.json")

    def check_writable(self) -> None:
        """Fail before any work if the model or the run folder could not be written."""
        out = self.model
        if os.path.isdir(out):
            raise IsADirectoryError(f"output path {out} is a directory; give a file name such as model.ngf")
        parent = os.path.dirname(out)
        if not os.path.isdir(parent):
            raise FileNotFoundError(f"cannot write {out}: folder {parent} does not exist")
        _probe(parent)
        if os.path.exists(out) and not os.access(out, os.W_OK):
            raise PermissionError(f"output file {out} exists and is not writable")
        if os.path.exists(self.folder) and not os.path.isdir(self.folder):
            raise FileExistsError(f"{self.folder} exists and is not a folder; move it away (the run keeps its "
                                  "checkpoint, dataset and log there)")
        if os.path.isdir(self.folder):
            _probe(self.folder)

    def make_folder(self) -> None:
        os.makedirs(self.folder, exist_ok=True)

    def lock(self) -> "RunLock":
        """Take the run folder for this process (creating it), or raise InputError when another process holds it.

        An exclusive ``flock`` on the folder itself (no lock file): the kernel drops it when the holder exits or
        is killed, so a dead run never blocks the next one. Release with ``.release()`` or ``with``."""
        self.make_folder()
        return RunLock(self.folder)

    def clean_stale_temporaries(self, min_age_s: float = 60.0) -> int:
        """Remove temporary files that a killed save left in the run folder or beside the model (untouched for
        ``min_age_s`` seconds, so a save in progress is never hit); returns how many."""
        n = 0
        places = [(self.folder, name) for name in ("checkpoint.pt", "dataset.npz", "log.json")]
        places.append(os.path.split(self.model))
        now = time.time()
        for folder, name in places:
            for tmp in glob.glob(os.path.join(glob.escape(folder), f".tmp-*-{glob.escape(name)}")):
                try:
                    if now - os.path.getmtime(tmp) > min_age_s:
                        os.unlink(tmp)
                        n += 1
                except OSError:
                    pass
        return n


class RunLock:
    """An exclusive advisory lock (``fcntl.flock``) on a folder, held until ``release()`` or process exit."""

    def __init__(self, folder: str):
        import fcntl

        self.folder, self._fd = folder, os.open(folder, os.O_RDONLY)
        try:
            fcntl.flock(self._fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            os.close(self._fd)
            self._fd = None
            raise InputError(f"another training run is using {folder} (two runs cannot write one model): wait for "
                             "it to finish, or write the model to another file") from None

    def release(self) -> None:
        if self._fd is not None:
            os.close(self._fd)  # closing the descriptor drops the flock
            self._fd = None

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.release()


def _probe(folder: str) -> None:
    try:
        fd, tmp = tempfile.mkstemp(prefix=".write-test-", dir=folder)
        os.close(fd)
        os.unlink(tmp)
    except OSError as e:
        raise PermissionError(f"cannot write to {folder}: {e.strerror or e}") from e


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

    model = Model(net=copy.deepcopy(net).cpu().eval(), querier=copy.deepcopy(querier).cpu().eval(), mesh=mesh,
                  center=mesh.center, scale=mesh.scale, config=info)
    save(model, path)
    return model
