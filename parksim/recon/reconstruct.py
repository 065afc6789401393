"""``reconstruct``: validate inputs, train (fresh, resumed, or on from a photometric run), then write the bundle."""

from __future__ import annotations

import datetime
from collections.abc import Callable
from pathlib import Path

import numpy as np

from parksim.bundle import Bundle, recorded_path, save
from parksim.data import DatasetReader
from parksim.fileio import atomic_write, remove_stale_temps

from .checkpoint import checkpoint_path, load_checkpoint
from .config import TrainConfig, dump_config, load_config
from .plots import plot_metrics
from .pose_refine import POSES_KEY
from .scaled import full_size_rig
from .trainer import METRICS_FILE, Trainer

__all__ = ["reconstruct", "CONFIG_FILE"]

CONFIG_FILE = "config.yaml"


def _resolve_config(out_dir: Path, config_path: str | Path | None, resume: bool) -> TrainConfig:
    """The run's config; a resumed run must keep the one it started with (its ``run.device`` aside)."""
    if not resume:
        if (out_dir / CONFIG_FILE).exists() or checkpoint_path(out_dir).exists():
            raise ValueError(f"{out_dir} already holds a run; pass --resume to continue it or choose another folder")
        return load_config(config_path) if config_path is not None else TrainConfig()
    if not (out_dir / CONFIG_FILE).is_file():
        raise ValueError(f"{out_dir / CONFIG_FILE} is missing: the earlier run never wrote its config (it stopped "
                         "before training began), so there is nothing to resume; run again without --resume")
    stored = load_config(out_dir / CONFIG_FILE)
    if config_path is not None and not load_config(config_path).same_run(stored):
        raise ValueError(f"--config {config_path} differs from the config the run in {out_dir} started with")
    return stored


def _remove_stale_temps(out_dir: Path, log: Callable[[str], None]) -> None:
    """Delete the temp files killed writes left in the run's folder (each kill mid-checkpoint leaves one that size)."""
    stale = [p for folder in (out_dir, checkpoint_path(out_dir).parent) for p in remove_stale_temps(folder)]
    if stale:
        log(f"removed {len(stale)} temp file(s) left by a killed run: {', '.join(p.name for p in stale)}")


def _start_from(trainer: Trainer, photometric_run: Path) -> None:
    """Put ``trainer`` at the end of the photometric phase of the run in ``photometric_run`` (its checkpoint)."""
    if trainer.slot_step is None:
        raise ValueError(f"starting from {photometric_run} needs a slot-aware phase: set slot_aware.iterations > 0 "
                         "and slot_aware.detector")
    trainer.start_from_photometric(load_checkpoint(checkpoint_path(photometric_run)), str(photometric_run))
    trainer.init_note = f"{trainer.init_note}; photometric phase from {photometric_run}"
    trainer.log(f"starting the slot-aware phase from {photometric_run} at iteration {trainer.step}")


