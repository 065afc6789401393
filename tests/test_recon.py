"""Reconstruction: training improves a tiny scene, kill-and-resume is exact, bad inputs fail cleanly."""

from __future__ import annotations

import math
import os
import re
import shutil
import subprocess
import sys
from pathlib import Path

import pytest
import torch
import yaml

from parksim.bundle import load
from parksim.data import DatasetReader
from parksim.recon.checkpoint import CheckpointError, checkpoint_path
from parksim.recon.config import ConfigError, TrainConfig, load_config
from parksim.recon.evaluate import evaluate_bundle, evaluate_views
from parksim.recon.init import initial_scene
from parksim.recon.losses import ssim_map
from parksim.recon.plots import read_metrics
from parksim.recon.reconstruct import reconstruct
from parksim.recon.response import CameraResponse
from parksim.recon.strategy_mcmc import relocation_correction

ROOT = Path(__file__).resolve().parents[1]
TINY = "tiny"


@pytest.fixture(scope="session")
def full_run(tiny_data: Path, tmp_path_factory: pytest.TempPathFactory) -> Path:
    """An uninterrupted tiny run."""
    return reconstruct(tiny_data, tmp_path_factory.mktemp("runs") / "full", TINY, log=lambda s: None)


def _files(folder: Path) -> dict[str, bytes]:
    return {str(p.relative_to(folder)): p.read_bytes() for p in sorted(folder.rglob("*")) if p.is_file()}


def test_loss_down_and_test_psnr_up(full_run: Path, tiny_data: Path) -> None:
    records = [r for r in read_metrics(full_run / "metrics.jsonl") if "loss" in r]
    assert records[-1]["iteration"] == load_config(TINY).photometric.iterations
    assert sum(r["loss"] for r in records[-2:]) < sum(r["loss"] for r in records[:2])
    reader = DatasetReader(tiny_data)
    views = [(f, c) for f in reader.split["test"] for c in reader.rig.names]
    config = load_config(TINY)
    start, _ = initial_scene(reader, config.init, 1, torch.Generator().manual_seed(config.run.seed))
    bundle = load(full_run)
    response = CameraResponse(reader.rig, 0.0)
    response.load_dict(bundle.meta["camera_response"])
    before = evaluate_views(start, reader, views, None, slots=False).mean("psnr")
    after = evaluate_views(bundle.scene, reader, views, response).mean("psnr")
    assert after > before + 0.5


def test_kill_and_resume_matches_uninterrupted(full_run: Path, tiny_data: Path, tmp_path: Path) -> None:
    out = tmp_path / "resumed"
    reconstruct(tiny_data, out, TINY, stop_after=10, log=lambda s: None)
    assert not (out / "gaussians.ply").exists() and checkpoint_path(out).is_file()
    with open(out / "metrics.jsonl", "a") as f:  # a line written after the checkpoint by the "killed" run
        f.write('{"iteration": 15, "loss": 9.0}\n')
    reconstruct(tiny_data, out, None, resume=True, log=lambda s: None)
    a, b = load(full_run).scene, load(out).scene
    assert len(a) == len(b)
    for name in ("means", "quats", "log_scales", "opacity_logits", "sh"):
        torch.testing.assert_close(getattr(a, name), getattr(b, name), rtol=1e-4, atol=1e-5)
    assert [r["iteration"] for r in read_metrics(out / "metrics.jsonl")] == \
        [r["iteration"] for r in read_metrics(full_run / "metrics.jsonl")]


def test_corrupt_checkpoint_is_a_clear_error_and_nothing_changes(full_run: Path, tiny_data: Path,
                                                                 tmp_path: Path) -> None:
    out = tmp_path / "broken"
    shutil.copytree(full_run, out)
    ckpt = checkpoint_path(out)
    ckpt.write_bytes(ckpt.read_bytes()[:1000])
    before = _files(out)
    with pytest.raises(CheckpointError, match="corrupt or truncated"):
        reconstruct(tiny_data, out, None, resume=True, log=lambda s: None)
    assert _files(out) == before


