"""The photometric phase of ParkGaussian: fit Gaussians to the surround-view fisheye images.

Each iteration renders ``batch_size`` random (train frame, camera) views with ``parksim.render``, applies
the camera's learned response (and, with ``lr.exposure`` > 0, the view's own exposure correction,
``parksim.recon.exposure``, whose identity penalty joins the loss), and minimises (1 - lambda) L1 + lambda D-SSIM
over the camera's scene mask plus the strategy's regulariser; Adam follows the 3DGS schedule and the densification
strategy (MCMC by default) runs after each step. When ``slot_aware.iterations`` > 0 and a detector is configured
(``slot_aware.detector``, or one passed in; the ``direct_ipm`` variant needs none), the slot-aware phase follows:
each iteration renders the four cameras of a random train frame and minimises ``parksim.recon.slot_aware``'s
L_rgb + L_align + L_ipm + L_cam. Both phases' iterations are in the learning-rate schedule (``schedule_iterations``).
With pose refinement on (``pose_opt``, ``parksim.recon.pose_refine``) the photometric phase also trains a correction per
frame's ego pose (per image for per-image datasets) and per camera's extrinsics; the slot-aware phase keeps them.

The run trains on ``run.device`` (``parksim.device.resolve_device``): the Gaussians, their Adam state, the images,
masks, poses, camera response and detector live there, and so do the strategy's random draws (a generator on that
device; the views each step renders are drawn on the CPU, as is the initial point cloud). Off the CPU a step reads
nothing back to the host: its loss and PSNR stay tensors until a metrics line is written (``run.log_every``).
Checkpoints hold CPU tensors, so a run resumes on any device.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import torch
from torch import Tensor
from tqdm import tqdm

from parksim.data import DatasetReader
from parksim.device import describe_device, resolve_device
from parksim.gaussians import GaussianScene
from parksim.render import render

from .checkpoint import checkpoint_path, load_checkpoint, save_checkpoint, tensors_to
from .compile_notice import compile_notice
from .config import TrainConfig, parse_config
from .detectors import Detector
from .evaluate import evaluate_views
from .exposure import ImageExposure
from .heap import keep_freed_memory
from .init import initial_scene
from .losses import photometric_loss, sum_terms
from .masks import scene_mask
from .metrics import psnr, psnr_tensor
from .metrics_log import METRICS_FILE, append_record, cut_back
from .params import GaussianParams
from .pose_refine import PoseCorrections, align_poses, refinement_enabled
from .response import CameraResponse
from .scaled import at_scale
from .schedule import exp_decay, sh_degree_at
from .slot_aware import SlotAwareStep, SlotAwareTerms, SlotFrame, frame_has_slots, spec_of
from .strategy import StepInfo, ViewInfo, make_strategy

__all__ = ["Trainer", "scene_extent", "host_record", "METRICS_FILE"]


def scene_extent(reader: DatasetReader) -> float:
    """3DGS's scene scale: 1.1 x the largest camera-centre distance from their mean (at least 1 m).

    Args:
        reader: the dataset (its camera poses).

    Returns:
        The extent in metres; the means' learning rate and the densification thresholds scale with it.
    """
    centres = reader.camera_centres()
    return max(1.0, 1.1 * float((centres - centres.mean(0)).norm(dim=1).max()))


def host_record(record: dict[str, Any]) -> dict[str, Any]:
    """A step's record (``Trainer.iteration``) with every tensor in it read back as a float.

    Args:
        record: the record; on the CPU it holds no tensors and comes back equal.

    Returns:
        A record of plain values for the metrics log.
    """
    return {k: float(v) if isinstance(v, Tensor) else v for k, v in record.items()}


@dataclass
class _Batch:
    """Rendered views of one iteration with their targets and masks."""

    preds: list[Tensor]
    gts: list[Tensor]
    masks: list[Tensor]
    infos: list[ViewInfo]


class Trainer:
    """Owns the parameters, optimizers, strategy and RNG of one run; ``state()`` / ``resume`` round-trip them.

    Call ``initialise()`` (or ``resume(state)`` / ``from_checkpoint``), then ``train()``. Each ``iteration()``
    renders ``config.run.batch_size`` fisheye views of shape (H, W, 3) and returns that step's metrics record.
    ``params.tensors`` holds the Gaussians: ``means`` (N, 3), ``quats`` (N, 4), ``log_scales`` (N, 3),
    ``opacity_logits`` (N,), ``sh0`` (N, 1, 3) and ``shN`` (N, K - 1, 3) with K = (max SH degree + 1)^2.
    """

    def __init__(self, reader: DatasetReader, config: TrainConfig, out_dir: Path,
                 log: Callable[[str], None] = print, detector: Detector | None = None) -> None:
        """Set up a run; no parameters until ``initialise``, ``resume`` or ``start_from_photometric``.

        Args:
            reader: the dataset (rig, poses, images, split); training views are every (train frame, camera).
                With ``config.data.image_scale`` < 1 the run sees it through ``parksim.recon.scaled.at_scale``
                (``self.reader``): cameras scaled, images resized once as they are decoded.
            config: the validated run config (``parksim.recon.config.load_config``).
            out_dir: the run folder; checkpoints go to ``out_dir/checkpoints``, metrics to ``out_dir/metrics.jsonl``.
            log: one-line progress messages (``print`` by default).
            detector: slot detector guiding the slot-aware phase (needed only when ``config.slot_aware.iterations``).

        Raises:
            ValueError: the split has no training frames.
            DeviceError: ``config.run.device`` names a GPU this machine lacks (before anything is set up).
        """
        self.device = resolve_device(config.run.device)
        reader = at_scale(reader, config.data.image_scale)
        self.reader, self.cfg, self.out, self.log = reader, config, Path(out_dir), log
        keep_freed_memory()   # every step reuses its large buffers' pages (recon/heap.py)
        self.rig = reader.rig
        self.generator = torch.Generator().manual_seed(config.run.seed)
        self.device_generator = (self.generator if self.device.type == "cpu"
                                 else torch.Generator(self.device).manual_seed(config.run.seed))
        self.views = [(f, c) for f in reader.split["train"] for c in self.rig.names]
        if not self.views:
            raise ValueError(f"{reader.layout.root}: no training frames")
        self.test_views = [(f, c) for f in reader.split["test"] for c in self.rig.names][::config.run.eval_stride]
        self.masks = {c: scene_mask(self.rig.cameras[c], self.rig.bev).to(device=self.device,
                                                                           dtype=torch.float32)[None, None]
                      for c in self.rig.names}
        self._extrinsics = {c: self.rig.cameras[c].T_vehicle_camera.to(self.device) for c in self.rig.names}
        self.extent = scene_extent(reader)
        self.response = CameraResponse(self.rig, config.lr.response, self.device)
        self.exposure = ImageExposure(self.views, config.lr.exposure, self.device) if config.lr.exposure > 0 else None
        self.strategy = make_strategy(config.densify, self.extent)
        self.params: GaussianParams | None = None
        self.step, self.elapsed, self.cpu, self.init_note = 0, 0.0, 0.0, ""
        self._images: dict[tuple[int, str], Tensor] = {}
        self._poses: dict[tuple[int, str], Tensor] = {}
        self.slot_step = self._slot_step(detector)
        self.corrections = (PoseCorrections(reader, self.rig, config.pose_opt, config.schedule_iterations,
                                            device=self.device)
                            if refinement_enabled(config.pose_opt, reader.meta) else None)
        if self.corrections is not None:
            self.log(f"pose refinement on: a correction per {'image' if self.corrections.per_image else 'frame'}"
                     f"{' and per camera extrinsics' if self.corrections.extrinsics_on else ''}")

    def _slot_step(self, detector: Detector | None) -> SlotAwareStep | None:
        """The slot-aware step when phase 2 is on: iterations > 0 and a detector where the variant needs one."""
        sa = self.cfg.slot_aware
        if sa.iterations == 0:
            return None
        if not self.reader.has_vehicle_poses:
            self.log("slot-aware phase off: it renders all cameras at an ego pose and the dataset has per-image "
                     "poses only")
            return None
        if detector is None and sa.detector is not None:
            detector = sa.detector.load()
        if detector is None and spec_of(sa.variant).uses_detector:
            self.log("slot-aware phase off: slot_aware.detector is not set")
            return None
        return SlotAwareStep(self.rig, detector.to(self.device) if detector is not None else None, sa,
                             self.cfg.photometric.ssim_lambda, self.cfg.run.backend, self.response)

    @property
    def total_iterations(self) -> int:
        """Iterations of this run: the photometric phase plus the slot-aware phase when it is on."""
        return self.cfg.photometric.iterations + (self.cfg.slot_aware.iterations if self.slot_step else 0)

    # --- set-up ----------------------------------------------------------------------------
    def _lrs(self) -> dict[str, float]:
        """Initial learning rate per parameter tensor (the means' scaled by the scene extent)."""
        lr = self.cfg.lr
        return {"means": lr.means * self.extent, "quats": lr.quats, "log_scales": lr.scales,
                "opacity_logits": lr.opacity, "sh0": lr.sh0, "shN": lr.shN}

    def initialise(self, scene: GaussianScene | None = None) -> None:
        """Fresh parameters from the configured initial point cloud, or from ``scene`` (fine-tuning a bundle).

        Args:
            scene: Gaussians to start from (None: ``config.init``'s source).
        """
        if scene is None:
            scene, self.init_note = initial_scene(self.reader, self.cfg.init, self.cfg.photometric.sh_degree,
                                                  self.generator, self.device)
        else:
            self.init_note = f"a given scene of {len(scene)} Gaussians"
        self.params = GaussianParams.from_scene(scene, self.cfg.photometric.sh_degree, self._lrs(), self.device)
        self.log(f"initialised {len(scene)} Gaussians from {self.init_note}; scene extent {self.extent:.1f} m")

    def resume(self, state: dict[str, Any]) -> None:
        """Restore a checkpoint's parameters, optimizer moments, strategy, response, RNG and position.

        Args:
            state: a checkpoint as ``state()`` wrote it (``parksim.recon.checkpoint.load_checkpoint``).

        Raises:
            ValueError: the checkpoint was written with another config (its ``run.device`` may differ: a run resumes
                on any device), or without the pose corrections this run has.
        """
        if not parse_config(state["config"], "checkpoint config").same_run(self.cfg):
            raise ValueError("the checkpoint was written with a different config; resume with the run's config.yaml")
        self._restore(state)

    def start_from_photometric(self, state: dict[str, Any], source: str) -> None:
        """Continue a finished photometric run (its checkpoint ``state``) into this run's slot-aware phase.

        Lets several slot-aware variants share one photometric phase: everything that shapes phase 1
        (init, learning rates, photometric, densify) must equal this run's config, and phase 1 must be complete.

        Args:
            state: the photometric run's checkpoint.
            source: the run's name in error messages (its folder).

        Raises:
            ValueError: phase 1 settings differ from this config's, or the run stopped before the end of phase 1.
        """
        saved = parse_config(state["config"], f"{source} checkpoint config")
        differ = [k for k in ("data", "init", "lr", "photometric", "densify", "pose_opt")
                  if getattr(saved, k) != getattr(self.cfg, k)]
        if differ:
            raise ValueError(f"{source}: its photometric phase was trained with other {', '.join(differ)} settings "
                             "than this config's")
        if int(state["iteration"]) != self.cfg.photometric.iterations:
            raise ValueError(f"{source}: stopped at iteration {state['iteration']}, not at the end of the "
                             f"photometric phase ({self.cfg.photometric.iterations})")
        self._restore(state)

    def _restore(self, state: dict[str, Any]) -> None:
        """Load ``state`` (CPU tensors, from any device) onto this trainer's device, whichever way it was checked.

        The device generator continues from the checkpoint's when it was written on the same kind of device; else
        (a CPU checkpoint on a GPU, a GPU's on the CPU) it is reseeded from the seed and the iteration.

        Args:
            state: the checkpoint.

        Raises:
            ValueError: this run refines poses and the checkpoint holds no corrections.
        """
        self.params = GaussianParams(state["params"], self._lrs(), self.device)
        self.params.optimizer.load_state_dict(state["optimizer"])   # moves Adam's moments to the parameters' device
        self.response.load_state_dict(state["response"])
        if self.exposure is not None:
            self.exposure.load_state_dict(state["exposure"])
        self.strategy.load_state_dict(tensors_to(state["strategy"], self.device))
        self.generator.set_state(state["rng"])
        if self.device_generator is not self.generator:
            if state.get("rng_device_type") == self.device.type:
                self.device_generator.set_state(state["rng_device"])
            else:
                self.device_generator.manual_seed(self.cfg.run.seed + int(state["iteration"]))
        self.step, self.elapsed, self.init_note = int(state["iteration"]), float(state["elapsed"]), state["init"]
        self.cpu = float(state["cpu"])
        if self.corrections is not None:
            if "pose_opt" not in state:
                raise ValueError("the checkpoint holds no pose corrections (written without pose refinement); "
                                 "set pose_opt.enabled: false to continue it")
            self.corrections.load_state_dict(state["pose_opt"])

    def state(self) -> dict[str, Any]:
        """Everything ``resume`` needs.

        Returns:
            Iteration, timings, parameters (cloned), optimizer, response, strategy and RNG states (off the CPU also
            the device generator's, ``rng_device``, and its device type), the config as JSON values, the per-image
            exposure corrections when learned and the pose corrections when refining; tensors on this trainer's
            device (``save_checkpoint`` moves them to the CPU).
        """
        assert self.params is not None
        device_rng = ({} if self.device_generator is self.generator else
                      {"rng_device": self.device_generator.get_state(), "rng_device_type": self.device.type})
        return {"iteration": self.step, "elapsed": self.elapsed, "cpu": self.cpu, "init": self.init_note,
                "params": {k: v.detach().clone() for k, v in self.params.tensors.items()},
                "optimizer": self.params.optimizer.state_dict(), "response": self.response.state_dict(),
                "strategy": self.strategy.state_dict(), "rng": self.generator.get_state(), **device_rng,
                "config": self.cfg.model_dump(mode="json"),
                **({"exposure": self.exposure.state_dict()} if self.exposure is not None else {}),
                **({"pose_opt": self.corrections.state_dict()} if self.corrections is not None else {})}

    def decode_inputs(self) -> None:
        """Decode every train and test image now, so a corrupt file fails before the run writes anything.

        Otherwise it would fail at the iteration that first samples it. The train images are kept (evaluation
        reads its own).

        Raises:
            DatasetError: the first image that is missing, undecodable or of the wrong size.
        """
        tests = [(f, c) for f in self.reader.split["test"] for c in self.rig.names]
        decoded = self.reader.images(self.views + tests, progress=self.cfg.run.progress)
        self._images = {view: decoded[view].to(self.device) for view in self.views}

    # --- one iteration -----------------------------------------------------------------------
    def _image(self, frame: int, camera: str) -> Tensor:
        """A training image ``[H, W, 3]`` on the device (decoded and copied there once)."""
        key = (frame, camera)
        if key not in self._images:
            self._images[key] = self.reader.image(camera, frame).to(self.device)
        return self._images[key]

    def _view_pose(self, camera: str, frame: int) -> Tensor:
        """The ``T_world_vehicle`` a view renders at, on the device.

        Args:
            camera: the view's camera.
            frame: the view's frame.

        Returns:
            ``[4, 4]`` float64: the refined pose when refining, else the dataset's (copied to the device once).
        """
        if self.corrections is not None:
            return self.corrections.view_pose(camera, frame)
        key = (frame, camera)
        if key not in self._poses:
            self._poses[key] = self.reader.view_pose(camera, frame).to(self.device)
        return self._poses[key]

    def _render_batch(self, sh_degree: int) -> _Batch:
        assert self.params is not None
        picks = torch.randint(len(self.views), (self.cfg.run.batch_size,), generator=self.generator).tolist()
        scene = self.params.scene(sh_degree)
        batch = _Batch([], [], [], [])
        for i in picks:
            frame, camera = self.views[i]
            pose = self._view_pose(camera, frame)
            image = render(scene, self.rig, pose, cameras=[camera], backend=self.cfg.run.backend,
                           method=self.cfg.run.projection).images[camera]
            pred = self.response(image, camera)
            batch.preds.append(pred if self.exposure is None else self.exposure(pred, frame, camera))
            batch.gts.append(self._image(frame, camera))
            batch.masks.append(self.masks[camera])
            batch.infos.append(self._view_info(pose.detach(), camera))
        return batch

    def _view_info(self, pose: Tensor, camera: str) -> ViewInfo:
        cam = self.rig.cameras[camera]
        return ViewInfo((pose @ self._extrinsics[camera])[:3, 3], float(cam.model.fx), cam.model.width)

    def _slot_batch(self, sh_degree: int) -> tuple[_Batch, SlotAwareTerms]:
        """Slot-aware phase: all cameras of one random train frame, with the step's loss terms."""
        assert self.params is not None and self.slot_step is not None
        train = self.reader.split["train"]
        frame = train[int(torch.randint(len(train), (1,), generator=self.generator))]
        pose, names = self._slot_pose(frame), self.slot_step.ipm.cameras
        gt = SlotFrame({c: self._image(frame, c) for c in names}, {c: self.masks[c][0, 0] for c in names},
                       frame_has_slots(self.reader, frame))
        terms = self.slot_step(self.params.scene(sh_degree), pose, gt)
        batch = _Batch(list(terms.images.values()), list(gt.images.values()), [self.masks[c] for c in names],
                       [self._view_info(pose, c) for c in names])
        return batch, terms

    def _slot_pose(self, frame: int) -> Tensor:
        """The ego pose the slot-aware phase renders at: the refined one, frozen with the refined rig, when refining."""
        assert self.slot_step is not None
        if self.corrections is None:
            return self.reader.pose(frame).to(self.device)
        if self.slot_step.rig is self.rig:
            self.slot_step.rig = self.corrections.refined_rig()
        return self.corrections.ego_pose(frame).detach()

    def _set_lr(self) -> float:
        """Set and return this step's means learning rate (exponential decay over the schedule)."""
        lr = self.cfg.lr
        means_lr = exp_decay(self.step, self.cfg.schedule_iterations, lr.means * self.extent, lr.means_final_factor)
        assert self.params is not None
        self.params.set_lr("means", means_lr)
        return means_lr

    def iteration(self) -> dict[str, Any]:
        """One optimisation step; returns the step's log record.

        Returns:
            ``iteration``, ``loss``, ``rgb_loss``, train ``psnr`` of the first view, ``gaussians``, ``sh_degree``,
            ``means_lr``, the strategy's refinement counts and, in phase 2, the slot-aware terms. Off the CPU the
            photometric phase's ``loss``, ``rgb_loss`` and ``psnr`` are 0-dim device tensors (``float()`` reads
            one; ``host_record`` all), so that a step does not wait for the GPU.
        """
        assert self.params is not None
        ph = self.cfg.photometric
        means_lr = self._set_lr()
        sh_degree = sh_degree_at(self.step, ph.sh_degree_interval, ph.sh_degree)
        slot: dict[str, Any] = {}
        if self.step < ph.iterations:
            batch = self._render_batch(sh_degree)
            rgb = sum_terms(photometric_loss(p.permute(2, 0, 1)[None], g.permute(2, 0, 1)[None], m, ph.ssim_lambda)
                            for p, g, m in zip(batch.preds, batch.gts, batch.masks)) / len(batch.preds)
            objective = rgb if self.exposure is None else rgb + self.exposure.penalty()
        else:
            batch, terms = self._slot_batch(sh_degree)
            rgb, objective, slot = terms.rgb, terms.total, terms.record()
        info = StepInfo(self.step + 1, batch.infos, means_lr, self.device_generator)
        loss = objective + self.strategy.step_pre_backward(self.params, info)
        loss.backward()
        self.strategy.step_post_backward(self.params, info)
        self.params.optimizer.step()
        self.params.optimizer.zero_grad(set_to_none=True)
        self.response.step()
        if self.exposure is not None:
            self.exposure.step()
        if self.corrections is not None:
            self.corrections.step(self.step)
        self.step += 1
        refine = self.strategy.step_post_update(self.params, info)
        with torch.no_grad():
            pred, gt, mask = batch.preds[0].clamp(0, 1), batch.gts[0], batch.masks[0][0, 0] > 0
            train_psnr = psnr(pred, gt, mask) if self.device.type == "cpu" else psnr_tensor(pred, gt, mask)
        return {"iteration": self.step, "loss": self._number(loss), "rgb_loss": self._number(rgb),
                "psnr": train_psnr, "gaussians": len(self.params), "sh_degree": sh_degree, "means_lr": means_lr,
                **refine, **{k: v for k, v in slot.items() if k not in ("loss", "rgb_loss")}}

    def _number(self, value: Tensor) -> float | Tensor:
        """A loss for the step's record: a float on the CPU; off it the detached 0-dim tensor (read when logged)."""
        return float(value.detach()) if self.device.type == "cpu" else value.detach()

    # --- the run ------------------------------------------------------------------------------
    def evaluate(self) -> dict[str, float | None]:
        """Mean test-view PSNR/SSIM of the current parameters (no slot regions: cheap enough to run often).

        With pose refinement the test poses are first aligned (``pose_opt.test_steps``, Gaussians frozen).

        Returns:
            ``{"test_psnr": dB, "test_ssim": ...}``, None where there are no test views.
        """
        assert self.params is not None
        scene, rig, view_pose = self.params.snapshot(), self.rig, self.reader.view_pose
        if self.corrections is not None:
            rig = self.corrections.refined_rig()
            view_pose = align_poses(scene, self.reader, rig, self.test_views, self.response, self.cfg.pose_opt,
                                    self.cfg.pose_opt.test_steps, self.cfg.run.backend,
                                    self.cfg.photometric.ssim_lambda).view_pose
        report = evaluate_views(scene, self.reader, self.test_views, self.response, self.cfg.run.backend,
                                slots=False, rig=rig, view_pose=view_pose, method=self.cfg.run.projection)
        return {"test_psnr": report.mean("psnr"), "test_ssim": report.mean("ssim")}

    def truncate_metrics(self) -> None:
        """Drop metric lines past the current step (written by a run killed after its last checkpoint)."""
        cut_back(self.out / METRICS_FILE, self.step)

    def train(self, stop_after: int | None = None) -> None:
        """Run to ``total_iterations`` (or stop once ``stop_after`` iterations are done).

        Says which device it trains on (one log line), appends metrics every ``run.log_every`` steps (and test
        metrics every ``run.eval_every``) and checkpoints every ``run.checkpoint_every`` steps and at the end.

        Args:
            stop_after: the iteration to stop at (None: the end).
        """
        run, total = self.cfg.run, self.total_iterations
        end = total if stop_after is None else min(total, stop_after)
        self.log(f"training on {describe_device(self.device)}")
        bar = tqdm(total=total, initial=self.step, desc="reconstruct", unit="it", disable=not run.progress,
                   dynamic_ncols=True)
        with compile_notice(), bar:
            while self.step < end:
                start, start_cpu = time.perf_counter(), time.process_time()
                record = self.iteration()
                logged = self.step % run.log_every == 0 or self.step == total
                if logged:
                    record = host_record(record)   # off the CPU: waits for the GPU, so the clock covers the steps
                self.elapsed += time.perf_counter() - start
                self.cpu += time.process_time() - start_cpu
                clock = {"elapsed_s": self.elapsed, "cpu_s": self.cpu}
                if logged:
                    append_record(self.out / METRICS_FILE, {**record, **clock})
                if run.eval_every and (self.step % run.eval_every == 0 or self.step == total) and self.test_views:
                    append_record(self.out / METRICS_FILE, {"iteration": self.step, **clock, **self.evaluate()})
                if self.step % run.checkpoint_every == 0 or self.step == total:
                    save_checkpoint(checkpoint_path(self.out), self.state())
                bar.update(1)
                if logged or self.device.type == "cpu":
                    bar.set_postfix(loss=f"{float(record['loss']):.4f}", psnr=f"{float(record['psnr']):.2f}",
                                    n=record["gaussians"])

    @classmethod
    def from_checkpoint(cls, reader: DatasetReader, config: TrainConfig, out_dir: Path,
                        log: Callable[[str], None] = print) -> Trainer:
        """A trainer continuing the run in ``out_dir`` from its last checkpoint.

        Args:
            reader: the dataset.
            config: the run's config (must equal the checkpoint's).
            out_dir: the run folder.
            log: one-line progress messages.

        Returns:
            The trainer at the checkpoint's iteration.

        Raises:
            CheckpointError: the checkpoint is missing or unreadable.
            ValueError: as ``resume``.
        """
        state = load_checkpoint(checkpoint_path(out_dir))
        trainer = cls(reader, config, out_dir, log)
        trainer.resume(state)
        assert trainer.params is not None
        trainer.log(f"resumed at iteration {trainer.step} with {len(trainer.params)} Gaussians")
        return trainer
