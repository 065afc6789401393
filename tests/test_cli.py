"""The ``parksim`` command line: every subcommand explains itself, bad input is one clear line, render works."""

import subprocess
import sys

import numpy as np
import pytest

from parksim.cli import COMMANDS, main
from sim_fixtures import make_bundle


def run_cli(*argv: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "parksim.cli", *argv], capture_output=True, text=True, timeout=120)


def test_every_subcommand_has_help():
    top = run_cli("--help")
    assert top.returncode == 0
    for name in COMMANDS:
        assert name in top.stdout
        sub = run_cli(name, "--help")
        assert sub.returncode == 0 and "usage: parksim " + name in sub.stdout, name


@pytest.fixture(scope="module")
def bundle(tmp_path_factory):
    return make_bundle(tmp_path_factory.mktemp("bundle") / "garage", n=2000)


def test_render_writes_views_bev_and_depth(bundle, tmp_path, capsys):
    out = tmp_path / "render"
    assert main(["render", str(bundle), "--pose", "4.0,0.0,0.0", "--cameras", "front,left", "--bev", "--depth",
                 "--scale", "0.5", "-o", str(out)]) == 0
    assert sorted(p.name for p in out.iterdir()) == ["bev.png", "front.png", "front_depth.npy", "left.png",
                                                     "left_depth.npy"]
    depth = np.load(out / "front_depth.npy")
    assert np.isfinite(depth).all() and depth.max() > 0
    assert "rendered front, left, bev" in capsys.readouterr().out


@pytest.mark.parametrize("argv, message", [
    (["--pose", "1,2"], "pose must be a 4x4 matrix, (x, y, yaw)"),
    (["--pose", "1,nan,0"], "non-finite"),
    (["--pose", "a,b,c"], "comma-separated numbers"),
    (["--pose", "1,2,0", "--cameras", "roof"], "unknown camera(s) ['roof']"),
    (["--pose", "1,2,0", "--scale", "0"], "--scale must be in (0, 4]"),
])
def test_render_bad_input_is_one_line_and_exit_2(bundle, tmp_path, capsys, argv, message):
    assert main(["render", str(bundle), *argv, "-o", str(tmp_path / "x")]) == 2
    err = capsys.readouterr().err
    assert err.startswith("parksim render: error:") and message in err and err.count("\n") == 1
    assert not (tmp_path / "x").exists()


def test_missing_bundle_is_a_clear_error(tmp_path, capsys):
    assert main(["render", str(tmp_path / "nope"), "--pose", "0,0,0", "-o", str(tmp_path / "x")]) == 2
    assert "bundle folder not found" in capsys.readouterr().err
