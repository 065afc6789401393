"""``render()``: a Gaussian scene seen by (some of) the rig's cameras at an ego pose, plus the BEV.

Per requested camera: world -> camera transform, cull + project (``projection``), SH colour for
the survivors only, rasterize. When nothing needs a gradient (serving, evaluation) one kernel pass
projects and colours the scene for all requested cameras (``project_fast.project_views_fused``), which
reads each Gaussian once instead of once per camera. The BEV is the IPM of the rendered views, built
only when asked.
"""

from __future__ import annotations

import threading
import weakref
from collections import OrderedDict
from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np
import torch
from torch import Tensor

from ..camera import pixel_grid
from ..gaussians import GaussianScene
from ..geometry import as_pose, invert_transform
from ..ipm import IPM
from ..rig import Rig, RigCamera
from .actors import Actor, joined
from .device_memory import check_device_memory, render_bytes
from .project_device import device_supported, project_views_device
from .project_fast import FusedUTConfig, fused_supported, project_views_fused
from .projection import FAR_M, NEAR_M, UTParams, fused_config, project_gaussians
from .rasterize import rasterize, resolve_backend
from .rasterize._kernels import finish_image
from .rasterize.cpu import Image, composite_many
from .rasterize.gsplat_backend import rasterize_gsplat_views
from .scratch import thread_scratch
from .view_colors import view_colors

__all__ = ["render", "render_batch", "RenderResult", "bev_ipm", "PROJECTORS"]

PROJECTORS = ("auto", "device")
"""``render``'s projection choices: "auto" (the device kernels for CUDA scenes; on the CPU the fused inference kernel,
or the autograd path when a gradient is needed) or "device" (the device kernels on any device: on the CPU their
CPU target, how the GPU path is tested without a GPU)."""

_VIEW_CACHE_SIZE = 8
_MIN_ALPHA_FOR_DEPTH = 1e-4


@dataclass
class RenderResult:
    """Per-camera ``images`` (HxWx3 in [0,1]), ``alpha`` (HxW), ``depth`` and optional ``bev`` (HxWx3).

    ``depth`` is the alpha-normalised expected distance from the camera centre (0 where nothing is hit).

    Attributes:
        images: per camera name, ``(H, W, 3)`` RGB in [0, 1]; ``bg`` outside the lens circle.
        alpha: per camera name, ``(H, W)`` coverage ``1 - final transmittance``; 0 outside the lens circle.
        depth: per camera name, ``(H, W)`` distance in metres from the camera centre.
        bev: ``(Hb, Wb, 3)`` IPM of the rendered views in the rig's BEV spec, or None when not asked for.
    """

    images: dict[str, Tensor]
    alpha: dict[str, Tensor]
    depth: dict[str, Tensor]
    bev: Tensor | None = None


@dataclass
class _RigView:
    """The requested cameras of a rig at one scale, and their IPM once a BEV has been asked for."""

    rig: Rig
    ipm: IPM | None = None
    lens: dict[tuple[str, torch.device], Tensor] = field(default_factory=dict)
    lock: threading.Lock = field(default_factory=threading.Lock)

    def lens_mask(self, name: str, device: torch.device = torch.device("cpu")) -> Tensor:
        """Pixels inside camera ``name``'s valid image circle (outside it a lens records nothing).

        Kept on ``device`` so that a GPU render does not copy it every call.

        Returns:
            ``(H, W)`` bool mask on ``device``.
        """
        key = (name, device)
        if key not in self.lens:
            m = self.rig.cameras[name].model
            self.lens[key] = m.pixel_valid(pixel_grid(m.width, m.height)).to(device)
        return self.lens[key]


_VIEWS: OrderedDict[tuple[int, float, tuple[str, ...]], tuple[weakref.ref, _RigView]] = OrderedDict()


_VIEWS_LOCK = threading.Lock()


