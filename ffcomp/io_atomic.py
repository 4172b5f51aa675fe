"""Safe file output: atomic writes, registered temporary files, early output-path checks.

* :func:`atomic_open` writes a temporary file beside the target, fsyncs it, then ``os.replace``\\ s it:
  on any failure the target is untouched and the temporary file is removed.
* :func:`make_temp` creates a temporary file named ``.ffcomp-<kind>-<host>-<pid>-<random><suffix>``
  and registers it; :func:`cleanup_temps` (run at exit and by the CLI's signal handlers) removes
  every registered file, and :func:`sweep_stale` removes the files of runs that died without
  cleaning up (SIGKILL, power loss): their PID is no longer running on this host.
* :func:`check_output_path` finds what would make writing an output fail (missing directory,
  read-only file system, no permission, a directory or device named as the file) before any work.
* :func:`request_stop` records a stop signal (the CLI's handlers call it); :func:`commit` replaces a
  target with its finished temporary file only if none has arrived.
"""

from __future__ import annotations

import atexit
import contextlib
import os
import re
import secrets
import socket
import stat
import zlib
from pathlib import Path
from typing import IO, Iterator

from .errors import Interrupted, OutputError

__all__ = ["atomic_open", "atomic_write_text", "make_temp", "release_temp", "keep_temp", "cleanup_temps",
           "sweep_stale", "check_output_path", "commit", "request_stop", "stop_requested", "TEMP_PREFIX"]

#: every temporary file ffcomp creates starts with this
TEMP_PREFIX = ".ffcomp-"
_HOST = f"{zlib.crc32(socket.gethostname().encode()):08x}"
_NAME = re.compile(r"^\.ffcomp-[a-z]+-(?P<host>[0-9a-f]{8})-(?P<pid>\d+)-[0-9a-f]+")
_LIVE: set[str] = set()
_STOP: list[int] = []  # the stop signal that arrived, if one did (request_stop)


def request_stop(signum: int | None) -> None:
    """Record that a stop signal ``signum`` arrived (None: forget it, for a new run in the same
    process).  The CLI's handler raises :class:`~ffcomp.errors.Interrupted` as well, but Python
    swallows an exception raised while it runs a destructor or a garbage-collector callback
    ("Exception ignored in ..."): the run would go on and exit 0 after a SIGTERM, and a slicer
    would ship the file.  :func:`commit` and the CLI's exit check this record."""
    _STOP.clear()
    if signum is not None:
        _STOP.append(int(signum))


def stop_requested() -> int | None:
    """The stop signal recorded by :func:`request_stop`, or None."""
    return _STOP[0] if _STOP else None


def commit(tmp: str | os.PathLike, path: str | os.PathLike) -> None:
    """``os.replace(tmp, path)``, unless a stop signal has arrived: then
    :class:`~ffcomp.errors.Interrupted` (the target is left as it was)."""
    if _STOP:
        raise Interrupted(_STOP[0])
    os.replace(tmp, path)


def make_temp(directory: str | os.PathLike, kind: str, suffix: str = "") -> tuple[int, str]:
    """Create and register a temporary file in ``directory``; returns ``(fd, path)`` like ``mkstemp``.

    The name carries this host and process id so that :func:`sweep_stale` of a later run can tell a
    leftover of a dead run from a file a running ffcomp is still writing.
    """
    if not kind.isalpha() or not kind.islower():
        raise ValueError(f"temp kind must be lower-case letters, got {kind!r}")
    directory = os.fspath(directory) or "."
    for _ in range(100):
        path = os.path.join(directory, f"{TEMP_PREFIX}{kind}-{_HOST}-{os.getpid()}-{secrets.token_hex(4)}{suffix}")
        # registered before it exists: a stop signal between the creation and the registration
        # would otherwise leave the file behind (its handler runs between any two bytecodes)
        _LIVE.add(path)
        try:
            fd = os.open(path, os.O_RDWR | os.O_CREAT | os.O_EXCL, 0o600)
        except FileExistsError:
            _LIVE.discard(path)  # someone else's file: never ours to remove
            continue
        except OSError as e:
            _LIVE.discard(path)
            raise OutputError(directory, e, "cannot create a temporary file in the output directory") from e
        return fd, path
    raise OutputError(directory, None, "cannot find a free temporary file name")


