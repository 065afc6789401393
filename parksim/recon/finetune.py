"""Fine-tuning of a pruned scene (``parksim compact --finetune N``): N photometric steps, no densification.

The run's trainer takes the pruned Gaussians and the bundle's camera response and runs N iterations of its
photometric loss on the bundle's training views, with the Gaussian count fixed (ADC strategy with
``refine_stop: 0``: no clone, split, prune or opacity reset, and no MCMC noise or regularisers) and low
learning rates: positions at the value the training schedule ends with, every other rate times ``LR_SCALE``.
The Gaussians the pruning removed leave holes and seams that this closes (LightGaussian, Mini-Splatting).
"""

from __future__ import annotations

import time
from pathlib import Path

from tqdm import tqdm

from parksim.bundle import Bundle
from parksim.data import DatasetReader

from .config import TrainConfig, load_config
from .trainer import Trainer

__all__ = ["FINETUNE_ITERATIONS", "LR_SCALE", "bundle_config", "finetune_config", "finetune"]

FINETUNE_ITERATIONS = 300
"""Default steps (one view each): about one pass over a 90-frame, four-camera training set; chosen before any
result was seen."""
LR_SCALE = 0.2
"""Learning rates of everything but the positions, relative to the training run's."""


def bundle_config(directory: Path, meta: dict) -> TrainConfig:
    """The training config stored in a bundle folder (``meta["config"]``), or the default one when it has none."""
    path = directory / str(meta.get("config", "config.yaml"))
    return load_config(path) if path.is_file() else TrainConfig()


def finetune_config(config: TrainConfig, iterations: int, sh_degree: int) -> TrainConfig:
    """``config`` turned into a fine-tuning run: ``iterations`` photometric steps at ``sh_degree``, low constant
    learning rates, no densification, no slot-aware phase, no pose refinement, no checkpoints or evaluation."""
    lr = config.lr
    scaled = {k: getattr(lr, k) * LR_SCALE for k in ("sh0", "shN", "opacity", "scales", "quats", "response")}
    return config.model_copy(deep=True, update={
        "lr": lr.model_copy(update={"means": lr.means * lr.means_final_factor, "means_final_factor": 1.0, **scaled}),
        "photometric": config.photometric.model_copy(update={
            "iterations": iterations, "sh_degree": sh_degree, "sh_degree_interval": 0}),
        "slot_aware": config.slot_aware.model_copy(update={"iterations": 0}),
        "densify": config.densify.model_copy(update={
            "strategy": "adc", "adc": config.densify.adc.model_copy(update={"refine_stop": 0})}),
        "pose_opt": config.pose_opt.model_copy(update={"enabled": False}),
        "run": config.run.model_copy(update={"eval_every": 0, "progress": False})})


def finetune(bundle: Bundle, reader: DatasetReader, iterations: int = FINETUNE_ITERATIONS,
             config: TrainConfig | None = None, progress: bool = False) -> Bundle:
    """``bundle`` with its Gaussians (same count) and camera response fine-tuned for ``iterations`` steps on
    ``reader``'s training views, on the device its Gaussians are on; ``meta["finetune"]`` records the run
    (iterations, first and last loss, seconds)."""
    if iterations < 0:
        raise ValueError(f"fine-tuning iterations must be >= 0, got {iterations}")
    if bundle.poses is not None:
        raise ValueError("fine-tuning a pose-refined bundle is not supported (its poses differ from the dataset's): "
                         "pass --finetune 0")
    if iterations == 0:
        return bundle
    cfg = finetune_config(config or TrainConfig(), iterations, bundle.scene.sh_degree).on_device(
        str(bundle.scene.means.device))
    trainer = Trainer(reader, cfg, Path("."), log=lambda _: None)   # iteration() only: nothing is written
    trainer.response.load_dict(bundle.meta.get("camera_response", {}))
    trainer.initialise(bundle.scene)
    params = trainer.params
    assert params is not None   # initialise() sets it
    start, losses = time.perf_counter(), []
    for _ in tqdm(range(iterations), desc="fine-tuning", unit="it", disable=not progress, dynamic_ncols=True):
        losses.append(trainer.iteration()["loss"])   # off the CPU a device scalar: read once, after the loop
    if len(params) != len(bundle.scene):
        raise RuntimeError(f"fine-tuning changed the Gaussian count ({len(bundle.scene)} -> {len(params)})")
    losses = [float(loss) for loss in losses]
    head, tail = losses[:max(1, iterations // 10)], losses[-max(1, iterations // 10):]
    record = {"iterations": iterations, "lr_scale": LR_SCALE, "densify": "off",
              "loss_first_tenth": sum(head) / len(head), "loss_last_tenth": sum(tail) / len(tail),
              "seconds": round(time.perf_counter() - start, 1)}
    meta = {**bundle.meta, "camera_response": trainer.response.to_dict(), "finetune": record}
    return Bundle(params.snapshot(), bundle.rig, bundle.map, meta, bundle.visibility, bundle.poses)
