"""Every public function and method of the modules docs/api.md lists has an ``Args:`` and a ``Returns:`` section.

``make lint`` runs ruff's docstring rules on those modules (``API_MODULES`` in the Makefile), but ruff's D417
checks only docstrings that already have an ``Args:`` section, and its DOC201 skips one-line docstrings. This
test closes that gap for the public API: a function with parameters documents them, one that returns a value
says what, and the Makefile's list covers the file of every public name.
"""

from __future__ import annotations

import importlib
import inspect
import re
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]


def api_modules() -> list[str]:
    """The module names of docs/api.md's table (first column, backticked)."""
    rows = [line for line in (ROOT / "docs" / "api.md").read_text().splitlines() if line.startswith("| `parksim")]
    return [name for row in rows for name in re.findall(r"`(parksim[\w.]*)`", row.split("|")[1])]


def checked_paths() -> list[str]:
    """``API_MODULES`` of the Makefile: the files and folders ruff's docstring rules run on."""
    text = (ROOT / "Makefile").read_text().replace("\\\n", " ")
    match = re.search(r"^API_MODULES\s*:=(.*)$", text, re.MULTILINE)
    assert match, "the Makefile defines no API_MODULES"
    return match.group(1).split()


def public_objects(module_name: str) -> list[tuple[str, object]]:
    """``(qualified name, object)`` of every function and class in the module's ``__all__``, and of the public
    methods those classes define themselves (``__init__`` and ``__call__`` included, properties excluded)."""
    module = importlib.import_module(module_name)
    out: list[tuple[str, object]] = []
    for name in module.__all__:
        obj = getattr(module, name)
        if inspect.isfunction(obj):
            out.append((f"{module_name}.{name}", obj))
        elif inspect.isclass(obj) and obj.__module__.startswith("parksim"):
            out.append((f"{module_name}.{name}", obj))
            for attr, member in vars(obj).items():
                if attr.startswith("_") and attr not in ("__init__", "__call__"):
                    continue
                function = member.__func__ if isinstance(member, (classmethod, staticmethod)) else member
                if inspect.isfunction(function) and function.__code__.co_filename != "<string>":   # not generated
                    out.append((f"{module_name}.{name}.{attr}", (obj, attr, function)))
    return out


def _inherited(cls: type, attr: str, section: str) -> bool:
    """Whether a base class documents the method ``attr`` overrides with ``section``."""
    return any(section in (inspect.getdoc(vars(base)[attr]) or "")
               for base in cls.__mro__[1:] if attr in vars(base))


def _missing_sections(obj: object) -> list[str]:
    """The sections a function's docstring lacks: Args (it takes parameters), Returns (it returns a value)."""
    cls, attr, function = obj if isinstance(obj, tuple) else (None, None, obj)
    doc = function.__doc__ or ""
    signature = inspect.signature(function)
    params = [p for p in signature.parameters if p not in ("self", "cls")]
    returns = signature.return_annotation not in (inspect.Signature.empty, None, "None") and attr != "__init__"
    needed = ["Args:"] * bool(params) + ["Returns:"] * returns
    return [s for s in needed if s not in doc and not (cls is not None and _inherited(cls, attr, s))]


def _cases() -> list[tuple[str, object]]:
    return [case for module in api_modules() for case in public_objects(module)]


def test_api_table_is_read():
    modules = api_modules()
    assert "parksim.camera" in modules and "parksim.recon.config" in modules and "parksim.server" in modules


@pytest.mark.parametrize(("name", "obj"), _cases(), ids=[name for name, _ in _cases()])
def test_public_docstring_sections(name, obj):
    target = obj[2] if isinstance(obj, tuple) else obj
    assert inspect.getdoc(target), f"{name} has no docstring"
    if not inspect.isclass(target):
        missing = _missing_sections(obj)
        assert not missing, f"{name}'s docstring has no {' and no '.join(missing)} section"


def test_makefile_covers_the_api():
    paths = checked_paths()
    uncovered = set()
    for _, obj in _cases():
        source = Path(inspect.getsourcefile(obj[2] if isinstance(obj, tuple) else obj)).resolve()
        rel = source.relative_to(ROOT).as_posix()
        if not any(rel == p or rel.startswith(p.rstrip("/") + "/") for p in paths):
            uncovered.add(rel)
    assert not uncovered, f"API_MODULES in the Makefile misses {sorted(uncovered)} (docs/api.md names defined there)"
