"""A run's folder, without torch: its paths, its lock, and whether a call already finished it.

A run that writes ``spot.ngf`` keeps its work files in one folder beside it, ``spot.train/``: the checkpoint
(``checkpoint.pt``), the cached dataset (``dataset.npz``) and the training log (``log.json``). This module imports
neither torch nor Warp, so that a repeated ``train`` can say "already trained" before loading them
(``already_trained``); ``neurogf_warp.training`` loads its other modules on first use for the same reason.
"""
from __future__ import annotations

import glob
import json
import os
import tempfile
import time
from dataclasses import dataclass

from neurogf_warp.common.checks import InputError

__all__ = ["RunFiles", "RunLock", "call_key", "finished_log", "already_trained"]


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


def call_key(mesh, config, device, dataset, budget_seconds, settings) -> dict | None:
    """What identifies a ``train`` call cheaply, without torch or reading the mesh: the mesh file's path, size and
    modification time, and the arguments as given; None when an argument is an object (a repeat then takes the
    full path, which loads the mesh)."""
    if not isinstance(mesh, (str, os.PathLike)) or not os.path.isfile(mesh):
        return None
    if dataset is not None and not isinstance(dataset, (str, os.PathLike)):
        return None
    if config is not None and not isinstance(config, str) and not hasattr(config, "to_dict"):
        return None
    if device is not None and not isinstance(device, str):
        return None
    st = os.stat(mesh)
    key = {"mesh": [os.path.abspath(mesh), st.st_size, st.st_mtime_ns],
           "config": config if config is None or isinstance(config, str) else config.to_dict(), "device": device,
           "dataset": None if dataset is None else os.path.abspath(dataset), "budget_seconds": budget_seconds,
           "settings": settings}
    try:
        return json.loads(json.dumps(key))
    except (TypeError, ValueError, RecursionError):  # a setting that is not plain data (or nested too deep)
        return None


def finished_log(files: RunFiles, key: dict | None) -> dict | None:
    """The run's log when it says that the call ``key`` finished the run and the model file and checkpoint are
    still there; else None."""
    if key is None or not (os.path.isfile(files.model) and os.path.isfile(files.checkpoint)
                           and os.path.isfile(files.log)):
        return None
    try:
        with open(files.log) as f:
            log = json.load(f)
    except (OSError, ValueError):
        return None
    return log if isinstance(log, dict) and log.get("finished") and log.get("call") == key else None


def already_trained(mesh, out, *, config=None, device=None, dataset=None, budget_seconds=None,
                    **settings) -> dict | None:
    """For the command line, before it loads torch: the finished run's quality verdict (``validation_mre``,
    ``heat_mre``, ``worse_than_heat``, ``quality_warning``; {} for runs that predate it) when ``train`` with these
    arguments would answer "already trained" from ``out``, else None (then call ``train``, which also checks the
    rest). Arguments as ``train`` takes them."""
    log = finished_log(RunFiles.for_model(out), call_key(mesh, config, device, dataset, budget_seconds, settings))
    return None if log is None else dict(log.get("quality") or {})
