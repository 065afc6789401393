"""Per-camera photometric response: an RGB gain and a radial vignetting fall-off, learned with the scene.

Surround-view cameras differ in exposure and darken towards the lens' edge; without this a single
Gaussian scene must average four inconsistent colourings of the same floor. The mean log gain over
cameras is pinned to zero so that the response cannot absorb the scene's overall brightness.

A bundle saves it (``to_dict``) as its ``camera_response``: evaluation and the simulator (``parksim.sim.LocalSim``)
apply it, fixed (``CameraResponse.frozen``), to every view they render. Per-image exposure corrections
(``parksim.recon.exposure``) are training-only; this per-camera response is the reference a novel pose renders with.
"""

from __future__ import annotations

from typing import Any

import torch
from torch import Tensor

from parksim.camera import CameraModel, pixel_grid
from parksim.rig import Rig

__all__ = ["CameraResponse"]


class CameraResponse:
    """Learnable ``image * gain[camera] * (1 + v1 r^2 + v2 r^4)`` with r the radius relative to the lens circle.

    Its parameters and radius maps live on ``device`` (the images' device: the CPU by default); the maps are
    built for the rig's cameras scaled by ``scale`` (the size the images are rendered at).
    """

    def __init__(self, rig: Rig, lr: float, device: torch.device | None = None, scale: float = 1.0) -> None:
        """The identity response for ``rig``'s cameras.

        Args:
            rig: the rig (its camera models give the radius maps).
            lr: Adam learning rate (0: frozen, no optimizer).
            device: where the parameters and maps live (None: the CPU).
            scale: the images' size relative to the rig's cameras.
        """
        self.names = list(rig.names)
        n = len(self.names)
        self.log_gain = torch.zeros(n, 3, device=device, requires_grad=lr > 0)
        self.vignetting = torch.zeros(n, 2, device=device, requires_grad=lr > 0)
        self.optimizer = torch.optim.Adam([self.log_gain, self.vignetting], lr=lr) if lr > 0 else None
        models = {name: rig.cameras[name].model for name in self.names}
        self._r2 = {name: self._radius2(m if scale == 1.0 else m.scaled(scale)).to(device)
                    for name, m in models.items()}

    @classmethod
    def frozen(cls, rig: Rig, data: dict[str, Any], device: torch.device | None = None,
               scale: float = 1.0) -> CameraResponse:
        """A saved response, fixed, for images of ``rig`` rendered at ``scale`` on ``device``.

        Args:
            rig: the rig the images are rendered with.
            data: ``to_dict`` output (a bundle's ``camera_response``); cameras missing there keep the identity.
            device: where the images are.
            scale: their size relative to the rig's cameras.

        Returns:
            The response, with no optimizer.
        """
        response = cls(rig, 0.0, device, scale)
        response.load_dict(data)
        return response

    @staticmethod
    def _radius2(model: CameraModel) -> Tensor:
        """Squared normalised radius ``[H, W, 1]`` (1 on the lens' valid circle)."""
        uv = pixel_grid(model.width, model.height)
        fx, fy = float(model.fx), float(model.fy)
        x, y = (uv[..., 0] - float(model.cx)) / fx, (uv[..., 1] - float(model.cy)) / fy
        r2 = (x ** 2 + y ** 2) / model.rho_max ** 2
        return r2.to(torch.float32)[..., None]

    def __call__(self, image: Tensor, camera: str) -> Tensor:
        """Apply camera ``camera``'s response to a rendered ``[H, W, 3]`` image."""
        i = self.names.index(camera)
        gain = torch.exp(self.log_gain[i] - self.log_gain.mean(dim=0))
        r2 = self._r2[camera]
        v = self.vignetting[i]
        return image * gain * (1.0 + v[0] * r2 + v[1] * r2 * r2)

    def step(self) -> None:
        """One Adam step (no-op when the response is frozen)."""
        if self.optimizer is not None:
            self.optimizer.step()
            self.optimizer.zero_grad(set_to_none=True)

    def to_dict(self) -> dict[str, Any]:
        """JSON form for the bundle: per camera ``gain`` (RGB) and ``vignetting`` (r^2, r^4)."""
        gains = torch.exp(self.log_gain - self.log_gain.mean(dim=0)).detach()
        return {name: {"gain": gains[i].tolist(), "vignetting": self.vignetting[i].detach().tolist()}
                for i, name in enumerate(self.names)}

    def load_dict(self, data: dict[str, Any]) -> None:
        """Set the response from ``to_dict`` output (cameras missing there keep the identity response)."""
        with torch.no_grad():
            for i, name in enumerate(self.names):
                if name in data:
                    self.log_gain[i] = torch.log(torch.tensor(data[name]["gain"], dtype=torch.float32))
                    self.vignetting[i] = torch.tensor(data[name]["vignetting"], dtype=torch.float32)

    def state_dict(self) -> dict[str, Any]:
        """Checkpoint state: parameters and optimizer moments."""
        return {"log_gain": self.log_gain.detach().clone(), "vignetting": self.vignetting.detach().clone(),
                "optimizer": self.optimizer.state_dict() if self.optimizer is not None else None}

    def load_state_dict(self, state: dict[str, Any]) -> None:
        """Restore ``state_dict`` output."""
        with torch.no_grad():
            self.log_gain.copy_(state["log_gain"])
            self.vignetting.copy_(state["vignetting"])
        if self.optimizer is not None and state["optimizer"] is not None:
            self.optimizer.load_state_dict(state["optimizer"])
