"""Per-image exposure and white balance: an affine colour correction per training view, learned with the scene.

Real cameras auto-expose: the same floor comes out brighter in one frame than in the next, and each camera's
exposure and white balance drift on their own. Without a per-image term the Gaussians average those colourings
(or bake them into view-dependent colour). ``ImageExposure`` gives each training ``(frame, camera)`` view an RGB
gain and bias, ``image * exp(g) + b``, applied to the rendered image (after the camera's ``CameraResponse``) before
the loss. Both start at the identity and are pulled towards it by an L2 penalty (``IDENTITY_WEIGHT``); per camera,
their mean over that camera's views is pinned to zero, so the camera's common colouring stays with
``CameraResponse`` and the scene's brightness with the Gaussians.

The corrections exist only for training views: a novel pose has no image to fit, so it renders with the camera's
reference response (``CameraResponse``) alone, and the bundle holds no per-image terms.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import torch
from torch import Tensor

__all__ = ["ImageExposure", "IDENTITY_WEIGHT"]

IDENTITY_WEIGHT = 1e-2
"""Weight of the mean squared (pinned) log gain and bias added to the loss: a drift far smaller than the data's
pull, large enough that a view the data says nothing about stays at the identity."""


class ImageExposure:
    """Learnable ``image * exp(log_gain[view]) + bias[view]`` per training view, centred per camera.

    Parameters (``log_gain`` and ``bias``, ``[V, 3]`` for V views) and the per-camera row indices live on ``device``.
    """

    def __init__(self, views: Sequence[tuple[int, str]], lr: float, device: torch.device | None = None) -> None:
        """Identity corrections for ``views``, trained by Adam at ``lr``.

        Args:
            views: the training ``(frame, camera)`` views, each once.
            lr: Adam learning rate (> 0: a disabled correction is no object at all).
            device: where the parameters live (the images' device; None: the CPU).
        """
        self.index = {view: i for i, view in enumerate(views)}
        cameras = list(dict.fromkeys(c for _, c in views))
        self._rows = {c: torch.tensor([i for i, (_, cam) in enumerate(views) if cam == c], device=device)
                      for c in cameras}
        self.log_gain = torch.zeros(len(views), 3, device=device, requires_grad=True)
        self.bias = torch.zeros(len(views), 3, device=device, requires_grad=True)
        self.optimizer = torch.optim.Adam([self.log_gain, self.bias], lr=lr)

    def correction(self, frame: int, camera: str) -> tuple[Tensor, Tensor]:
        """The view's pinned correction: its parameters minus their mean over the camera's views.

        Args:
            frame: the view's frame.
            camera: the view's camera.

        Returns:
            ``(gain, bias)``, each ``[3]`` RGB: the image is multiplied by ``gain`` then ``bias`` is added.
        """
        i, rows = self.index[(frame, camera)], self._rows[camera]
        log_gain = self.log_gain[i] - self.log_gain[rows].mean(dim=0)
        return torch.exp(log_gain), self.bias[i] - self.bias[rows].mean(dim=0)

    def __call__(self, image: Tensor, frame: int, camera: str) -> Tensor:
        """Apply view ``(frame, camera)``'s correction to a rendered ``[H, W, 3]`` image.

        Args:
            image: the rendered view (through its camera's response).
            frame: the view's frame (a training frame).
            camera: the view's camera.

        Returns:
            The corrected ``[H, W, 3]`` image.
        """
        gain, bias = self.correction(frame, camera)
        return image * gain + bias

    def penalty(self) -> Tensor:
        """The identity penalty added to the loss.

        Averaged over every view, it is what a penalty on each step's sampled views is on average.

        Returns:
            0-dim: ``IDENTITY_WEIGHT`` x the mean over views of the squared pinned log gains and biases.
        """
        squares = [((p[rows] - p[rows].mean(dim=0)) ** 2).sum()
                   for p in (self.log_gain, self.bias) for rows in self._rows.values()]
        return IDENTITY_WEIGHT * torch.stack(squares).sum() / len(self.index)

    def step(self) -> None:
        """One Adam step (a no-op for a step that did not use the corrections)."""
        self.optimizer.step()
        self.optimizer.zero_grad(set_to_none=True)

    def state_dict(self) -> dict[str, Any]:
        """Checkpoint state: parameters and optimizer moments."""
        return {"log_gain": self.log_gain.detach().clone(), "bias": self.bias.detach().clone(),
                "optimizer": self.optimizer.state_dict()}

    def load_state_dict(self, state: dict[str, Any]) -> None:
        """Restore ``state_dict`` output (tensors from any device).

        Raises:
            ValueError: the state holds another number of views (it was written for another split).
        """
        if tuple(state["log_gain"].shape) != tuple(self.log_gain.shape):
            raise ValueError(f"the checkpoint's exposure corrections are for {state['log_gain'].shape[0]} views, "
                             f"this run has {self.log_gain.shape[0]}")
        with torch.no_grad():
            self.log_gain.copy_(state["log_gain"])
            self.bias.copy_(state["bias"])
        self.optimizer.load_state_dict(state["optimizer"])
