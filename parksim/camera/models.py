"""The three lens models: OpenCV fisheye (Kannala-Brandt), WoodScape radial polynomial, pinhole."""

from __future__ import annotations

from typing import Any

import torch
from torch import Tensor

from .base import CameraModel
from .ocam import OCamFisheye

__all__ = ["OpenCVFisheye", "RadialPolyFisheye", "Pinhole", "camera_from_dict"]


def _scale_centre(c: float, s: float) -> float:
    """Principal point at a new resolution, pixel centres at integers: (c + 0.5) s - 0.5."""
    return (c + 0.5) * s - 0.5


class OpenCVFisheye(CameraModel):
    """Kannala-Brandt as ``cv2.fisheye``: rho = theta (1 + k1 theta^2 + k2 theta^4 + k3 theta^6 + k4 theta^8).

    Unlike ``cv2.fisheye`` it is defined on the whole sphere up to ``max_fov_deg / 2``.
    """

    model = "opencv_fisheye"

    def __init__(self, width: int, height: int, fx: float | Tensor, fy: float | Tensor,
                 cx: float | Tensor, cy: float | Tensor, k: Tensor | list[float],
                 max_fov_deg: float = 190.0) -> None:
        if torch.as_tensor(k).numel() != 4:
            raise ValueError(f"OpenCVFisheye needs 4 distortion coefficients k1..k4, got {torch.as_tensor(k).numel()}")
        super().__init__(width, height, fx, fy, cx, cy, k, max_fov_deg)

    @classmethod
    def from_K_D(cls, K: Any, D: Any, size: tuple[int, int], max_fov_deg: float = 190.0) -> OpenCVFisheye:
        """From an OpenCV camera matrix ``K`` (3x3), ``D`` (4 values) and ``size = (width, height)``."""
        K = torch.as_tensor(K, dtype=torch.float64).reshape(3, 3)
        return cls(size[0], size[1], K[0, 0], K[1, 1], K[0, 2], K[1, 2],
                   torch.as_tensor(D, dtype=torch.float64).reshape(-1), max_fov_deg)

    @property
    def K(self) -> Tensor:
        """3x3 camera matrix (no skew)."""
        z = torch.zeros((), dtype=torch.float64)
        o = torch.ones((), dtype=torch.float64)
        return torch.stack([self.fx, z, self.cx, z, self.fy, self.cy, z, z, o]).reshape(3, 3)

    def q(self, theta: Tensor, k: Tensor) -> Tensor:
        t2 = theta * theta
        return 1 + t2 * (k[0] + t2 * (k[1] + t2 * (k[2] + t2 * k[3])))

    def drho(self, theta: Tensor, k: Tensor) -> Tensor:
        t2 = theta * theta
        return 1 + t2 * (3 * k[0] + t2 * (5 * k[1] + t2 * (7 * k[2] + t2 * 9 * k[3])))

    def to_dict(self) -> dict[str, Any]:
        return {"model": self.model, "width": self.width, "height": self.height,
                "fx": float(self.fx), "fy": float(self.fy), "cx": float(self.cx), "cy": float(self.cy),
                "k": [float(v) for v in self.k], "max_fov_deg": self.max_fov_deg}

    def scaled(self, s: float) -> OpenCVFisheye:
        return OpenCVFisheye(round(self.width * s), round(self.height * s), float(self.fx) * s,
                             float(self.fy) * s, _scale_centre(float(self.cx), s),
                             _scale_centre(float(self.cy), s), self.k.detach().clone(), self.max_fov_deg)


