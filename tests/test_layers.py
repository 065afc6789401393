"""Imports inside ``parksim`` follow the data flow: a module imports only from its own layer or the layers below,
and no two modules import each other, directly or round a longer circle.

The graph is read from the source (AST), so an import inside a function or under ``TYPE_CHECKING`` counts the same
as one at the top of a file: a lazy import hides a dependency from the reader, not from this test. A name taken from
a package ``__init__`` that only re-exports it counts as an import of the module that defines it, so the cycle check
is about real module dependencies, not about the packages' public faces.

``LAYERS`` is the table (docs copy it from here), bottom layer first. An entry names a module or a package (all its
submodules), relative to ``parksim``; the longest entry that matches a module gives its layer. ``""`` is the root
package's own ``__init__``.
"""

from __future__ import annotations

import ast
from collections.abc import Iterable
from dataclasses import dataclass
from pathlib import Path

import pytest

import parksim

LAYERS: tuple[tuple[str, tuple[str, ...]], ...] = (
    ("base", ("", "fileio", "checked_options", "plugins", "imageio", "geometry", "kernel_cache", "omp_env", "frames",
              "vehicle", "visibility", "assets", "device")),
    ("model", ("camera", "rig", "gaussians", "data", "calib", "bundle", "actor_asset")),
    ("render", ("render", "ipm", "_ipm_kernels", "sh_rotation", "ply_3dgs")),
    ("sources", ("synth", "importers", "actor_sources")),
    ("recon", ("recon", "compact", "sim", "scenarios")),
    ("serve", ("server", "client", "ray_proxy")),
    ("drive", ("env", "vector_env", "ray_sim", "planners")),
    ("bench", ("bench",)),
    ("commands", ("commands",)),
    ("cli", ("cli",)),
)
"""Layers, bottom first: what each holds and why it sits there.

- base: files, images, frames on the wire, maths and vehicle geometry that know nothing of scenes.
- model: the data types every stage passes on: cameras and rigs, Gaussians, datasets on disk, scene bundles.
- render: what turns Gaussians into pixels (the rasterizer, IPM to a BEV, SH rotation, 3DGS PLY import).
- sources: what makes datasets: the synthetic garage generator and the importers of recordings and other formats.
- recon: what consumes datasets and bundles: training and evaluation, compaction, the simulator core and the
  scenarios it runs in closed loop (so the server can host episodes).
- serve: the HTTP service over the simulator, and its client.
- drive: the gym environments and the planners that drive in them.
- bench: the benchmark harness, which may measure any of the above.
- commands: the ``parksim`` subcommands, each a thin shell over one library call.
- cli: the entry point that gathers the commands.
"""


@dataclass(frozen=True)
class Import:
    """One import statement's edge: ``source`` (module) imports ``target`` (module) at ``line``."""

    source: str
    target: str
    line: int


def module_files(root: Path, package: str) -> dict[str, Path]:
    """Every module of ``package`` (a folder under ``root``) by dotted name; a package by its own name."""
    files = {}
    for path in sorted((root / package).rglob("*.py")):
        parts = path.relative_to(root).with_suffix("").parts
        files[".".join(parts[:-1] if parts[-1] == "__init__" else parts)] = path
    return files


def _is_package(files: dict[str, Path], name: str) -> bool:
    return name in files and files[name].name == "__init__.py"


def _from_base(name: str, files: dict[str, Path], node: ast.ImportFrom) -> str:
    """The absolute module a ``from ... import`` statement in module ``name`` reads from."""
    if not node.level:
        return node.module or ""
    here = name.split(".") if _is_package(files, name) else name.split(".")[:-1]
    base = here[:len(here) - node.level + 1]
    return ".".join(base + ([node.module] if node.module else []))


def _owner(files: dict[str, Path], name: str) -> str | None:
    """The longest prefix of the dotted ``name`` that is one of ``files``, if any."""
    while name and name not in files:
        name = name.rpartition(".")[0]
    return name or None