def release_temp(path: str | None) -> None:
    """Remove a registered temporary file (if it still exists) and forget it."""
    if not path:
        return
    with contextlib.suppress(FileNotFoundError):
        os.unlink(path)
    _LIVE.discard(path)


def keep_temp(path: str) -> None:
    """Forget a temporary file that has been renamed into place (it is no longer ours to remove)."""
    _LIVE.discard(path)


def cleanup_temps() -> int:
    """Remove every registered temporary file; returns how many were removed.  Safe to call twice."""
    n = 0
    for p in list(_LIVE):
        try:
            os.unlink(p)
            n += 1
        except OSError:
            pass
        _LIVE.discard(p)
    return n


atexit.register(cleanup_temps)


def _pid_alive(pid: int) -> bool:
    if pid == os.getpid():
        return True
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:  # exists, owned by someone else
        return True
    return True


def sweep_stale(directory: str | os.PathLike) -> list[str]:
    """Remove ``.ffcomp-*`` temporary files in ``directory`` left by dead ffcomp runs of this host.

    Only files whose name carries this host's tag and the PID of a process that no longer runs are
    removed (a run still going, here or on another host sharing the directory, is left alone).
    Returns the removed names.
    """
    removed = []
    try:
        names = os.listdir(directory or ".")
    except OSError:
        return removed
    for name in names:
        m = _NAME.match(name)
        if not m or m["host"] != _HOST or _pid_alive(int(m["pid"])):
            continue
        with contextlib.suppress(OSError):
            os.unlink(os.path.join(directory, name))
            removed.append(name)
    return removed


def check_output_path(path: str | os.PathLike, what: str = "output") -> str:
    """Check, before any work, that ``path`` can be written atomically; returns the path to write.

    A symbolic link is followed (its target is replaced, the link kept).  Raises
    :class:`~ffcomp.errors.OutputError` naming the path and the reason when the directory is missing
    or not a directory, the path names a directory or something other than a regular file, or the
    directory cannot take a new file (permission denied, read-only file system): that is probed by
    creating and removing a temporary file there, which is what the real write will do.
    """
    p = os.fspath(path)
    if p == "":
        raise OutputError(p, None, f"empty {what} file name")
    if os.path.islink(p):
        p = os.path.realpath(p)
    parent = os.path.dirname(os.path.abspath(p))
    if os.path.isdir(p):
        raise OutputError(p, None, f"the {what} path is a directory: give a file name")
    if os.path.exists(p) and not stat.S_ISREG(os.stat(p).st_mode):
        raise OutputError(p, None, f"the {what} path exists and is not a regular file (a device or pipe "
                          "would be replaced): write to a regular file, or '-' for stdout")
    if not os.path.exists(parent):
        raise OutputError(p, None, f"the {what} directory {parent} does not exist")
    if not os.path.isdir(parent):
        raise OutputError(p, None, f"{parent} is not a directory")
    try:
        fd, probe = make_temp(parent, "probe")
    except OutputError as e:
        raise OutputError(p, e.errno, f"cannot write the {what} in {parent}") from e
    os.close(fd)
    release_temp(probe)
    return p


@contextlib.contextmanager
def atomic_open(path: str | Path, mode: str = "w", encoding: str | None = "utf-8") -> Iterator[IO]:
    """Open a temporary file next to ``path``; on clean exit it replaces ``path`` atomically."""
    path = Path(check_output_path(path))
    binary = "b" in mode
    fd, tmp = make_temp(path.parent, "write", ".tmp")
    try:
        with os.fdopen(fd, mode, encoding=None if binary else encoding, newline=None if binary else "") as f:
            yield f
            f.flush()
            os.fsync(f.fileno())
        try:
            st = os.stat(path)
            os.chmod(tmp, st.st_mode & 0o7777)
        except FileNotFoundError:
            os.chmod(tmp, 0o644)
        commit(tmp, path)
        keep_temp(tmp)
    except BaseException:
        release_temp(tmp)
        raise


def atomic_write_text(path: str | Path, text: str) -> None:
    with atomic_open(path, "w") as f:
        f.write(text)
