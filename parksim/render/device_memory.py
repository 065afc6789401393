"""Refuse a GPU render that would not fit in the card's memory before it starts, instead of failing inside it.

A CUDA out-of-memory error in the middle of a render leaves the caching allocator fragmented and, in a server, takes
the request (and perhaps the process) down. ``render_batch`` on a CUDA scene first bounds what it will allocate
(``render_bytes``) and compares it with what the device has (``check_device_memory``): past the card's total memory
the render can never run (a server answers 413), past what is free now it may later (503 with Retry-After).
"""

from __future__ import annotations

import torch

__all__ = ["DeviceMemoryError", "render_bytes", "check_device_memory", "memory_verdict", "BYTES_PER_VIEW_GAUSSIAN",
           "BYTES_PER_VIEW_PIXEL"]

BYTES_PER_VIEW_GAUSSIAN = 256
"""Bound per (view, Gaussian): the projection's dense rows (means, conics, colours, depth, drawn: 37 B in float32),
the rasterizer's float32 copies, radii and opacities (about 40 B), and gsplat's tile intersections (an int64 key and an
int32 index per touched tile, twice for the sort: 24 B per tile; a drawn Gaussian touches a few tiles on average),
with room for the autograd state of a training step."""
BYTES_PER_VIEW_PIXEL = 96
"""Bound per (view, pixel): RGB + depth, alpha, final transmittance and last index, the lens mask, background and
finished image, depth normalisation (about 64 B in float32), and the BEV's share."""


class DeviceMemoryError(RuntimeError):
    """A render that does not fit the GPU: ``never`` when it exceeds the card's total memory, else not now."""

    def __init__(self, message: str, never: bool) -> None:
        super().__init__(message)
        self.never = never
        self.retry_after = 1


def render_bytes(gaussians: int, views: int, pixels_per_view: int) -> int:
    """Upper estimate of the device memory one render of ``views`` images allocates.

    Args:
        gaussians: Gaussians in the scene.
        views: images rendered together (poses x cameras).
        pixels_per_view: the largest image's pixel count.

    Returns:
        Bytes.
    """
    return views * (gaussians * BYTES_PER_VIEW_GAUSSIAN + pixels_per_view * BYTES_PER_VIEW_PIXEL)


def memory_verdict(needed: int, available: int, total: int, card: str) -> DeviceMemoryError | None:
    """The refusal for a render of ``needed`` bytes on a card with ``total`` bytes, ``available`` now; None if it fits.

    Args:
        needed: bytes, from ``render_bytes``.
        available: bytes free now (driver's free memory plus torch's unused cache).
        total: the card's memory in bytes.
        card: the card's name, for the message.

    Returns:
        The error to raise (``never`` past ``total``), or None.
    """
    if needed > total:
        return DeviceMemoryError(f"this render needs about {needed / 2**30:.1f} GiB of GPU memory; {card} has "
                                 f"{total / 2**30:.1f} GiB: fewer poses, cameras or Gaussians, or a smaller scale",
                                 never=True)
    if needed > available:
        return DeviceMemoryError(f"this render needs about {needed / 2**30:.1f} GiB of GPU memory; "
                                 f"{available / 2**30:.1f} GiB is free now", never=False)
    return None


def check_device_memory(device: torch.device, needed: int) -> None:
    """Raise unless ``needed`` bytes fit on ``device`` now (free memory plus what torch's cache holds unused).

    Asks the driver (no stream synchronisation); a CPU device always fits.

    Args:
        device: where the render runs.
        needed: bytes, from ``render_bytes``.

    Raises:
        DeviceMemoryError: ``never`` True past the card's total memory, False past what is available now.
    """
    if device.type != "cuda":
        return
    free, total = torch.cuda.mem_get_info(device)
    cached = torch.cuda.memory_reserved(device) - torch.cuda.memory_allocated(device)
    error = memory_verdict(needed, free + cached, total, torch.cuda.get_device_name(device))
    if error is not None:
        raise error