def _reexports(files: dict[str, Path], package: str) -> dict[str, str]:
    """Names a package's ``__init__`` imports from its own modules: name -> the module it takes it from."""
    found = {}
    for node in ast.parse(files[package].read_text()).body:
        if isinstance(node, ast.ImportFrom):
            base = _from_base(package, files, node)
            for alias in node.names:
                if base in files:
                    found[alias.asname or alias.name] = base
    return found


def _resolve(files: dict[str, Path], module: str, name: str, seen: frozenset[str] = frozenset()) -> str:
    """The module that really provides ``name`` when it is imported from ``module``: a submodule of that name, the
    module an ``__init__`` re-exports it from (followed through further re-exports), or ``module`` itself."""
    if f"{module}.{name}" in files:
        return f"{module}.{name}"
    if _is_package(files, module) and module not in seen:
        source = _reexports(files, module).get(name)
        if source is not None and source != module:
            return _resolve(files, source, name, seen | {module})
    return module


def import_graph(root: Path, package: str) -> list[Import]:
    """Every import between modules of ``package`` (under ``root``), wherever it stands in a file."""
    files = module_files(root, package)
    edges = []
    for name, path in files.items():
        for node in ast.walk(ast.parse(path.read_text(), filename=str(path))):
            targets: list[str | None] = []
            if isinstance(node, ast.Import):
                targets = [_owner(files, alias.name) for alias in node.names]
            elif isinstance(node, ast.ImportFrom):
                base = _owner(files, _from_base(name, files, node))
                if base is not None:
                    targets = [_resolve(files, base, alias.name) for alias in node.names if alias.name != "*"]
                    targets += [base] if any(alias.name == "*" for alias in node.names) else []
            edges += [Import(name, t, node.lineno) for t in targets if t is not None and t != name]
    return edges


def layer_of(module: str, package: str, layers: tuple[tuple[str, tuple[str, ...]], ...]) -> int | None:
    """Index of the layer the longest matching entry puts ``module`` in; None when no entry matches."""
    best: tuple[int, int] | None = None   # (length of the entry, layer)
    for index, (_, entries) in enumerate(layers):
        for entry in entries:
            full = f"{package}.{entry}" if entry else package
            if module == full or (entry and module.startswith(full + ".")):
                if best is None or len(full) > best[0]:
                    best = (len(full), index)
    return None if best is None else best[1]


def upward_imports(edges: Iterable[Import], package: str,
                   layers: tuple[tuple[str, tuple[str, ...]], ...]) -> list[str]:
    """Each import from a lower layer into a higher one, as a readable line."""
    found = []
    for e in edges:
        low, high = layer_of(e.source, package, layers), layer_of(e.target, package, layers)
        if low is not None and high is not None and high > low:
            found.append(f"{e.source}:{e.line} ({layers[low][0]}) imports {e.target} ({layers[high][0]})")
    return sorted(set(found))


def cycles(edges: Iterable[Import]) -> list[list[str]]:
    """The strongly connected components of the graph with more than one module (Tarjan), each sorted."""
    graph: dict[str, set[str]] = {}
    for e in edges:
        graph.setdefault(e.source, set()).add(e.target)
        graph.setdefault(e.target, set())
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on_stack: set[str] = set()
    found: list[list[str]] = []

    def visit(v: str) -> None:
        index[v] = low[v] = len(index)
        stack.append(v)
        on_stack.add(v)
        for w in sorted(graph[v]):
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in on_stack:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            component = []
            while True:
                w = stack.pop()
                on_stack.discard(w)
                component.append(w)
                if w == v:
                    break
            if len(component) > 1:
                found.append(sorted(component))

    for v in sorted(graph):
        if v not in index:
            visit(v)
    return sorted(found)


def _describe(component: list[str], edges: Iterable[Import]) -> str:
    inside = set(component)
    lines = sorted({f"  {e.source}:{e.line} -> {e.target}" for e in edges if e.source in inside and e.target in inside})
    return " <-> ".join(component) + "\n" + "\n".join(lines)


