"""gsplat's 3DGUT on ParkSim's scene, rig and pose: the reference ``parksim bench gpu`` times ParkSim's CUDA render
against, in the same process and run.

3DGUT is ``gsplat.rasterization(camera_model="fisheye", with_ut=True, with_eval3d=True, radial_coeffs=...)``
(gsplat >= 1.5): an unscented-transform projection through the fisheye model and Gaussians evaluated in 3D along
each pixel's ray. The rig's OpenCV (Kannala-Brandt) fisheyes map one to one onto gsplat's fisheye model:
``k1..k4`` are its ``radial_coeffs``, ``fx, fy, cx, cy`` its ``Ks`` with the principal point moved by half a pixel
(gsplat puts pixel centres at ``j + 0.5``, ParkSim at ``j``), and ``T_camera_world`` its ``viewmats`` (OpenCV axes in
both). gsplat culls what lies behind a camera's image plane, so its images lack the outer ring of a 190-degree
lens: this is a speed reference, not an image one. It renders the camera views only (gsplat has no BEV).
"""

from __future__ import annotations

import inspect
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any

import torch
from torch import Tensor

from ..camera import OpenCVFisheye
from ..geometry import as_pose, invert_transform
from ..render.projection import FAR_M, NEAR_M
from ..rig import Rig

__all__ = ["GutCameras", "gut_cameras", "require_gut", "gut_closure", "gut_images", "LABEL"]

LABEL = "gsplat 3DGUT (fisheye, with_ut + with_eval3d), the same cameras without BEV, same run"
"""The reference label of the figures timed against 3DGUT."""


@dataclass(frozen=True)
class GutCameras:
    """A rig's cameras at one pose, as gsplat's ``rasterization`` takes them (float32, on one device).

    Attributes:
        names: the cameras, in the order of the tensors' first dimension.
        viewmats: ``(C, 4, 4)`` ``T_camera_world``.
        Ks: ``(C, 3, 3)`` camera matrices, principal point in gsplat's pixel convention (centres at ``j + 0.5``).
        radial: ``(C, 4)`` the fisheye coefficients ``k1..k4``.
        width: image width in pixels (every camera's).
        height: image height in pixels.
    """

    names: tuple[str, ...]
    viewmats: Tensor
    Ks: Tensor
    radial: Tensor
    width: int
    height: int


def gut_cameras(rig: Rig, names: Sequence[str], scale: float, pose: Tensor | Sequence[float],
                device: torch.device | str = "cpu") -> GutCameras:
    """The cameras ``names`` of ``rig`` at ``scale``, with the vehicle at ``pose``, for gsplat's fisheye model.

    Args:
        rig: the rig (its cameras' models and ``T_vehicle_camera``).
        names: cameras to render, all of one size.
        scale: image size relative to the rig's cameras (as ``render``'s ``scale``).
        pose: ``T_world_vehicle`` in any form ``render`` takes.
        device: where the tensors go.

    Returns:
        The cameras as gsplat takes them.

    Raises:
        ValueError: a lens other than OpenCV fisheye (gsplat's fisheye model is that one), or cameras of
            different sizes (one ``rasterization`` call renders one size).
    """
    cams = [rig.cameras[name] for name in names]
    models = [cam.model if scale == 1.0 else cam.model.scaled(scale) for cam in cams]
    others = sorted({type(m).__name__ for m in models if not isinstance(m, OpenCVFisheye)})
    if others:
        raise ValueError(f"gsplat 3DGUT reference: its fisheye model is OpenCV's (Kannala-Brandt), the rig has "
                         f"{', '.join(others)}; pass --no-gut")
    sizes = sorted({(m.width, m.height) for m in models})
    if len(sizes) != 1:
        raise ValueError(f"gsplat 3DGUT reference: one rasterization call renders one image size, the cameras have "
                         f"{sizes}; pass --no-gut")
    T_world_vehicle = as_pose(pose)
    viewmats = torch.stack([invert_transform(T_world_vehicle @ cam.T_vehicle_camera) for cam in cams])
    Ks = torch.stack([torch.tensor([[float(m.fx), 0.0, float(m.cx) + 0.5], [0.0, float(m.fy), float(m.cy) + 0.5],
                                    [0.0, 0.0, 1.0]], dtype=torch.float64) for m in models])
    radial = torch.stack([m.k.detach().to(torch.float64) for m in models])
    width, height = sizes[0]

    def on_device(t: Tensor) -> Tensor:
        return t.to(device=device, dtype=torch.float32).contiguous()

    return GutCameras(tuple(names), on_device(viewmats), on_device(Ks), on_device(radial), width, height)


