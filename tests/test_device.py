"""``--device`` on ``parksim render``, ``serve`` and ``compact``, ``device=`` on ``LocalSim`` and the env, and
``--replica-gpus`` on ``parksim serve --ray``.

On a machine without a usable GPU (no CUDA device, or the CUDA extra missing) ``cuda`` is one line and exit
status 2 before anything is read or written, and the default ``auto`` is the CPU, bit for bit what the commands
did before they had the flag. Tests that need the GPU to be missing skip where there is one.
"""

from __future__ import annotations

import socket
from pathlib import Path

import numpy as np
import pytest
import torch

from parksim.cli import build_parser, main
from parksim.device import DeviceError, cuda_extra_missing, resolve_device
from parksim.env import ParkingEnv
from parksim.imageio import read_image, to_uint8
from parksim.render import render
from parksim.server import Settings, create_app
from parksim.sim import LocalSim
from sim_fixtures import make_bundle

NO_GPU = not torch.cuda.is_available() or bool(cuda_extra_missing())
"""No usable CUDA device here: ``auto`` is the CPU and ``cuda`` an error."""
needs_no_gpu = pytest.mark.skipif(not NO_GPU, reason="a usable CUDA device is here: cuda resolves")
POSE = "4,0,0"


@pytest.fixture(scope="module")
def bundle(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return make_bundle(tmp_path_factory.mktemp("bundle") / "garage", n=2000)


def one_line(err: str, command: str) -> str:
    """The single stderr line of a failed ``parksim COMMAND`` (besides a numba kernel-compile notice)."""
    lines = [line for line in err.splitlines() if not line.startswith("compiling render kernels")]
    assert len(lines) == 1 and err.endswith("\n"), err
    assert lines[0].startswith(f"parksim {command}: error: "), err
    return lines[0]


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


@needs_no_gpu
def test_auto_is_the_cpu_here():
    assert resolve_device() == resolve_device("auto") == torch.device("cpu")


@pytest.mark.parametrize("spec", ["cpu", " CPU ", torch.device("cpu")])
def test_cpu_resolves(spec):
    assert resolve_device(spec) == torch.device("cpu")


@pytest.mark.parametrize("spec, why", [
    pytest.param("cuda", "no CUDA device here", marks=needs_no_gpu),
    pytest.param("cuda:1", "no CUDA device here", marks=needs_no_gpu),
    ("gpu", "not one of auto, cpu, cuda, cuda:N"),
    ("cuda:x", "not one of auto, cpu, cuda, cuda:N"),
])
def test_bad_devices_are_one_line_naming_the_value(spec, why):
    with pytest.raises(DeviceError) as raised:
        resolve_device(spec)
    text = str(raised.value)
    assert "\n" not in text and f"device {spec!r}" in text and why in text


def _argv(command: str, bundle: Path, out: Path, device: str) -> list[str]:
    return {"render": ["render", str(bundle), "--pose", POSE, "-o", str(out), "--device", device],
            "compact": ["compact", str(bundle), "-o", str(out), "--quiet", "--device", device],
            "serve": ["serve", "--scenes", str(bundle), "--port", str(_free_port()), "--device", device]}[command]


@pytest.mark.parametrize("device, message", [
    pytest.param("cuda", "device 'cuda': no CUDA device here", marks=needs_no_gpu),
    ("gpu", "device 'gpu': not one of auto, cpu, cuda, cuda:N"),
])
@pytest.mark.parametrize("command", ["render", "compact", "serve"])
def test_a_device_that_cannot_run_is_one_line_and_writes_nothing(bundle, tmp_path, capsys, command, device,
                                                                  message):
    out = tmp_path / "out"
    assert main(_argv(command, bundle, out, device)) == 2
    assert message in one_line(capsys.readouterr().err, command)
    assert list(tmp_path.iterdir()) == []


def test_render_on_the_cpu_is_the_default_render_byte_for_byte(bundle, tmp_path, capsys):
    """``--device cpu`` writes the files the flagless command writes, and those are the library's render."""
    argv = ["render", str(bundle), "--pose", POSE, "--bev", "--depth", "--scale", "0.5"]
    assert main([*argv, "-o", str(tmp_path / "default")]) == 0
    assert main([*argv, "--device", "cpu", "-o", str(tmp_path / "cpu")]) == 0
    out = capsys.readouterr().out
    assert out.count(" on cpu in ") == (2 if NO_GPU else 1), out
    files = sorted(p.name for p in (tmp_path / "cpu").iterdir())
    assert files == sorted(p.name for p in (tmp_path / "default").iterdir()) and "bev.png" in files
    if NO_GPU:
        for name in files:
            assert (tmp_path / "cpu" / name).read_bytes() == (tmp_path / "default" / name).read_bytes(), name
    from parksim.bundle import load

    b = load(bundle)
    want = render(b.scene, b.rig, [4.0, 0.0, 0.0], bev=True, scale=0.5)
    for name, image in want.images.items():
        assert np.array_equal(to_uint8(read_image(tmp_path / "cpu" / f"{name}.png")), to_uint8(image)), name
        assert np.array_equal(np.load(tmp_path / "cpu" / f"{name}_depth.npy"), want.depth[name].detach().numpy()), name
    assert np.array_equal(to_uint8(read_image(tmp_path / "cpu" / "bev.png")), to_uint8(want.bev))


def test_local_sim_on_the_cpu_renders_as_the_default(bundle):
    default, cpu = LocalSim(bundle), LocalSim(bundle, device="cpu")
    assert default.device == cpu.device == torch.device("cpu") or not NO_GPU
    a, b = (sim.render([4.0, 0.5, 0.2], bev=True, scale=0.5, depth=True) for sim in (default, cpu))
    assert a.images.keys() == b.images.keys() == set(cpu.cameras)
    for name in a.images:
        assert np.array_equal(a.images[name], b.images[name]) and np.array_equal(a.depth[name], b.depth[name])
    assert np.array_equal(a.bev, b.bev)


def test_local_sim_keeps_a_given_bundle_unchanged(bundle):
    """A ``Bundle`` handed in is not moved: the simulator keeps its own copy when its device differs."""
    from parksim.bundle import load

    b = load(bundle)
    means = b.scene.means
    sim = LocalSim(b, device="cpu")
    assert b.scene.means is means and sim.bundle.scene.means.device == torch.device("cpu")


@needs_no_gpu
def test_local_sim_refuses_cuda_before_reading_the_bundle(tmp_path):
    with pytest.raises(DeviceError, match="no CUDA device here"):
        LocalSim(tmp_path / "no-such-bundle", device="cuda")


@needs_no_gpu
def test_env_on_cuda_raises_the_device_error(bundle):
    with pytest.raises(DeviceError, match="device 'cuda': no CUDA device here"):
        ParkingEnv(bundle=bundle, device="cuda")


def test_env_on_the_cpu_observes_as_the_default(bundle):
    default, cpu = ParkingEnv(bundle=bundle), ParkingEnv(bundle=bundle, device="cpu")
    a, _ = default.reset(seed=3)
    b, _ = cpu.reset(seed=3)
    assert a.keys() == b.keys() and all(np.array_equal(a[k], b[k]) for k in a)


@pytest.mark.parametrize("source", [{"server": "http://127.0.0.1:9"}, {"sim": object()}])
def test_env_device_with_a_server_or_sim_is_a_value_error(source):
    with pytest.raises(ValueError, match="device='cpu' applies to bundle= only") as raised:
        ParkingEnv(device="cpu", **source)
    assert "\n" not in str(raised.value)


def test_server_refuses_a_bad_device_instead_of_every_bundle(bundle):
    """The device is resolved once, before any bundle loads: a bad one is the caller's error, not a refusal."""
    with pytest.raises(DeviceError, match="device 'gpu'"):
        create_app(bundle.parent, Settings(device="gpu"))
    assert create_app(bundle.parent, Settings(device="cpu")).state.registry.get(None).device == torch.device("cpu")


def test_replica_gpus_is_parsed_and_reserved():
    pytest.importorskip("ray.serve")
    from parksim.server.ray_serve import Scaling

    args = build_parser().parse_args(["serve", "--scenes", "s", "--ray", "--replica-gpus", "0.25"])
    assert args.replica_gpus == 0.25 and args.device == "auto"
    actor = Scaling(2, None, 1, args.replica_gpus).options(Settings())["ray_actor_options"]
    assert actor["num_gpus"] == 0.25 and actor["num_cpus"] == 1
    assert "CUDA_VISIBLE_DEVICES" not in actor["runtime_env"]["env_vars"]
    cpu_only = Scaling().options(Settings())["ray_actor_options"]
    assert cpu_only["num_gpus"] == 0 and cpu_only["runtime_env"]["env_vars"]["CUDA_VISIBLE_DEVICES"] == ""


@pytest.mark.parametrize("argv, message", [
    (["--replica-gpus", "-1"], "argument --replica-gpus: must be a finite number >= 0, got -1"),
    (["--replica-gpus", "0.5"], "--replica-gpus only applies with --ray"),
    (["--ray", "--device", "cuda"], "--device cuda with --ray needs --replica-gpus > 0"),
    (["--ray", "--replica-gpus", "1", "--device", "gpu"], "device 'gpu': not one of auto, cpu, cuda, cuda:N"),
])
def test_bad_gpu_flags_are_one_line_before_anything_starts(bundle, capsys, argv, message):
    assert main(["serve", "--scenes", str(bundle), "--port", str(_free_port()), *argv]) == 2
    assert message in one_line(capsys.readouterr().err, "serve")
