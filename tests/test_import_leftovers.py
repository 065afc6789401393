"""What a killed import or a run that never started leaves behind: stale temp folders, empty parents, resume."""

from __future__ import annotations

import os
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from parksim.cli import main


@pytest.fixture(scope="module")
def exported(tiny_data: Path, tmp_path_factory: pytest.TempPathFactory) -> Path:
    """The session's tiny dataset exported as nerfstudio (read only)."""
    out = tmp_path_factory.mktemp("leftovers") / "exported"
    assert main(["export", "nerfstudio", str(tiny_data), "-o", str(out)]) == 0
    return out


def _temps(parent: Path) -> list[Path]:
    return sorted(parent.glob(".out.tmp-*"))


def test_a_killed_imports_temp_folder_goes_at_the_next_import_a_live_ones_stays(exported: Path,
                                                                               tmp_path: Path) -> None:
    parent = tmp_path / "parent"
    for _ in range(5):   # the tiny import writes for ~0.1 s: catch it mid-write (a fresh try if it finished first)
        shutil.rmtree(parent, ignore_errors=True)
        proc = subprocess.Popen([sys.executable, "-m", "parksim.cli", "import", "nerfstudio", str(exported),
                                 "-o", str(parent / "out"), "--quiet"], stdout=subprocess.DEVNULL)
        deadline = time.monotonic() + 120
        while not (parent.is_dir() and _temps(parent)) and proc.poll() is None and time.monotonic() < deadline:
            pass   # poll tightly
        if proc.poll() is None:
            break
    else:
        pytest.fail("five imports each ended before their temp folder could be seen")
    proc.send_signal(signal.SIGKILL)
    assert proc.wait() == -signal.SIGKILL
    stale = _temps(parent)
    assert len(stale) == 1 and stale[0].is_dir() and not (parent / "out").exists()
    live = parent / stale[0].name.replace(f".tmp-{proc.pid}-", f".tmp-{os.getpid()}-")   # this process's: alive
    assert live != stale[0], f"{stale[0].name} does not name its writer's PID"
    live.mkdir()
    assert main(["import", "nerfstudio", str(exported), "-o", str(parent / "out"), "--quiet"]) == 0
    assert (parent / "out" / "meta.json").is_file()
    assert _temps(parent) == [live]


def test_a_failed_import_removes_the_parents_it_made_and_only_those(exported: Path, tmp_path: Path,
                                                                       capsys) -> None:
    src = tmp_path / "src"
    shutil.copytree(exported, src)
    png = next(src.rglob("*.png"))
    data = bytearray(png.read_bytes())
    data[-100:-60] = bytes(40)   # a damaged PNG: its header passes, decoding it (as the dataset is written) fails
    png.write_bytes(data)
    (tmp_path / "kept").mkdir()
    assert main(["import", "nerfstudio", str(src), "-o", str(tmp_path / "kept" / "a" / "b" / "out"),
                 "--quiet", "--strict"]) == 2   # --strict: refused mid-write (else the frame is dropped)
    assert "cannot decode the image" in capsys.readouterr().err
    assert sorted(p.name for p in tmp_path.iterdir()) == ["kept", "src"]
    assert list((tmp_path / "kept").iterdir()) == []


def test_resume_without_a_config_says_the_earlier_run_never_wrote_it(tiny_data: Path, tmp_path: Path,
                                                                      capsys) -> None:
    run = tmp_path / "run"
    run.mkdir()   # what a reconstruct onto a full disk leaves
    assert main(["reconstruct", str(tiny_data), "-o", str(run), "--resume"]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "never wrote its config" in err and str(run / "config.yaml") in err, err
