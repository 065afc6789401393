"""Central radial camera on the whole sphere: the shared projection and unprojection.

Every model here maps a ray at angle ``theta`` off the optical axis to a radial image
distance ``rho(theta) = theta * q(theta)`` (in normalised units, then scaled by
``fx, fy`` and shifted by ``cx, cy``). Projection computes ``theta = atan2(r, z)`` and
never divides by ``z``, so points behind the image plane (a 190 deg lens sees them)
project correctly instead of mirroring. Subclasses supply only ``q`` and ``drho``.
"""

from __future__ import annotations

import math
from abc import ABC, abstractmethod
from typing import Any, ClassVar

import torch
from torch import Tensor

__all__ = ["CameraModel", "pixel_grid"]

_FOLD_SCAN_STEPS = 4096


def pixel_grid(width: int, height: int, dtype: torch.dtype = torch.float64,
               device: torch.device | str | None = None) -> Tensor:
    """Pixel centres ``[H, W, 2]`` as (u, v) = (column, row), centres at integer coordinates.

    Args:
        width: image width ``W`` in pixels.
        height: image height ``H`` in pixels.
        dtype: float dtype of the grid.
        device: device of the grid (default: torch's default device).

    Returns:
        ``[H, W, 2]`` grid with ``grid[i, j] = (j, i)``.

    Example:
        >>> pixel_grid(3, 2)[1, 2].tolist()
        [2.0, 1.0]
    """
    v, u = torch.meshgrid(torch.arange(height, dtype=dtype, device=device),
                          torch.arange(width, dtype=dtype, device=device), indexing="ij")
    return torch.stack([u, v], dim=-1)


def _sinc(theta: Tensor) -> Tensor:
    """sin(theta)/theta, smooth through 0."""
    return torch.sinc(theta / math.pi)


def _pow2_normalised(v: Tensor) -> Tensor:
    """``v[..., k]`` scaled by the power of two that puts its largest |component| in ``[2, 4)``.

    Far and near points then square without overflow or underflow, and a power-of-two scale is
    exact: no bit of the direction is lost. Autograd sees the scale as a constant, which is right
    for the scale-invariant maps it feeds. A vector with an infinite or NaN component has no
    direction to trust: NaN, with zero gradient.

    Returns:
        ``v`` times ``2^(2 - e)``, its shape and dtype; all NaN where a component is infinite or NaN.
    """
    m = v.detach().abs().amax(-1, keepdim=True)
    finite = torch.isfinite(m) & (m > 0)
    _, e = torch.frexp(torch.where(finite, m, torch.ones_like(m)))
    # e >= that of the smallest normal number keeps 2^(2 - e) finite for subnormal m; 2^(2 - e) is normal for any m.
    e = e.clamp(min=math.frexp(torch.finfo(v.dtype).tiny)[1])
    scaled = v * torch.ldexp(torch.ones_like(m), 2 - e)
    return torch.where(torch.isfinite(m), scaled, torch.full_like(v, math.nan))