def _rig_view(rig: Rig, scale: float, names: tuple[str, ...]) -> _RigView:
    """Cached scaled sub-rig (keyed by rig identity: rigs are treated as immutable once rendered)."""
    key = (id(rig), scale, names)
    with _VIEWS_LOCK:
        hit = _VIEWS.get(key)
        if hit is not None and hit[0]() is rig:
            _VIEWS.move_to_end(key)
            return hit[1]
        cams = {n: rig.cameras[n] if scale == 1.0 else
                RigCamera(n, rig.cameras[n].model.scaled(scale), rig.cameras[n].T_vehicle_camera) for n in names}
        view = _RigView(Rig(cams, rig.bev))
        _VIEWS[key] = (weakref.ref(rig), view)
        while len(_VIEWS) > _VIEW_CACHE_SIZE:
            _VIEWS.popitem(last=False)
        return view


def bev_ipm(rig: Rig, scale: float = 1.0, cameras: Sequence[str] | None = None) -> IPM:
    """The IPM that ``render(..., bev=True)`` uses for these cameras at ``scale``: built once, then shared.

    Args:
        rig: the rig (cached by identity: do not change a rig once rendered).
        scale: image size relative to the rig's cameras, as given to ``render``.
        cameras: the cameras the BEV blends (default: all of the rig's).

    Returns:
        The IPM from those cameras at that scale into ``rig.bev``; the same object on every call.

    Raises:
        KeyError: a camera name the rig does not have.
    """
    view = _rig_view(rig, float(scale), tuple(cameras) if cameras is not None else tuple(rig.names))
    with view.lock:
        if view.ipm is None:
            view.ipm = IPM(view.rig, rig.bev)
    return view.ipm


def _rows(t: Tensor, rows: Tensor | None) -> Tensor:
    """``t`` itself when every row is kept (``rows`` None), else the rows ``rows`` (gathered, differentiably)."""
    return t if rows is None else t.index_select(0, rows)


def _fast_path(scene: GaussianScene, pose: Tensor | Sequence[float], cameras: Sequence[RigCamera], method: str,
               backend: str) -> bool:
    """Whether the one-pass inference kernel applies: nothing needs a gradient, UT, CPU float, built-in lenses."""
    tensors = (scene.means, scene.quats, scene.log_scales, scene.opacity_logits, scene.sh)
    needs_grad = torch.is_grad_enabled() and (any(t.requires_grad for t in tensors)
                                              or (isinstance(pose, Tensor) and pose.requires_grad))
    return (not needs_grad and method == "ut" and resolve_backend(backend, scene.means.device) == "numba"
            and all(fused_supported(cam.model, scene.means, scene.quats, scene.log_scales, None) for cam in cameras)
            and scene.sh.dtype == scene.means.dtype)


def _device_path(scene: GaussianScene, cams: Sequence[RigCamera], method: str, projector: str) -> bool:
    """Whether the device kernels project this render: asked for, or "auto" on a CUDA scene (built-in lenses).

    Returns:
        True to take ``_device_views``.

    Raises:
        ValueError: "device" asked for with a lens the kernels do not serve.
    """
    if projector == "auto" and scene.means.device.type != "cuda":
        return False
    served = all(device_supported(cam.model) for cam in cams)
    if projector == "device" and not served:
        kinds = sorted({type(cam.model).__name__ for cam in cams if not device_supported(cam.model)})
        raise ValueError(f"render: projector='device' needs built-in lenses with constant intrinsics (not {kinds})")
    return served


def _device_views(scene: GaussianScene, cams: Sequence[RigCamera], T_world_cameras: Sequence[Tensor],
                  cfgs: Sequence[FusedUTConfig], lenses: Sequence[Tensor], background: Tensor, backend: str
                  ) -> list[tuple[Tensor, Tensor, Tensor]]:
    """Device path: every camera projected and coloured in one kernel launch, then composited (differentiable).

    On CUDA with gsplat and cameras of one size, all views go through one gsplat call on dense rows (no host
    synchronisation); otherwise each view's drawn rows go to ``rasterize`` with ``backend``.

    Returns:
        Per camera, in ``cams``' order, ``(image [H, W, 3], alpha [H, W], depth [H, W])`` in the scene's dtype.
    """
    proj = project_views_device(scene.means, scene.quats, scene.log_scales, scene.sh, scene.sh_degree,
                                torch.stack(list(T_world_cameras)), [cam.model for cam in cams], cfgs)
    opacities = torch.sigmoid(scene.opacity_logits)[None] * proj.drawn
    sizes = {(cam.model.width, cam.model.height) for cam in cams}
    if resolve_backend(backend, scene.means.device) == "gsplat" and len(sizes) == 1:
        width, height = sizes.pop()
        rgb, alpha, depth = rasterize_gsplat_views(proj.means2d, proj.conics, proj.colors, opacities, proj.depths,
                                                   width, height, bg=background)
        planes = [(rgb[v], alpha[v], depth[v]) for v in range(len(cams))]
    else:
        planes = []
        for v, cam in enumerate(cams):
            rows = proj.drawn[v].nonzero().squeeze(1)
            planes.append(rasterize(proj.means2d[v, rows], proj.conics[v, rows], proj.colors[v, rows],
                                    opacities[v, rows], proj.depths[v, rows], cam.model.width, cam.model.height,
                                    backend=backend, bg=background))
    return [_finish(*plane, lens, background) for plane, lens in zip(planes, lenses)]


