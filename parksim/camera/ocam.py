"""OCamCalib (Scaramuzza) omnidirectional model on the whole sphere, read from its own files.

Axes. Ours (``base.py``): camera frame x right, y down, z forward; pixels (u, v) = (column, row),
0-based, pixel centres at integers. OCamCalib's ``cam2world``/``world2cam`` (``ocam_functions.c``)
index pixels (row, column) and return rays (x_o, y_o, z_o) with x_o along rows, y_o along columns
and ``z_o = ss(rho) < 0`` for a ray in front of the lens, so ``(x_o, y_o, z_o) = (y, x, -z)``: a
proper rotation (det +1). ``world2cam``'s angle ``atan(z_o / sqrt(x_o^2 + y_o^2))`` is therefore
``theta - pi/2``, with ``theta`` our angle off the optical axis.

Model. A ray at ``theta`` lands at sensor radius ``rho`` (pixels, before the affine) in its own
azimuth, and the image offset from the centre is the affine ``[u - yc, v - xc] = [[1, e], [d, c]]
rho (x, y) / r``, which is OCamCalib's ``row = c X + d Y + xc``, ``column = e X + Y + yc`` written
in our axes. The radial map comes from one polynomial:

- ``ss`` (cam2world) when the file has it: ``theta(rho) = atan2(rho, -ss(rho))`` is explicit and
  ``project`` solves for ``rho`` (Newton kept in a bisection bracket, started from ``invpol``),
  so ``invpol`` only seeds the solve and ``project`` is ``ss``'s exact inverse;
- otherwise ``invpol`` (world2cam): ``rho(theta) = invpol(theta - pi/2) - invpol(-pi/2)``, and
  ``unproject`` solves for ``theta``. The constant ``invpol(-pi/2)`` is the fit's residual on the
  axis (thousandths of a pixel); dropping it puts the axis on the centre, as ``world2cam`` itself
  does for a point exactly on the axis, instead of a ring of that radius.

Valid angle: ``max_fov_deg / 2`` (files don't state it: 360 means no limit), cut where the defining
polynomial folds back and where ``rho`` reaches the image's farthest corner, past which nothing
was calibrated. ``fx = 1``, ``fy = c``, ``cx = yc``, ``cy = xc`` hold the affine's diagonal for
code that reads them; ``d, e`` are the off-diagonal terms.

Surround-view JSON (``from_json``, as SensorsCalibration's ``ocam_samples``): ``cam_K`` is
``[[c', d', u0], [e', 1, v0], [0, 0, 1]]`` and ``cam_dist`` the inverse polynomial, used by a
``world2cam`` whose first output is the column and whose input is ``(x, y, -z)``. The same lens in
OCamCalib's terms: ``c = 1/c'``, ``d = e'/c'``, ``e = d'/c'``, ``invpol = c' cam_dist``,
``(xc, yc) = (v0, u0)``.
"""

from __future__ import annotations

import json
import math
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

import torch
from torch import Tensor

from .base import CameraModel, _sinc

__all__ = ["OCamFisheye"]

_SCAN_STEPS = 4096


def _polyval(c: Tensor, x: Tensor) -> Tensor:
    """``sum_i c[i] x^i`` (lowest degree first, Horner), differentiable in both."""
    out = c[-1] + torch.zeros_like(x)
    for i in range(len(c) - 2, -1, -1):
        out = out * x + c[i]
    return out


def _polyder(c: Tensor) -> Tensor:
    """Coefficients of the derivative (lowest degree first)."""
    return c[1:] * torch.arange(1, len(c), dtype=c.dtype, device=c.device)


