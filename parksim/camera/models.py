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

    Example:
        >>> cam = OpenCVFisheye(640, 480, 150.0, 150.0, 319.5, 239.5, [0.05, -0.01, 0.0, 0.0])
        >>> uv, valid = cam.project(torch.tensor([1.0, 0.0, -0.05], dtype=torch.float64))  # 93 deg off the axis
        >>> round(uv[0].item(), 1), valid.item()
        (577.8, True)
    """

    model = "opencv_fisheye"

    def __init__(self, width: int, height: int, fx: float | Tensor, fy: float | Tensor,
                 cx: float | Tensor, cy: float | Tensor, k: Tensor | list[float],
                 max_fov_deg: float = 190.0) -> None:
        """Kannala-Brandt intrinsics as OpenCV writes them.

        Args:
            width: image width in pixels.
            height: image height in pixels.
            fx: focal length in pixels (``K[0, 0]``).
            fy: focal length in pixels (``K[1, 1]``).
            cx: principal point column in pixels (``K[0, 2]``).
            cy: principal point row in pixels (``K[1, 2]``).
            k: ``(4,)`` distortion ``k1..k4`` (OpenCV's ``D``).
            max_fov_deg: full field of view in degrees; valid rays are within half of it.

        Raises:
            ValueError: ``k`` does not hold 4 values, or an intrinsic the base class refuses.
        """
        if torch.as_tensor(k).numel() != 4:
            raise ValueError(f"OpenCVFisheye needs 4 distortion coefficients k1..k4, got {torch.as_tensor(k).numel()}")
        super().__init__(width, height, fx, fy, cx, cy, k, max_fov_deg)

    @classmethod
    def from_K_D(cls, K: Any, D: Any, size: tuple[int, int], max_fov_deg: float = 190.0) -> OpenCVFisheye:
        """From an OpenCV camera matrix ``K`` (3x3), ``D`` (4 values) and ``size = (width, height)``.

        Args:
            K: ``(3, 3)`` camera matrix (array-like; skew is ignored).
            D: ``(4,)`` fisheye distortion ``k1..k4`` (array-like).
            size: ``(width, height)`` in pixels.
            max_fov_deg: full field of view in degrees.

        Returns:
            The camera model.
        """
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
        """``1 + k1 theta^2 + k2 theta^4 + k3 theta^6 + k4 theta^8`` (``CameraModel.q``)."""
        t2 = theta * theta
        return 1 + t2 * (k[0] + t2 * (k[1] + t2 * (k[2] + t2 * k[3])))

    def drho(self, theta: Tensor, k: Tensor) -> Tensor:
        """``1 + 3 k1 theta^2 + 5 k2 theta^4 + 7 k3 theta^6 + 9 k4 theta^8`` (``CameraModel.drho``)."""
        t2 = theta * theta
        return 1 + t2 * (3 * k[0] + t2 * (5 * k[1] + t2 * (7 * k[2] + t2 * 9 * k[3])))

    def to_dict(self) -> dict[str, Any]:
        """Model name, size, ``fx, fy, cx, cy``, ``k`` and ``max_fov_deg`` (``CameraModel.to_dict``)."""
        return {"model": self.model, "width": self.width, "height": self.height,
                "fx": float(self.fx), "fy": float(self.fy), "cx": float(self.cx), "cy": float(self.cy),
                "k": [float(v) for v in self.k], "max_fov_deg": self.max_fov_deg}

    def scaled(self, s: float) -> OpenCVFisheye:
        """Focal lengths times ``s``, principal point by the pixel-centre rule (``CameraModel.scaled``)."""
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
        """WoodScape intrinsics as its calibration JSON writes them.

        Args:
            width: image width in pixels.
            height: image height in pixels.
            k: ``(4,)`` ``k1..k4``, rho in pixels per power of theta (radians).
            cx_offset: principal point offset from the image centre, columns (pixels).
            cy_offset: principal point offset from the image centre, rows (pixels).
            aspect_ratio: vertical over horizontal pixel scale (``fy`` with ``fx = 1``).
            max_fov_deg: full field of view in degrees.

        Raises:
            ValueError: ``k`` does not hold 4 values, or an intrinsic the base class refuses.
        """
        if torch.as_tensor(k).numel() != 4:
            raise ValueError(f"RadialPolyFisheye needs 4 coefficients k1..k4, got {torch.as_tensor(k).numel()}")
        self.cx_offset, self.cy_offset, self.aspect_ratio = float(cx_offset), float(cy_offset), float(aspect_ratio)
        super().__init__(width, height, 1.0, aspect_ratio, cx_offset + width / 2 - 0.5,
                         cy_offset + height / 2 - 0.5, k, max_fov_deg)

    def q(self, theta: Tensor, k: Tensor) -> Tensor:
        """``k1 + k2 theta + k3 theta^2 + k4 theta^3`` (``CameraModel.q``)."""
        return k[0] + theta * (k[1] + theta * (k[2] + theta * k[3]))

    def drho(self, theta: Tensor, k: Tensor) -> Tensor:
        """``k1 + 2 k2 theta + 3 k3 theta^2 + 4 k4 theta^3`` (``CameraModel.drho``)."""
        return k[0] + theta * (2 * k[1] + theta * (3 * k[2] + theta * 4 * k[3]))

    def to_dict(self) -> dict[str, Any]:
        """Model name, size, ``k``, the offsets, ``aspect_ratio`` and ``max_fov_deg`` (``CameraModel.to_dict``)."""
        return {"model": self.model, "width": self.width, "height": self.height,
                "k": [float(v) for v in self.k], "cx_offset": self.cx_offset, "cy_offset": self.cy_offset,
                "aspect_ratio": self.aspect_ratio, "max_fov_deg": self.max_fov_deg}

    def scaled(self, s: float) -> RadialPolyFisheye:
        """``k`` times ``s`` (rho is in pixels), offsets by the pixel-centre rule (``CameraModel.scaled``)."""
        w, h = round(self.width * s), round(self.height * s)
        cx, cy = _scale_centre(float(self.cx), s), _scale_centre(float(self.cy), s)
        return RadialPolyFisheye(w, h, self.k.detach() * s, cx - (w / 2 - 0.5), cy - (h / 2 - 0.5),
                                 self.aspect_ratio, self.max_fov_deg)


class Pinhole(CameraModel):
    """Ideal perspective camera: rho = tan(theta), valid below 90 deg off the axis."""

    model = "pinhole"

    def __init__(self, width: int, height: int, fx: float | Tensor, fy: float | Tensor,
                 cx: float | Tensor, cy: float | Tensor, max_fov_deg: float = 170.0) -> None:
        """Pinhole intrinsics; no distortion.

        Args:
            width: image width in pixels.
            height: image height in pixels.
            fx: focal length in pixels.
            fy: focal length in pixels.
            cx: principal point column in pixels.
            cy: principal point row in pixels.
            max_fov_deg: full field of view in degrees, below 180.

        Raises:
            ValueError: ``max_fov_deg`` of 180 or more, or an intrinsic the base class refuses.
        """
        if max_fov_deg >= 180:
            raise ValueError(f"Pinhole: max_fov_deg must be below 180, got {max_fov_deg}")
        super().__init__(width, height, fx, fy, cx, cy, [], max_fov_deg)

    def q(self, theta: Tensor, k: Tensor) -> Tensor:
        """``tan(theta) / theta``; ``k`` is unused (``CameraModel.q``)."""
        # tan(theta)/theta; the series keeps the axis exact in value and gradient.
        small = theta.abs() < 1e-4
        safe = torch.where(small, torch.ones_like(theta), theta)
        t2 = theta * theta
        return torch.where(small, 1 + t2 / 3 + 2 * t2 * t2 / 15, torch.tan(safe) / safe)

    def drho(self, theta: Tensor, k: Tensor) -> Tensor:
        """``1 / cos(theta)^2``; ``k`` is unused (``CameraModel.drho``)."""
        return 1 / torch.cos(theta) ** 2

    def to_dict(self) -> dict[str, Any]:
        """Model name, size, ``fx, fy, cx, cy`` and ``max_fov_deg`` (``CameraModel.to_dict``)."""
        return {"model": self.model, "width": self.width, "height": self.height,
                "fx": float(self.fx), "fy": float(self.fy), "cx": float(self.cx), "cy": float(self.cy),
                "max_fov_deg": self.max_fov_deg}

    def scaled(self, s: float) -> Pinhole:
        """Focal lengths times ``s``, principal point by the pixel-centre rule (``CameraModel.scaled``)."""
        return Pinhole(round(self.width * s), round(self.height * s), float(self.fx) * s, float(self.fy) * s,
                       _scale_centre(float(self.cx), s), _scale_centre(float(self.cy), s), self.max_fov_deg)


_MODELS: dict[str, type[CameraModel]] = {c.model: c for c in (OpenCVFisheye, RadialPolyFisheye, Pinhole,
                                                                        OCamFisheye)}


def camera_from_dict(d: dict[str, Any]) -> CameraModel:
    """Inverse of ``to_dict``; names the unknown model or the missing/extra keys.

    Args:
        d: ``{"model": name, **constructor arguments}``, as ``CameraModel.to_dict`` writes it.

    Returns:
        The camera model of that class.

    Raises:
        ValueError: ``d`` is not a mapping with a ``model`` key, names an unknown model, or its keys or values
            do not fit that model's constructor.

    Example:
        >>> camera_from_dict(Pinhole(64, 48, 50.0, 50.0, 31.5, 23.5).to_dict()).width
        64
    """
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