def _finish(image: Tensor, alpha: Tensor, depth_sum: Tensor, lens: Tensor, background: Tensor
            ) -> tuple[Tensor, Tensor, Tensor]:
    """A camera's ``(image, alpha, depth)``: background outside its lens circle, depth normalised by alpha."""
    image = torch.where(lens.unsqueeze(-1), image, background)
    alpha, depth_sum = alpha * lens, depth_sum * lens
    covered = alpha > _MIN_ALPHA_FOR_DEPTH
    return image, alpha, torch.where(covered, depth_sum / torch.where(covered, alpha, 1.0), 0.0)


def _composite_views(scene: GaussianScene, cams: Sequence[RigCamera], T_world_cameras: Sequence[Tensor],
                     cfgs: Sequence[FusedUTConfig], lenses: Sequence[Tensor], background: Tensor
                     ) -> list[tuple[Tensor, Tensor, Tensor]]:
    """Inference path: each camera's ``(image, alpha, depth)`` from one projection pass and the CPU compositor.

    Projected rows and compositor planes are scratch memory reused by the next render; ``finish`` copies.

    Returns:
        Per camera, in ``cams``' order, ``(image [H, W, 3], alpha [H, W], depth [H, W])`` in the scene's dtype.
    """
    proj = project_views_fused(scene.means, scene.quats, scene.log_scales, torch.sigmoid(scene.opacity_logits),
                               scene.sh, scene.sh_degree, [invert_transform(T) for T in T_world_cameras],
                               [cam.model for cam in cams], cfgs, alloc=thread_scratch())
    images = [Image(proj.means2d[k], proj.conics[k], proj.colors[k], proj.opacities[k], proj.depths[k],
                    cam.model.width, cam.model.height) for k, cam in enumerate(cams)]
    bg = background.to(torch.float32).numpy()

    def finish(k: int, rgb: np.ndarray, depth_sum: np.ndarray, t_final: np.ndarray) -> tuple[Tensor, Tensor, Tensor]:
        image, alpha, depth = (torch.empty(shape, dtype=torch.float32)
                               for shape in (rgb.shape, t_final.shape, t_final.shape))
        finish_image(rgb, depth_sum, t_final, lenses[k].numpy(), bg, np.float32(_MIN_ALPHA_FOR_DEPTH),
                     image.numpy(), alpha.numpy(), depth.numpy())
        dtype = scene.means.dtype
        return image.to(dtype), alpha.to(dtype), depth.to(dtype)

    return composite_many(images, finish)


def _render_camera(scene: GaussianScene, cam: RigCamera, T_world_camera: Tensor, opacity: Tensor, background: Tensor,
                   backend: str, method: str, ut_params: UTParams | None, cull: bool) -> tuple[Tensor, Tensor, Tensor]:
    """Differentiable path, one camera: ``(image, alpha, depth sum)`` by projection, SH colour and rasterizer."""
    dtype = scene.means.dtype
    T_camera_world = invert_transform(T_world_camera).to(dtype)
    R, t = T_camera_world[:3, :3], T_camera_world[:3, 3]
    proj = project_gaussians(torch.addmm(t, scene.means, R.T), (scene.quats, scene.log_scales, R), cam.model,
                             method=method, ut_params=ut_params, cull=cull)
    rows = None if bool(proj.valid.all()) else proj.valid.nonzero().squeeze(1)
    keep = _rows(proj.index, rows)
    colors = view_colors(scene.sh, scene.means, keep, T_world_camera[:3, 3].to(scene.means), scene.sh_degree)
    return rasterize(_rows(proj.means2d, rows), _rows(proj.conics, rows), colors, opacity.index_select(0, keep),
                     _rows(proj.depths, rows), cam.model.width, cam.model.height, backend=backend, bg=background)


