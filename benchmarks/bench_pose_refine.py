"""Pose refinement on a synthetic dataset with known pose errors: test PSNR and recovered-pose error.

``parksim synth tiny --frames 30 --resolution WxH`` (27 train, 3 test frames). Its copy gets every frame's ego pose
perturbed by 5 cm and 0.5 deg (random directions, seed 0, right-multiplied in the vehicle frame) and the front
camera's extrinsics by 2 cm and 0.3 deg. Three runs of one fixed schedule (``overrides``, set before any result):
clean data without refinement, perturbed without, perturbed with. Evaluation: clean and plain runs at the dataset's
test poses; the refined run with its refined rig after test-time pose alignment (``pose_opt.test_steps`` steps,
Gaussians frozen) and, for reference, without it. Pose errors against the truth: ego poses (which carry the gauge:
the refined train frames' corrections have zero mean, so the perturbations' mean stays in them, reported as
``gauge_floor``), each camera's world pose (free of that gauge, not of the world frame the scene may drift in) and
the extrinsics. Writes ``results.json`` in ``--out`` and prints a markdown summary.

    .venv/bin/python benchmarks/bench_pose_refine.py --out /tmp/bench_pose_refine2
    .venv/bin/python benchmarks/bench_pose_refine.py --out /tmp/bench_pose_refine --resolution 160x120 \
        --iterations 600 --pose-lr 5e-3
"""

from __future__ import annotations

import argparse
import json
import math
import shutil
import statistics
import time
from pathlib import Path
from typing import Any

import torch
import yaml

from parksim.cli import main as cli_main
from parksim.data import DatasetReader
from parksim.recon.config import PRESETS_DIR
from parksim.recon.evaluate import evaluate_bundle
from parksim.recon.pose_refine import pose_error, so3xr3
from parksim.recon.reconstruct import reconstruct
from parksim.rig import Rig

EGO_CM, EGO_DEG, EXT_CM, EXT_DEG, SEED, CAMERA = 5.0, 0.5, 2.0, 0.3, 0, "front"
FRAMES = 30


