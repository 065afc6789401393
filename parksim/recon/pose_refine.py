"""Pose refinement: learned SO3xR3 corrections of the ego (or per-image) poses and of the cameras' extrinsics.

Recorded odometry and calibration are never exact, so, as nerfstudio's camera optimizer and gsplat's pose
optimisation do, each pose gets a 6-vector ``(omega, v)`` (axis-angle in rad, translation in m) trained by its
own Adam. A frame's ego pose becomes ``T_world_vehicle @ D(delta_frame)`` (correction in the vehicle frame);
a camera's extrinsics become ``[exp(omega) R, c + v]`` (rotation in vehicle axes about the camera centre ``c``).
Per-image datasets (no ego poses) get one correction per image, right-multiplied in the camera frame, and no
extrinsic corrections (their extrinsics never reach the renderer). All corrections start at exactly the identity,
so a zero correction renders bit-identically to none. ``render`` is differentiable in a tensor pose (the UT
projection kernel returns the rotation's gradient), so corrections are rendered through the view pose.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from typing import Any

import torch
from torch import Tensor

from parksim.data import DatasetReader
from parksim.gaussians import GaussianScene
from parksim.geometry import invert_transform
from parksim.render import render
from parksim.rig import Rig, RigCamera

from .config import PoseRefineConfig
from .losses import photometric_loss, sum_terms
from .masks import scene_mask
from .schedule import exp_decay

__all__ = ["PoseCorrections", "so3xr3", "refinement_enabled", "align_poses", "pose_error", "POSES_KEY"]

POSES_KEY = "pose_refinement"
"""The bundle.json key holding the refinement summary (and the test-time alignment settings evaluation uses)."""

Key = int | tuple[int, str]
Response = Callable[[Tensor, str], Tensor]


def so3xr3(delta: Tensor) -> Tensor:
    """``[[exp(omega^), v], [0, 0, 0, 1]]`` (4x4) of ``delta = (omega, v)``; exactly the identity at zero."""
    w, v = delta[:3], delta[3:]
    zero = w.new_zeros(())
    skew = torch.stack([zero, -w[2], w[1], w[2], zero, -w[0], -w[1], w[0], zero]).reshape(3, 3)
    bottom = torch.cat([delta.new_zeros(1, 3), delta.new_ones(1, 1)], 1)   # made on delta's device: no host copy
    return torch.cat([torch.cat([torch.linalg.matrix_exp(skew), v[:, None]], 1), bottom])


def refinement_enabled(cfg: PoseRefineConfig, dataset_meta: dict[str, Any]) -> bool:
    """``pose_opt.enabled``, with ``auto`` = on exactly for imported recordings (meta.json ``source: import``)."""
    return dataset_meta.get("source") == "import" if cfg.enabled == "auto" else bool(cfg.enabled)


def pose_error(estimate: Tensor, truth: Tensor) -> tuple[float, float]:
    """Translation (cm) and rotation (deg) between two 4x4 rigid transforms."""
    rel = invert_transform(truth) @ estimate
    cos = ((rel[:3, :3].diagonal().sum() - 1) / 2).clamp(-1.0, 1.0)
    return float((estimate[:3, 3] - truth[:3, 3]).norm()) * 100, math.degrees(float(torch.arccos(cos)))


class PoseCorrections:
    """Corrections of one dataset's poses (``keys``: frames, or (frame, camera) images) and, optionally, extrinsics.

    ``rig`` is the rig rendered with (the dataset's in training, a bundle's refined one in evaluation);
    ``view_pose(camera, frame)`` is the corrected ``T_world_vehicle`` to pass with it to ``render``. The corrections,
    the recorded poses they correct and the extrinsics they use live on ``device`` (the Gaussians'; default the
    CPU), so the corrected poses are made there; ``refined_rig`` is a CPU rig as every rig is.
    """

    def __init__(self, reader: DatasetReader, rig: Rig, cfg: PoseRefineConfig, iterations: int,
                 frames: Sequence[int] | None = None, extrinsics: bool | None = None,
                 device: torch.device | None = None) -> None:
        self.reader, self.rig, self.cfg, self.iterations = reader, rig, cfg, iterations
        self.per_image = not reader.has_vehicle_poses
        self.frames = frames = list(reader.frames if frames is None else frames)
        self.keys: list[Key] = [(f, c) for f in frames for c in rig.names] if self.per_image else [f for f in frames]
        self.rows = {k: i for i, k in enumerate(self.keys)}
        self.extrinsics_on = (cfg.extrinsics if extrinsics is None else extrinsics) and not self.per_image
        self.poses = torch.zeros(len(self.keys), 6, dtype=torch.float64, device=device, requires_grad=True)
        self.extrinsics = torch.zeros(len(rig.names), 6, dtype=torch.float64, device=device,
                                      requires_grad=self.extrinsics_on)
        groups = [{"params": [self.poses], "name": "poses"}]
        if self.extrinsics_on:
            groups.append({"params": [self.extrinsics], "name": "extrinsics"})
        self.optimizer = torch.optim.Adam(groups, lr=cfg.lr, eps=1e-15, weight_decay=cfg.weight_decay)
        trained = [self.rows[f] for f in reader.split["train"] if f in self.rows]
        self._gauge = (torch.tensor(trained, dtype=torch.int64, device=device)
                       if self.extrinsics_on and trained else None)
        self._extrinsic = {c: rig.cameras[c].T_vehicle_camera.to(device) for c in rig.names}
        self._centres = {c: T[:3, 3] for c, T in self._extrinsic.items()}
        self._inverse = {c: invert_transform(T) for c, T in self._extrinsic.items()}
        self._recorded = {k: (reader.camera_pose(k[1], k[0]) if isinstance(k, tuple) else reader.pose(k)).to(device)
                          for k in self.keys}

    # --- corrected poses ---------------------------------------------------------------------
    def _row(self, camera: str, frame: int) -> Tensor:
        return self.poses[self.rows[(frame, camera) if self.per_image else frame]]

    def _extrinsic_delta(self, camera: str) -> Tensor:
        """``T_vehicle_camera' @ T_vehicle_camera^-1``: rotation in vehicle axes about the camera centre."""
        D = so3xr3(self.extrinsics[self.rig.names.index(camera)])
        R, c = D[:3, :3], self._centres[camera]
        return torch.cat([torch.cat([R, (c - R @ c + D[:3, 3])[:, None]], 1), D[3:]])

    def ego_pose(self, frame: int) -> Tensor:
        """The corrected ``T_world_vehicle`` of a frame (ego datasets only)."""
        return self._recorded[frame] @ so3xr3(self.poses[self.rows[frame]])

    def camera_pose(self, camera: str, frame: int) -> Tensor:
        """The corrected ``T_world_camera`` of one image (per-image datasets only)."""
        return self._recorded[(frame, camera)] @ so3xr3(self._row(camera, frame))

    def view_pose(self, camera: str, frame: int) -> Tensor:
        """Corrected ``T_world_vehicle`` at which ``render(scene, self.rig, ., cameras=[camera])`` shows the image."""
        if self.per_image:
            return self.camera_pose(camera, frame) @ self._inverse[camera]
        pose = self.ego_pose(frame)
        return pose @ self._extrinsic_delta(camera) if self.extrinsics_on else pose

    # --- results -----------------------------------------------------------------------------
    @torch.no_grad()
    def refined_rig(self) -> Rig:
        """The rig with the corrected extrinsics (``self.rig`` itself when they are not refined)."""
        if not self.extrinsics_on:
            return self.rig
        cams = {c: RigCamera(c, cam.model, (self._extrinsic_delta(c) @ self._extrinsic[c]).cpu())
                for c, cam in self.rig.cameras.items()}
        return Rig(cams, self.rig.bev)

    @torch.no_grad()
    def refined_poses(self, refined: Sequence[int]) -> dict[str, Any]:
        """poses.json content (the dataset's schema) with the corrected pose of each of ``self.frames``;
        ``refined`` lists the frames whose corrections were fitted (the others keep the dataset's pose)."""
        frames, stamps = [], dict(zip(self.reader.frames, self.reader.timestamps))
        for frame in self.frames:
            stamp = stamps[frame]
            entry: dict[str, Any] = {"frame": frame, "timestamp": stamp}
            if self.per_image:
                entry["T_world_camera"] = {c: self.camera_pose(c, frame).tolist() for c in self.rig.names}
            else:
                entry["T_world_vehicle"] = self.ego_pose(frame).tolist()
            frames.append(entry)
        return {"frames": frames, "refined": sorted(refined)}

    @torch.no_grad()
    def summary(self) -> dict[str, Any]:
        """Sizes of the learned corrections: mean and max over poses, and each camera's (cm and deg)."""
        def sizes(deltas: Tensor) -> tuple[list[float], list[float]]:
            return ((deltas[:, 3:].norm(dim=1) * 100).tolist(), torch.rad2deg(deltas[:, :3].norm(dim=1)).tolist())

        cm, deg = sizes(self.poses)
        out: dict[str, Any] = {"mode": "image" if self.per_image else "ego", "poses": len(self.keys),
                               "mean_translation_cm": sum(cm) / len(cm), "max_translation_cm": max(cm),
                               "mean_rotation_deg": sum(deg) / len(deg), "max_rotation_deg": max(deg)}
        if self.extrinsics_on:
            ecm, edeg = sizes(self.extrinsics)
            out["extrinsics"] = {c: {"translation_cm": ecm[i], "rotation_deg": edeg[i]}
                                 for i, c in enumerate(self.rig.names)}
        return out

    # --- optimisation ------------------------------------------------------------------------
    def step(self, iteration: int) -> None:
        """One Adam step at the decayed learning rate of ``iteration``, then the gauge fix; clears the gradients.

        A correction common to every frame moves all cameras as one correction common to every camera's
        extrinsics does, so the pair is fixed only up to that shared motion, along which Adam drifts freely. The
        gauge: the trained frames' corrections have zero mean, so odometry errors are taken as zero-mean noise and
        their common part as the rig's calibration error, which the extrinsics' own gradients then carry."""
        lr = exp_decay(iteration, self.iterations, self.cfg.lr, self.cfg.lr_final_factor)
        for group in self.optimizer.param_groups:
            group["lr"] = lr
        self.optimizer.step()
        self.optimizer.zero_grad(set_to_none=True)
        if self._gauge is not None:
            with torch.no_grad():
                self.poses[self._gauge] -= self.poses[self._gauge].mean(0)

    def state_dict(self) -> dict[str, Any]:
        """Checkpoint state: the corrections and their Adam moments."""
        return {"poses": self.poses.detach().clone(), "extrinsics": self.extrinsics.detach().clone(),
                "optimizer": self.optimizer.state_dict()}

    def load_state_dict(self, state: dict[str, Any]) -> None:
        """Restore ``state_dict`` output (from a run over the same dataset and config)."""
        if state["poses"].shape != self.poses.shape:
            raise ValueError(f"checkpoint holds {state['poses'].shape[0]} pose corrections, this dataset needs "
                             f"{self.poses.shape[0]}")
        with torch.no_grad():
            self.poses.copy_(state["poses"])
            self.extrinsics.copy_(state["extrinsics"])
        self.optimizer.load_state_dict(state["optimizer"])