def test_config_typo_names_the_key_and_writes_nothing(tiny_data: Path, tmp_path: Path) -> None:
    bad = tmp_path / "bad.yaml"
    bad.write_text("photometric:\n  iteratons: 5\n")
    out = tmp_path / "never"
    with pytest.raises(ConfigError, match=r"photometric\.iteratons"):
        reconstruct(tiny_data, out, bad, log=lambda s: None)
    assert not out.exists()


def test_existing_run_is_not_overwritten(full_run: Path, tiny_data: Path) -> None:
    before = _files(full_run)
    with pytest.raises(ValueError, match="--resume"):
        reconstruct(tiny_data, full_run, TINY, log=lambda s: None)
    assert _files(full_run) == before


def test_paper_defaults_are_the_shipped_config() -> None:
    config = load_config("parkgaussian")
    assert config == TrainConfig()
    assert (config.photometric.iterations, config.slot_aware.iterations) == (20_000, 10_000)
    assert config.photometric.ssim_lambda == 0.2 and config.lr.means_final_factor == 0.01
    load_config("cpu_fast")


def test_the_30_minute_presets_differ_only_where_their_rows_do() -> None:
    """cpu_30min_ewa is cpu_30min but for the projection; the slot-aware one can start --from a cpu_30min run."""
    base, ewa, slot = (load_config(n) for n in ("cpu_30min", "cpu_30min_ewa", "cpu_30min_slot_aware"))
    assert (base.run.projection, ewa.run.projection) == ("ut", "ewa")
    assert ewa.model_copy(update={"run": ewa.run.model_copy(update={"projection": "ut"})}) == base
    assert all(getattr(slot, k) == getattr(base, k) for k in ("run", "init", "lr", "photometric", "densify"))
    assert base.slot_aware.iterations == 0 and slot.slot_aware.iterations > 0


def test_ewa_projection_is_a_photometric_baseline_the_bundle_records(full_run: Path, tiny_data: Path,
                                                                     tmp_path: Path) -> None:
    config = load_config(TINY).model_dump(mode="json")
    config["run"]["projection"] = "ewa"
    path = tmp_path / "ewa.yaml"
    path.write_text(yaml.safe_dump(config))
    out = reconstruct(tiny_data, tmp_path / "ewa", path, log=lambda s: None)
    assert load(out).meta["projection"] == "ewa" and load(full_run).meta["projection"] == "ut"
    first = [read_metrics(run / "metrics.jsonl")[0]["rgb_loss"] for run in (out, full_run)]
    assert first[0] != first[1]   # same seed and views: only the footprints differ
    scored = evaluate_bundle(out, tiny_data, tmp_path / "eval", offpath=False)["overall"]["psnr"]
    reader, bundle = DatasetReader(tiny_data), load(out)
    response = CameraResponse(reader.rig, 0.0)
    response.load_dict(bundle.meta["camera_response"])
    views = [(f, c) for f in reader.split["test"] for c in reader.rig.names]
    by = {m: evaluate_views(bundle.scene, reader, views, response, method=m).mean("psnr") for m in ("ewa", "ut")}
    assert scored == by["ewa"] != by["ut"]   # eval renders a bundle with the projection it was trained with
    config["slot_aware"]["iterations"] = 5
    path.write_text(yaml.safe_dump(config))
    with pytest.raises(ConfigError, match="photometric-only baseline"):
        load_config(path)


def test_relocation_keeps_opacity_and_is_identity_for_one_copy() -> None:
    o = torch.tensor([0.3, 0.7, 0.95])
    s = torch.rand(3, 3) + 0.1
    new_o, new_s = relocation_correction(o, s, torch.ones(3))
    torch.testing.assert_close(new_o, o)
    torch.testing.assert_close(new_s, s)
    copies = torch.tensor([2.0, 3.0, 5.0])
    new_o, new_s = relocation_correction(o, s, copies)
    torch.testing.assert_close(1 - (1 - new_o) ** copies, o)
    assert bool((new_s < s).all())