class RadialPolyFisheye(CameraModel):
    """WoodScape ``radial_poly``: rho = k1 theta + k2 theta^2 + k3 theta^3 + k4 theta^4 in pixels.

    As WoodScape defines it: ``u = rho x/chi + cx_offset + width/2 - 0.5`` and
    ``v = rho y/chi * aspect_ratio + cy_offset + height/2 - 0.5``.
    """

    model = "radial_poly"

    def __init__(self, width: int, height: int, k: Tensor | list[float], cx_offset: float = 0.0,
                 cy_offset: float = 0.0, aspect_ratio: float = 1.0, max_fov_deg: float = 190.0) -> None:
        if torch.as_tensor(k).numel() != 4:
            raise ValueError(f"RadialPolyFisheye needs 4 coefficients k1..k4, got {torch.as_tensor(k).numel()}")
        self.cx_offset, self.cy_offset, self.aspect_ratio = float(cx_offset), float(cy_offset), float(aspect_ratio)
        super().__init__(width, height, 1.0, aspect_ratio, cx_offset + width / 2 - 0.5,
                         cy_offset + height / 2 - 0.5, k, max_fov_deg)

    def q(self, theta: Tensor, k: Tensor) -> Tensor:
        return k[0] + theta * (k[1] + theta * (k[2] + theta * k[3]))

    def drho(self, theta: Tensor, k: Tensor) -> Tensor:
        return k[0] + theta * (2 * k[1] + theta * (3 * k[2] + theta * 4 * k[3]))

    def to_dict(self) -> dict[str, Any]:
        return {"model": self.model, "width": self.width, "height": self.height,
                "k": [float(v) for v in self.k], "cx_offset": self.cx_offset, "cy_offset": self.cy_offset,
                "aspect_ratio": self.aspect_ratio, "max_fov_deg": self.max_fov_deg}

    def scaled(self, s: float) -> RadialPolyFisheye:
        w, h = round(self.width * s), round(self.height * s)
        cx, cy = _scale_centre(float(self.cx), s), _scale_centre(float(self.cy), s)
        return RadialPolyFisheye(w, h, self.k.detach() * s, cx - (w / 2 - 0.5), cy - (h / 2 - 0.5),
                                 self.aspect_ratio, self.max_fov_deg)


class Pinhole(CameraModel):
    """Ideal perspective camera: rho = tan(theta), valid below 90 deg off the axis."""

    model = "pinhole"

    def __init__(self, width: int, height: int, fx: float | Tensor, fy: float | Tensor,
                 cx: float | Tensor, cy: float | Tensor, max_fov_deg: float = 170.0) -> None:
        if max_fov_deg >= 180:
            raise ValueError(f"Pinhole: max_fov_deg must be below 180, got {max_fov_deg}")
        super().__init__(width, height, fx, fy, cx, cy, [], max_fov_deg)

    def q(self, theta: Tensor, k: Tensor) -> Tensor:
        # tan(theta)/theta; the series keeps the axis exact in value and gradient.
        small = theta.abs() < 1e-4
        safe = torch.where(small, torch.ones_like(theta), theta)
        t2 = theta * theta
        return torch.where(small, 1 + t2 / 3 + 2 * t2 * t2 / 15, torch.tan(safe) / safe)

    def drho(self, theta: Tensor, k: Tensor) -> Tensor:
        return 1 / torch.cos(theta) ** 2

    def to_dict(self) -> dict[str, Any]:
        return {"model": self.model, "width": self.width, "height": self.height,
                "fx": float(self.fx), "fy": float(self.fy), "cx": float(self.cx), "cy": float(self.cy),
                "max_fov_deg": self.max_fov_deg}

    def scaled(self, s: float) -> Pinhole:
        return Pinhole(round(self.width * s), round(self.height * s), float(self.fx) * s, float(self.fy) * s,
                       _scale_centre(float(self.cx), s), _scale_centre(float(self.cy), s), self.max_fov_deg)


_MODELS: dict[str, type[CameraModel]] = {c.model: c for c in (OpenCVFisheye, RadialPolyFisheye, Pinhole,
                                                                        OCamFisheye)}


def camera_from_dict(d: dict[str, Any]) -> CameraModel:
    """Inverse of ``to_dict``; names the unknown model or the missing/extra keys."""
    if not isinstance(d, dict) or "model" not in d:
        raise ValueError(f"camera intrinsics must be a mapping with a 'model' key, got {d!r}")
    cls = _MODELS.get(d["model"])
    if cls is None:
        raise ValueError(f"unknown camera model {d['model']!r}; known models: {sorted(_MODELS)}")
    args = {key: v for key, v in d.items() if key != "model"}
    try:
        return cls(**args)
    except TypeError as e:
        raise ValueError(f"bad intrinsics for camera model {d['model']!r}: {e}") from None