def _last_ok(ok: Callable[[Tensor], Tensor], hi: float) -> float:
    """Largest x in [0, hi] with ``ok`` on all of [0, x]: a scan, then bisection; 0 if ``ok(0)`` fails."""
    grid = torch.linspace(0.0, hi, _SCAN_STEPS + 1, dtype=torch.float64)
    bad = (~ok(grid)).nonzero()
    if len(bad) == 0:
        return hi
    i = int(bad[0])
    if i == 0:
        return 0.0
    lo, up = float(grid[i - 1]), float(grid[i])
    for _ in range(60):
        mid = 0.5 * (lo + up)
        if bool(ok(torch.tensor(mid, dtype=torch.float64))):
            lo = mid
        else:
            up = mid
    return lo


def _taylor_shift(n: int, h: float) -> Tensor:
    """``T`` with ``sum_i p_i (t - h)^i = sum_j (T p)_j t^j`` for ``n`` coefficients."""
    T = torch.zeros(n, n, dtype=torch.float64)
    for i in range(n):
        for j in range(i + 1):
            T[j, i] = math.comb(i, j) * (-h) ** (i - j)
    return T


def _floats(values: Sequence[float] | Tensor | None, name: str, least: int) -> Tensor | None:
    if values is None:
        return None
    t = torch.as_tensor(values, dtype=torch.float64).reshape(-1)
    if t.numel() < least or not torch.isfinite(t).all():
        raise ValueError(f"OCamFisheye: {name} needs at least {least} finite coefficients, got {t.tolist()}")
    return t