def test_ssim_matches_kornia() -> None:
    import kornia

    g = torch.Generator().manual_seed(0)
    a, b = torch.rand(1, 3, 30, 40, generator=g), torch.rand(1, 3, 30, 40, generator=g)
    torch.testing.assert_close(ssim_map(a, b), kornia.metrics.ssim(a, b, 11))
    assert math.isclose(float(ssim_map(a, a).mean()), 1.0, rel_tol=1e-5)


def test_eval_report_has_slot_scores_and_no_invented_lpips(full_run: Path, tiny_data: Path, tmp_path: Path) -> None:
    from parksim.recon.evaluate import evaluate_bundle

    result = evaluate_bundle(full_run, tiny_data, tmp_path / "eval")
    assert result["overall"]["psnr"] > 10 and 0 < result["overall"]["ssim"] <= 1
    assert result["overall"]["lpips"] is None and result["lpips"].startswith("not computed")
    assert "LPIPS: not computed" in (tmp_path / "eval" / "eval.md").read_text()
    assert any(v.get("slot_psnr") is not None for v in result["views"])
    assert len(list((tmp_path / "eval" / "renders").glob("*.png"))) == len(result["views"])


def test_lpips_from_weight_files(tmp_path: Path) -> None:
    from parksim.recon.lpips import _NETS, LPIPS, LPIPSError, _features

    g = torch.Generator().manual_seed(0)
    backbone = {f"features.{k}": torch.randn(v.shape, generator=g) * 0.1
                for k, v in _features(_NETS["alex"][0]).state_dict().items()}
    torch.save(backbone, tmp_path / "alexnet.pth")
    widths = [64, 192, 384, 256, 256]
    torch.save({f"lin{i}.model.1.weight": torch.rand(1, c, 1, 1, generator=g) for i, c in enumerate(widths)},
               tmp_path / "alex.pth")
    lpips = LPIPS("alex", tmp_path / "alexnet.pth", tmp_path / "alex.pth")
    a, b = torch.rand(64, 64, 3, generator=g), torch.rand(64, 64, 3, generator=g)
    mask = torch.ones(64, 64, dtype=torch.bool)
    assert lpips(a, a, mask) == 0.0 and lpips(a, b, mask) > 0
    with pytest.raises(LPIPSError, match="do not fit"):
        LPIPS("vgg", tmp_path / "alexnet.pth", tmp_path / "alex.pth")


def test_similarity_alignment_recovers_a_known_transform() -> None:
    from parksim.geometry import rotation_from_quaternion
    from parksim.recon.colmap import align_similarity

    g = torch.Generator().manual_seed(1)
    src = torch.randn(20, 3, generator=g, dtype=torch.float64).numpy()
    R = rotation_from_quaternion(torch.randn(4, generator=g, dtype=torch.float64)).numpy()
    dst = 2.5 * src @ R.T + [1.0, -2.0, 0.5]
    s, R_est, t = align_similarity(src, dst)
    assert abs(s - 2.5) < 1e-9 and abs(R_est - R).max() < 1e-9 and abs(t - [1.0, -2.0, 0.5]).max() < 1e-9


def test_colmap_errors_are_clear(tmp_path: Path) -> None:
    pytest.importorskip("pycolmap")
    from parksim.recon.colmap import ColmapError, read_colmap_points

    with pytest.raises(ColmapError, match="not found"):
        read_colmap_points(tmp_path / "none")
    (tmp_path / "empty").mkdir()
    with pytest.raises(ColmapError, match="not a readable COLMAP model"):
        read_colmap_points(tmp_path / "empty")


