"""``parksim batch``: many tiny scenes as Ray tasks on one local Ray instance; a broken dataset fails alone after
its retry, a re-run skips finished bundles, a run with a checkpoint resumes, and Ray stays optional."""

from __future__ import annotations

import contextlib
import io
import shutil
import subprocess
import sys
from collections.abc import Iterator
from pathlib import Path

import pytest

ray = pytest.importorskip("ray")

from parksim.bundle import load  # noqa: E402
from parksim.cli import main as cli_main  # noqa: E402
from parksim.recon.reconstruct import reconstruct  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]


@pytest.fixture(scope="module")
def ray_address() -> Iterator[str]:
    """One local Ray instance for the module (2 CPUs, small object store, no dashboard), shut down at the end."""
    context = ray.init(num_cpus=2, object_store_memory=150 * 1024**2, include_dashboard=False, log_to_driver=False)
    yield context.address_info["gcs_address"]
    ray.shutdown()


@pytest.fixture(scope="module")
def datasets(tiny_data: Path, tmp_path_factory: pytest.TempPathFactory) -> dict[str, Path]:
    """A tiny synth dataset made once, copied under other names (b; c, whose run will be killed half-way; bad, whose
    rig.json is corrupt)."""
    root = tmp_path_factory.mktemp("batch-data")
    for name in ("a", "b", "c", "bad"):
        shutil.copytree(tiny_data, root / name)
    (root / "bad" / "rig.json").write_text('{"cameras": ')
    return {name: root / name for name in ("a", "b", "c", "bad")}


def batch(*argv: str) -> tuple[int, str, str]:
    """``parksim batch ARGV`` in this process (so it uses the module's Ray instance): exit code, stdout, stderr."""
    out, err = io.StringIO(), io.StringIO()
    with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
        code = cli_main(["batch", *argv])
    return code, out.getvalue(), err.getvalue()


@pytest.fixture(scope="module")
def first_run(ray_address: str, datasets: dict[str, Path], tmp_path_factory: pytest.TempPathFactory
              ) -> tuple[Path, int, str, str]:
    """a and b trained from scratch, c resumed from a run stopped at iteration 10 (as a kill would), bad failing."""
    scenes = tmp_path_factory.mktemp("batch") / "scenes"
    reconstruct(datasets["c"], scenes / "c", "tiny", stop_after=10, log=lambda s: None)
    code, out, err = batch(*(str(datasets[n]) for n in ("a", "b", "c", "bad")), "-o", str(scenes), "--config",
                           "tiny", "--cpus-per-task", "1", "--progress-every", "0")
    return scenes, code, out, err


def _row(table: str, name: str) -> list[str]:
    return next(line.split() for line in table.splitlines() if line.split()[0] == name)


def _files(folder: Path) -> dict[str, tuple[int, bytes]]:
    return {str(p.relative_to(folder)): (p.stat().st_mtime_ns, p.read_bytes())
            for p in sorted(folder.rglob("*")) if p.is_file()}


def test_two_scenes_train_and_a_broken_one_fails_alone_after_one_retry(first_run, datasets) -> None:
    scenes, code, out, err = first_run
    assert code == 1
    for name in ("a", "b"):
        bundle = load(scenes / name)
        assert bundle.meta["iterations"] == 20 and bundle.meta["dataset"] == str(datasets[name])
        assert _row(out, name)[1:4] == ["trained", "1", "20"]
        assert f"{name}: iteration 20, train PSNR" in err
    assert not (scenes / "bad").exists()
    attempts = [line for line in err.splitlines() if line.startswith("bad: attempt")]
    assert len(attempts) == 2 and all("DatasetError" in line and "rig.json" in line for line in attempts)
    assert attempts[0].endswith("; retrying (from its last checkpoint, if any)") and attempts[1].endswith("giving up")
    bad = _row(out, "bad")
    assert bad[1:3] == ["failed", "2"] and "DatasetError:" in bad and any("rig.json" in cell for cell in bad)
    assert err.rstrip().splitlines()[-1] == "parksim batch: 1 of 4 scene(s) failed: bad"


def test_a_killed_run_resumes_from_its_checkpoint_and_ends_as_an_uninterrupted_one(first_run) -> None:
    scenes, code, out, err = first_run
    assert "c: resumed at iteration 10" in err and _row(out, "c")[1:4] == ["resumed", "1", "20"]
    resumed, straight = load(scenes / "c").scene, load(scenes / "a").scene   # c is a copy of a's data
    assert len(resumed) == len(straight)
    for name in ("means", "quats", "log_scales", "opacity_logits", "sh"):   # as test_recon's kill-and-resume test
        assert getattr(resumed, name).allclose(getattr(straight, name), rtol=1e-4, atol=1e-5), name


def test_a_rerun_joining_the_cluster_skips_finished_bundles_and_leaves_them_alone(first_run, ray_address,
                                                                                 datasets) -> None:
    """Through the entry point, joining the module's instance with --address."""
    scenes = first_run[0]
    names = ("a", "b", "c")
    before = {name: _files(scenes / name) for name in names}
    done = subprocess.run([sys.executable, "-m", "parksim.cli", "batch", *(str(datasets[n]) for n in names),
                           "-o", str(scenes), "--config", "tiny", "--address", ray_address],
                          capture_output=True, text=True, timeout=240, cwd=ROOT)
    assert done.returncode == 0, done.stderr
    assert [_row(done.stdout, n)[1] for n in names] == ["skipped"] * 3
    assert {name: _files(scenes / name) for name in names} == before


def test_a_finished_bundle_of_another_config_is_refused_and_kept(first_run, datasets) -> None:
    scenes = first_run[0]
    before = _files(scenes / "a")
    code, out, err = batch(str(datasets["a"]), "-o", str(scenes), "--config", "cpu_fast")
    assert code == 1 and _row(out, "a")[1:3] == ["failed", "0"] and "holds a run with another config" in out
    assert _files(scenes / "a") == before


def test_duplicate_dataset_names_are_refused_before_any_work(datasets, tmp_path) -> None:
    other = tmp_path / "elsewhere" / "a"
    shutil.copytree(datasets["a"], other)
    code, out, err = batch(str(datasets["a"]), str(other), "-o", str(tmp_path / "scenes"), "--config", "tiny")
    assert code == 2 and err.count("\n") == 1 and "would both write" in err
    assert not (tmp_path / "scenes").exists()


def test_without_ray_batch_says_install_the_extra(datasets, tmp_path, monkeypatch) -> None:
    monkeypatch.setitem(sys.modules, "ray", None)
    code, out, err = batch(str(datasets["a"]), "-o", str(tmp_path / "scenes"), "--config", "tiny")
    assert code == 2 and err.count("\n") == 1 and "install parksim[ray]" in err
    assert not (tmp_path / "scenes").exists()


def test_reconstruct_and_the_cli_do_not_import_ray() -> None:
    """``batch`` is registered, yet building the CLI and importing the trainer leave Ray unimported."""
    code = ("import sys; import parksim.cli as cli, parksim.recon.reconstruct; cli.build_parser(); "
            "assert 'batch' in cli.COMMANDS; assert 'ray' not in sys.modules, 'ray imported'")
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120, cwd=ROOT)
    assert done.returncode == 0, done.stderr