def render(scene: GaussianScene, rig: Rig, pose: Tensor | Sequence[float], cameras: Sequence[str] | None = None,
           bev: bool = False, scale: float = 1.0, backend: str = "auto", bg: Sequence[float] = (0.0, 0.0, 0.0),
           method: str = "ut", ut_params: UTParams | None = None, cull: bool = True, projector: str = "auto",
           actors: Sequence[Actor] | None = None) -> RenderResult:
    """Render ``cameras`` of the rig with the vehicle at ``pose``, and optionally the BEV.

    Differentiable in the scene's tensors (and in a tensor pose) with a differentiable backend. On a CUDA scene
    every camera is projected in one launch of the device kernels and composited by gsplat; on the CPU, when no
    gradient is needed (``torch.no_grad()`` or plain tensors), all cameras are projected in one fused kernel pass.

    Args:
        scene: N Gaussians in the world frame (means ``(N, 3)``, quats ``(N, 4)``, log-scales ``(N, 3)``,
            opacity logits ``(N,)``, SH ``(N, K, 3)``), one float dtype.
        rig: the cameras (lens models and ``T_vehicle_camera``) and the BEV spec.
        pose: ``T_world_vehicle`` ``(4, 4)``, ``(x, y, yaw)`` on the ground or ``(x, y, z, roll, pitch, yaw)``
            (metres, radians).
        cameras: names of the cameras to render (default: all of the rig's).
        bev: also blend the rendered views into the rig's BEV (IPM).
        scale: image size relative to the rig's cameras (0.5 halves width and height).
        backend: rasterizer, one of ``rasterize.BACKENDS`` ("auto": gsplat on CUDA if installed, else numba).
        bg: background colour ``(3,)`` behind the Gaussians.
        method: 2D footprints by the unscented transform ("ut") or first-order EWA ("ewa").
        ut_params: unscented-transform parameters (default ``UTParams()``).
        cull: False projects every Gaussian into every camera (only to measure what culling saves).
        projector: one of ``PROJECTORS``: "auto", or "device" to run the device kernels on any device.
        actors: Gaussian actors (``parksim.render.actors.Actor``: an asset at a pose) rendered with the scene in
            the same pass, so they hide and are hidden by it in every view, the BEV and depth; None or empty
            renders the scene alone, exactly as without the argument.

    Returns:
        ``RenderResult``: per camera name an image ``(H, W, 3)`` in [0, 1], alpha ``(H, W)`` and depth
        ``(H, W)`` (``H, W`` the camera's size times ``scale``), and the BEV ``(rig.bev.height, rig.bev.width,
        3)`` or None; the scene's dtype.

    Raises:
        KeyError: a camera name the rig does not have.
        ValueError: ``scale`` not positive, a bad ``backend`` / ``method`` / ``projector``, or "device" asked of
            a render it cannot serve (a lens model of one's own, intrinsics that need a gradient).
        DeviceMemoryError: on a GPU, the render would not fit its memory (``parksim.render.device_memory``).
    """
    return render_batch(scene, rig, [pose], cameras, bev, scale, backend, bg, method, ut_params, cull, projector,
                        actors)[0]


