"""Atomic file writes: write a temporary file beside the destination, then rename over it, so a
reader never sees a half-written output and a failure (or an interruption) leaves nothing behind.

Only regular files are ever replaced: an existing symlink, device, FIFO, socket or folder at the
destination is refused with :class:`~trafficweaving.errors.InputError` (renaming over it would
replace the link or the device node itself, not write through it).
"""

from __future__ import annotations

import os
import re
import stat
import uuid
from contextlib import contextmanager
from pathlib import Path
from typing import BinaryIO, Iterator

from .errors import InputError


def check_output_file(path: str | os.PathLike, what: str = "output") -> Path:
    """``path`` as a :class:`Path` if a file may be written there: not empty, not an existing
    symlink or non-regular file, its folder (created on writing if missing) not a file.
    ``what`` names the option or role in the error message."""
    text = os.fspath(path)
    if not text.strip():
        raise InputError(f"{what}: empty path (expected a file path to write)")
    path = Path(text)
    try:
        mode = os.lstat(path).st_mode
    except (FileNotFoundError, NotADirectoryError):
        mode = None
    if mode is not None and stat.S_ISLNK(mode):
        raise InputError(f"{what} {path}: is a symbolic link (expected a regular file path; links are not replaced)")
    if mode is not None and stat.S_ISDIR(mode):
        raise InputError(f"{what} {path}: is a folder (expected a file path to write)")
    if mode is not None and not stat.S_ISREG(mode):
        raise InputError(f"{what} {path}: is a special file (expected a regular file path; devices, FIFOs and "
                         f"sockets are not replaced)")
    _check_parents(path, what)
    return path


def _check_parents(path: Path, what: str) -> None:
    """InputError when the nearest existing folder above ``path`` is a file (nothing could be
    created below it)."""
    for parent in path.parents:
        if parent.exists():
            if not parent.is_dir():
                raise InputError(f"{what} {path}: {parent} is not a folder (expected a path in a folder)")
            break


def check_output_folder(path: str | os.PathLike, what: str = "output folder") -> Path:
    """``path`` as a :class:`Path` if outputs may be written into it: not empty, not an existing
    file (a symlink to a folder is written through), not below a file."""
    text = os.fspath(path)
    if not text.strip():
        raise InputError(f"{what}: empty path (expected a folder)")
    path = Path(text)
    if path.exists() and not path.is_dir():
        raise InputError(f"{what} {path}: is a file (expected a folder)")
    _check_parents(path, what)
    return path


def same_file(a: str | os.PathLike, b: str | os.PathLike) -> bool:
    """Whether paths ``a`` and ``b`` name one file, existing or not: the same path once
    symlinks, ``.`` and ``..`` are resolved, or the same existing file (a hard link)."""
    if os.path.realpath(a) == os.path.realpath(b):
        return True
    try:
        return os.path.samefile(a, b)
    except OSError:  # either does not exist (yet)
        return False


@contextmanager
def atomic_write(path: str | os.PathLike) -> Iterator[BinaryIO]:
    """Open a binary temporary file in ``path``'s folder (created if needed); on a clean exit it
    replaces ``path``, on an exception (including an interruption) it is removed. Permissions
    follow the umask. ``path`` must pass :func:`check_output_file`."""
    path = check_output_file(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.name}.{os.getpid()}.{uuid.uuid4().hex}.tmp")
    try:
        with os.fdopen(os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o666), "wb") as f:
            yield f
        os.replace(tmp, path)
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise


TEMPORARY_NAME = re.compile(r"\.(?P<name>.+)\.(?P<pid>[0-9]+)\.[0-9a-f]{32}\.tmp")
"""The names of :func:`atomic_write`'s temporary files: ``.NAME.PID.HEX.tmp`` beside the
destination ``NAME``, written by process ``PID``."""


def _running(pid: int) -> bool:
    """Whether a process ``pid`` (> 0) exists."""
    try:
        os.kill(pid, 0)
    except (ProcessLookupError, OverflowError):
        return False
    except PermissionError:  # another user's
        pass
    return True


def remove_stale_temporaries(folder: str | os.PathLike, names: re.Pattern) -> list[Path]:
    """Remove the temporary files :func:`atomic_write` left in ``folder`` for destinations whose
    name fully matches ``names`` when its process was killed before it could remove them (e.g.
    SIGKILL): the regular files named :data:`TEMPORARY_NAME` written by a process that is no
    longer running, or by this one (call it before this process writes there). Returns the paths
    removed."""
    folder = Path(folder)
    removed = []
    for path in sorted(folder.iterdir()) if folder.is_dir() else []:
        match = TEMPORARY_NAME.fullmatch(path.name)
        if not match or not names.fullmatch(match["name"]) or path.is_symlink() or not path.is_file():
            continue
        pid = int(match["pid"])
        if pid == os.getpid() or pid <= 0 or not _running(pid):
            path.unlink(missing_ok=True)
            removed.append(path)
    return removed
