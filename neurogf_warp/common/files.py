"""Every file the library and the command line write goes through ``atomic_write``, under one rule.

The rule for a target path:

- a new path, or an existing **regular file**, which is replaced atomically: the data goes to a temporary
  file beside the target, ``.tmp-<pid>-<random>-<name>``, which is flushed, synced and renamed over it, so a
  failed or killed write leaves the previous file as it was;
- a **symbolic link** is followed: its final target is written (atomically, by the same rule) and the link
  stays a link;
- anything else that exists (a folder, a device such as ``/dev/null``, a FIFO, a socket) is refused: such a
  path is not a file we could replace without destroying something;
- an **input** is never a target: a path that is the same file (after links, or a hard link to it) as an
  input of the same call or command is refused, whatever ``force`` options say. Inputs are those passed as
  ``inputs=`` and, inside ``input_guard()``, every file the readers note with ``note_input`` (meshes, models,
  references, datasets read so far).

A writer killed outright (SIGKILL, power loss) leaves its temporary file behind; the next write to the same
target removes such leftovers when they are stale: their writer process is gone, or they have not been
written to for ``STALE_SECONDS``. Only files named after this target in our pattern are touched, never the
target itself or anything else in the folder. (On a folder shared between machines, a writer on another
machine counts as gone: its write then fails, and its target, as always, keeps its previous content.)
"""
from __future__ import annotations

import contextlib
import errno
import os
import re
import stat
import tempfile
import threading
import time

from neurogf_warp.common.checks import InputError

__all__ = ["atomic_write", "atomic_write_bytes", "output_target", "input_guard", "note_input", "check_input_file",
           "remove_stale_temp_files", "DiskFullError"]

TEMP_PREFIX = ".tmp-"
# A temporary file whose writer is still alive (or whose pid may have been reused) counts as stale after
# this long without a write; temp files of older versions, which carry no pid, after OLD_STYLE_SECONDS.
STALE_SECONDS = 3600.0
OLD_STYLE_SECONDS = 60.0

_guard_lock = threading.Lock()
_guards: list[list[str]] = []  # one list of input paths per open input_guard(), innermost last


@contextlib.contextmanager
def input_guard():
    """Within this block, no write may replace a file that a reader noted as an input (``note_input``).

    The command line opens one per command, ``train`` one per call: an output path that names the mesh, the
    model or any other file the command read is refused instead of destroying it.
    """
    noted: list[str] = []
    with _guard_lock:
        _guards.append(noted)
    try:
        yield noted
    finally:
        with _guard_lock:
            _guards.remove(noted)


def note_input(path) -> None:
    """Record ``path`` as an input of every open ``input_guard()`` (nothing happens outside one)."""
    try:
        path = os.fspath(path)
    except TypeError:
        return
    with _guard_lock:
        for noted in _guards:
            noted.append(path)


def _kind(mode: int) -> str:
    if stat.S_ISDIR(mode):
        return "a folder"
    if stat.S_ISCHR(mode) or stat.S_ISBLK(mode):
        return "a device"
    if stat.S_ISFIFO(mode):
        return "a FIFO (named pipe)"
    if stat.S_ISSOCK(mode):
        return "a socket"
    return "a special file"


def _same_file(a: str, b) -> bool:
    try:
        b = os.fspath(b)
    except TypeError:  # an in-memory input (arrays, a Mesh): no file to protect
        return False
    try:
        return os.path.samefile(a, b)
    except (OSError, ValueError):
        return os.path.realpath(a) == os.path.realpath(b)