ROOT = Path(parksim.__file__).resolve().parents[1]


@pytest.fixture(scope="module")
def graph() -> list[Import]:
    return import_graph(ROOT, "parksim")


def test_every_module_has_a_layer():
    unplaced = [m for m in module_files(ROOT, "parksim") if layer_of(m, "parksim", LAYERS) is None]
    assert not unplaced, f"add these modules to LAYERS in {Path(__file__).name}: {unplaced}"


def test_every_layer_entry_names_a_module():
    files = module_files(ROOT, "parksim")
    stale = [e for _, entries in LAYERS for e in entries if (f"parksim.{e}" if e else "parksim") not in files]
    assert not stale, f"LAYERS names modules that do not exist: {stale}"


def test_no_upward_imports(graph):
    found = upward_imports(graph, "parksim", LAYERS)
    assert not found, "imports against the data flow (move the code down, or the module up):\n" + "\n".join(found)


def test_no_import_cycles(graph):
    found = cycles(graph)
    assert not found, "modules that import each other:\n" + "\n".join(_describe(c, graph) for c in found)


def test_graph_sees_what_it_checks(graph):
    """The graph holds the imports the checks rely on: function-level ones, and re-exports followed to their
    defining module (``parksim.render.render`` is defined in ``parksim.render.api``)."""
    pairs = {(e.source, e.target) for e in graph}
    assert ("parksim.sim", "parksim.render.api") in pairs      # `from .render import render` inside a method
    assert ("parksim.render", "parksim.render.api") in pairs
    assert ("parksim.cli", "parksim.commands.dispatch") in pairs    # `from .commands.dispatch import main`


def _write(root: Path, files: dict[str, str]) -> None:
    for rel, text in files.items():
        path = root / rel
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_text(text)


SYNTHETIC_LAYERS = (("low", ("", "util", "core")), ("high", ("app",)))


def test_catches_an_upward_import_hidden_in_a_function(tmp_path):
    _write(tmp_path, {
        "pkg/__init__.py": "",
        "pkg/util.py": "def helper():\n    from pkg.app import main\n    return main\n",
        "pkg/app.py": "from .util import helper\n\ndef main():\n    return helper\n",
    })
    found = upward_imports(import_graph(tmp_path, "pkg"), "pkg", SYNTHETIC_LAYERS)
    assert found == ["pkg.util:2 (low) imports pkg.app (high)"]
    assert cycles(import_graph(tmp_path, "pkg")) == [["pkg.app", "pkg.util"]]


def test_catches_a_cycle_hidden_in_a_function_and_through_a_reexport(tmp_path):
    _write(tmp_path, {
        "pkg/__init__.py": "",
        "pkg/core/__init__.py": "from .a import A\nfrom .b import B\n",
        "pkg/core/a.py": "class A:\n    def b(self):\n        from . import b\n        return b.B()\n",
        "pkg/core/b.py": "from pkg.core import A\n\nclass B(A):\n    pass\n",
        "pkg/core/c.py": "from pkg.core import B\n",
    })
    edges = import_graph(tmp_path, "pkg")
    assert not upward_imports(edges, "pkg", SYNTHETIC_LAYERS)
    assert cycles(edges) == [["pkg.core.a", "pkg.core.b"]]          # the __init__ re-exports are not a cycle
    assert Import("pkg.core.c", "pkg.core.b", 1) in edges             # B is read from the module that defines it


def test_a_clean_package_passes(tmp_path):
    _write(tmp_path, {
        "pkg/__init__.py": "",
        "pkg/util.py": "X = 1\n",
        "pkg/app.py": "from . import util\n\ndef main():\n    from pkg.util import X\n    return util.X + X\n",
    })
    edges = import_graph(tmp_path, "pkg")
    assert {(e.source, e.target) for e in edges} == {("pkg.app", "pkg.util")}
    assert not upward_imports(edges, "pkg", SYNTHETIC_LAYERS) and not cycles(edges)