@pytest.mark.slow
@pytest.mark.skipif(not os.environ.get("PARKSIM_COLMAP_DATA"),
                    reason="set PARKSIM_COLMAP_DATA to a 640x480 synthetic dataset (e.g. data/scene1): "
                           "SfM takes ~1 min")
def test_sfm_recovers_poses_up_to_similarity(tmp_path: Path) -> None:
    pytest.importorskip("pycolmap")
    from parksim.recon.colmap import pose_errors, run_sfm, vehicle_poses

    data = Path(os.environ["PARKSIM_COLMAP_DATA"])
    reader = DatasetReader(data)
    model = run_sfm(data, tmp_path / "sfm", ["front"], frame_stride=2)
    errors = pose_errors(vehicle_poses(model, reader), reader)
    assert errors["frames"] >= 0.8 * len(reader.frames[::2])
    assert errors["position_rmse_m"] < 0.05 * errors["trajectory_length_m"] and errors["rotation_mean_deg"] < 2.0


def test_adc_strategy_densifies_and_keeps_optimizer_rows_aligned(tiny_data: Path, tmp_path: Path) -> None:
    from parksim.recon.trainer import Trainer

    base = load_config(TINY).model_dump()
    base["densify"]["strategy"] = "adc"
    base["densify"]["adc"].update(grad_threshold=1e-9, refine_start=2, refine_every=3, refine_stop=20, cap_max=1200)
    config = TrainConfig.model_validate(base)
    trainer = Trainer(DatasetReader(tiny_data), config, tmp_path, log=lambda s: None)
    trainer.initialise()
    n0 = len(trainer.params)
    stats = [trainer.iteration() for _ in range(6)]
    assert any(s.get("cloned", 0) + s.get("split", 0) > 0 for s in stats)
    assert len(trainer.params) != n0 and len(trainer.params) <= 1200
    for name, tensor in trainer.params.tensors.items():
        state = trainer.params.optimizer.state[tensor]
        assert state["exp_avg"].shape == tensor.shape, name


# --- a killed run leaves nothing that stops the next one --------------------------------------------
def test_resume_drops_a_torn_metrics_tail_and_says_so(full_run: Path, tiny_data: Path, tmp_path: Path,
                                                       capsys: pytest.CaptureFixture[str]) -> None:
    out = tmp_path / "torn"
    reconstruct(tiny_data, out, TINY, stop_after=10, log=lambda s: None)
    with open(out / "metrics.jsonl", "a") as f:  # the disk filled up mid-line
        f.write('{"iteration": 12, "loss": 0.3')
    capsys.readouterr()
    reconstruct(tiny_data, out, None, resume=True, log=lambda s: None)
    err = capsys.readouterr().err
    assert err.count("torn last line") == 1 and "metrics.jsonl" in err
    assert [r["iteration"] for r in read_metrics(out / "metrics.jsonl")] == \
        [r["iteration"] for r in read_metrics(full_run / "metrics.jsonl")]


def test_a_torn_line_before_the_tail_names_the_line_and_changes_nothing(tmp_path: Path) -> None:
    from parksim.recon.metrics_log import cut_back

    path = tmp_path / "metrics.jsonl"
    path.write_text('{"iteration": 2}\n{"iteration": 4, "lo\n{"iteration": 6}\n')
    before = path.read_bytes()
    with pytest.raises(CheckpointError, match=r"metrics\.jsonl line 2: not a JSON record"):
        cut_back(path, 6)
    assert path.read_bytes() == before


def test_cutting_back_the_metrics_replaces_the_file(tmp_path: Path) -> None:
    """A rewrite in place that is killed would lose the kept records too; a new file is renamed over the old one."""
    from parksim.recon.metrics_log import cut_back

    path = tmp_path / "metrics.jsonl"
    path.write_text('{"iteration": 2}\n{"iteration": 4}\n{"iteration": 6}\n')
    inode = path.stat().st_ino
    cut_back(path, 4)
    assert path.read_text() == '{"iteration": 2}\n{"iteration": 4}\n'
    assert path.stat().st_ino != inode and [p.name for p in tmp_path.iterdir()] == ["metrics.jsonl"]