def output_target(path, inputs=(), what: str = "output") -> str:
    """Check ``path`` against the writing rule (module docstring) and return the file to write.

    Parameters
    ----------
    path : str or os.PathLike
        The output path as given.
    inputs : iterable of str, os.PathLike or other objects
        Inputs of the same call; paths among them may not be the target (other objects are ignored).
    what : str
        What is written, for messages ("model file", "output").

    Returns
    -------
    str
        The path to write: ``path`` itself, or for a symbolic link the file it finally points to.

    Raises
    ------
    IsADirectoryError
        ``path`` is a folder.
    InputError (a ValueError)
        ``path`` is a device, FIFO, socket or other non-regular file, or the same file as an input.
    """
    if not isinstance(path, (str, bytes, os.PathLike)):
        raise InputError(f"the {what} path must be a file name (str or os.PathLike), got "
                         f"{'None' if path is None else type(path).__name__}")
    path = os.fspath(path)
    if isinstance(path, bytes):
        path = os.fsdecode(path)
    if path == "":
        raise InputError(f"the {what} path is empty: pass a file name")
    target = os.path.realpath(path) if os.path.islink(path) else path
    try:
        mode = os.stat(target).st_mode
    except FileNotFoundError:
        mode = None
    except OSError as e:
        raise InputError(f"cannot write {what} {path}: {e.strerror or e}") from e
    if mode is not None and stat.S_ISDIR(mode):
        raise IsADirectoryError(f"cannot write {what} {path}: it is a folder; give a file name inside it or elsewhere")
    if mode is not None and not stat.S_ISREG(mode):
        raise InputError(f"cannot write {what} {path}: it is {_kind(mode)}, not a regular file, and would be "
                         "replaced; pass a regular file path")
    if mode is not None:
        with _guard_lock:
            noted = [p for g in _guards for p in g]
        for inp in list(inputs) + noted:
            if _same_file(target, inp):
                raise InputError(f"cannot write {what} {path}: it is the input file {os.fspath(inp)}, which the write "
                                 "would destroy; choose another output path")
    return target


def atomic_write(path, write, inputs=(), what: str = "output") -> str:
    """Call ``write(binary_file)`` on a temporary file beside the target, then move it into place.

    Parameters
    ----------
    path : str or os.PathLike
        The target, checked by ``output_target`` (regular files only, links followed, inputs refused). Its
        folder must exist. An existing target keeps its permissions; a new one gets the umask's (not
        ``mkstemp``'s 0600).
    write : callable
        ``write(f)`` writes the whole content to the binary file object ``f``.
    inputs : iterable, optional
        Inputs of the same call, which may not be the target (see ``output_target``).
    what : str
        What is written, for messages.

    Returns
    -------
    str, the path written (as given).

    Raises
    ------
    FileNotFoundError, IsADirectoryError
        The folder does not exist, or ``path`` is a folder.
    InputError (a ValueError)
        ``path`` is not a regular file, or it is an input (see ``output_target``).
    DiskFullError (an OSError)
        The disk or quota is full; the target keeps its previous content.
    """
    given = os.fspath(path)
    path = output_target(given, inputs, what)
    folder = os.path.dirname(os.path.abspath(path))
    if not os.path.isdir(folder):
        raise FileNotFoundError(f"cannot write {given}: folder {folder} does not exist")
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
    return given


class DiskFullError(OSError):
    """A write ran out of disk space (or quota); the target was left as it was."""


def _disk_full(e: OSError) -> bool:
    """An out-of-space error: ENOSPC/EDQUOT, or numpy's short-write message, which carries no errno."""
    if e.errno in (errno.ENOSPC, getattr(errno, "EDQUOT", errno.ENOSPC)):
        return True
    return bool(re.search(r"\d+ requested and \d+ written", str(e)))


def atomic_write_bytes(path, data: bytes, inputs=(), what: str = "output") -> str:
    """``atomic_write`` of a bytes object."""
    return atomic_write(path, lambda f: f.write(data), inputs, what)


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


def check_input_file(path, what: str = "input file", note: bool = True) -> str:
    """``path`` as a str when it names a readable regular file (links followed), noted as an input.

    Parameters
    ----------
    path : str or os.PathLike
    what : str
        What the file is, for messages ("mesh file", "model file").
    note : bool
        ``note_input(path)`` now; readers that note a file only once it has been read pass False (a file that
        failed to load, such as a damaged model that ``train`` writes again, is no input to protect).

    Raises
    ------
    FileNotFoundError
        Nothing exists at ``path`` (or a link points nowhere).
    IsADirectoryError
        ``path`` is a folder.
    InputError (a ValueError)
        ``path`` is a device (``/dev/null``), a FIFO, a socket or another non-regular file: reading it would
        give no file's content, or block.
    PermissionError
        The file is not readable.
    """
    path = os.fspath(path)
    try:
        mode = os.stat(path).st_mode
    except FileNotFoundError:
        raise FileNotFoundError(f"{what} not found: {path}") from None
    except OSError as e:
        raise InputError(f"cannot read {what} {path}: {e.strerror or e}") from None
    if stat.S_ISDIR(mode):
        raise IsADirectoryError(f"{what} {path} is a folder: give the file itself")
    if not stat.S_ISREG(mode):
        raise InputError(f"{what} {path} is not a regular file (it is {_kind(mode)}): give a file on disk")
    if not os.access(path, os.R_OK):
        raise PermissionError(f"{what} is not readable: {path}")
    if note:
        note_input(path)
    return path
