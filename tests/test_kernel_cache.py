"""The numba cache folder follows the kernels' whole source, so editing an inlined helper never runs stale code."""

from __future__ import annotations

import os
import re
from pathlib import Path

import numba
import pytest

from parksim import kernel_cache


@pytest.fixture
def tree(tmp_path, monkeypatch):
    """A stand-in package root with every kernel source (packages with nested helpers, modules) and another
    module; numba's setting restored."""
    kernel_files = [e if e.endswith(".py") else f"{e}/kernels.py" for e in kernel_cache.KERNEL_SOURCES]
    nested = [f"{e}/lens/helpers.py" for e in kernel_cache.KERNEL_SOURCES if not e.endswith(".py")]
    for rel in (*kernel_files, *nested, "cli.py"):
        (tmp_path / rel).parent.mkdir(parents=True, exist_ok=True)
        (tmp_path / rel).write_text(f"# {rel}\n")
    monkeypatch.setattr(kernel_cache, "_ROOT", tmp_path)
    monkeypatch.setattr(numba.config, "CACHE_DIR", numba.config.CACHE_DIR)
    monkeypatch.delenv("NUMBA_CACHE_DIR", raising=False)
    kernel_cache.configure.cache_clear()
    yield tmp_path
    kernel_cache.configure.cache_clear()


def test_hash_follows_every_kernel_source_but_not_other_modules(tree):
    base = kernel_cache.source_hash()
    (tree / "cli.py").write_text("# edited, not kernel source\n")
    assert kernel_cache.source_hash() == base
    edits = [e for e in kernel_cache.KERNEL_SOURCES if e.endswith(".py")]
    edits += [f"{e}/lens/helpers.py" for e in kernel_cache.KERNEL_SOURCES if not e.endswith(".py")]
    for rel in edits:
        (tree / rel).write_text((tree / rel).read_text() + "X = 1\n")
        changed = kernel_cache.source_hash()
        assert changed != base, rel
        base = changed


def test_configure_uses_a_folder_per_source_and_drops_stale_ones(tree):
    others = [tree / "__pycache__" / f"numba-{k:016d}" for k in range(kernel_cache.KEEP_OTHERS + 2)]
    for age, folder in enumerate(others):          # others[0] is the oldest
        folder.mkdir(parents=True)
        os.utime(folder, (1000 + age, 1000 + age))
    kernel_cache.configure()
    expected = tree / "__pycache__" / f"numba-{kernel_cache.source_hash()}"
    assert numba.config.CACHE_DIR == str(expected)
    kept = [f.exists() for f in others]
    assert kept == [False, False] + [True] * kernel_cache.KEEP_OTHERS   # the newest others stay


def test_a_users_numba_cache_dir_wins(tree, monkeypatch):
    monkeypatch.setenv("NUMBA_CACHE_DIR", str(tree / "mine"))
    before = numba.config.CACHE_DIR
    kernel_cache.configure()
    assert numba.config.CACHE_DIR == before and not (tree / "__pycache__").exists()


def test_every_module_with_cached_kernels_is_hashed():
    """Each ``KERNEL_SOURCES`` entry exists (a renamed kernel file left there would break every import) and
    covers every parksim module that compiles a cached numba kernel, so none of them can run stale code."""
    root = Path(kernel_cache.__file__).resolve().parent
    hashed: set[Path] = set()
    for entry in kernel_cache.KERNEL_SOURCES:
        path = root / entry
        assert path.exists(), f"KERNEL_SOURCES names {entry}, which is not in {root}"
        hashed |= set(path.rglob("*.py")) if path.is_dir() else {path}
    cached = re.compile(r"@numba\.njit\([^)]*cache=True")
    kernels = {f for f in root.rglob("*.py") if cached.search(f.read_text())}
    assert root / "_ipm_kernels.py" in kernels and root / "render" / "_project_kernels.py" in kernels
    assert kernels <= hashed, sorted(str(f.relative_to(root)) for f in kernels - hashed)