class CameraModel(ABC):
    """Base class: intrinsics as float64 tensors (set ``requires_grad`` to optimise them).

    ``fx, fy`` scale the normalised radial image, ``cx, cy`` is the principal point in
    pixels with pixel centres at integer coordinates (OpenCV), ``k`` the model's radial
    coefficients and ``theta_max`` the largest valid angle off the axis: the smaller of
    half the lens' field of view and the first fold-back of ``rho`` (``drho <= 0``).
    """

    model: ClassVar[str] = ""

    def __init__(self, width: int, height: int, fx: float | Tensor, fy: float | Tensor,
                 cx: float | Tensor, cy: float | Tensor, k: Tensor | list[float],
                 max_fov_deg: float) -> None:
        """Check and store the intrinsics, then find ``theta_max``.

        Args:
            width: image width in pixels.
            height: image height in pixels.
            fx: horizontal scale of the normalised radial image, in pixels (> 0).
            fy: vertical scale of the normalised radial image, in pixels (> 0).
            cx: principal point column in pixels (pixel centres at integers).
            cy: principal point row in pixels.
            k: ``(K,)`` the model's radial coefficients (K depends on the model, 0 for a pinhole).
            max_fov_deg: the lens' full field of view in degrees, in (0, 360].

        Raises:
            ValueError: a non-positive image size or focal length, a non-finite intrinsic, ``max_fov_deg``
                outside (0, 360], or a ``rho(theta)`` that does not increase at the optical axis.
        """
        self.width = int(width)
        self.height = int(height)
        if self.width <= 0 or self.height <= 0:
            raise ValueError(f"{type(self).__name__}: image size must be positive, got {width}x{height}")
        as_t = lambda v: torch.as_tensor(v, dtype=torch.float64)  # noqa: E731
        self.fx, self.fy, self.cx, self.cy = as_t(fx), as_t(fy), as_t(cx), as_t(cy)
        self.k = as_t(k).reshape(-1)
        self.max_fov_deg = float(max_fov_deg)
        values = torch.cat([self.fx.reshape(1), self.fy.reshape(1), self.cx.reshape(1),
                            self.cy.reshape(1), self.k]).detach()
        if not torch.isfinite(values).all():
            raise ValueError(f"{type(self).__name__}: intrinsics must be finite, got {values.tolist()}")
        if self.fx.item() <= 0 or self.fy.item() <= 0:
            raise ValueError(f"{type(self).__name__}: focal lengths must be positive, "
                             f"got fx={self.fx.item()}, fy={self.fy.item()}")
        if not 0 < self.max_fov_deg <= 360:
            raise ValueError(f"{type(self).__name__}: max_fov_deg must be in (0, 360], got {max_fov_deg}")
        self.theta_max = self._valid_theta_max()

    # --- what a model defines -------------------------------------------------------
    @abstractmethod
    def q(self, theta: Tensor, k: Tensor) -> Tensor:
        """The model's ``rho(theta) / theta``, smooth at theta = 0.

        Args:
            theta: ``(...)`` angles off the optical axis in radians.
            k: ``(K,)`` radial coefficients (``self.k``, or a cast copy of it).

        Returns:
            ``(...)`` ``q(theta)``, ``theta``'s dtype, differentiable in ``theta`` and ``k``.
        """

    @abstractmethod
    def drho(self, theta: Tensor, k: Tensor) -> Tensor:
        """The model's ``d rho / d theta``: where it is not positive the lens folds back.

        Args:
            theta: ``(...)`` angles off the optical axis in radians.
            k: ``(K,)`` radial coefficients.

        Returns:
            ``(...)`` the derivative, ``theta``'s dtype.
        """

    @abstractmethod
    def to_dict(self) -> dict[str, Any]:
        """Serialisable intrinsics, read back by ``parksim.camera.camera_from_dict``.

        Returns:
            ``{"model": name, ...}`` with the constructor's arguments as plain floats and lists.
        """

    @abstractmethod
    def scaled(self, s: float) -> CameraModel:
        """The same lens imaged at ``s`` times the resolution (pixel-centre convention).

        Args:
            s: resolution factor (0.5 halves width and height, rounded to whole pixels).

        Returns:
            A new model of the same class; the intrinsics are detached copies.
        """

    # --- shared machinery -----------------------------------------------------------
    def rho(self, theta: Tensor, k: Tensor) -> Tensor:
        """Normalised radial image distance ``rho(theta) = theta * q(theta)``.

        Args:
            theta: ``(...)`` angles off the optical axis in radians.
            k: ``(K,)`` radial coefficients.

        Returns:
            ``(...)`` radial distances (pixels once scaled by ``fx, fy``).
        """
        return theta * self.q(theta, k)

    def _valid_theta_max(self) -> float:
        """Half the field of view, cut at the first fold-back of rho (scan, then bisection)."""
        limit = min(math.radians(self.max_fov_deg) / 2.0, math.pi - 1e-3)
        k = self.k.detach()
        grid = torch.linspace(0.0, limit, _FOLD_SCAN_STEPS + 1, dtype=torch.float64)
        bad = (self.drho(grid, k) <= 0).nonzero()
        if len(bad) == 0:
            return limit
        i = int(bad[0])
        if i == 0:
            raise ValueError(f"{type(self).__name__}: rho(theta) is not increasing at the optical axis "
                             f"(k={k.tolist()})")
        lo, hi = float(grid[i - 1]), float(grid[i])
        for _ in range(60):
            mid = 0.5 * (lo + hi)
            if float(self.drho(torch.tensor(mid, dtype=torch.float64), k)) > 0:
                lo = mid
            else:
                hi = mid
        return lo

    def _intrinsics(self, like: Tensor) -> tuple[Tensor, Tensor, Tensor, Tensor, Tensor]:
        cast = lambda t: t.to(dtype=like.dtype, device=like.device)  # noqa: E731
        return cast(self.fx), cast(self.fy), cast(self.cx), cast(self.cy), cast(self.k)

    @property
    def rho_max(self) -> float:
        """Normalised radial distance of the valid image circle's edge."""
        t = torch.tensor(self.theta_max, dtype=torch.float64)
        return float(self.rho(t, self.k.detach()))

    def theta_of(self, points: Tensor) -> Tensor:
        """Angle off the optical axis ``(...)`` of points ``(..., 3)``, ``atan2(r, z)``; no gradient guard (masks).

        Args:
            points: ``(..., 3)`` camera-frame points.

        Returns:
            ``(...)`` angles in [0, pi] radians; NaN for a point with an infinite or NaN coordinate.
        """
        p = _pow2_normalised(points)
        return torch.atan2(p[..., :2].norm(dim=-1), p[..., 2])

    def project(self, points: Tensor) -> tuple[Tensor, Tensor]:
        """Project camera-frame points (OpenCV axes: x right, y down, z forward) to pixels.

        Valid means: not the camera centre (``|p|^2 <= tiny``), within ``theta_max`` and inside
        the image. Invalid points still get finite pixels (beyond the lens they land on the rim of
        the image circle in their own direction, never mirrored), and finite gradients. Only the
        direction matters: a point of any finite magnitude lands where its unit point does. A point
        with an infinite or NaN coordinate has no direction: NaN pixels, invalid, zero gradient.

        Args:
            points: ``(..., 3)`` float points in the camera frame, any batch shape.

        Returns:
            ``(uv, valid)``: pixels ``(..., 2)`` as (column, row) with pixel centres at integers,
            same dtype as ``points``, and a bool mask ``(...)``.

        Raises:
            ValueError: ``points`` does not end in a dimension of 3.

        Example:
            >>> from parksim.camera import Pinhole
            >>> cam = Pinhole(64, 48, 50.0, 50.0, 31.5, 23.5)
            >>> uv, valid = cam.project(torch.tensor([[0.0, 0.0, 2.0], [1.0, 0.5, 2.0]], dtype=torch.float64))
            >>> uv.tolist(), valid.tolist()
            ([[31.5, 23.5], [56.5, 36.0]], [True, True])
        """
        if points.shape[-1] != 3:
            raise ValueError(f"project expects points[..., 3], got shape {tuple(points.shape)}")
        fx, fy, cx, cy, k = self._intrinsics(points)
        tiny = torch.finfo(points.dtype).tiny
        axis_eps = math.sqrt(torch.finfo(points.dtype).eps)

        centre = (points.detach() ** 2).sum(-1) <= tiny
        x, y, z = _pow2_normalised(points).unbind(-1)
        x = torch.where(centre, torch.zeros_like(x), x)
        y = torch.where(centre, torch.zeros_like(y), y)
        z = torch.where(centre, torch.ones_like(z), z)
        n = torch.sqrt(x * x + y * y + z * z)

        r2 = x * x + y * y
        on_axis = r2 <= (axis_eps * n) ** 2
        r = torch.sqrt(torch.where(on_axis, torch.ones_like(r2), r2))
        theta = torch.where(on_axis, torch.where(z > 0, torch.zeros_like(z), torch.full_like(z, math.pi)),
                            torch.atan2(r, z))

        beyond = theta > self.theta_max
        theta_in = torch.where(beyond, torch.zeros_like(theta), theta)
        # rho/r = theta q(theta) / (n sin theta) = q / (sinc n): exact and smooth through the axis.
        inside_scale = self.q(theta_in, k) / (_sinc(theta_in) * n)
        t_max = torch.tensor(self.theta_max, dtype=points.dtype, device=points.device)
        rim_scale = self.rho(t_max, k) / torch.where(on_axis, torch.ones_like(r), r)
        scale = torch.where(beyond, rim_scale, inside_scale)

        u = fx * scale * x + cx
        v = fy * scale * y + cy
        uv = torch.stack([u, v], dim=-1)
        valid = (~centre) & (~beyond) & self.in_image(uv)
        return uv, valid

    def in_image(self, uv: Tensor) -> Tensor:
        """Pixel inside the image rectangle (edges at -0.5 and size - 0.5).

        Args:
            uv: ``(..., 2)`` pixels as (column, row).

        Returns:
            ``(...)`` bool mask.
        """
        u, v = uv[..., 0], uv[..., 1]
        return (u >= -0.5) & (u <= self.width - 0.5) & (v >= -0.5) & (v <= self.height - 0.5)

    def _normalised(self, uv: Tensor) -> tuple[Tensor, Tensor]:
        fx, fy, cx, cy, _ = self._intrinsics(uv)
        return (uv[..., 0] - cx) / fx, (uv[..., 1] - cy) / fy

    def pixel_valid(self, uv: Tensor) -> Tensor:
        """Pixel inside the image and inside the lens' valid circle (``theta <= theta_max``).

        Args:
            uv: ``(..., 2)`` pixels as (column, row).

        Returns:
            ``(...)`` bool mask: the pixels whose ``unproject`` ray is the lens' own.
        """
        mx, my = self._normalised(uv)
        return self.in_image(uv) & (mx * mx + my * my <= self.rho_max ** 2)

    def _solve_theta(self, rho: Tensor, k: Tensor) -> Tensor:
        """Theta with rho(theta) = rho on [0, theta_max]: Newton safeguarded by bisection."""
        kd = k.detach()
        rho = rho.detach()
        lo = torch.zeros_like(rho)
        hi = torch.full_like(rho, self.theta_max)
        q0 = self.q(torch.zeros((), dtype=rho.dtype, device=rho.device), kd)
        theta = torch.clamp(rho / q0, max=self.theta_max)
        for _ in range(40 if rho.dtype == torch.float64 else 25):
            f = self.rho(theta, kd) - rho
            lo = torch.where(f <= 0, theta, lo)
            hi = torch.where(f >= 0, theta, hi)
            step = theta - f / self.drho(theta, kd)
            inside = (step >= lo) & (step <= hi) & torch.isfinite(step)
            theta = torch.where(inside, step, 0.5 * (lo + hi))
        return theta

    def unproject(self, uv: Tensor) -> Tensor:
        """Unit rays in the camera frame through pixels, also past 90 deg off the axis.

        Pixels outside the valid circle give the ray at ``theta_max`` in their direction
        (``pixel_valid`` tells them apart), however far out. Gradients follow the implicit
        function theorem: one Newton step taken with autograd from the converged, detached root.

        Args:
            uv: ``(..., 2)`` float pixels as (column, row), pixel centres at integers.

        Returns:
            ``(..., 3)`` unit rays, same dtype as ``uv``.

        Raises:
            ValueError: ``uv`` does not end in a dimension of 2.

        Example:
            >>> from parksim.camera import Pinhole
            >>> cam = Pinhole(64, 48, 50.0, 50.0, 31.5, 23.5)
            >>> cam.unproject(torch.tensor([[31.5, 23.5], [56.5, 36.0]], dtype=torch.float64)).tolist()
            [[0.0, 0.0, 1.0], [0.4364357804719848, 0.2182178902359924, 0.8728715609439696]]
        """
        if uv.shape[-1] != 2:
            raise ValueError(f"unproject expects uv[..., 2], got shape {tuple(uv.shape)}")
        _, _, _, _, k = self._intrinsics(uv)
        mx, my = self._normalised(uv)
        nonzero = (mx != 0) | (my != 0)
        rho = torch.hypot(torch.where(nonzero, mx, torch.ones_like(mx)), my)   # 1 at the centre: no 0/0 gradient
        theta0 = self._solve_theta(rho, k)
        interior = nonzero & (theta0 < self.theta_max)
        newton = theta0 - (self.rho(theta0, k) - rho) / self.drho(theta0, k.detach()).detach()
        theta = torch.where(interior, newton, theta0)
        theta = torch.where(nonzero, theta, torch.zeros_like(theta))
        # sin(theta)/rho = sinc(theta)/q(theta) in the interior; at the rim the pixel gives only a direction,
        # taken from its power-of-two scaled offset (a far-out or infinite pixel overflows nothing).
        inner = interior | ~nonzero
        hx, hy = _pow2_normalised(torch.stack([mx, my], dim=-1)).unbind(-1)
        h = torch.sqrt(torch.where(inner, torch.ones_like(hx), hx * hx + hy * hy))
        lateral = _sinc(theta) / self.q(theta, k)
        rim = torch.sin(theta) / h
        zero = torch.zeros_like(mx)
        ray = torch.stack([torch.where(inner, lateral * torch.where(inner, mx, zero), rim * hx),
                           torch.where(inner, lateral * torch.where(inner, my, zero), rim * hy),
                           torch.cos(theta)], dim=-1)
        return ray

    def __repr__(self) -> str:
        """The class name and ``to_dict()``."""
        return f"{type(self).__name__}({self.to_dict()})"
