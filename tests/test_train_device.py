"""Training on a device (issue [15]): ``run.device`` and ``--device`` on reconstruct, eval and batch, the GPU presets,
checkpoints of CPU tensors that resume on any device, and the torch D-SSIM and PSNR a GPU step uses.

Without a GPU the CUDA cases are skipped and ``--device cuda`` must be one line and exit 2; with one (and the CUDA
extra) the same tests train, check and resume on it.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import pytest
import torch
import yaml

from parksim.cli import main
from parksim.device import cuda_extra_missing
from parksim.recon.checkpoint import checkpoint_path
from parksim.recon.config import ConfigError, TrainConfig, load_config, parse_config, preset_names
from parksim.recon.losses import _DSSIM, dssim_loss, dssim_torch
from parksim.recon.metrics import psnr, psnr_tensor
from parksim.recon.plots import read_metrics
from parksim.recon.reconstruct import CONFIG_FILE, reconstruct

HAS_CUDA = torch.cuda.is_available() and not cuda_extra_missing()
DEVICES = ["cpu", pytest.param("cuda", marks=pytest.mark.skipif(not HAS_CUDA, reason="needs a GPU and the CUDA extra"))]
NO_GPU = pytest.mark.skipif(torch.cuda.is_available(), reason="this machine has a GPU: --device cuda is valid here")


@pytest.fixture(scope="module")
def default_run(tiny_data: Path, tmp_path_factory: pytest.TempPathFactory) -> Path:
    """The tiny preset trained as the CLI trains it without --device."""
    return reconstruct(tiny_data, tmp_path_factory.mktemp("device") / "default", "tiny", log=lambda s: None)


def _tensors(value: Any, where: str = "") -> dict[str, torch.Tensor]:
    """Every tensor in a nested state, by its path."""
    if isinstance(value, torch.Tensor):
        return {where: value}
    items = value.items() if isinstance(value, dict) else enumerate(value) if isinstance(value, (list, tuple)) else []
    return {k: t for key, v in items for k, t in _tensors(v, f"{where}/{key}").items()}


def _files(folder: Path) -> dict[str, bytes]:
    return {str(p.relative_to(folder)): p.read_bytes() for p in sorted(folder.rglob("*")) if p.is_file()}


# --- config and presets --------------------------------------------------------------------------------------------
def test_run_device_is_cpu_by_default_and_in_every_cpu_preset() -> None:
    assert TrainConfig().run.device == "cpu"
    for name in preset_names():
        assert load_config(name).run.device == ("cuda" if name.startswith("gpu_") else "cpu"), name


def test_a_bad_device_name_is_a_config_error_and_the_device_is_not_part_of_the_run() -> None:
    with pytest.raises(ConfigError, match=r"run\.device"):
        parse_config({"run": {"device": "gpu"}}, "x.yaml")
    base = load_config("tiny")
    assert base.on_device("cuda:1").run.device == "cuda:1" and base.on_device("cuda:1").same_run(base)
    assert base.on_device("cuda:1") != base
    other_seed = base.model_copy(update={"run": base.run.model_copy(update={"seed": 1})})
    assert not other_seed.same_run(base)


def test_gpu_presets_validate_and_follow_the_schedules_they_cite() -> None:
    fast, paper, parkgaussian, cpu_30min = (load_config(n) for n in ("gpu_fast", "gpu_paper", "parkgaussian",
                                                                     "cpu_30min"))
    # gpu_paper is the paper's schedule: parkgaussian's numbers in everything but the run mechanics
    assert paper.model_copy(update={"run": parkgaussian.run}) == parkgaussian
    assert paper.schedule_iterations == 30_000 and paper.densify.mcmc == TrainConfig().densify.mcmc
    # gpu_fast: photometric only like cpu_30min, longer, a larger cap, refinement ending before the last steps
    mcmc = fast.densify.mcmc
    assert fast.slot_aware.iterations == 0 and fast.photometric.iterations > cpu_30min.photometric.iterations
    assert mcmc.cap_max > cpu_30min.densify.mcmc.cap_max and mcmc.refine_stop < fast.photometric.iterations
    assert fast.photometric.sh_degree == 3 and fast.run.log_every >= cpu_30min.run.log_every


# --- the commands without a GPU --------------------------------------------------------------------------------------
@NO_GPU
@pytest.mark.parametrize("command", ["reconstruct", "reconstruct-preset", "eval", "batch"])
def test_cuda_without_a_gpu_is_one_line_exit_2_and_writes_nothing(command: str, default_run: Path, tiny_data: Path,
                                                                    tmp_path: Path,
                                                                    capsys: pytest.CaptureFixture[str]) -> None:
    if command == "batch":
        pytest.importorskip("ray")
    out = tmp_path / "out"
    argv = {"reconstruct": ["reconstruct", str(tiny_data), "-o", str(out), "--config", "tiny", "--device", "cuda"],
            "reconstruct-preset": ["reconstruct", str(tiny_data), "-o", str(out), "--config", "gpu_fast"],
            "eval": ["eval", str(default_run), str(tiny_data), "-o", str(out), "--device", "cuda"],
            "batch": ["batch", str(tiny_data), "-o", str(out), "--config", "tiny", "--device", "cuda"]}[command]
    before = _files(default_run)
    assert main(argv) == 2
    captured = capsys.readouterr()
    assert captured.out == "" and len(captured.err.strip().splitlines()) == 1
    assert "device 'cuda'" in captured.err and "--device cpu" in captured.err
    assert not out.exists() and _files(default_run) == before


def test_batch_refuses_gpu_settings_no_task_could_run_with(tmp_path: Path,
                                                           capsys: pytest.CaptureFixture[str]) -> None:
    pytest.importorskip("ray")
    from parksim.recon.batch import check_gpus

    with pytest.raises(ValueError, match="needs --gpus-per-task > 0"):
        check_gpus("cuda", 0.0)
    with pytest.raises(ValueError, match="a fraction below 1 or a whole number"):
        check_gpus("cpu", 1.5)
    assert main(["batch", str(tmp_path), "-o", str(tmp_path / "out"), "--gpus-per-task", "-1"]) == 2
    assert "--gpus-per-task" in capsys.readouterr().err


# --- on a device ----------------------------------------------------------------------------------------------------
def test_device_cpu_reproduces_the_default_bit_for_bit(default_run: Path, tiny_data: Path, tmp_path: Path) -> None:
    run = reconstruct(tiny_data, tmp_path / "cpu", "tiny", log=lambda s: None, device="cpu")
    assert (run / "gaussians.ply").read_bytes() == (default_run / "gaussians.ply").read_bytes()
    assert (run / CONFIG_FILE).read_text() == (default_run / CONFIG_FILE).read_text()
    a, b = (_tensors(torch.load(checkpoint_path(r), weights_only=True)) for r in (run, default_run))
    assert a.keys() == b.keys() and all(torch.equal(a[k], b[k]) for k in a)

    def records(r: Path) -> list[dict[str, Any]]:
        return [{k: v for k, v in rec.items() if k not in ("elapsed_s", "cpu_s")}
                for rec in read_metrics(r / "metrics.jsonl")]

    assert records(run) == records(default_run)


@pytest.mark.parametrize("device", DEVICES)
def test_checkpoints_hold_cpu_tensors_and_resume_on_the_cpu(device: str, default_run: Path, tiny_data: Path,
                                                             tmp_path: Path) -> None:
    out = tmp_path / "run"
    logs: list[str] = []
    reconstruct(tiny_data, out, "tiny", stop_after=10, log=logs.append, device=device)
    assert sum(line.startswith(f"training on {device}") for line in logs) == 1
    state = torch.load(checkpoint_path(out), weights_only=True)   # no map_location: tensors as they were saved
    tensors = _tensors(state)
    assert tensors and {t.device.type for t in tensors.values()} == {"cpu"}
    assert yaml.safe_load((out / CONFIG_FILE).read_text())["run"]["device"] == device
    reconstruct(tiny_data, out, None, resume=True, log=lambda s: None, device="cpu")
    assert json.loads((out / "bundle.json").read_text())["iterations"] == load_config("tiny").photometric.iterations
    if device == "cpu":   # the CPU's own resume is as exact as test_recon's kill-and-resume
        a, b = (torch.load(checkpoint_path(r), weights_only=True)["params"] for r in (out, default_run))
        for name in a:
            torch.testing.assert_close(a[name], b[name], rtol=1e-4, atol=1e-5)


def test_a_run_written_for_a_gpu_resumes_on_the_cpu(tiny_data: Path, tmp_path: Path) -> None:
    """A run started with ``run.device: cuda`` (its config.yaml and checkpoint say so, as a GPU machine writes them)
    continues with ``--device cpu``; the config is compared without its device."""
    out = tmp_path / "run"
    reconstruct(tiny_data, out, "tiny", stop_after=10, log=lambda s: None)
    stored = load_config(out / CONFIG_FILE).on_device("cuda")
    (out / CONFIG_FILE).write_text(yaml.safe_dump(stored.model_dump(mode="json"), sort_keys=False))
    state = torch.load(checkpoint_path(out), weights_only=True)
    torch.save({**state, "config": stored.model_dump(mode="json")}, checkpoint_path(out))
    if not torch.cuda.is_available():
        with pytest.raises(ValueError, match="no CUDA device"):
            reconstruct(tiny_data, out, None, resume=True, log=lambda s: None)
    reconstruct(tiny_data, out, "tiny", resume=True, log=lambda s: None, device="cpu")
    assert [r["iteration"] for r in read_metrics(out / "metrics.jsonl")][-1] == 20
    assert load_config(out / CONFIG_FILE).run.device == "cuda"   # the run's own record is kept


# --- the losses and metrics a GPU step uses ---------------------------------------------------------------------------
def _images(seed: int) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    g = torch.Generator().manual_seed(seed)
    pred, gt = torch.rand(2, 3, 40, 53, generator=g), torch.rand(2, 3, 40, 53, generator=g)
    mask = torch.rand(2, 1, 40, 53, generator=g)
    mask[mask < 0.3] = 0.0
    return pred, gt, mask


def _value_and_grad(fn: Any, pred: torch.Tensor, gt: torch.Tensor, mask: torch.Tensor) -> tuple[float, torch.Tensor]:
    leaf = pred.detach().clone().requires_grad_()
    loss = fn(leaf, gt, mask)
    loss.backward()
    return float(loss.detach()), leaf.grad


@pytest.mark.parametrize("device", DEVICES)
def test_torch_dssim_equals_the_fused_cpu_kernel_in_float32(device: str) -> None:
    """The D-SSIM a GPU trains with (``dssim_torch``; ``dssim_loss`` off the CPU) against the numba kernels, both in
    float32: value and gradient within float32 rounding of sums over a few hundred terms."""
    pred, gt, mask = _images(3)
    want, want_grad = _value_and_grad(_DSSIM.apply, pred, gt, mask)
    fn = dssim_torch if device == "cpu" else dssim_loss
    got, got_grad = _value_and_grad(fn, *(t.to(device) for t in (pred, gt, mask)))
    eps = torch.finfo(torch.float32).eps
    assert got_grad.device.type == device and abs(got - want) <= 64 * eps
    assert (got_grad.cpu() - want_grad).abs().max().item() <= 64 * eps * want_grad.abs().max().item()
    gt_leaf = gt.clone().to(device).requires_grad_()   # differentiable in every input, unlike the fused kernel
    dssim_torch(pred.to(device), gt_leaf, mask.to(device)).backward()
    assert gt_leaf.grad is not None and torch.isfinite(gt_leaf.grad).all()


def test_the_device_psnr_equals_the_host_one() -> None:
    p, g, m = _images(4)
    pred, gt, mask = p[0].permute(1, 2, 0), g[0].permute(1, 2, 0), m[0, 0] > 0.5
    assert float(psnr_tensor(pred, gt, mask)) == pytest.approx(psnr(pred, gt, mask), rel=1e-12)
    assert float(psnr_tensor(gt, gt, mask)) == psnr(gt, gt, mask) == float("inf")
