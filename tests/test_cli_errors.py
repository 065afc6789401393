"""Every bad input to ``parksim``: one line on stderr, exit status 2, nothing half-written.

Read-only and full disks are real tmpfs mounts (we run as root, where chmod does not stop writes);
those tests skip, saying why, where mounting is not allowed.
"""

from __future__ import annotations

import errno
import os
import pickle
import socket
import subprocess
import sys
import time
from collections.abc import Iterator
from pathlib import Path

import httpx
import pytest

from parksim.cli import describe, main
from parksim.recon.config import dump_config, load_config
from sim_fixtures import make_bundle

PARKSIM = str(Path(sys.executable).with_name("parksim"))
"""The installed console script, as a user runs it."""


def one_line(err: str, command: str) -> str:
    """The single stderr line of a failed ``parksim COMMAND``, checked to be the only one (besides the notice
    that numba kernels are being compiled, printed when another change to the source invalidated their cache)."""
    lines = [line for line in err.splitlines() if not line.startswith("compiling render kernels")]
    assert len(lines) == 1 and err.endswith("\n"), err
    assert lines[0].startswith(f"parksim {command}: error: "), err
    return lines[0]


def mount_tmpfs(where: Path, options: str) -> Iterator[Path]:
    """A real tmpfs mounted at ``where`` for the test, unmounted after; skips where mounting is not allowed."""
    where.mkdir()
    done = subprocess.run(["mount", "-t", "tmpfs", "-o", options, "tmpfs", str(where)], capture_output=True, text=True)
    if done.returncode:
        pytest.skip(f"cannot mount a tmpfs ({done.stderr.strip()}): needs root with CAP_SYS_ADMIN")
    try:
        yield where
    finally:
        subprocess.run(["umount", "-l", str(where)], check=True)


@pytest.fixture
def read_only(tmp_path: Path) -> Iterator[Path]:
    yield from mount_tmpfs(tmp_path / "ro", "ro,size=64k")


@pytest.fixture
def small_disk(tmp_path: Path) -> Iterator[Path]:
    yield from mount_tmpfs(tmp_path / "disk", "size=64k")


