"""Atomic file writes: a failed or killed write leaves any previous file as it was.

The data goes to a temporary file beside the target, ``.tmp-<pid>-<random>-<name>``, which is flushed,
synced and renamed over the target. A writer killed outright (SIGKILL, power loss) leaves its temporary
file behind; the next write to the same target removes such leftovers when they are stale: their writer
process is gone, or they have not been written to for ``STALE_SECONDS``. Only files named after this target
in our pattern are touched, never the target itself or anything else in the folder. (On a folder shared
between machines, a writer on another machine counts as gone: its write then fails, and its target, as
always, keeps its previous content.)
"""
from __future__ import annotations

import errno
import os
import re
import tempfile
import time

__all__ = ["atomic_write", "atomic_write_bytes", "remove_stale_temp_files", "DiskFullError"]

TEMP_PREFIX = ".tmp-"
# A temporary file whose writer is still alive (or whose pid may have been reused) counts as stale after
# this long without a write; temp files of older versions, which carry no pid, after OLD_STYLE_SECONDS.
STALE_SECONDS = 3600.0
OLD_STYLE_SECONDS = 60.0


def atomic_write(path, write) -> str:
    """Call ``write(binary_file)`` on a temporary file beside ``path``, then move it into place.

    Parameters
    ----------
    path : str or os.PathLike
        The target. Its folder must exist. An existing target keeps its permissions; a new one gets the
        umask's (not ``mkstemp``'s 0600).
    write : callable
        ``write(f)`` writes the whole content to the binary file object ``f``.

    Returns
    -------
    str, the path written.

    Raises
    ------
    FileNotFoundError, IsADirectoryError
        The folder does not exist, or ``path`` is a folder.
    DiskFullError (an OSError)
        The disk or quota is full; the target keeps its previous content.
    """
    path = os.fspath(path)
    folder = os.path.dirname(os.path.abspath(path))
    if not os.path.isdir(folder):
        raise FileNotFoundError(f"cannot write {path}: folder {folder} does not exist")
    if os.path.isdir(path):
        raise IsADirectoryError(f"cannot write {path}: it is a folder; give a file name inside it or elsewhere")
    remove_stale_temp_files(path)
    fd, tmp = tempfile.mkstemp(prefix=f"{TEMP_PREFIX}{os.getpid()}-", suffix="-" + os.path.basename(path), dir=folder)
    try:
        os.chmod(tmp, _mode_for(path))  # mkstemp makes 0600; a saved file should look like any other
        with os.fdopen(fd, "wb") as f:
            write(f)
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, path)
    except BaseException as e:
        try:
            os.unlink(tmp)
        except OSError:
            pass
        if isinstance(e, OSError) and _disk_full(e):
            raise DiskFullError(errno.ENOSPC, f"cannot write {path}: no space left on the device (the file is "
                                f"{'unchanged' if os.path.exists(path) else 'not written'}); free some space or "
                                "write to another disk") from e
        raise
    return path


class DiskFullError(OSError):
    """A write ran out of disk space (or quota); the target was left as it was."""


def _disk_full(e: OSError) -> bool:
    """An out-of-space error: ENOSPC/EDQUOT, or numpy's short-write message, which carries no errno."""
    if e.errno in (errno.ENOSPC, getattr(errno, "EDQUOT", errno.ENOSPC)):
        return True
    return bool(re.search(r"\d+ requested and \d+ written", str(e)))


def atomic_write_bytes(path, data: bytes) -> str:
    """``atomic_write`` of a bytes object."""
    return atomic_write(path, lambda f: f.write(data))


def remove_stale_temp_files(path) -> list[str]:
    """Remove leftover temporary files of killed atomic writes to ``path``; returns the paths removed.

    A temporary file is stale when the process that wrote it no longer exists, or when it has not been
    modified for ``STALE_SECONDS`` (``OLD_STYLE_SECONDS`` for names without a pid). Errors while cleaning
    (a file removed meanwhile, no permission) are ignored: cleaning never makes a write fail.
    """
    path = os.fspath(path)
    folder = os.path.dirname(os.path.abspath(path))
    name = re.escape(os.path.basename(path))
    # mkstemp's random part is 8 characters of [a-z0-9_]
    ours = re.compile(rf"^{re.escape(TEMP_PREFIX)}(?:(\d+)-)?[a-z0-9_]{{8}}-{name}$")
    removed = []
    try:
        entries = os.listdir(folder)
    except OSError:
        return removed
    now = time.time()
    for entry in entries:
        m = ours.match(entry)
        if m is None:
            continue
        full = os.path.join(folder, entry)
        try:
            age = now - os.lstat(full).st_mtime
        except OSError:
            continue
        pid = int(m.group(1)) if m.group(1) else None
        if pid is None:
            stale = age > OLD_STYLE_SECONDS
        else:
            stale = age > STALE_SECONDS or (pid != os.getpid() and not _alive(pid))
        if stale:
            try:
                os.unlink(full)
                removed.append(full)
            except OSError:
                pass
    return removed


def _alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except OSError as e:
        return e.errno == errno.EPERM  # exists, owned by someone else
    return True


def _mode_for(path: str) -> int:
    """The replaced file's permissions, or what the umask gives a new file."""
    try:
        return os.stat(path).st_mode & 0o777
    except FileNotFoundError:
        umask = os.umask(0)
        os.umask(umask)
        return 0o666 & ~umask
