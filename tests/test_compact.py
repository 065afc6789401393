"""Scene compaction: the weight pass against the torch oracle, pruning, SH lowering, visibility, bundle I/O, CLI."""

import dataclasses
import math
import shutil

import numpy as np
import pytest
import torch

from parksim import bundle as bundle_io
from parksim.cli import main
from parksim.compact import (
    CompactOptions,
    lower_sh,
    measure_bundle,
    pose_weights,
    reduce_bundle,
    select,
    summed_weights,
)
from parksim.data import DatasetReader
from parksim.gaussians import GaussianScene
from parksim.recon.config import load_config
from parksim.recon.evaluate import evaluate_views
from parksim.recon.finetune import finetune
from parksim.recon.trainer import Trainer
from parksim.render import render
from parksim.render.rasterize.contribution import max_weights
from parksim.render.rasterize.reference import max_weights_reference
from parksim.render.sh import eval_sh
from parksim.sim import LocalSim
from sim_fixtures import make_bundle
from tolerances import f32_ulp

OPTIONS = CompactOptions(cell=8.0, per_cell=2, margin=1.0, ranking="benefit-cost")
COSTLY, CHEAP = -4, -3
"""Rows of the garage fixture's two added, visible Gaussians: a wide faint one and a small opaque one."""


def _random_2d(m: int, width: int, height: int, seed: int) -> tuple[torch.Tensor, ...]:
    """Random image-space Gaussians, a few big opaque ones in front so that pixels stop early."""
    g = torch.Generator().manual_seed(seed)
    means = torch.rand(m, 2, generator=g) * torch.tensor([width, height], dtype=torch.float32)
    sigma = 0.5 + 5 * torch.rand(m, 2, generator=g)
    rho = 0.8 * (torch.rand(m, generator=g) - 0.5)
    cov = torch.stack([sigma[:, 0] ** 2, rho * sigma[:, 0] * sigma[:, 1], sigma[:, 1] ** 2], 1)
    det = cov[:, 0] * cov[:, 2] - cov[:, 1] ** 2
    conics = torch.stack([cov[:, 2], -cov[:, 1], cov[:, 0]], 1) / det[:, None]
    opacities = torch.rand(m, generator=g)
    opacities[: m // 10] = 0.99
    depths = 1 + 10 * torch.rand(m, generator=g)
    depths[: m // 10] *= 0.1
    return means, conics, opacities, depths


def test_max_weights_match_the_torch_oracle():
    width, height = 53, 37
    means, conics, opacities, depths = _random_2d(400, width, height, seed=1)
    # One Gaussian right behind an opaque stack covering it: every pixel it reaches stops before it.
    centre = torch.tensor([20.0, 20.0])
    means[-1], conics[-1], opacities[-1], depths[-1] = centre, torch.tensor([1.0, 0, 1.0]), 0.9, 50.0
    stack = slice(-9, -1)
    means[stack], conics[stack], opacities[stack], depths[stack] = centre, torch.tensor([0.01, 0, 0.01]), 0.99, 0.01
    fast = max_weights(means, conics, opacities, depths, width, height)
    ref = max_weights_reference(means.double(), conics.double(), opacities.double(), depths.double(), width, height)
    assert torch.allclose(fast.double(), ref, atol=2e-5)
    assert fast[-1] == 0 and ref[-1] == 0
    assert (fast > 0).sum() > 100 and ((fast > 0) == (ref > 0)).all()


@pytest.fixture(scope="module")
def garage(tmp_path_factory, tiny_data):
    """A small garage bundle (the ``tiny`` preset's, like ``tiny_data``) measured with the benefit-cost ranking.

    Four Gaussians are appended, in front of the first training frame: a wide faint one (COSTLY) and a small
    opaque one (CHEAP), then two that can never show: a transparent one and one past far.
    """
    path = make_bundle(tmp_path_factory.mktemp("garage") / "full", n=600, size=(64, 48))
    b = bundle_io.load(path)
    s = b.scene
    reader = DatasetReader(tiny_data)
    ahead = reader.pose(reader.split["train"][0]).float() @ torch.tensor([[4.0, 2.0, 1.5, 1.0], [4.0, -1.0, 1.0, 1.0],
                                                                          [10.0, 0.0, 1.0, 1.0], [5000.0, 0, 1, 1]]).T
    extra = GaussianScene(ahead[:3].T.contiguous(), s.quats[:4], torch.log(torch.tensor([1.5, 0.05, 0.1, 0.1]))
                          [:, None].expand(4, 3).contiguous(), torch.tensor([-3.5, 5.0, -12.0, 5.0]), s.sh[:4],
                          s.sh_degree)
    scene = GaussianScene(*(torch.cat([getattr(s, k), getattr(extra, k)]) for k in
                            ("means", "quats", "log_scales", "opacity_logits", "sh")), s.sh_degree)
    refined = {"frames": [{"frame": 0, "timestamp": 0.0, "T_world_vehicle": torch.eye(4).tolist()}], "refined": [0]}
    b = bundle_io.Bundle(scene, b.rig, b.map, b.meta, poses=refined)
    bundle_io.save(path, b)
    measured = measure_bundle(b, OPTIONS, reader=reader)
    return path, b, measured.grid, measured.weights, measured


def test_never_seen_gaussians_are_dropped_and_seen_ones_kept(garage):
    _, b, grid, weights, _ = garage
    best = weights.amax(dim=0)
    n = len(b.scene)
    assert best[n - 2] == 0 and best[n - 1] == 0
    keep = select(best, 1.0)
    assert n - 2 not in keep and n - 1 not in keep
    assert torch.equal(keep, (best > 0).nonzero().squeeze(1))
    half = select(best, 0.5)
    assert len(half) == round(0.5 * n) and best[half].min() >= best[~torch.isin(torch.arange(n), half)].max()
    assert len(select(best, 100.0)) == 100


def test_compact_render_matches_full_at_measured_poses(garage):
    _, b, grid, weights, measured = garage
    compact = reduce_bundle(b, measured, OPTIONS)
    assert len(compact.scene) < len(b.scene)
    for pose in grid.poses[::7]:
        full = render(b.scene, b.rig, pose.tolist())
        small = render(compact.scene, b.rig, pose.tolist())
        for name in b.rig.names:
            assert torch.allclose(full.images[name], small.images[name], atol=1e-5), name


def test_weights_are_those_of_the_render(garage):
    _, b, grid, _, _ = garage
    w = pose_weights(b.scene, b.rig, grid.poses[3].tolist())
    keep = (w > 0).nonzero().squeeze(1)
    full = render(b.scene, b.rig, grid.poses[3].tolist())
    alone = render(b.scene.subset(keep), b.rig, grid.poses[3].tolist())
    dropped = render(b.scene.subset((w == w.max()).logical_not()), b.rig, grid.poses[3].tolist())
    assert all(torch.equal(full.images[n], alone.images[n]) for n in b.rig.names)
    assert any(not torch.allclose(full.images[n], dropped.images[n], atol=1e-3) for n in b.rig.names)


def test_lower_sh_stays_within_tolerance():
    scene = GaussianScene.random(200, sh_degree=2, seed=3)
    scene.sh[:100, 1:] *= 1e-3          # negligible view dependence
    scene.sh[100:150, 4:] = 0.0         # degree 1 only
    lowered, degrees = lower_sh(scene, tolerance=0.01)
    assert (degrees[:100] == 0).all() and (degrees[100:150] <= 1).all() and (degrees[150:] == 2).all()
    assert lowered.sh_degree == 2
    dirs = torch.nn.functional.normalize(torch.randn(200, 3, generator=torch.Generator().manual_seed(0)), dim=1)
    change = (eval_sh(scene.sh, dirs, 2) - eval_sh(lowered.sh, dirs, 2)).abs()
    assert change.max() <= 0.01 and change[150:].max() == 0
    flat, degrees = lower_sh(scene.subset(torch.arange(100)), tolerance=0.01)
    assert flat.sh_degree == 0 and flat.sh.shape == (100, 1, 3)


def test_visibility_subset_render_equals_full_render(garage, tmp_path):
    path, b, grid, weights, measured = garage
    out = tmp_path / "compact"
    bundle_io.save(out, reduce_bundle(b, measured, OPTIONS))
    full, compact = LocalSim(path), LocalSim(out)
    assert compact.bundle.visibility is not None and full.bundle.visibility is None
    subsets = 0
    for pose in grid.poses[::5]:
        subset = compact.scene_at(pose.tolist())
        subsets += len(subset) < len(compact.bundle.scene)
        a, c = full.render(pose.tolist()), compact.render(pose.tolist())
        for name in b.rig.names:
            assert np.abs(a.images[name].astype(int) - c.images[name].astype(int)).max() <= 1, name
    assert subsets > 0, "no cell culled anything: the test would not notice a wrong subset"
    assert compact.scene_at([-50.0, 0.0, 0.0]) is compact.bundle.scene             # outside the grid
    assert compact.scene_at([*grid.poses[0][:2], 0.5, 0, 0, 0]) is compact.bundle.scene  # not planar


def test_cell_budget_keeps_the_most_visible_from_each_cell(garage):
    _, b, grid, weights, measured = garage
    compact = reduce_bundle(b, measured, dataclasses.replace(OPTIONS, cell_budget=0.3))
    kept = weights[:, select(weights.amax(dim=0), 1.0)]
    for c in np.unique(grid.cells):
        members = torch.from_numpy(compact.visibility.members(c)).long()
        others = ~torch.isin(torch.arange(kept.shape[1]), members)
        assert len(members) == round(0.3 * kept.shape[1])
        assert kept[c, members].min() >= kept[c, others].max()


def test_visibility_round_trip_and_old_bundles(garage, tmp_path):
    path, b, grid, weights, measured = garage
    compact = reduce_bundle(b, measured, OPTIONS)
    bundle_io.save(tmp_path / "c", compact)
    back = bundle_io.load(tmp_path / "c")
    assert back.meta["visibility"] == "visibility.npz" and back.meta["compaction"]["gaussians"] == len(back.scene)
    assert np.array_equal(back.visibility.indices, compact.visibility.indices)
    assert bundle_io.load(path).visibility is None
    (tmp_path / "c" / "visibility.npz").unlink()
    with pytest.raises(bundle_io.BundleError, match="visibility"):
        bundle_io.load(tmp_path / "c")


def test_cli_writes_a_compact_bundle(garage, tmp_path, capsys):
    path = garage[0]
    out = tmp_path / "small"
    argv = ["compact", str(path), "-o", str(out), "--cell", "8", "--poses-per-cell", "1", "--budget", "0.5",
            "--cell-budget", "0.5", "--finetune", "0", "--quiet"]   # the default ranking needs no dataset
    assert main(argv) == 0
    assert "visibility cells" in capsys.readouterr().out
    small = bundle_io.load(out)
    assert small.meta["compaction"]["ranking"] == "weight"
    assert len(small.scene) == round(0.5 * len(bundle_io.load(path).scene)) and small.visibility is not None
    assert small.poses == garage[1].poses is not None   # refined poses travel with the compact bundle
    assert main(argv) == 2
    assert "exists; pass --overwrite" in capsys.readouterr().err
    assert main(argv + ["--overwrite", "--no-visibility"]) == 0
    assert bundle_io.load(out).visibility is None
    assert not [p for p in tmp_path.iterdir() if p.name.startswith(".")]


@pytest.mark.parametrize("budget", ["0", "-1", "2.5", "nan"])
def test_cli_rejects_a_bad_budget(garage, tmp_path, capsys, budget):
    assert main(["compact", str(garage[0]), "-o", str(tmp_path / "x"), f"--budget={budget}"]) == 2
    assert "budget" in capsys.readouterr().err and not (tmp_path / "x").exists()


def test_cli_errors_are_one_line_and_write_nothing(garage, tmp_path, capsys):
    assert main(["compact", str(tmp_path / "missing"), "-o", str(tmp_path / "x")]) == 2
    assert "bundle folder not found" in capsys.readouterr().err
    no_map = tmp_path / "no_map"
    shutil.copytree(garage[0], no_map)
    (no_map / "map.json").unlink()
    assert main(["compact", str(no_map), "-o", str(tmp_path / "x"), "--quiet"]) == 2
    err = capsys.readouterr().err
    assert "map.json" in err and len(err.strip().splitlines()) == 1 and not (tmp_path / "x").exists()


def test_options_are_checked_before_measuring():
    with pytest.raises(ValueError, match="sh tolerance"):
        CompactOptions(sh_tolerance=math.nan)
    with pytest.raises(ValueError, match="cell"):
        CompactOptions(cell=0.0)
    with pytest.raises(ValueError, match="cell budget"):
        CompactOptions(cell_budget=1.5)


def test_benefit_is_each_gaussians_share_of_the_rendered_alpha(garage, tiny_data):
    """Summed over Gaussians, the benefit is the alpha of every training view summed over its pixels."""
    b, reader = garage[1], DatasetReader(tiny_data)
    benefit = summed_weights(b.scene, b.rig, reader)
    alphas = [render(b.scene, b.rig, reader.view_pose(c, f), cameras=[c]).alpha[c].double()
              for f in reader.split["train"] for c in b.rig.names]
    total = sum(float(a.sum()) for a in alphas)
    # each pixel's alpha and each Gaussian's gradient are float32 running sums: one rounding per pixel at the sum
    assert abs(float(benefit.sum()) - total) <= sum(a.numel() * f32_ulp(float(a.sum())) for a in alphas)
    assert (benefit >= 0).all() and benefit[-2:].eq(0).all()


def test_benefit_cost_ranks_a_costly_faint_gaussian_below_a_small_opaque_one(garage):
    _, b, _, weights, measured = garage
    score, best, pairs, benefit = measured.score("benefit-cost"), weights.amax(dim=0), measured.pairs, measured.benefit
    assert pairs[COSTLY] > 5 * pairs[CHEAP] and benefit[CHEAP] > 0 and benefit[COSTLY] > 0
    assert score[CHEAP] > score[COSTLY] and torch.equal(score[best > 0], (benefit / pairs)[best > 0])
    n, seen = len(b.scene), int((best > 0).sum())
    for budget in (0.5, 100.0):
        keep = select(best, budget, score=score)
        assert len(keep) == (round(budget * n) if budget <= 1 else int(budget)) < seen
        dropped = (best > 0) & ~torch.isin(torch.arange(n), keep)
        assert score[keep].min() >= score[dropped].max()
    # what the ranking is for: at the same count, the kept scene costs fewer pairs than the weight ranking's
    by_weight = select(best, 0.5, score=measured.score("weight"))
    assert not torch.equal(by_weight, select(best, 0.5, score=score))
    assert pairs[select(best, 0.5, score=score)].sum() < pairs[by_weight].sum()


def test_finetune_runs_n_steps_without_densifying_and_raises_psnr(garage, tiny_data, monkeypatch):
    _, b, _, weights, measured = garage
    reader = DatasetReader(tiny_data)
    keep = select(weights.amax(dim=0), 0.5, score=measured.score("benefit-cost"))
    pruned = bundle_io.Bundle(b.scene.subset(keep), b.rig, b.map, b.meta)
    steps, real = [], Trainer.iteration
    monkeypatch.setattr(Trainer, "iteration", lambda self: steps.append(len(self.params)) or real(self))
    # the tiny preset densifies from step 5 (MCMC adds Gaussians): fine-tuning must switch that off
    tuned = finetune(pruned, reader, 12, load_config("tiny"))
    assert steps == [len(keep)] * 12 and len(tuned.scene) == len(keep) and tuned.meta["finetune"]["iterations"] == 12
    views = [(f, c) for f in reader.split["test"] for c in reader.rig.names]
    before, after = (evaluate_views(x.scene, reader, views, None, slots=False).mean("psnr") for x in (pruned, tuned))
    assert after > before
    with pytest.raises(ValueError, match="pose-refined"):
        finetune(b, reader, 1)


@pytest.mark.parametrize("value", ["-1", "1.5", "x"])
def test_cli_rejects_a_bad_finetune_count(garage, tmp_path, capsys, value):
    assert main(["compact", str(garage[0]), "-o", str(tmp_path / "x"), f"--finetune={value}"]) == 2
    err = capsys.readouterr().err
    assert "--finetune" in err and len(err.strip().splitlines()) == 1 and not (tmp_path / "x").exists()


def test_cli_fine_tunes_with_the_dataset_and_needs_one(garage, tiny_data, tmp_path, capsys):
    src = tmp_path / "unrefined"
    shutil.copytree(garage[0], src)
    (src / "poses.json").unlink()
    out = tmp_path / "tuned"
    argv = ["compact", str(src), "-o", str(out), "--cell", "8", "--poses-per-cell", "1", "--budget", "0.5",
            "--no-visibility", "--finetune", "3", "--ranking", "benefit-cost", "--quiet"]
    assert main(argv) == 2
    err = capsys.readouterr().err
    assert "records no dataset" in err and len(err.strip().splitlines()) == 1 and not out.exists()
    assert main([*argv, "--dataset", str(tiny_data)]) == 0
    assert "fine-tuned 3 steps" in capsys.readouterr().out
    meta = bundle_io.load(out).meta
    assert meta["finetune"]["iterations"] == 3 and meta["compaction"]["ranking"] == "benefit-cost"


def test_finetuning_renders_at_the_full_sh_degree_from_its_first_step():
    """A fine-tuned scene already has its SH degree: no ramp from 0 (the training schedule's) on its first steps."""
    from parksim.recon.finetune import finetune_config
    from parksim.recon.schedule import sh_degree_at

    ph = finetune_config(load_config("tiny"), 300, 3).photometric
    assert [sh_degree_at(step, ph.sh_degree_interval, ph.sh_degree) for step in (0, 1, 2, 299)] == [3, 3, 3, 3]
    assert [sh_degree_at(step, 500, 3) for step in (0, 499, 500, 1500, 9000)] == [0, 0, 1, 3, 3]