def align_poses(scene: GaussianScene, reader: DatasetReader, rig: Rig, views: Sequence[tuple[int, str]],
                response: Response | None, cfg: PoseRefineConfig, steps: int, backend: str = "auto",
                ssim_lambda: float = 0.2) -> PoseCorrections:
    """Test-time pose alignment (as BARF and its successors evaluate): Gaussians, rig and response frozen,
    only the views' own pose corrections are fitted, full batch, for ``steps`` Adam steps (``cfg.test_lr``) of the
    training loss. Runs on the scene's device (``response`` must be there too)."""
    device = scene.means.device
    frames = sorted({f for f, _ in views})
    corr = PoseCorrections(reader, rig, cfg.model_copy(update={"lr": cfg.test_lr}), steps, frames=frames,
                           extrinsics=False, device=device)
    frozen = GaussianScene(scene.means.detach(), scene.quats.detach(), scene.log_scales.detach(),
                           scene.opacity_logits.detach(), scene.sh.detach(), scene.sh_degree)
    masks = {c: scene_mask(rig.cameras[c], rig.bev).to(device=device, dtype=torch.float32)[None, None]
             for c in {c for _, c in views}}
    targets = {(f, c): reader.image(c, f).to(device) for f, c in views}
    for step in range(steps):
        losses = []
        for frame, camera in views:
            image = render(frozen, rig, corr.view_pose(camera, frame), cameras=[camera], backend=backend).images[camera]
            pred = response(image, camera) if response is not None else image
            losses.append(photometric_loss(pred.permute(2, 0, 1)[None], targets[(frame, camera)].permute(2, 0, 1)[None],
                                           masks[camera], ssim_lambda))
        (corr.poses.grad,) = torch.autograd.grad(sum_terms(losses) / len(losses), [corr.poses])
        corr.step(step)
    return corr
