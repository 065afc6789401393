"""Differentiable surround-view inverse perspective mapping (fisheye images <-> BEV).

Each BEV pixel is a ground point (z = 0) in the vehicle frame; it is projected into every
camera through the exact lens model and sampled bilinearly, and the cameras are blended
with smooth weights that sum to one wherever any camera sees the point (ParkGaussian,
"Differentiable Surround-View IPM"). Grids and weights depend only on the rig and the BEV
spec, so they are built once and every call is one ``grid_sample`` per camera over only the
BEV pixels it contributes to (its weight > 0): cheap, and differentiable with respect to the images.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence

import numpy as np
import torch
import torch.nn.functional as F
from torch import Tensor

from ._ipm_kernels import blend_taps
from .camera import pixel_grid
from .geometry import invert_transform, transform_points
from .rig import BEVSpec, Rig

__all__ = ["IPM"]


def _smoothstep(x: Tensor) -> Tensor:
    """C1 ramp from 0 (x <= 0) to 1 (x >= 1)."""
    x = x.clamp(0.0, 1.0)
    return x * x * (3.0 - 2.0 * x)


def _to_grid(uv: Tensor, width: int, height: int) -> Tensor:
    """Pixel coordinates (centres at integers) -> ``grid_sample`` coordinates (align_corners=True)."""
    scale = torch.tensor([2.0 / max(width - 1, 1), 2.0 / max(height - 1, 1)], dtype=uv.dtype)
    return uv * scale - 1.0


def _as_nchw(image: Tensor) -> tuple[Tensor, bool, bool]:
    """HxW, HxWxC or BxHxWxC -> BxCxHxW, remembering what to undo."""
    squeeze_c = image.ndim == 2
    if squeeze_c:
        image = image.unsqueeze(-1)
    batched = image.ndim == 4
    if not batched:
        image = image.unsqueeze(0)
    return image.permute(0, 3, 1, 2), batched, squeeze_c


def _from_nchw(x: Tensor, batched: bool, squeeze_c: bool) -> Tensor:
    """BxCxHxW -> the layout ``_as_nchw`` was given."""
    x = x.permute(0, 2, 3, 1)
    if not batched:
        x = x.squeeze(0)
    return x.squeeze(-1) if squeeze_c else x


class IPM:
    """Fisheye images -> BEV (``__call__``) and BEV maps -> fisheye images (``to_cameras``).

    Each BEV pixel is a ground point (z = 0 in the vehicle frame) blended from the cameras that see
    it, weighted ``w ~ fade / d^falloff`` so the nearest, sharpest camera dominates away from seams.

    Attributes:
        mask: ``(spec.height, spec.width)`` bool, the BEV pixels some camera sees, outside the spec's ``ego_box``.
        weights: per camera name, its ``(spec.height, spec.width)`` blend weight; they sum to 1 where ``mask``.
        pixel_coords: per camera name, ``(spec.height, spec.width, 2)`` float64 pixel (u, v) of each BEV pixel.

    Example:
        >>> import torch
        >>> from parksim.camera import Pinhole
        >>> from parksim.rig import BEVSpec, Rig, RigCamera
        >>> T = torch.tensor([[0.0, -1, 0, 0], [-1, 0, 0, 0], [0, 0, -1, 1], [0, 0, 0, 1]])  # 1 m up, looking down
        >>> rig = Rig({"down": RigCamera("down", Pinhole(32, 32, 16.0, 16.0, 15.5, 15.5), T)}, BEVSpec(4, 4, 0.25))
        >>> bev = IPM(rig)({"down": torch.ones(32, 32, 3, dtype=torch.float64)})
        >>> bev.shape, bool(torch.allclose(bev, torch.ones(4, 4, 3, dtype=torch.float64)))
        (torch.Size([4, 4, 3]), True)
    """

    def __init__(self, rig: Rig, spec: BEVSpec | None = None, cameras: Sequence[str] | None = None,
                 edge_px: float = 24.0, falloff: float = 4.0, dtype: torch.dtype = torch.float32) -> None:
        """Project every BEV pixel into every camera once: the sampling grids and blend weights.

        Args:
            rig: the cameras (lens models and ``T_vehicle_camera``).
            spec: the BEV grid (default: the rig's).
            cameras: names of the cameras to blend (default: all of the rig's).
            edge_px: width in pixels of the smooth fade of each camera's weight at its image border and lens edge.
            falloff: power of the ground distance in the weight.
            dtype: float dtype of the precomputed sampling grids and weights.

        Raises:
            ValueError: a name in ``cameras`` that the rig does not have.
        """
        self.rig = rig
        self.spec = spec or rig.bev
        self.cameras = list(cameras) if cameras is not None else rig.names
        unknown = [c for c in self.cameras if c not in rig.cameras]
        if unknown:
            raise ValueError(f"IPM: unknown cameras {unknown}; the rig has {rig.names}")
        self.dtype = dtype
        s = self.spec
        xy = s.pixel_to_ground(pixel_grid(s.width, s.height))
        ground = torch.cat([xy, torch.zeros_like(xy[..., :1])], dim=-1)

        self.pixel_coords: dict[str, Tensor] = {}
        raw: dict[str, Tensor] = {}
        for name in self.cameras:
            cam = rig.cameras[name]
            p_cam = transform_points(invert_transform(cam.T_vehicle_camera), ground)
            uv, valid = cam.model.project(p_cam)
            raw[name] = self._weight(cam.model, p_cam, uv, valid, edge_px, falloff)
            self.pixel_coords[name] = uv
        total = torch.stack(list(raw.values())).sum(0)
        seen = total > 0
        if s.ego_box is not None:
            x0, x1, y0, y1 = s.ego_box
            seen &= ~((xy[..., 0] >= x0) & (xy[..., 0] <= x1) & (xy[..., 1] >= y0) & (xy[..., 1] <= y1))
        self.mask = seen
        safe_total = torch.where(seen, total, torch.ones_like(total))
        self.weights = {n: torch.where(seen, w / safe_total, torch.zeros_like(w)).to(dtype) for n, w in raw.items()}
        self._taps: dict[str, tuple[Tensor, Tensor, Tensor]] = {}
        for n in self.cameras:
            rows = self.weights[n].flatten().nonzero().squeeze(1)
            grid = _to_grid(self.pixel_coords[n], rig.cameras[n].model.width, rig.cameras[n].model.height)
            self._taps[n] = (rows, grid.reshape(1, 1, -1, 2)[:, :, rows].to(dtype), self.weights[n].flatten()[rows])
        self._back: dict[str, tuple[Tensor, Tensor]] = {}
        self._gather_taps: dict[str, tuple[np.ndarray, np.ndarray, np.ndarray]] = {}
        self._device_taps: dict[tuple[str, str, torch.dtype], tuple[Tensor, Tensor, Tensor]] = {}

    @staticmethod
    def _weight(model, p_cam: Tensor, uv: Tensor, valid: Tensor, edge_px: float, falloff: float) -> Tensor:
        """Smooth, non-negative weight: zero outside the view, fading over ``edge_px`` at every edge."""
        border = torch.stack([uv[..., 0] + 0.5, model.width - 0.5 - uv[..., 0],
                              uv[..., 1] + 0.5, model.height - 0.5 - uv[..., 1]], dim=-1).amin(-1)
        focal = float(torch.sqrt(model.fx * model.fy))
        theta = model.theta_of(p_cam).clamp(max=model.theta_max)
        lens = (model.rho_max - model.rho(theta, model.k.to(theta))) * focal  # pixels to the lens' valid edge
        fade = _smoothstep(border / edge_px) * _smoothstep(lens / edge_px)
        dist = p_cam.norm(dim=-1).clamp_min(1e-6)
        return torch.where(valid, fade / dist ** falloff, torch.zeros_like(dist))

    def _check(self, images: Mapping[str, Tensor]) -> None:
        missing = [c for c in self.cameras if c not in images]
        if missing:
            raise ValueError(f"IPM needs images for cameras {self.cameras}; missing {missing}")
        for name in self.cameras:
            img, model = images[name], self.rig.cameras[name].model
            hw = tuple(img.shape[-3:-1]) if img.ndim >= 3 else tuple(img.shape)
            if hw != (model.height, model.width):
                raise ValueError(f"image for camera {name!r} is {hw[1]}x{hw[0]} (WxH) but the rig says "
                                 f"{model.width}x{model.height}")

    def __call__(self, images: Mapping[str, Tensor]) -> Tensor:
        """Blend the cameras' images into the BEV.

        Differentiable; when no image needs a gradient, single float32 HxWxC images take a numba gather
        (``_ipm_kernels.blend_taps``) with the same taps and weights instead of one ``grid_sample`` per camera.

        Args:
            images: per camera name, its image ``(H, W, C)``, ``(H, W)`` or ``(B, H, W, C)`` at the rig's size;
                one layout for all.

        Returns:
            The BEV ``(spec.height, spec.width[, C])`` or ``(B, spec.height, spec.width, C)``, the images'
            layout and dtype; 0 where no camera sees the ground (``mask`` False).

        Raises:
            ValueError: an image is missing for one of the IPM's cameras, or is not at the rig's size.
        """
        self._check(images)
        if self._gather_applies(images):
            return self._gather(images)
        planes = {name: _as_nchw(images[name]) for name in self.cameras}
        first, batched, squeeze_c = planes[self.cameras[0]]   # the images share one layout
        out = first.new_zeros(first.shape[0], first.shape[1], self.spec.height * self.spec.width)
        for name, (x, _, _) in planes.items():
            rows, grid, weight = self._taps_like(name, x)
            grid = grid.expand(x.shape[0], -1, -1, -1)
            sampled = F.grid_sample(x, grid, mode="bilinear", padding_mode="zeros", align_corners=True)[:, :, 0]
            out = out.index_add(2, rows, sampled * weight)
        return _from_nchw(out.unflatten(2, (self.spec.height, self.spec.width)), batched, squeeze_c)

    def _taps_like(self, name: str, x: Tensor) -> tuple[Tensor, Tensor, Tensor]:
        """Camera ``name``'s taps on ``x``'s device and dtype, copied to a GPU once.

        The CPU ones are converted on each call as before; a GPU's are kept, so a render there copies nothing.

        Returns:
            ``(rows, grid, weights)`` as ``_taps`` holds them, on ``x``'s device and in its dtype.
        """
        rows, grid, weight = self._taps[name]
        if x.device.type == "cpu":
            return rows, grid.to(x), weight.to(x)
        key = (name, str(x.device), x.dtype)
        if key not in self._device_taps:
            self._device_taps[key] = (rows.to(x.device), grid.to(x), weight.to(x))
        return self._device_taps[key]

    def _gather_applies(self, images: Mapping[str, Tensor]) -> bool:
        """Whether ``_gather`` serves this call: no gradient needed, each image one float32 HxWxC CPU tensor."""
        chosen = [images[n] for n in self.cameras]
        needs_grad = torch.is_grad_enabled() and any(img.requires_grad for img in chosen)
        return not needs_grad and all(img.ndim == 3 and img.dtype == torch.float32 and img.device.type == "cpu"
                                      for img in chosen)

    def _gather(self, images: Mapping[str, Tensor]) -> Tensor:
        """``__call__`` without autograd: per camera, the precomputed bilinear taps gathered and summed."""
        channels = images[self.cameras[0]].shape[-1]
        out = np.zeros((self.spec.height * self.spec.width, channels), np.float32)
        for name in self.cameras:
            rows, idx, w = self._bilinear_taps(name)
            img = np.ascontiguousarray(images[name].detach().numpy()).reshape(-1, channels)
            blend_taps(img, rows, idx, w, out)
        return torch.from_numpy(out).unflatten(0, (self.spec.height, self.spec.width))

    def _bilinear_taps(self, name: str) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """The bilinear taps of camera ``name`` as ``grid_sample`` reads them (align_corners=True, zero padding).

        Returns:
            ``(rows [n], idx [n, 4], w [n, 4])``: the flat BEV pixel of each tap, the flat image index of its 4
            neighbours and their bilinear weights times the blend weight (0 for a neighbour outside the image).
        """
        if name not in self._gather_taps:
            rows, grid, weight = self._taps[name]
            model = self.rig.cameras[name].model
            g = grid.reshape(-1, 2).to(torch.float32)
            ix, iy = (g[:, 0] + 1) / 2 * (model.width - 1), (g[:, 1] + 1) / 2 * (model.height - 1)
            x0, y0 = ix.floor(), iy.floor()
            fx, fy = ix - x0, iy - y0
            idx, w = [], []
            corners = ((0, 0, (1 - fx) * (1 - fy)), (1, 0, fx * (1 - fy)), (0, 1, (1 - fx) * fy), (1, 1, fx * fy))
            for dx, dy, wt in corners:
                x, y = x0 + dx, y0 + dy
                inside = (x >= 0) & (x <= model.width - 1) & (y >= 0) & (y <= model.height - 1)
                idx.append(torch.where(inside, y * model.width + x, 0).to(torch.int64))
                w.append(torch.where(inside, wt * weight.to(torch.float32), 0.0))
            self._gather_taps[name] = (rows.numpy().astype(np.int64), torch.stack(idx, -1).numpy(),
                                       torch.stack(w, -1).numpy().astype(np.float32))
        return self._gather_taps[name]

    def _back_grid(self, name: str) -> tuple[Tensor, Tensor]:
        """Per fisheye pixel: where its ray meets the ground in the BEV (grid) and whether it does."""
        if name not in self._back:
            cam = self.rig.cameras[name]
            m = cam.model
            uv = pixel_grid(m.width, m.height)
            rays = cam.model.unproject(uv) @ cam.T_vehicle_camera[:3, :3].T
            origin = cam.T_vehicle_camera[:3, 3]
            down = rays[..., 2] < -1e-9
            s = torch.where(down, -origin[2] / torch.where(down, rays[..., 2], -torch.ones_like(rays[..., 2])),
                            torch.zeros_like(rays[..., 2]))
            hit = origin[:2] + s.unsqueeze(-1) * rays[..., :2]
            bev_uv = self.spec.ground_to_pixel(hit)
            inside = ((bev_uv[..., 0] >= -0.5) & (bev_uv[..., 0] <= self.spec.width - 0.5)
                      & (bev_uv[..., 1] >= -0.5) & (bev_uv[..., 1] <= self.spec.height - 0.5))
            valid = down & inside & m.pixel_valid(uv)
            grid = _to_grid(bev_uv, self.spec.width, self.spec.height).to(self.dtype).unsqueeze(0)
            self._back[name] = (grid, valid)
        return self._back[name]

    def to_cameras(self, bev_map: Tensor, cameras: Sequence[str] | None = None) -> dict[str, Tensor]:
        """Back-project a BEV map into each camera: each pixel's ray meets the ground and looks the map up there.

        Args:
            bev_map: ``(spec.height, spec.width)``, ``(spec.height, spec.width, C)`` or ``(B, ..., C)``.
            cameras: names of the cameras to fill (default: the IPM's).

        Returns:
            Per camera name, ``(H, W[, C])`` (or ``(B, H, W, C)``) at the camera's size, the map's layout and
            dtype; 0 where the pixel's ray misses the BEV or the lens.

        Raises:
            ValueError: ``bev_map`` is not at the BEV spec's size.
        """
        expected = (self.spec.height, self.spec.width)
        hw = tuple(bev_map.shape[-3:-1]) if bev_map.ndim >= 3 else tuple(bev_map.shape)
        if hw != expected:
            raise ValueError(f"BEV map is {hw[1]}x{hw[0]} (WxH) but the BEV spec is {expected[1]}x{expected[0]}")
        x, batched, squeeze_c = _as_nchw(bev_map)
        out = {}
        for name in cameras or self.cameras:
            grid, valid = self._back_grid(name)
            grid = grid.to(x).expand(x.shape[0], -1, -1, -1)
            sampled = F.grid_sample(x, grid, mode="bilinear", padding_mode="zeros", align_corners=True)
            out[name] = _from_nchw(sampled * valid.to(x), batched, squeeze_c)
        return out
