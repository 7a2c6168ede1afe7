"""Locks on what a stage writes (a run, an edit, an output folder or file).

Two processes never write the same thing: a stage holds an OS file lock (`fcntl.flock`) on a
small hidden lock file while it works, and a second process asking for the same lock is refused
at once with a SineError that names the holder's PID and command. The OS releases the lock when
the holder ends, however it ends (kill -9 included), so a lock never outlives its process and
needs no cleaning. Lock files stay where they are (removing one would race with a process
about to lock it), except in a folder the lock itself created and nothing else was written
into: that folder is removed again, so a stage stopped by a bad input leaves no trace.

    with lock_folder(run.root, f"run {run.root}"):        # RUN/.sine.lock
        ...
    with lock_entry(run.edit(name), f"edit {name}"):     # RUN/edits/.NAME.lock
        ...

Within one process the locks nest: a stage that calls another stage holding the same lock (the
demo, a batch) does not refuse itself. A folder that cannot be written at all (read-only, or
another user's) is not locked: nothing can be written there, so a stage that only finds its
result already done still works, and one that would write fails on its first write with one
readable line (`render.io.write_error`).
"""

from __future__ import annotations

import contextlib
import errno
import fcntl
import os
import sys
from pathlib import Path

from render.errors import SineError

_HELD: dict[str, int] = {}  # lock file -> how many nested holds this process has on it
_UNWRITABLE = (errno.EACCES, errno.EPERM, errno.EROFS)


def folder_lock_path(folder: str | os.PathLike) -> Path:
    """The lock file of a folder a stage writes into: FOLDER/.sine.lock."""
    return Path(folder) / ".sine.lock"


def entry_lock_path(path: str | os.PathLike) -> Path:
    """The lock file of a file or folder that is replaced whole: PARENT/.NAME.lock."""
    path = Path(path)
    return path.parent / f".{path.name}.lock"


def lock_folder(folder: str | os.PathLike, what: str):
    """Holds the lock of `folder` (created if missing); see the module docstring."""
    return hold(folder_lock_path(folder), what)


def lock_entry(path: str | os.PathLike, what: str):
    """Holds the lock of `path`, a file or folder replaced whole (its parent is created)."""
    return hold(entry_lock_path(path), what)


@contextlib.contextmanager
def hold(lock_path: Path, what: str):
    """Holds an exclusive lock on `lock_path` for the block; a SineError at once when another
    process holds it."""
    key = os.path.abspath(lock_path)
    if _HELD.get(key):
        _HELD[key] += 1
        try:
            yield
        finally:
            _HELD[key] -= 1
        return
    lock_path = Path(lock_path)
    created = not lock_path.parent.exists()
    fd = _open(lock_path)
    if fd is None:  # a folder nobody here may write: nothing to protect
        yield
        return
    try:
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            raise SineError(
                f"{what} is busy: {_holder(fd)} is writing it; wait for it to finish (or stop "
                f"it), then run this again"
            ) from None
        os.ftruncate(fd, 0)
        os.pwrite(fd, f"{os.getpid()} {' '.join(_command())}\n".encode(), 0)
        _HELD[key] = 1
        try:
            yield
        finally:
            del _HELD[key]
            if created:
                _remove_if_unused(lock_path)
    finally:
        os.close(fd)  # releases the lock


def _remove_if_unused(lock_path: Path) -> None:
    """Removes the folder made for `lock_path` when the block wrote nothing else into it (a
    stage that stopped on a bad input leaves no trace)."""
    try:
        if [p.name for p in lock_path.parent.iterdir()] == [lock_path.name]:
            lock_path.unlink()
            lock_path.parent.rmdir()
    except OSError:
        pass


def _open(lock_path: Path) -> int | None:
    """An fd of the lock file (created with its folder), None where the folder is read-only."""
    try:
        lock_path.parent.mkdir(parents=True, exist_ok=True)
        return os.open(lock_path, os.O_RDWR | os.O_CREAT, 0o666)
    except OSError as exc:
        if exc.errno in _UNWRITABLE:
            return None
        raise


def _holder(fd: int) -> str:
    """'process PID (`command`)' of the lock's holder, as it wrote itself into the file."""
    text = os.pread(fd, 4096, 0).decode(errors="replace").strip()
    pid, _, command = text.partition(" ")
    if not pid.isdigit():
        return "another process"
    return f"process {pid}" + (f" (`{command}`)" if command else "")


def _command() -> list[str]:
    """This process's command line as the user typed it (`sine edit ...`, not the script path)."""
    argv = list(sys.argv)
    if argv and Path(argv[0]).name in ("sine", "sine_cli.py", "-m"):
        argv[0] = "sine"
    return argv
