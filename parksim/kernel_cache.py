"""Numba's on-disk kernel cache, keyed by the source of every kernel and every helper it inlines.

Numba drops a cached kernel only when the kernel's own file changes, but our kernels inline helpers and
constants from other files (the lens in ``_project_kernels``, the ellipse, the tile constants): after such a
helper changes, a stale cache would silently run the old code. So, unless ``NUMBA_CACHE_DIR`` is set, the
cache goes to a folder named by a hash of the kernel packages' sources; all but the newest few others are removed.
"""

from __future__ import annotations

import functools
import hashlib
import os
import shutil
from pathlib import Path

import numba

__all__ = ["configure", "source_hash", "KERNEL_SOURCES", "KEEP_OTHERS"]

_ROOT = Path(__file__).resolve().parent
KERNEL_SOURCES = ("render", "synth", "gaussians.py", "_ipm_kernels.py", "recon/_ssim_kernels.py", "bench/pairs.py")
"""What the kernels and their inlined helpers are built from (packages or files under ``parksim/``)."""
_PREFIX = "numba-"
KEEP_OTHERS = 2
"""Cache folders of other sources kept (most recently written first); older ones are removed (~3 MB each)."""


def source_hash() -> str:
    """Hash of every ``.py`` file in ``KERNEL_SOURCES``, by path and content."""
    h = hashlib.sha256()
    for entry in KERNEL_SOURCES:
        path = _ROOT / entry
        for file in sorted(path.rglob("*.py")) if path.is_dir() else [path]:
            h.update(str(file.relative_to(_ROOT)).encode())
            h.update(file.read_bytes())
    return h.hexdigest()[:16]


def _writable_home() -> Path | None:
    """Where cache folders live: ``parksim/__pycache__`` in a writable checkout, else the user's cache."""
    for base in (_ROOT / "__pycache__", Path(os.environ.get("XDG_CACHE_HOME", Path.home() / ".cache")) / "parksim"):
        try:
            base.mkdir(parents=True, exist_ok=True)
        except OSError:
            continue
        if os.access(base, os.W_OK):
            return base
    return None


def _mtime(path: Path) -> float:
    """Modification time, or -1 for a folder another process removed meanwhile."""
    try:
        return path.stat().st_mtime
    except OSError:
        return -1.0


@functools.cache
def configure() -> None:
    """Point numba's cache at this source's folder (before any kernel module is imported); keep a user's choice."""
    if os.environ.get("NUMBA_CACHE_DIR"):
        return
    home = _writable_home()
    if home is None:
        return   # numba's own default (and its own fallbacks) then
    current = home / f"{_PREFIX}{source_hash()}"
    others = sorted((d for d in home.glob(f"{_PREFIX}*") if d != current), key=_mtime)
    for old in others[:-KEEP_OTHERS]:   # the newest few stay: another process may still be running that source
        shutil.rmtree(old, ignore_errors=True)
    numba.config.CACHE_DIR = str(current)  # type: ignore[attr-defined]  # numba.config sets its names at import
