"""Checks that a command's output can be written, made before any work so a run never fails at its end."""

from __future__ import annotations

import errno
import os
import tempfile
from pathlib import Path

from ..fileio import existing_ancestor

__all__ = ["check_output_folder", "check_output_file"]


def _probe(folder: Path, output: Path) -> None:
    """Create and delete a file in ``folder``: the OS's own verdict (read-only, no permission, not a folder),
    reported against ``output``."""
    try:
        fd, name = tempfile.mkstemp(prefix=".parksim-probe-", dir=folder)
    except OSError as e:
        raise OSError(e.errno, f"{e.strerror} (cannot write in {folder})", str(output)) from None
    os.close(fd)
    os.unlink(name)


def check_output_folder(path: Path, overwrite: bool | None = None) -> None:
    """Fail unless ``path`` can become (or, with ``overwrite`` None, receive files as) an output folder.

    ``overwrite`` False: an existing ``path`` is an error naming --overwrite; True: it will be replaced;
    None: files are added to it. A file at ``path`` is always an error.
    """
    if path.exists() and not path.is_dir():
        raise NotADirectoryError(errno.ENOTDIR, "exists and is not a folder", str(path))
    if path.exists() and overwrite is False:
        raise FileExistsError(errno.EEXIST, "already exists; pass --overwrite to replace it", str(path))
    _probe(existing_ancestor(path), path)
    if path.exists() and overwrite is None:
        _probe(path, path)


def check_output_file(path: Path) -> None:
    """Fail unless a file can be written at ``path`` (not a folder, its folder writable)."""
    if path.is_dir():
        raise IsADirectoryError(errno.EISDIR, "is a folder, not a file", str(path))
    _probe(existing_ancestor(path), path)
