"""Atomic file writes: a file appears whole or not at all, so a killed process never leaves half a file."""

from __future__ import annotations

import json
import os
import re
import shutil
from pathlib import Path
from typing import Any, Callable

__all__ = ["atomic_write", "write_json", "atomic_directory", "remove_stale_temps"]

_TEMP_NAME = re.compile(r"\..+\.tmp\d+(\.[^.]*)?")
"""``atomic_write``'s temp names: ``.{name}.tmp{pid}{suffix}``."""


def atomic_write(path: str | Path, write: Callable[[Path], None]) -> None:
    """Call ``write(tmp)`` on a temp path next to ``path``, then rename: the file appears whole or not at all."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.name}.tmp{os.getpid()}{path.suffix}")
    try:
        write(tmp)
        os.replace(tmp, path)
    finally:
        tmp.unlink(missing_ok=True)


def remove_stale_temps(folder: str | Path) -> list[Path]:
    """Delete the temp files ``atomic_write`` left in ``folder`` when its process was killed; returns them.

    Only for a folder no other process is writing into (a run's folder as the run starts).
    """
    stale = [p for p in Path(folder).glob(".*.tmp*") if _TEMP_NAME.fullmatch(p.name) and p.is_file()]
    for p in stale:
        p.unlink(missing_ok=True)
    return stale


def write_json(path: str | Path, data: Any) -> None:
    """Atomically write indented JSON."""
    atomic_write(path, lambda p: p.write_text(json.dumps(data, indent=1) + "\n"))


def atomic_directory(path: str | Path, write: Callable[[Path], None]) -> None:
    """Fill a temp folder next to ``path`` with ``write(tmp)``, then swap it in: the folder appears complete or not at all.

    An existing ``path`` is replaced (the caller decides whether that is allowed).
    """
    path = Path(path)
    tmp, old = (path.with_name(f".{path.name}.{kind}{os.getpid()}") for kind in ("tmp", "old"))
    try:
        tmp.mkdir(parents=True)
        write(tmp)
        if path.exists():
            os.replace(path, old)
        os.replace(tmp, path)
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
        shutil.rmtree(old, ignore_errors=True)