def reconstruct(data_dir: str | Path, out_dir: str | Path, config_path: str | Path | None = None,
                resume: bool = False, stop_after: int | None = None, log: Callable[[str], None] = print,
                start_from: str | Path | None = None, device: str | None = None) -> Path:
    """Train a scene from ``data_dir`` into ``out_dir``; returns ``out_dir`` once the bundle is written.

    Every input (dataset, config, checkpoint, detector) is checked before anything is written. ``stop_after``
    ends the run early (as a kill would, after a checkpoint) and writes no bundle. ``start_from`` names a
    finished photometric run (its folder, checkpoint kept) whose state this run continues from: only the
    slot-aware iterations are trained, so variants share one photometric phase. ``device`` overrides the config's
    ``run.device`` (a fresh run's config.yaml records it); a resumed run may continue on another device than the one
    it started on.

    Args:
        data_dir: the dataset folder (``parksim.data`` layout).
        out_dir: the run's folder: config, checkpoints, metrics and, at the end, the bundle.
        config_path: a YAML file or a packaged preset name (default: ``TrainConfig()``, the paper's numbers).
        resume: continue the run in ``out_dir`` from its last checkpoint, with the config it started with.
        stop_after: stop after this iteration (as a kill would) and write no bundle.
        log: receives one line per progress message.
        start_from: a finished photometric run's folder to continue the slot-aware phase from.
        device: ``auto``, ``cpu`` or ``cuda[:N]`` to train on (None: the config's ``run.device``).

    Returns:
        ``out_dir`` as a Path.

    Raises:
        ValueError: ``resume`` with ``start_from``; a fresh run into a folder that holds one; a resumed run given
            another config; a resumed run whose folder has no config (its run never wrote one); ``start_from``
            without a slot-aware phase. ``DatasetError`` and ``ConfigError`` (both
            ValueErrors) for a broken dataset or config; ``DeviceError`` (a ValueError) for a device name that is
            malformed or names a GPU this machine lacks.
    """
    out_dir = Path(out_dir)
    if resume and start_from is not None:
        raise ValueError("--resume continues this run; --from starts a new one: give one of them")
    reader = DatasetReader(data_dir)
    config = _resolve_config(out_dir, config_path, resume)
    if device is not None:
        config = config.on_device(device)
    if resume:
        trainer = Trainer.from_checkpoint(reader, config, out_dir, log)
        trainer.decode_inputs()
        trainer.truncate_metrics()
        _remove_stale_temps(out_dir, log)
    else:
        trainer = Trainer(reader, config, out_dir, log)
        trainer.decode_inputs()
        if start_from is not None:
            _start_from(trainer, Path(start_from))
        else:
            trainer.initialise()
        out_dir.mkdir(parents=True, exist_ok=True)
        _remove_stale_temps(out_dir, log)
        (out_dir / METRICS_FILE).unlink(missing_ok=True)
        atomic_write(out_dir / CONFIG_FILE, lambda p: p.write_text(dump_config(config)))
    trainer.train(stop_after=stop_after)
    if trainer.step < trainer.total_iterations:
        return out_dir
    assert trainer.params is not None
    phase = "slot_aware" if trainer.slot_step else "photometric"
    rig, poses, ego = reader.rig, None, reader.poses.numpy() if reader.has_vehicle_poses else None
    if trainer.corrections is not None:
        rig = full_size_rig(trainer.corrections.refined_rig(), reader.rig)   # trained at data.image_scale
        poses = trainer.corrections.refined_poses(reader.split["train"])
        ego = ego if ego is None else np.array([f["T_world_vehicle"] for f in poses["frames"]])
    meta = {"dataset": str(Path(data_dir).resolve()), "phase": phase, "iterations": trainer.step,
            "gaussians": len(trainer.params), "train_seconds": round(trainer.elapsed, 1), "init": trainer.init_note,
            "projection": config.run.projection, "image_scale": config.data.image_scale,
            "config": CONFIG_FILE, "metrics": METRICS_FILE, "camera_response": trainer.response.to_dict(),
            "recorded_path": recorded_path(ego) if ego is not None else None,
            "poses": "ego" if reader.has_vehicle_poses else "camera",
            "created": datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="seconds")}
    if trainer.corrections is not None:
        meta[POSES_KEY] = {**trainer.corrections.summary(), "config": config.pose_opt.model_dump(mode="json")}
    world_map = reader.map if reader.layout.map.is_file() else None
    scene = trainer.params.snapshot().to(device="cpu").spatially_sorted()   # a bundle is CPU tensors, as on the CPU
    save(out_dir, Bundle(scene, rig, world_map, meta, poses=poses))
    if (out_dir / METRICS_FILE).is_file():
        plot_metrics(out_dir / METRICS_FILE, out_dir / "metrics.png")
    log(f"wrote {out_dir}: {len(trainer.params)} Gaussians after {trainer.step} iterations "
        f"({trainer.elapsed:.0f} s of training)")
    return out_dir