def test_stale_temp_files_are_removed_at_start_and_resume(tiny_data: Path, tmp_path: Path) -> None:
    out = tmp_path / "debris"
    kept = out / ".notes.txt"

    def litter() -> list[Path]:
        stale = [out / "checkpoints" / ".last.pt.tmp4242.pt", out / ".metrics.png.tmp4242.png",
                 out / ".config.yaml.tmp77.yaml"]
        for p in stale:
            p.parent.mkdir(parents=True, exist_ok=True)
            p.write_bytes(b"\0" * 1000)
        return stale

    stale = litter()
    kept.write_text("not a temp file")
    reconstruct(tiny_data, out, TINY, stop_after=10, log=lambda s: None)   # to the first checkpoint
    assert not any(p.exists() for p in stale)
    stale = litter()
    reconstruct(tiny_data, out, None, resume=True, stop_after=11, log=lambda s: None)
    assert not any(p.exists() for p in stale) and kept.is_file()


def test_a_corrupt_training_image_fails_before_training_naming_it(tiny_data: Path, tmp_path: Path) -> None:
    from parksim.data import DatasetError

    data = tmp_path / "data"
    shutil.copytree(tiny_data, data)
    reader = DatasetReader(data)
    bad = reader.layout.image(reader.rig.names[-1], reader.split["train"][-1])
    bad.write_bytes(os.urandom(bad.stat().st_size))
    out = tmp_path / "never"
    with pytest.raises(DatasetError, match=re.escape(str(bad))):
        reconstruct(data, out, TINY, log=lambda s: None)
    assert not out.exists()


# --- the first run's kernel compile is announced, a cached run is quiet ----------------------------
def test_compile_notice_is_said_once_per_block_and_only_for_a_real_compile() -> None:
    import numba

    from parksim.recon.compile_notice import NOTICE, compile_notice

    said: list[str] = []
    add, scale = numba.njit(lambda x: x + 1), numba.njit(lambda x: 2 * x)
    with compile_notice(said.append):
        add(1), add(2.5), scale(3)          # three compiles, one notice
    assert said == [NOTICE]
    with compile_notice(said.append):
        add(4)                              # compiled already: nothing to say
    scale(1.5)                              # outside a block: nobody listens
    assert said == [NOTICE]


def test_compile_notice_is_quiet_when_numba_s_disk_cache_has_the_kernel(tmp_path: Path) -> None:
    (tmp_path / "kern.py").write_text("import numba\n\n@numba.njit(cache=True)\ndef twice(x):\n    return 2 * x\n")
    script = ("import kern\nfrom parksim.recon.compile_notice import compile_notice\n"
              "with compile_notice():\n    kern.twice(3)\n")
    env = {**os.environ, "NUMBA_CACHE_DIR": str(tmp_path / "cache"),
           "PYTHONPATH": os.pathsep.join([str(tmp_path), str(ROOT)])}
    runs = [subprocess.run([sys.executable, "-c", script], env=env, cwd=tmp_path, capture_output=True, text=True,
                           timeout=120, check=True) for _ in range(2)]
    assert "compiling render kernels" in runs[0].stderr          # cold cache: compiled
    assert "compiling render kernels" not in runs[1].stderr      # loaded from the cache folder
    assert list((tmp_path / "cache").rglob("kern.twice-*.nbi"))


