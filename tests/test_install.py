"""``pip install .`` gives a Python environment one new importable name, ``parksim``, holding every module of the
checkout and the package data, importable without the checkout.

The wheel is built offline from a copy of the checkout (``--no-build-isolation``: the test environment's setuptools,
which the ``test`` extra pins; the copy keeps ``build/`` out of the checkout) and installed without dependencies
into a fresh venv, whose top-level names are listed before and after.
"""

from __future__ import annotations

import json
import shutil
import subprocess
import sys
import venv
import zipfile
from pathlib import Path

import pytest

import parksim

ROOT = Path(parksim.__file__).resolve().parents[1]
LIST_NAMES = "import json, pkgutil; print(json.dumps(sorted({m.name for m in pkgutil.iter_modules()})))"


def _run(*argv: str | Path, cwd: Path) -> str:
    done = subprocess.run([str(a) for a in argv], cwd=cwd, capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, f"{' '.join(map(str, argv))}\n{done.stdout}\n{done.stderr}"
    return done.stdout


RUN_OUTPUTS = {"out", "data", "scenes", "detectors", "checkpoints", "build", "dist"}
"""Top-level folders of a working checkout that hold what runs wrote, not sources (.gitignore's)."""


@pytest.fixture(scope="module")
def built(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, Path]:
    """The wheel ``pip`` builds from a copy of the checkout as a clone has it (every top-level folder, so a stray
    package beside ``parksim`` would be found by the build too), and the copy."""
    tmp = tmp_path_factory.mktemp("install")
    src = tmp / "src"
    unversioned = shutil.ignore_patterns("__pycache__", "*.pyc", "*.egg-info", ".*")

    def ignore(folder: str, names: list[str]) -> set[str]:
        return set(unversioned(folder, names)) | (RUN_OUTPUTS & set(names) if Path(folder) == ROOT else set())

    shutil.copytree(ROOT, src, ignore=ignore)
    _run(sys.executable, "-m", "pip", "wheel", "--no-deps", "--no-build-isolation", "--no-index", "-q",
         "-w", tmp / "dist", src, cwd=tmp)
    found = sorted((tmp / "dist").glob("parksim-*.whl"))
    assert len(found) == 1, found
    return found[0], src


def test_the_wheel_holds_every_module_and_nothing_beside_parksim(built: tuple[Path, Path]) -> None:
    wheel, src = built
    names = zipfile.ZipFile(wheel).namelist()
    tops = {n.split("/")[0] for n in names}
    assert {t for t in tops if not t.endswith(".dist-info")} == {"parksim"}
    source = {p.relative_to(src).as_posix() for p in (src / "parksim").rglob("*.py")}
    assert {n for n in names if n.endswith(".py")} == source
    for data in ("parksim/configs/tiny.yaml", "parksim/server/viewer/index.html"):
        assert data in names


def test_installing_adds_only_the_name_parksim(built: tuple[Path, Path], tmp_path: Path) -> None:
    wheel, _ = built
    env = tmp_path / "venv"
    venv.create(env, with_pip=False, symlinks=True)
    python = env / "bin" / "python"
    before = set(json.loads(_run(python, "-I", "-c", LIST_NAMES, cwd=tmp_path)))
    _run(sys.executable, "-m", "pip", "--python", python, "install", "--no-deps", "--no-index", "-q", wheel,
         cwd=tmp_path)
    after = set(json.loads(_run(python, "-I", "-c", LIST_NAMES, cwd=tmp_path)))
    assert after - before == {"parksim"} and before <= after
    where = _run(python, "-I", "-c", "import parksim; print(parksim.__file__)", cwd=tmp_path).strip()
    assert Path(where).is_relative_to(env), where   # the installed copy, not the checkout