def overrides(iterations: int, pose_lr: float) -> dict[str, Any]:
    """The runs' overrides of the tiny preset: SH degree 1 after a third, MCMC relocation over the first 80 %."""
    return {"run": {"log_every": 50, "checkpoint_every": 100000},
            "photometric": {"iterations": iterations, "sh_degree_interval": iterations // 3},
            "densify": {"mcmc": {"refine_start": 50, "refine_stop": iterations * 4 // 5, "refine_every": 50}},
            "pose_opt": {"lr": pose_lr, "lr_final_factor": 0.01, "test_steps": 100, "test_lr": 5e-3}}


def _merge(base: dict[str, Any], over: dict[str, Any]) -> dict[str, Any]:
    return {**base, **{k: _merge(base.get(k, {}), v) if isinstance(v, dict) else v for k, v in over.items()}}


def _delta(g: torch.Generator, cm: float, deg: float) -> torch.Tensor:
    """A correction of exactly ``cm`` and ``deg`` in random directions."""
    axis, move = (v / v.norm() for v in torch.randn(2, 3, generator=g, dtype=torch.float64))
    return torch.cat([axis * math.radians(deg), move * cm / 100])


def perturb(clean: Path, out: Path) -> dict[int, torch.Tensor]:
    """Copy ``clean`` with every ego pose and the front camera's extrinsics off by the stated amounts; returns
    each frame's perturbation (the 6-vector, as ``so3xr3`` takes it)."""
    shutil.copytree(clean, out)
    g = torch.Generator().manual_seed(SEED)
    poses = json.loads((out / "poses.json").read_text())
    deltas = {}
    for entry in poses["frames"]:
        T = torch.tensor(entry["T_world_vehicle"], dtype=torch.float64)
        deltas[entry["frame"]] = _delta(g, EGO_CM, EGO_DEG)
        entry["T_world_vehicle"] = (T @ so3xr3(deltas[entry["frame"]])).tolist()
    (out / "poses.json").write_text(json.dumps(poses))
    rig = json.loads((out / "rig.json").read_text())
    T = torch.tensor(rig["cameras"][CAMERA]["T_vehicle_camera"], dtype=torch.float64)
    rig["cameras"][CAMERA]["T_vehicle_camera"] = (T @ so3xr3(_delta(g, EXT_CM, EXT_DEG))).tolist()
    (out / "rig.json").write_text(json.dumps(rig))
    return deltas


def _world_fit(estimate: list[torch.Tensor], truth: list[torch.Tensor]) -> torch.Tensor:
    """The rigid ``W`` taking the estimated camera centres closest to the true ones (Kabsch, least squares)."""
    p, q = (torch.stack([T[:3, 3] for T in ts]) for ts in (estimate, truth))
    pc, qc = p.mean(0), q.mean(0)
    u, _, vt = torch.linalg.svd((p - pc).T @ (q - qc))
    flip = torch.diag(torch.tensor([1.0, 1.0, float(torch.sign(torch.linalg.det(vt.T @ u.T)))], dtype=p.dtype))
    W = torch.eye(4, dtype=p.dtype)
    W[:3, :3] = vt.T @ flip @ u.T
    W[:3, 3] = qc - W[:3, :3] @ pc
    return W


def _camera_errors(poses: dict[int, torch.Tensor], rig: Rig, truth: DatasetReader, frames: list[int],
                   world_fit: bool = False) -> dict[str, float]:
    """Median and max error of every camera's world pose (ego pose times extrinsics): free of the frames/extrinsics
    gauge; ``world_fit`` first moves all estimates by the one rigid motion that fits them best (the scene's own
    world frame is free too: Gaussians and cameras moved together render the same images)."""
    views = [(f, c) for f in frames for c in rig.names]
    est = [poses[f] @ rig.cameras[c].T_vehicle_camera for f, c in views]
    true = [truth.pose(f) @ truth.rig.cameras[c].T_vehicle_camera for f, c in views]
    W = _world_fit(est, true) if world_fit else torch.eye(4, dtype=torch.float64)
    errs = [pose_error(W @ e, t) for e, t in zip(est, true)]
    return {"median_cm": statistics.median(e[0] for e in errs), "max_cm": max(e[0] for e in errs),
            "median_deg": statistics.median(e[1] for e in errs), "max_deg": max(e[1] for e in errs)}


def _errors(poses: dict[int, torch.Tensor], truth: DatasetReader, frames: list[int]) -> dict[str, float]:
    errs = [pose_error(poses[f], truth.pose(f)) for f in frames]
    return {"median_cm": statistics.median(e[0] for e in errs), "max_cm": max(e[0] for e in errs),
            "median_deg": statistics.median(e[1] for e in errs), "max_deg": max(e[1] for e in errs)}


def _poses(table: dict[str, Any]) -> dict[int, torch.Tensor]:
    return {e["frame"]: torch.tensor(e["T_world_vehicle"], dtype=torch.float64) for e in table["frames"]}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", type=Path, required=True)
    ap.add_argument("--resolution", default="240x180", help="WxH of the synthetic cameras")
    ap.add_argument("--iterations", type=int, default=2000)
    ap.add_argument("--pose-lr", type=float, default=1e-3)
    args = ap.parse_args()
    out = args.out
    out.mkdir(parents=True, exist_ok=False)
    clean, noisy = out / "clean", out / "perturbed"
    assert cli_main(["synth", "tiny", "--frames", str(FRAMES), "--resolution", args.resolution, "-o", str(clean),
                     "--quiet"]) == 0
    deltas = perturb(clean, noisy)
    base = _merge(yaml.safe_load((PRESETS_DIR / "tiny.yaml").read_text()), overrides(args.iterations, args.pose_lr))
    results: dict[str, Any] = {"config": base}
    for name, data, refine in (("clean", clean, False), ("perturbed", noisy, False), ("refined", noisy, True)):
        config = out / f"{name}.yaml"
        config.write_text(yaml.safe_dump(_merge(base, {"pose_opt": {"enabled": refine}})))
        wall, cpu = time.perf_counter(), time.process_time()
        run = reconstruct(data, out / f"run_{name}", config, log=lambda s: None)
        train = {"wall_s": time.perf_counter() - wall, "cpu_s": time.process_time() - cpu}
        wall, cpu = time.perf_counter(), time.process_time()
        ev = evaluate_bundle(run, data, out / f"eval_{name}")
        results[name] = {**train, "eval_wall_s": time.perf_counter() - wall, "eval_cpu_s": time.process_time() - cpu,
                         "psnr": ev["overall"]["psnr"], "ssim": ev["overall"]["ssim"],
                         "pose_alignment": ev["pose_alignment"]}
        if refine:
            results[name]["psnr_unaligned"] = evaluate_bundle(run, data, out / "eval_unaligned",
                                                              align_steps=0)["overall"]["psnr"]
            results["aligned_test_poses"] = ev["aligned_test_poses"]
        print(name, json.dumps(results[name]), flush=True)
    truth, given = DatasetReader(clean), DatasetReader(noisy)
    refined = json.loads((out / "run_refined" / "poses.json").read_text())
    train, test = truth.split["train"], truth.split["test"]
    recorded = {f: given.pose(f) for f in truth.frames}
    refined_rig = Rig.load(out / "run_refined" / "rig.json")
    # the correction vector that undoes so3xr3((w, v)) is (-w, translation of its inverse); the gauge zeroes their mean
    undo = [torch.cat([-deltas[f][:3], torch.linalg.inv(so3xr3(deltas[f]))[:3, 3]]) for f in train]
    floor = torch.stack(undo).mean(0)
    results["pose_error"] = {
        "gauge_floor": {"cm": float(floor[3:].norm()) * 100, "deg": math.degrees(float(floor[:3].norm()))},
        "train_before": _errors(recorded, truth, train), "train_after": _errors(_poses(refined), truth, train),
        "test_before": _errors(recorded, truth, test),
        "test_after": _errors(_poses(results["aligned_test_poses"]), truth, test),
        "train_cameras_before": _camera_errors(recorded, given.rig, truth, train),
        "train_cameras_after": _camera_errors(_poses(refined), refined_rig, truth, train),
        "train_cameras_after_world_fit": _camera_errors(_poses(refined), refined_rig, truth, train, world_fit=True),
        "train_cameras_before_world_fit": _camera_errors(recorded, given.rig, truth, train, world_fit=True),
        "test_cameras_before": _camera_errors(recorded, given.rig, truth, test),
        "test_cameras_after": _camera_errors(_poses(results["aligned_test_poses"]), refined_rig, truth, test),
        **{f"extrinsics_{when}": {c: pose_error(r.cameras[c].T_vehicle_camera, truth.rig.cameras[c].T_vehicle_camera)
                                  for c in truth.rig.names}
           for when, r in (("before", given.rig), ("after", refined_rig))}}
    (out / "results.json").write_text(json.dumps(results, indent=1))
    print(json.dumps(results["pose_error"], indent=1))
    print("| run | test PSNR | SSIM | train wall s | train CPU s |\n| --- | --- | --- | --- | --- |")
    for name in ("clean", "perturbed", "refined"):
        r = results[name]
        print(f"| {name} | {r['psnr']:.2f} | {r['ssim']:.3f} | {r['wall_s']:.0f} | {r['cpu_s']:.0f} |")
    print(f"refined run without test-time alignment: {results['refined']['psnr_unaligned']:.2f} dB")


if __name__ == "__main__":
    main()