# --- densification strategies share one contract ---------------------------------------------------
def test_strategy_registry_is_the_config_s_choice_and_an_unknown_name_is_a_config_error() -> None:
    from typing import get_args

    from parksim.recon.config import DensifyConfig, parse_config
    from parksim.recon.strategy import STRATEGIES, make_strategy

    assert set(get_args(DensifyConfig.model_fields["strategy"].annotation)) == set(STRATEGIES)
    with pytest.raises(ConfigError, match=r"densify\.strategy: unknown strategy 'gmm'; choose one of mcmc, adc"):
        make_strategy(DensifyConfig().model_copy(update={"strategy": "gmm"}), 1.0)
    with pytest.raises(ConfigError, match=r"densify\.strategy"):
        parse_config({"densify": {"strategy": "gmm"}}, "test")


@pytest.mark.parametrize("name", ["mcmc", "adc"])
def test_every_registered_strategy_keeps_the_contract(name: str, tiny_data: Path, tmp_path: Path) -> None:
    import inspect

    from parksim.recon.strategy import STRATEGIES, Strategy
    from parksim.recon.trainer import Trainer

    cls = STRATEGIES[name]
    assert issubclass(cls, Strategy) and not inspect.isabstract(cls)
    for hook in ("__init__", "step_pre_backward", "step_post_backward", "step_post_update", "state_dict",
                 "load_state_dict"):
        assert inspect.signature(getattr(cls, hook)) == inspect.signature(getattr(Strategy, hook)), hook
    base = load_config(TINY).model_dump()
    base["densify"]["strategy"] = name
    base["densify"][name].update(refine_start=0, refine_every=2)
    trainer = Trainer(DatasetReader(tiny_data), TrainConfig.model_validate(base), tmp_path, log=lambda s: None)
    trainer.initialise()
    assert type(trainer.strategy) is cls
    refined = [trainer.iteration() for _ in range(2)][-1]     # step 2 refines
    assert set(refined) >= {"mcmc": {"relocated", "added"}, "adc": {"cloned", "split", "pruned"}}[name]
    state = trainer.strategy.state_dict()
    again = cls(trainer.cfg.densify, trainer.extent)
    again.load_state_dict(state)
    assert again.state_dict().keys() == state.keys()
    assert all(torch.equal(again.state_dict()[k], v) for k, v in state.items())


def test_slot_region_mask_equals_the_brute_force_floor_distance(tiny_data: Path) -> None:
    """Cached rays, 2 m cells and per-chunk segment culling change nothing: every pixel's ray hits the floor within
    SLOT_RADIUS of some slot edge (distance to every edge, float64) exactly where the mask says so."""
    from parksim.camera import pixel_grid
    from parksim.recon.metrics import SLOT_RADIUS, slot_region_mask, slot_segments

    reader = DatasetReader(tiny_data)
    segments = slot_segments(reader.map)
    a, ab = segments[:, 0], segments[:, 1] - segments[:, 0]
    slot_pixels = 0
    for frame in reader.split["test"]:
        for name, cam in reader.rig.cameras.items():
            T = reader.pose(frame).to(torch.float64) @ cam.T_vehicle_camera
            grid = pixel_grid(cam.model.width, cam.model.height)
            rays = cam.model.unproject(grid) @ T[:3, :3].T
            down = rays[..., 2] < -1e-6
            t = torch.where(down, -T[2, 3] / torch.where(down, rays[..., 2], -1.0), 0.0)
            hit = (T[:2, 3] + t[..., None] * rays[..., :2])[..., None, :]
            s = (((hit - a) * ab).sum(-1) / (ab * ab).sum(-1)).clamp(0, 1)
            near = (hit - (a + s[..., None] * ab)).norm(dim=-1).amin(-1) <= SLOT_RADIUS
            depth = reader.depth(name, frame)
            expected = down & cam.model.pixel_valid(grid) & near & ((depth <= 0) | (depth >= t - 0.1))
            mask = slot_region_mask(cam, reader.pose(frame), segments, depth)
            assert torch.equal(mask, expected), (frame, name)
            slot_pixels += int(mask.sum())
    assert slot_pixels > 1000
