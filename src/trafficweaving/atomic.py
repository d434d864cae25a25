"""Atomic file writes: write a temporary file beside the destination, then rename over it, so a
reader never sees a half-written output and a failure (or an interruption) leaves nothing behind.

Only regular files are ever replaced: an existing symlink, device, FIFO, socket or folder at the
destination is refused with :class:`~trafficweaving.errors.InputError` (renaming over it would
replace the link or the device node itself, not write through it).
"""

from __future__ import annotations

import os
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
    for parent in path.parents:
        if parent.exists():
            if not parent.is_dir():
                raise InputError(f"{what} {path}: {parent} is not a folder (expected a path in a folder)")
            break
    return path


def check_output_folder(path: str | os.PathLike, what: str = "output folder") -> Path:
    """``path`` as a :class:`Path` if outputs may be written into it: not empty, not an existing
    file (a symlink to a folder is written through)."""
    text = os.fspath(path)
    if not text.strip():
        raise InputError(f"{what}: empty path (expected a folder)")
    path = Path(text)
    if path.exists() and not path.is_dir():
        raise InputError(f"{what} {path}: is a file (expected a folder)")
    return path


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
