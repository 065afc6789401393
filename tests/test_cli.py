"""The ``parksim`` command line: every subcommand explains itself, bad input is one clear line, render works."""

import argparse
import json
import os
import subprocess
import sys

import numpy as np
import pytest

from parksim.cli import COMMANDS, build_parser, main
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


def _parsers(parser: argparse.ArgumentParser):
    """``parser`` and every subcommand parser below it."""
    yield parser
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            for sub in action.choices.values():
                yield from _parsers(sub)


def test_help_states_each_default_once_and_never_none():
    """No "(default: None)" noise, no default stated by hand and again by the formatter, every parser described."""
    for parser in _parsers(build_parser()):
        assert parser.description, f"{parser.prog} has no description"
        formatter = parser._get_formatter()
        for action in parser._actions:
            if action.help in (None, argparse.SUPPRESS):
                continue
            text = formatter._expand_help(action)
            assert "(default: None)" not in text and "(default: [])" not in text, (parser.prog, text)
            assert text.lower().count("default") <= 1, (parser.prog, text)


def test_help_adds_a_meaningful_default():
    help_text = {p.prog: p.format_help() for p in _parsers(build_parser())}
    assert "in (0, 4] (default: 1.0)" in " ".join(help_text["parksim render"].split())
    assert "(default: 8000)" in help_text["parksim serve"]
    assert "(default: 0.002)" in help_text["parksim detector train"]


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
    (["--pose", "1,2,0", "--scale", "0"], "argument --scale: must be a finite number in (0, 4], got 0"),
])
def test_render_bad_input_is_one_line_and_exit_2(bundle, tmp_path, capsys, argv, message):
    assert main(["render", str(bundle), *argv, "-o", str(tmp_path / "x")]) == 2
    err = capsys.readouterr().err
    assert err.startswith("parksim render: error:") and message in err and err.count("\n") == 1
    assert not (tmp_path / "x").exists()


def test_missing_bundle_is_a_clear_error(tmp_path, capsys):
    assert main(["render", str(tmp_path / "nope"), "--pose", "0,0,0", "-o", str(tmp_path / "x")]) == 2
    assert "bundle folder not found" in capsys.readouterr().err


def test_eval_report_appears_whole_and_a_rerun_replaces_it(bundle, tmp_path, capsys):
    """The report goes through a temp folder: other files in OUTPUT stay, renders/ is replaced as a whole, and
    OUTPUT gets the usual permissions (not a temp folder's 0700)."""
    data = tmp_path / "data"
    assert main(["synth", "tiny", "-o", str(data), "--frames", "2", "--points", "300", "--quiet"]) == 0
    out = tmp_path / "report"
    assert main(["eval", str(bundle), str(data), "-o", str(out)]) == 0
    assert sorted(p.name for p in out.iterdir()) == ["eval.json", "eval.md", "renders"]
    assert out.stat().st_mode & 0o777 == 0o777 & ~_umask()
    (out / "notes.txt").write_text("mine")
    (out / "renders" / "stale.png").write_bytes(b"old")
    assert main(["eval", str(bundle), str(data), "-o", str(out)]) == 0
    assert sorted(p.name for p in out.iterdir()) == ["eval.json", "eval.md", "notes.txt", "renders"]
    assert not (out / "renders" / "stale.png").exists() and len(list((out / "renders").iterdir())) == 4
    assert [p.name for p in tmp_path.iterdir() if p.name.startswith(".")] == []
    assert "report: " in capsys.readouterr().out


def test_eval_projection_override_is_recorded_and_changes_the_render(bundle, tmp_path, capsys):
    """--projection renders with another projection than the trained one (what the server does to EWA-trained
    scenes: it renders every scene with UT); eval.json says which. Several scenes refuse it in one line."""
    data = tmp_path / "data"
    assert main(["synth", "tiny", "-o", str(data), "--frames", "2", "--points", "300", "--quiet"]) == 0
    reports = {}
    for name, extra in (("trained", []), ("ewa", ["--projection", "ewa"])):
        assert main(["eval", str(bundle), str(data), "-o", str(tmp_path / name), *extra]) == 0
        reports[name] = json.loads((tmp_path / name / "eval.json").read_text())
    assert reports["trained"]["projection"] == "ut" and reports["ewa"]["projection"] == "ewa"
    assert reports["trained"]["overall"]["psnr"] != reports["ewa"]["overall"]["psnr"]
    capsys.readouterr()
    assert main(["eval", str(bundle), str(bundle), str(data), "-o", str(tmp_path / "both"), "--projection", "ut"]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "--projection and --image-scale apply to one SCENE" in err


def _umask() -> int:
    mask = os.umask(0)
    os.umask(mask)
    return mask


@pytest.mark.parametrize("send", [
    "signal.pthread_kill(threading.get_ident(), signal.SIGINT)",   # Ctrl-C handed to a thread other than the main one
    "os.kill(os.getpid(), signal.SIGTERM)",
])
def test_serve_wait_stops_on_sigint_or_sigterm_whatever_it_inherited(send):
    """``parksim serve --ray`` waits for Ctrl-C or SIGTERM while Ray's threads run. It must stop when the signal
    lands on another thread, and when it started with SIGINT ignored (as a background job of a non-interactive
    shell does: the Ray server's Ctrl-C test hung whenever the suite was run that way)."""
    code = ("import os, signal, threading, time\n"
            "signal.signal(signal.SIGINT, signal.SIG_IGN)   # as inherited from a background job\n"
            "from parksim.server.launch import wait_for_interrupt\n"
            "def poke():\n"
            "    time.sleep(0.3)\n"
            f"    {send}\n"
            "threading.Thread(target=poke, daemon=True).start()\n"
            "wait_for_interrupt()\n"
            "print('stopped')\n")
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=30)
    assert done.returncode == 0 and done.stdout.strip() == "stopped", done.stderr