def render_batch(scene: GaussianScene, rig: Rig, poses: Sequence[Tensor | Sequence[float]],
                 cameras: Sequence[str] | None = None, bev: bool = False, scale: float = 1.0, backend: str = "auto",
                 bg: Sequence[float] = (0.0, 0.0, 0.0), method: str = "ut", ut_params: UTParams | None = None,
                 cull: bool = True, projector: str = "auto", actors: Sequence[Actor] | None = None
                 ) -> list[RenderResult]:
    """``render`` at B poses at once: B x C views projected in one pass and composited together.

    On a CUDA scene the B x C views take one launch of the device kernels and one gsplat call, and the B BEVs one
    batched IPM; on the CPU without gradients the fused kernel projects all views in one pass over the scene and
    the compositor shares its threads among them. Each result equals ``render`` at that pose.

    Args:
        scene: as ``render``.
        rig: as ``render``.
        poses: B poses, each in a form ``render`` takes.
        cameras: as ``render``.
        bev: as ``render``.
        scale: as ``render``.
        backend: as ``render``.
        bg: as ``render``.
        method: as ``render``.
        ut_params: as ``render``.
        cull: as ``render``.
        projector: as ``render``.
        actors: as ``render``, the same at every pose of the batch.

    Returns:
        B ``RenderResult``s, in ``poses``' order.

    Raises:
        KeyError: a camera name the rig does not have.
        ValueError: as ``render``, or no pose.
        DeviceMemoryError: on a GPU, the render would not fit its memory (``parksim.render.device_memory``).
    """
    if actors:   # the scene and the actors' Gaussians as one scene (the scene's rows staged, not copied per frame)
        with joined(scene, actors) as both:
            return render_batch(both, rig, poses, cameras, bev, scale, backend, bg, method, ut_params, cull, projector)
    names = tuple(cameras) if cameras is not None else tuple(rig.names)
    unknown = [n for n in names if n not in rig.cameras]
    if unknown:
        raise KeyError(f"render: unknown camera(s) {unknown}; the rig has {rig.names}")
    if not scale > 0:
        raise ValueError(f"render: scale must be positive, got {scale}")
    if projector not in PROJECTORS:
        raise ValueError(f"render: projector must be one of {PROJECTORS}, got {projector!r}")
    if method not in ("ut", "ewa"):
        raise ValueError(f"render: method must be 'ut' or 'ewa', got {method!r}")
    if not len(poses):
        raise ValueError("render_batch: no pose")
    view = _rig_view(rig, float(scale), names)
    dtype, device = scene.means.dtype, scene.means.device
    background = torch.as_tensor(bg, dtype=dtype, device=device)
    cams = [view.rig.cameras[name] for name in names] * len(poses)
    T_world_cameras = []   # on the pose's device (the CPU for plain poses): the device path moves them in one copy
    for pose in poses:
        T_world_vehicle = as_pose(pose)
        T_world_cameras += [T_world_vehicle @ cam.T_vehicle_camera.to(T_world_vehicle) for cam in cams[:len(names)]]
    lenses = [view.lens_mask(name, device) for name in names] * len(poses)   # cached on the scene's device
    on_device = _device_path(scene, cams, method, projector)
    if not on_device:
        T_world_cameras = [T.to(device) for T in T_world_cameras]
    if on_device:
        check_device_memory(device, render_bytes(len(scene), len(cams),
                                                 max(c.model.width * c.model.height for c in cams)))
        params = ut_params or UTParams()
        cfgs = [fused_config(params, NEAR_M, FAR_M, float(max(c.model.width, c.model.height)), cull, method == "ewa")
                for c in cams]
        views = _device_views(scene, cams, T_world_cameras, cfgs, lenses, background, backend)
    elif all(_fast_path(scene, pose, cams, method, backend) for pose in poses):
        params = ut_params or UTParams()
        cfgs = [fused_config(params, NEAR_M, FAR_M, float(max(c.model.width, c.model.height)), cull) for c in cams]
        views = _composite_views(scene, cams, T_world_cameras, cfgs, lenses, background)
    else:
        opacity = torch.sigmoid(scene.opacity_logits)
        views = [_finish(*_render_camera(scene, cam, T, opacity, background, backend, method, ut_params, cull),
                         lens, background) for cam, T, lens in zip(cams, T_world_cameras, lenses)]
    results = []
    for b in range(len(poses)):
        mine = views[b * len(names):(b + 1) * len(names)]
        images, alphas, depths = ({name: v[i] for name, v in zip(names, mine)} for i in range(3))
        results.append(RenderResult(images, alphas, depths))
    if bev:   # on the GPU one batched IPM; on the CPU each pose's own (the gather kernel takes single images)
        ipm = bev_ipm(rig, scale, names)
        if device.type == "cuda" and len(results) > 1:
            bevs = list(ipm({name: torch.stack([r.images[name] for r in results]) for name in names}))
        else:
            bevs = [ipm(r.images) for r in results]
        for r, image in zip(results, bevs):
            r.bev = image
    return results