@pytest.fixture(scope="module")
def bundle(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return make_bundle(tmp_path_factory.mktemp("bundle") / "garage", n=2000)


@pytest.fixture(scope="module")
def dataset(tmp_path_factory: pytest.TempPathFactory) -> Path:
    out = tmp_path_factory.mktemp("data") / "tiny"
    assert main(["synth", "tiny", "-o", str(out), "--frames", "2", "--resolution", "64x48", "--bev-px", "64",
                 "--points", "300", "--quiet"]) == 0
    return out


def test_output_on_a_read_only_disk_is_one_line_before_any_work(bundle, dataset, read_only, capsys):
    out = read_only / "out"
    for argv in (["render", str(bundle), "--pose", "4,0,0", "-o", str(out)],
                 ["synth", "tiny", "-o", str(out), "--quiet"],
                 ["reconstruct", str(dataset), "-o", str(out), "--config", "tiny"],
                 ["compact", str(bundle), "-o", str(out), "--quiet"]):
        assert main(argv) == 2
        assert f"{out}: Read-only file system" in one_line(capsys.readouterr().err, argv[0])


def test_render_to_an_existing_file(bundle, tmp_path, capsys):
    target = tmp_path / "views"
    target.write_text("mine")
    assert main(["render", str(bundle), "--pose", "4,0,0", "-o", str(target)]) == 2
    assert f"{target}: exists and is not a folder" in one_line(capsys.readouterr().err, "render")
    assert target.read_text() == "mine"


def test_render_that_fills_the_disk_leaves_nothing(bundle, small_disk, capsys):
    out = small_disk / "views"
    assert main(["render", str(bundle), "--pose", "4,0,0", "--depth", "-o", str(out)]) == 2
    assert f"{out}: No space left on device" in one_line(capsys.readouterr().err, "render")
    assert list(small_disk.iterdir()) == []


def test_render_adds_to_an_existing_folder(bundle, tmp_path, capsys):
    out = tmp_path / "views"
    out.mkdir()
    (out / "notes.txt").write_text("mine")
    assert main(["render", str(bundle), "--pose", "4,0,0", "--cameras", "front", "-o", str(out)]) == 0
    assert sorted(p.name for p in out.iterdir()) == ["front.png", "notes.txt"]
    assert [p.name for p in tmp_path.iterdir()] == ["views"]


def test_synth_into_an_existing_folder_names_overwrite(tmp_path, capsys):
    out = tmp_path / "data"
    out.mkdir()
    (out / "keep.txt").write_text("mine")
    assert main(["synth", "tiny", "-o", str(out), "--quiet"]) == 2
    assert f"{out}: already exists; pass --overwrite to replace it" in one_line(capsys.readouterr().err, "synth")
    assert [p.name for p in out.iterdir()] == ["keep.txt"]


@pytest.mark.parametrize("argv, message", [
    (["--bev-px", "0"], "argument --bev-px: must be an integer in [1, 2048], got 0"),
    (["--resolution", "100000x100000"], "argument --resolution: each side must be 1 to 2048 px, got 100000x100000"),
    (["--resolution", "640by480"], "argument --resolution: expected WxH like 640x480, got '640by480'"),
    (["--length", "-10"], "argument --length: must be a finite number > 0, got -10"),
    (["--length", "nan"], "argument --length: must be a finite number > 0, got nan"),
    (["--length", "19"], "garage length must be at least 22 m"),
    (["--frames", "0"], "argument --frames: must be an integer >= 1, got 0"),
    (["--points", "many"], "argument --points: expected an integer in [1, 10000000], got 'many'"),
])
def test_synth_bad_arguments(tmp_path, capsys, argv, message):
    assert main(["synth", "tiny", "-o", str(tmp_path / "x"), "--quiet", *argv]) == 2
    assert message in one_line(capsys.readouterr().err, "synth")
    assert list(tmp_path.iterdir()) == []


@pytest.mark.parametrize("argv, message", [
    (["--port", "99999"], "argument --port: must be an integer in [1, 65535], got 99999"),
    (["--port", "0"], "argument --port: must be an integer in [1, 65535], got 0"),
    (["--workers", "0"], "argument --workers: must be an integer >= 1, got 0"),
    (["--queue", "-1"], "argument --queue: must be an integer >= 0, got -1"),
    (["--max-scale", "inf"], "argument --max-scale: must be a finite number > 0, got inf"),
])
def test_serve_bad_arguments(bundle, capsys, argv, message):
    assert main(["serve", "--scenes", str(bundle), *argv]) == 2
    assert message in one_line(capsys.readouterr().err, "serve")


def test_serve_on_a_busy_port_fails_before_loading(bundle):
    with socket.socket() as busy:
        busy.bind(("127.0.0.1", 0))
        busy.listen()
        port = busy.getsockname()[1]
        done = subprocess.run([PARKSIM, "serve", "--scenes", str(bundle), "--port", str(port)],
                              capture_output=True, text=True, timeout=120)
    assert done.returncode == 2 and done.stdout == ""
    assert f"127.0.0.1:{port}: cannot listen there: Address already in use" in one_line(done.stderr, "serve")


def test_serve_listens_on_the_socket_it_checked(bundle):
    with socket.socket() as probe:
        probe.bind(("127.0.0.1", 0))
        port = probe.getsockname()[1]
    proc = subprocess.Popen([PARKSIM, "serve", "--scenes", str(bundle), "--port", str(port)],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        deadline = time.monotonic() + 120
        while True:
            try:
                reply = httpx.get(f"http://127.0.0.1:{port}/healthz", timeout=5)
                break
            except httpx.TransportError:
                assert proc.poll() is None and time.monotonic() < deadline, proc.stderr.read() if proc.stderr else ""
                time.sleep(0.2)
        assert reply.status_code == 200 and reply.json()["scenes"] == ["garage"]
    finally:
        proc.terminate()
        out, _ = proc.communicate(timeout=30)
    assert out.startswith(f"serving garage on http://127.0.0.1:{port}")


def test_disk_full_during_a_checkpoint_is_one_line_naming_it(dataset, tmp_path, small_disk, capsys):
    config = load_config("tiny")
    config = config.model_copy(update={
        "photometric": config.photometric.model_copy(update={"iterations": 2}),
        "run": config.run.model_copy(update={"checkpoint_every": 1})})
    path = tmp_path / "short.yaml"
    path.write_text(dump_config(config))
    out = small_disk / "run"
    assert main(["reconstruct", str(dataset), "-o", str(out), "--config", str(path)]) == 2
    err = one_line(capsys.readouterr().err, "reconstruct")
    assert f"{out / 'checkpoints' / 'last.pt'}: No space left on device" in err
    assert not [p.name for p in (out / "checkpoints").iterdir() if p.name != "last.pt"]


def test_a_pickle_checkpoint_is_one_line(dataset, tmp_path, capsys):
    out = tmp_path / "run"
    (out / "checkpoints").mkdir(parents=True)
    (out / "config.yaml").write_text(dump_config(load_config("tiny")))
    (out / "checkpoints" / "last.pt").write_bytes(pickle.dumps({"iteration": 3, "params": object}))
    assert main(["reconstruct", str(dataset), "-o", str(out), "--resume"]) == 2
    err = capsys.readouterr().err
    assert "Warning" not in err   # torch's two-line legacy-format warning is not passed on
    assert f"{out / 'checkpoints' / 'last.pt'}: a pickled object" in one_line(err, "reconstruct")


def test_bad_yaml_config_is_one_line(dataset, tmp_path, capsys):
    bad = tmp_path / "bad.yaml"
    bad.write_text("run: [1,\n  2\n")
    assert main(["reconstruct", str(dataset), "-o", str(tmp_path / "run"), "--config", str(bad)]) == 2
    assert f"{bad}: not valid YAML" in one_line(capsys.readouterr().err, "reconstruct")
    assert not (tmp_path / "run").exists()


def test_usage_errors_are_one_line(capsys):
    assert main(["synth"]) == 2
    required = "parksim synth: error: the following arguments are required: preset, -o/--output\n"
    assert capsys.readouterr().err == required
    assert main(["nosuch"]) == 2
    err = capsys.readouterr().err
    assert err.startswith("parksim: error: argument COMMAND: invalid choice: 'nosuch'") and err.count("\n") == 1


def test_config_preset_by_name_from_any_folder(tmp_path):
    """The installed ``parksim`` run from an unrelated folder finds the packaged ``tiny`` training preset."""
    def parksim(*argv: str) -> subprocess.CompletedProcess:
        return subprocess.run([PARKSIM, *argv], cwd=tmp_path, capture_output=True, text=True, timeout=900)

    made = parksim("synth", "tiny", "-o", "d", "--frames", "2", "--resolution", "64x48", "--bev-px", "64",
                   "--points", "300", "--quiet")
    assert made.returncode == 0, made.stderr
    trained = parksim("reconstruct", "d", "-o", "s", "--config", "tiny")
    assert trained.returncode == 0, trained.stderr
    assert (tmp_path / "s" / "bundle.json").is_file() and "wrote s:" in trained.stdout


def test_unknown_config_lists_presets_before_any_output(dataset, tmp_path):
    done = subprocess.run([PARKSIM, "reconstruct", str(dataset), "-o", "s", "--config", "nosuch"], cwd=tmp_path,
                          capture_output=True, text=True, timeout=300)
    assert done.returncode == 2
    err = one_line(done.stderr, "reconstruct")
    assert "nosuch: neither a config file nor a packaged preset (presets: " in err and "tiny" in err
    assert list(tmp_path.iterdir()) == []


@pytest.mark.parametrize("error, line", [
    (OSError(errno.ENOSPC, os.strerror(errno.ENOSPC), "run/checkpoints/last.pt"),
     "run/checkpoints/last.pt: No space left on device"),
    (OSError(errno.EROFS, os.strerror(errno.EROFS), "a", None, "b"), "a -> b: Read-only file system"),
    (FileNotFoundError("bundle folder not found: x"), "bundle folder not found: x"),
    (MemoryError("Unable to allocate 74.5 GiB"), "out of memory: Unable to allocate 74.5 GiB"),
    (ValueError("first line\n  second line"), "first line second line"),
    (OSError(errno.EIO, os.strerror(errno.EIO)), None),
    (RuntimeError("a bug"), None),
])
def test_describe_maps_expected_errors_to_one_line(error, line):
    assert describe(error) == line


def test_describe_folds_pydantic_errors():
    from parksim.server import Settings

    with pytest.raises(ValueError) as raised:
        Settings(workers=0, queue_size=-1)
    assert describe(raised.value) == ("workers: Input should be greater than or equal to 1; "
                                      "queue_size: Input should be greater than or equal to 0")