class OCamFisheye(CameraModel):
    """OCamCalib's model: ``ss`` and/or ``invpol`` polynomials, centre (xc = row, yc = column), affine c, d, e.

    ``k`` is the defining polynomial (``ss`` if given, else ``invpol``), lowest degree first as in
    ``calib_results.txt``; ``xc, yc`` are 0-based (C convention).
    """

    model = "ocam"

    def __init__(self, width: int, height: int, xc: float, yc: float, ss: Sequence[float] | Tensor | None = None,
                 invpol: Sequence[float] | Tensor | None = None, c: float = 1.0, d: float = 0.0, e: float = 0.0,
                 max_fov_deg: float = 360.0) -> None:
        """OCamCalib's parameters, 0-based, as ``calib_results.txt`` lists them.

        Args:
            width: image width in pixels.
            height: image height in pixels.
            xc: distortion centre row in pixels (OCamCalib's ``xc``, 0-based).
            yc: distortion centre column in pixels (OCamCalib's ``yc``, 0-based).
            ss: ``(S,)`` cam2world polynomial, lowest degree first, ``ss[0] < 0``; None if absent.
            invpol: ``(P,)`` world2cam polynomial, lowest degree first, at least 2 terms; None if absent.
            c: affine diagonal term (> 0).
            d: affine off-diagonal term.
            e: affine off-diagonal term (``c - d e > 0``).
            max_fov_deg: full field of view in degrees (360: no limit beyond the polynomial and the image).

        Raises:
            ValueError: neither polynomial given, too few or non-finite coefficients, ``ss[0] >= 0``, a singular
                or flipped affine, or a polynomial that does not map rays outward at the axis.
        """
        ss_t, invpol_t = _floats(ss, "ss", 1), _floats(invpol, "invpol", 2)
        defining = invpol_t if ss_t is None else ss_t
        if defining is None:
            raise ValueError("OCamFisheye: needs the ss (cam2world) or the invpol (world2cam) polynomial")
        if ss_t is not None and not ss_t[0] < 0:
            raise ValueError(f"OCamFisheye: ss[0] must be negative (cam2world's z points away from the scene), "
                             f"got {float(ss_t[0])}")
        if not all(math.isfinite(v) for v in (c, d, e)) or not c > 0 or not c - d * e > 0:
            raise ValueError(f"OCamFisheye: the affine [[c, d], [e, 1]] needs c > 0 and c - d e > 0, got {c}, {d}, {e}")
        self.by_ss = ss_t is not None
        self.d = torch.tensor(float(d), dtype=torch.float64)
        self.e = torch.tensor(float(e), dtype=torch.float64)
        # The polynomial that does not define the model: ss-defined models start Newton from invpol.
        self.other = invpol_t if self.by_ss else None
        self._shift = None if self.by_ss else _taylor_shift(len(defining), math.pi / 2)
        self._corner = self._corner_radius(int(width), int(height), float(xc), float(yc), float(c), float(d), float(e))
        self._rho_hi = 0.0   # ss models: the sensor radius of theta_max, Newton's bracket (set by _valid_theta_max)
        super().__init__(width, height, 1.0, c, yc, xc, defining, max_fov_deg)

    @staticmethod
    def _corner_radius(width: int, height: int, xc: float, yc: float, c: float, d: float, e: float) -> float:
        """Sensor radius (before the affine) of the image corner farthest from the centre."""
        det = c - d * e
        radius = 0.0
        for u in (-0.5, width - 0.5):
            for v in (-0.5, height - 0.5):
                du, dv = u - yc, v - xc
                radius = max(radius, math.hypot((c * du - e * dv) / det, (dv - d * du) / det))
        return radius

    # --- construction from files -------------------------------------------------------
    @classmethod
    def from_calib_results(cls, path: str | Path, one_based: bool = False,
                           max_fov_deg: float = 360.0) -> OCamFisheye:
        """From OCamCalib's ``calib_results.txt``; ``one_based`` for a centre written MATLAB-style (from 1).

        A polynomial written with 0 coefficients counts as absent.

        Args:
            path: the ``calib_results.txt`` file (5 data lines: ss, invpol, centre, affine, image size).
            one_based: subtract 1 from the centre (MATLAB's convention).
            max_fov_deg: full field of view in degrees (the file does not state it).

        Returns:
            The camera model.

        Raises:
            ValueError: the file is malformed or its parameters are refused; the message names the file.
        """
        path = Path(path)
        try:
            lines = path.read_text().splitlines()
            rows = [line.split() for line in lines if line.strip() and not line.lstrip().startswith("#")]
            values = [[float(v) for v in row] for row in rows[:5]]
        except ValueError as err:
            raise ValueError(f"{path}: {err}") from None
        if len(values) < 5:
            raise ValueError(f"{path}: expected 5 data lines (ss, invpol, centre, affine, size), found {len(values)}")
        polys = []
        for name, row in zip(("ss", "invpol"), values[:2]):
            if not row or not row[0].is_integer() or int(row[0]) != len(row) - 1:
                raise ValueError(f"{path}: the {name} line must be a count then that many coefficients, got {row}")
            polys.append(row[1:] or None)
        shapes = {"centre": (values[2], 2), "affine": (values[3], 3), "image size": (values[4], 2)}
        for name, (row, n) in shapes.items():
            if len(row) != n:
                raise ValueError(f"{path}: the {name} line needs {n} numbers, got {row}")
        (xc, yc), (c, d, e), (height, width) = values[2], values[3], values[4]
        if not (height.is_integer() and width.is_integer()):
            raise ValueError(f"{path}: image size must be integers, got {values[4]}")
        shift = 1.0 if one_based else 0.0
        try:
            return cls(int(width), int(height), xc - shift, yc - shift, polys[0], polys[1], c, d, e, max_fov_deg)
        except ValueError as err:
            raise ValueError(f"{path}: {err}") from None

    @classmethod
    def from_json(cls, path: str | Path, max_fov_deg: float = 360.0) -> OCamFisheye:
        """From a surround-view calibration JSON: ``img_dist_w/h``, ``cam_K`` and ``cam_dist`` under ``param``.

        The file is ``{name: {"param": {...}}}`` (one camera) or the ``param`` mapping itself.

        Args:
            path: the JSON file.
            max_fov_deg: full field of view in degrees (the file does not state it).

        Returns:
            The camera model, its parameters converted to OCamCalib's (see the module docstring).

        Raises:
            ValueError: the file does not hold surround-view OCam intrinsics or they are refused; the message
                names the file.
        """
        path = Path(path)
        try:
            doc = json.loads(path.read_text())
            param = doc if "cam_K" in doc else next(iter(doc.values()))["param"]
            K = torch.tensor(param["cam_K"]["data"], dtype=torch.float64)
            dist = torch.tensor(param["cam_dist"]["data"], dtype=torch.float64).reshape(-1)
            width, height = int(param["img_dist_w"]), int(param["img_dist_h"])
        except (KeyError, TypeError, ValueError, AttributeError, StopIteration, RuntimeError) as err:
            raise ValueError(f"{path}: not surround-view OCam intrinsics ({type(err).__name__}: {err})") from None
        if K.shape != (3, 3) or K[1, 1] != 1 or K[2].tolist() != [0.0, 0.0, 1.0]:
            raise ValueError(f"{path}: cam_K must be [[c, d, u0], [e, 1, v0], [0, 0, 1]], got {K.tolist()}")
        cp, dp, ep = float(K[0, 0]), float(K[0, 1]), float(K[1, 0])
        if not cp > 0:
            raise ValueError(f"{path}: cam_K[0][0] must be positive, got {cp}")
        try:
            return cls(width, height, float(K[1, 2]), float(K[0, 2]), None, dist * cp,
                       1.0 / cp, ep / cp, dp / cp, max_fov_deg)
        except ValueError as err:
            raise ValueError(f"{path}: {err}") from None

    # --- the radial map ------------------------------------------------------------------
    def _alpha(self, rho: Tensor, k: Tensor) -> Tensor:
        """cam2world's angle off the axis at sensor radius ``rho`` (ss models)."""
        return torch.atan2(rho, -_polyval(k, rho))

    def _valid_theta_max(self) -> float:
        """Half the field of view, cut where the defining polynomial folds back and at the farthest corner."""
        k = self.k.detach()
        limit = min(math.radians(self.max_fov_deg) / 2.0, math.pi - 1e-3)
        if self.by_ss:
            dk = _polyder(k)
            # d theta / d rho > 0 <=> rho ss'(rho) - ss(rho) > 0; theta stays within the field of view.
            self._rho_hi = _last_ok(lambda r: (r * _polyval(dk, r) - _polyval(k, r) > 0) & (self._alpha(r, k) <= limit),
                                    self._corner)
            theta = float(self._alpha(torch.tensor(self._rho_hi, dtype=torch.float64), k))
        else:
            theta = _last_ok(lambda t: (self.drho(t, k) > 0) & (self.rho(t, k) <= self._corner), limit)
        if not theta > 0:
            raise ValueError(f"OCamFisheye: the {'ss' if self.by_ss else 'invpol'} polynomial does not map "
                             f"rays outward at the optical axis (k={k.tolist()})")
        return theta

    def _intrinsics(self, like: Tensor) -> tuple[Tensor, Tensor, Tensor, Tensor, Tensor]:
        """As the base class, except that ``k`` stays float64: the radial map is always evaluated in float64."""
        fx, fy, cx, cy, _ = super()._intrinsics(like)
        return fx, fy, cx, cy, self.k.to(device=like.device)

    def _solve_rho(self, theta: Tensor, k: Tensor) -> Tensor:
        """Detached ``rho`` with cam2world angle ``theta``: ``rho cos(theta) + ss(rho) sin(theta) = 0`` on [0, rho_hi].

        That residual is ``|(rho, ss)| sin(theta(rho) - theta)``: its sign brackets the root, so Newton
        steps that leave the bracket are replaced by bisection. Starts from ``invpol`` when the file has it.

        Returns:
            ``theta``'s shape, float64 sensor radii in pixels, detached.
        """
        k, theta = k.detach(), theta.detach()
        dk = _polyder(k)
        cos, sin = torch.cos(theta), torch.sin(theta)
        lo, hi = torch.zeros_like(theta), torch.full_like(theta, self._rho_hi)
        if self.other is not None:
            rho = _polyval(self.other.to(theta), theta - math.pi / 2)
        else:
            rho = theta * (self._rho_hi / self.theta_max)
        rho = torch.minimum(torch.maximum(rho, lo), hi)
        tol = 8 * torch.finfo(torch.float64).eps * self._rho_hi
        for _ in range(40):
            f = rho * cos + _polyval(k, rho) * sin
            lo = torch.where(f <= 0, rho, lo)
            hi = torch.where(f >= 0, rho, hi)
            step = rho - f / (cos + _polyval(dk, rho) * sin)
            new = torch.where((step >= lo) & (step <= hi) & torch.isfinite(step), step, 0.5 * (lo + hi))
            done = bool(((new - rho).abs() <= tol).all())   # at rounding level (Newton can swap two neighbours)
            rho = new
            if done:
                break
        return rho

    def _about_axis(self, k: Tensor) -> Tensor | None:
        """Invpol models: ``s`` with ``invpol(theta - pi/2) = sum_j s_j theta^j`` (``s_0`` gets dropped); else None."""
        return None if self._shift is None else self._shift.to(k) @ k

    def _q64(self, theta: Tensor, k: Tensor) -> Tensor:
        """``q`` in float64."""
        s = self._about_axis(k)
        if s is not None:
            return _polyval(s[1:], theta)
        # q solves h(q) = q cos(theta) + ss(theta q) sinc(theta) = 0 (the residual above over theta), smooth
        # through the axis (q(0) = -ss[0]). One Newton step with autograd from the detached root gives the
        # implicit-function-theorem gradients in theta and k.
        t = theta.detach()
        rho = self._solve_rho(t, k)
        positive = t > 0
        q0 = torch.where(positive, rho / torch.where(positive, t, torch.ones_like(t)), -k.detach()[0])
        h = q0 * torch.cos(theta) + _polyval(k, theta * q0) * _sinc(theta)
        dh = torch.cos(t) + _polyval(_polyder(k.detach()), t * q0) * torch.sin(t)
        return q0 - h / dh

    def q(self, theta: Tensor, k: Tensor) -> Tensor:
        """``rho / theta``, computed in float64 and returned in ``theta``'s dtype.

        Expanding ``invpol`` about the axis cancels terms of ~1e5 px, and ``ss`` has powers of ``rho``
        near 1e10: in float32 either would move pixels by tenths.

        Args:
            theta: ``(...)`` angles off the optical axis in radians.
            k: ``(K,)`` the defining polynomial (``self.k``).

        Returns:
            ``(...)`` ``rho / theta`` in pixels per radian, ``theta``'s dtype.
        """
        return self._q64(theta.to(torch.float64), k.to(torch.float64)).to(theta.dtype)

    def drho(self, theta: Tensor, k: Tensor) -> Tensor:
        """``d rho / d theta`` in float64, returned in ``theta``'s dtype (``CameraModel.drho``)."""
        t, k = theta.to(torch.float64), k.to(torch.float64)
        s = self._about_axis(k)
        if s is not None:
            return _polyval(_polyder(s), t).to(theta.dtype)
        rho = t * self._q64(t, k)
        p, dp = _polyval(k, rho), _polyval(_polyder(k), rho)
        return ((rho * rho + p * p) / (rho * dp - p)).to(theta.dtype)   # 1 / (d theta / d rho)

    def radial_polynomials(self) -> tuple[Tensor | None, Tensor, float]:
        """The radial map as compiled kernels evaluate it (``parksim.render._project_kernels._ocam_rho``).

        Returns:
            ``(ss, series, rho_hi)``, float64, lowest degree first. invpol models: ``ss`` None and ``series``
            ``(P - 1,)`` with ``rho(theta) = sum_j series_j theta^(j + 1)`` (``invpol`` about the axis, constant
            dropped, as ``q``). ss models: ``ss`` ``(S,)``, ``series`` the ``invpol`` seeding the radius solve
            (``(0,)`` when the file has none) and ``rho_hi`` its bracket (0 for invpol models).
        """
        k = self.k.detach().to(torch.float64)
        s = self._about_axis(k)
        if s is not None:
            return None, s[1:], 0.0
        seed = torch.zeros(0, dtype=torch.float64) if self.other is None else self.other.detach().to(torch.float64)
        return k, seed, self._rho_hi

    def _solve_theta(self, rho: Tensor, k: Tensor) -> Tensor:
        if not self.by_ss:
            return super()._solve_theta(rho, k)
        r, k = rho.detach().to(torch.float64), k.detach().to(torch.float64)
        t_max = torch.full_like(r, self.theta_max)
        return torch.where(r < self._rho_hi, torch.minimum(self._alpha(r, k), t_max), t_max).to(rho.dtype)

    # --- the affine ----------------------------------------------------------------------
    def _normalised(self, uv: Tensor) -> tuple[Tensor, Tensor]:
        """Sensor offsets: the affine ``[[fx, e], [d, fy]]`` inverted."""
        fx, fy, cx, cy, _ = self._intrinsics(uv)
        d, e = self.d.to(uv), self.e.to(uv)
        du, dv = uv[..., 0] - cx, uv[..., 1] - cy
        det = fx * fy - d * e
        return (fy * du - e * dv) / det, (fx * dv - d * du) / det

    def project(self, points: Tensor) -> tuple[Tensor, Tensor]:
        """As ``CameraModel.project``, with OCamCalib's off-diagonal affine terms ``d, e`` added.

        The shared projection applies the diagonal (``fx, fy``); validity is then taken on the final
        pixel: not the camera centre, within ``theta_max`` and inside the image.

        Args:
            points: ``(..., 3)`` camera-frame points.

        Returns:
            ``(uv, valid)``: ``(..., 2)`` pixels as (column, row) and a ``(...)`` bool mask.
        """
        uv, _ = super().project(points)
        fx, fy, cx, cy, _ = self._intrinsics(points)
        d, e = self.d.to(points), self.e.to(points)
        du, dv = uv[..., 0] - cx, uv[..., 1] - cy      # fx mx and fy my
        uv = torch.stack([uv[..., 0] + e * dv / fy, uv[..., 1] + d * du / fx], dim=-1)
        tiny = torch.finfo(points.dtype).tiny
        lens = ((points.detach() ** 2).sum(-1) > tiny) & (self.theta_of(points) <= self.theta_max)
        return uv, lens & self.in_image(uv)

    # --- serialisation ---------------------------------------------------------------------
    def to_dict(self) -> dict[str, Any]:
        """OCamCalib's parameters: ``xc, yc``, ``ss``, ``invpol``, ``c, d, e`` (``CameraModel.to_dict``)."""
        k = [float(v) for v in self.k]
        other = None if self.other is None else [float(v) for v in self.other]
        return {"model": self.model, "width": self.width, "height": self.height,
                "xc": float(self.cy), "yc": float(self.cx),
                "ss": k if self.by_ss else None, "invpol": other if self.by_ss else k,
                "c": float(self.fy), "d": float(self.d), "e": float(self.e), "max_fov_deg": self.max_fov_deg}

    def scaled(self, s: float) -> OCamFisheye:
        """Sensor radii scale by ``s``: ``invpol`` times ``s``, ``ss[i]`` times ``s^(1 - i)``."""
        k = self.k.detach()
        powers = s ** (1 - torch.arange(len(k), dtype=torch.float64))
        centre = lambda p: (p + 0.5) * s - 0.5  # noqa: E731
        ss = k * powers if self.by_ss else None
        invpol = self.other if self.by_ss else k
        return OCamFisheye(round(self.width * s), round(self.height * s), centre(float(self.cy)),
                           centre(float(self.cx)), ss, None if invpol is None else invpol * s, float(self.fy),
                           float(self.d), float(self.e), self.max_fov_deg)