def require_gut() -> None:
    """Check that gsplat is importable and has 3DGUT (``rasterization(with_ut=...)``, gsplat >= 1.5).

    Raises:
        ValueError: one line naming what is missing.
    """
    try:
        import gsplat
    except ImportError:
        raise ValueError("gsplat is not installed (pip install 'parksim[cuda]')") from None
    if "with_ut" not in inspect.signature(gsplat.rasterization).parameters:
        version = getattr(gsplat, "__version__", "?")
        raise ValueError(f"gsplat {version} has no 3DGUT (rasterization(with_ut=...), gsplat >= 1.5); "
                         "pass --no-gut")


def _rasterize(means: Tensor, quats: Tensor, log_scales: Tensor, opacity_logits: Tensor, sh: Tensor,
               sh_degree: int, cams: GutCameras) -> Tensor:
    """``(C, H, W, 3)`` 3DGUT images of the Gaussians (activations inside, as ParkSim's render does them)."""
    import gsplat

    colors, _, _ = gsplat.rasterization(
        means, quats, log_scales.exp(), torch.sigmoid(opacity_logits), sh, cams.viewmats, cams.Ks, cams.width,
        cams.height, near_plane=NEAR_M, far_plane=FAR_M, sh_degree=sh_degree, packed=False, camera_model="fisheye",
        with_ut=True, with_eval3d=True, radial_coeffs=cams.radial)
    return colors


def gut_closure(scene: Any, cams: GutCameras, backward: bool) -> Callable[[], None]:
    """One timed 3DGUT render of ``cams`` (and, with ``backward``, back-propagation of the fixed weighting
    ``parksim.bench.cases.render_case`` puts on ParkSim's images), ending with ``torch.cuda.synchronize()``.

    Args:
        scene: a CUDA ``GaussianScene`` (float32).
        cams: the cameras on the scene's device.
        backward: also back-propagate to the Gaussians' parameters.

    Returns:
        The closure.
    """
    tensors = [scene.means, scene.quats, scene.log_scales, scene.opacity_logits, scene.sh]
    means, quats, log_scales, logits, sh = ([t.detach().clone().requires_grad_(True) for t in tensors] if backward
                                            else tensors)
    weights = torch.rand((cams.height, cams.width, 3), generator=torch.Generator().manual_seed(1)).to(scene.means)

    def once() -> None:
        with torch.set_grad_enabled(backward):
            images = _rasterize(means, quats, log_scales, logits, sh, scene.sh_degree, cams)
        if backward:
            (images * weights).sum().backward()
        torch.cuda.synchronize()

    return once


def gut_images(scene: Any, cams: GutCameras) -> dict[str, Tensor]:
    """3DGUT's image of every camera, without gradients.

    Args:
        scene: a CUDA ``GaussianScene`` (float32).
        cams: the cameras on the scene's device.

    Returns:
        Camera name -> ``(H, W, 3)`` image.
    """
    with torch.no_grad():
        images = _rasterize(scene.means, scene.quats, scene.log_scales, scene.opacity_logits, scene.sh,
                            scene.sh_degree, cams)
    return dict(zip(cams.names, images))
