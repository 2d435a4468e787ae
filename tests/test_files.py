"""Atomic writes: a save killed with SIGKILL leaves the old file, and the next save removes its leftovers."""
import os
import signal
import subprocess
import sys
import time

import pytest

from neurogf_warp.common import files

WRITER = """
import sys, time
from neurogf_warp.common.files import atomic_write

def write(f):
    f.write(b"half of the new content")
    f.flush()
    print("writing", flush=True)
    time.sleep(600)

atomic_write(sys.argv[1], write)
"""


def temp_files(folder):
    return sorted(n for n in os.listdir(folder) if n.startswith(".tmp-"))


@pytest.mark.skipif(not hasattr(signal, "SIGKILL"), reason="needs SIGKILL")
def test_killed_save_keeps_old_file_and_next_save_cleans_up(tmp_path):
    target = tmp_path / "model.ngf"
    target.write_bytes(b"old content")
    proc = subprocess.Popen([sys.executable, "-c", WRITER, str(target)], stdout=subprocess.PIPE,
                            cwd=os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
    try:
        assert proc.stdout.readline().strip() == b"writing"
    finally:
        proc.send_signal(signal.SIGKILL)
        proc.wait()
    assert target.read_bytes() == b"old content"
    left = temp_files(tmp_path)
    assert len(left) == 1 and left[0].startswith(f".tmp-{proc.pid}-") and left[0].endswith("-model.ngf")
    files.atomic_write_bytes(target, b"new content")
    assert target.read_bytes() == b"new content"
    assert temp_files(tmp_path) == []


def test_only_our_stale_temp_files_are_removed(tmp_path):
    target = tmp_path / "m.ngf"
    dead = subprocess.Popen([sys.executable, "-c", "pass"])
    dead.wait()
    parent = os.getppid()  # alive, and not this process
    names = {
        f".tmp-{dead.pid}-abcd_123-m.ngf": True,           # writer gone
        f".tmp-{parent}-abcd_124-m.ngf": False,            # writer alive, recent
        f".tmp-{parent}-abcd_125-m.ngf.old": False,        # another target
        f".tmp-{dead.pid}-abcd_126-other.ngf": False,      # another target
        ".tmp-abcd_127-m.ngf": False,                      # older versions' name, recent
        ".tmp-abcd_128-m.ngf": True,                       # older versions' name, a few minutes old
        f".tmp-{parent}-abcd_129-m.ngf": True,             # writer pid alive but silent for hours
        f".tmp-{dead.pid}-too_long_x-m.ngf": False,        # not mkstemp's pattern
        "m.ngf.bak": False,
    }
    now = time.time()
    for n in names:
        (tmp_path / n).write_bytes(b"x")
    os.utime(tmp_path / ".tmp-abcd_128-m.ngf", (now - 5 * files.OLD_STYLE_SECONDS,) * 2)
    os.utime(tmp_path / f".tmp-{parent}-abcd_129-m.ngf", (now - 2 * files.STALE_SECONDS,) * 2)
    files.atomic_write_bytes(target, b"data")
    kept = set(os.listdir(tmp_path))
    for n, removed in names.items():
        assert (n not in kept) == removed, n
    assert target.read_bytes() == b"data"
    # our own pid is a writer in progress (another thread), not a leftover
    mine = tmp_path / f".tmp-{os.getpid()}-abcd_130-m.ngf"
    mine.write_bytes(b"x")
    files.atomic_write_bytes(target, b"data")
    assert mine.exists()


def test_missing_folder_is_a_clear_error(tmp_path):
    with pytest.raises(FileNotFoundError, match="does not exist"):
        files.atomic_write_bytes(tmp_path / "no" / "m.ngf", b"x")


def test_a_folder_as_target_is_named_not_a_temp_file(tmp_path):
    (tmp_path / "m.ngf").mkdir()
    with pytest.raises(IsADirectoryError, match=r"cannot write .*m\.ngf: it is a folder; give a file name") as e:
        files.atomic_write_bytes(tmp_path / "m.ngf", b"x")
    assert ".tmp-" not in str(e.value)
    assert temp_files(tmp_path) == []


@pytest.mark.parametrize("failure", [
    lambda: OSError(28, "No space left on device"),         # ENOSPC from write, flush or fsync
    lambda: OSError("48485 requested and 992 written"),    # numpy's short write: no errno
])
@pytest.mark.parametrize("existing", [True, False])
def test_a_full_disk_says_so_and_keeps_the_old_file(tmp_path, failure, existing):
    target = tmp_path / "d.npy"
    if existing:
        target.write_bytes(b"old")

    def write(f):
        f.write(b"partial")
        raise failure()

    with pytest.raises(OSError, match="no space left on the device") as e:
        files.atomic_write(target, write)
    assert isinstance(e.value, files.DiskFullError)
    assert ("unchanged" if existing else "not written") in str(e.value)
    assert target.exists() == existing and (not existing or target.read_bytes() == b"old")
    assert temp_files(tmp_path) == []
    # any other OSError passes through unchanged
    with pytest.raises(OSError, match="^boom$"):
        files.atomic_write(target, lambda f: (_ for _ in ()).throw(OSError("boom")))
