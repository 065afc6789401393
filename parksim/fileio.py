"""Atomic file writes: a file appears whole or not at all, so a killed process never leaves half a file."""

from __future__ import annotations

import contextlib
import errno
import json
import os
import re
import shutil
import socket
import time
import uuid
import zlib
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any, NoReturn

__all__ = ["atomic_write", "write_json", "atomic_directory", "atomic_files", "existing_ancestor",
           "remove_stale_temps", "STALE_AGE_S"]

_TEMP_NAME = re.compile(r"\..+\.tmp\d+(\.[^.]*)?")
"""``atomic_write``'s temp names: ``.{name}.tmp{pid}{suffix}``."""

_HOST = f"{zlib.crc32(socket.gethostname().encode()):08x}"
"""This machine in temp folder names: a PID says whether its writer is alive only on the machine that ran it."""

STALE_AGE_S = 24 * 3600
"""A temp folder whose writer cannot be checked (another machine's, or one named before names held a PID) is
stale once untouched this long."""


def atomic_write(path: str | Path, write: Callable[[Path], object]) -> None:
    """Call ``write(tmp)`` on a temp path next to ``path``, then rename: the file appears whole or not at all."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.name}.tmp{os.getpid()}{path.suffix}")
    try:
        write(tmp)
        os.replace(tmp, path)
    except Exception as e:
        _raise_write_error(e, path)
    finally:
        tmp.unlink(missing_ok=True)


def _raise_write_error(error: Exception, path: Path) -> NoReturn:
    """Re-raise a failed write of ``path`` so that it names ``path``: a full disk as ENOSPC (torch's zip writer
    reports one as a RuntimeError, numpy as an OSError without errno), an OSError without a file name with it."""
    has_errno = isinstance(error, OSError) and bool(error.errno)
    if not has_errno and os.statvfs(existing_ancestor(path)).f_bavail == 0:
        raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC), str(path)) from error
    if isinstance(error, OSError) and has_errno and error.filename is None:
        raise OSError(error.errno, error.strerror, str(path)) from error
    raise error


def remove_stale_temps(folder: str | Path) -> list[Path]:
    """Delete the temp files ``atomic_write`` left in ``folder`` when its process was killed; returns them.

    Only for a folder no other process is writing into (a run's folder as the run starts).
    """
    stale = [p for p in Path(folder).glob(".*.tmp*") if _TEMP_NAME.fullmatch(p.name) and p.is_file()]
    for p in stale:
        p.unlink(missing_ok=True)
    return stale


def _temp_tag() -> str:
    """A temp folder's tag, ``{pid}-{host}-{random}``: whoever finds the folder later can tell whether its
    writer still runs."""
    return f"{os.getpid()}-{_HOST}-{uuid.uuid4().hex[:8]}"


def _remove_stale_temp_folders(path: Path) -> None:
    """Delete the ``.{name}.tmp-*`` folders that killed writers of ``path`` left next to it: those whose process
    (on this machine) is gone, and those that cannot be checked once untouched for :data:`STALE_AGE_S`. A folder of
    a writer that still runs (a concurrent import into the same name) stays."""
    name = re.compile(rf"\.{re.escape(path.name)}\.tmp-(?:(\d+)-([0-9a-f]{{8}})-[0-9a-f]{{8}}|[0-9a-f]{{12}})")
    for p in path.parent.iterdir():
        m = name.fullmatch(p.name)
        if m is None or not p.is_dir() or p.is_symlink():
            continue
        stale = False
        if m[1] is not None and m[2] == _HOST:
            stale = not _alive(int(m[1]))
        else:
            with contextlib.suppress(FileNotFoundError):   # another writer's cleanup got there first
                stale = time.time() - p.lstat().st_mtime > STALE_AGE_S
        if stale:
            shutil.rmtree(p, ignore_errors=True)


def _alive(pid: int) -> bool:
    """Whether process ``pid`` runs on this machine."""
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:   # another user's process
        return True
    return True


def write_json(path: str | Path, data: Any) -> None:
    """Atomically write indented JSON."""
    atomic_write(path, lambda p: p.write_text(json.dumps(data, indent=1) + "\n"))


@contextlib.contextmanager
def atomic_directory(path: str | Path, overwrite: bool = True) -> Iterator[Path]:
    """Yield a temp folder next to ``path``; when the block ends it replaces ``path`` whole, and if the block
    fails nothing is left (nor the parents of ``path`` it made, while empty); a killed process leaves only a
    ``.{name}.tmp-*`` folder, never a half-written ``path``, and the next write of ``path`` removes it.

    ``overwrite=False`` refuses an existing ``path`` before anything is made.
    """
    path = Path(path)
    if path.exists() and not overwrite:
        raise FileExistsError(f"{path} already exists (pass overwrite to replace it)")
    made = [p for p in path.absolute().parents if not p.exists()]
    path.parent.mkdir(parents=True, exist_ok=True)
    _remove_stale_temp_folders(path)
    tag = _temp_tag()
    tmp, old = path.with_name(f".{path.name}.tmp-{tag}"), path.with_name(f".{path.name}.old-{tag}")
    tmp.mkdir()   # not tempfile.mkdtemp: its mode 0700 would make the output private to its writer
    try:
        yield tmp
        if path.exists():
            os.replace(path, old)
        os.replace(tmp, path)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        for folder in made:   # deepest first: only the parents this call made, and only while empty
            with contextlib.suppress(OSError):
                folder.rmdir()
        raise
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
        shutil.rmtree(old, ignore_errors=True)


def atomic_files(folder: str | Path, write: Callable[[Path], object]) -> None:
    """Fill a temp folder with ``write(tmp)``, then move what it made into ``folder`` (made if missing): a failed
    ``write`` creates nothing, and no file in ``folder`` is ever half-written.

    Unlike :func:`atomic_directory`, other files already in ``folder`` stay (an output folder may hold other
    work); an entry of the same name is replaced, a subfolder as a whole.
    """
    folder = Path(folder)
    _remove_stale_temp_folders(existing_ancestor(folder) / folder.name)
    tmp = existing_ancestor(folder) / f".{folder.name}.tmp-{_temp_tag()}"
    tmp.mkdir()   # not tempfile.mkdtemp: its mode 0700 would make the output private
    try:
        write(tmp)
        if not folder.exists():
            folder.parent.mkdir(parents=True, exist_ok=True)
            os.replace(tmp, folder)
            return
        for item in sorted(tmp.iterdir()):
            target = folder / item.name
            if target.is_dir() and not target.is_symlink():
                os.replace(target, tmp / f".replaced-{item.name}")
            os.replace(item, target)
    except Exception as e:
        _raise_write_error(e, folder)
    finally:
        shutil.rmtree(tmp, ignore_errors=True)


def existing_ancestor(path: str | Path) -> Path:
    """The closest existing folder above ``path``: where a new ``path`` (and any missing parents) would go."""
    parent = Path(path).absolute().parent
    while not parent.exists():
        parent = parent.parent
    return parent
