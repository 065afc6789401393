"""Which torch device a command, the simulator or the trainer runs on: ``auto``, ``cpu`` or ``cuda[:N]``.

One rule for every entry point (``--device`` on the commands, ``device=`` on ``LocalSim``, the env and the trainer):
``auto`` picks the first CUDA device when torch sees one and the CUDA extra (gsplat and numba-cuda) is installed, else
the CPU; an explicit ``cuda`` that cannot run is a one-line ``DeviceError`` naming what is missing, never a fallback.
"""

from __future__ import annotations

import importlib.util
import re
from typing import TYPE_CHECKING

if TYPE_CHECKING:   # torch is imported where it is used, so the commands' parsers can take DEVICE_HELP cheaply
    import torch

__all__ = ["DeviceError", "DEVICE_HELP", "resolve_device", "describe_device", "cuda_extra_missing"]

DEVICE_HELP = ("where to run: auto (a CUDA GPU when there is one and the CUDA extra is installed, else the CPU), "
               "cpu, or cuda[:N]")
"""The ``--device`` help text every command shares."""

_SPEC = re.compile(r"^(auto|cpu|cuda(?::(\d+))?)$")
_CUDA_EXTRA = ("gsplat", "numba_cuda")
"""Modules the GPU path needs beyond torch: gsplat's rasterizer and numba-cuda for the projection kernels."""


class DeviceError(ValueError):
    """A device name that is malformed or names hardware or packages this machine does not have (one line)."""


def cuda_extra_missing() -> list[str]:
    """The modules of the CUDA extra that are not installed (empty when ``pip install 'parksim[cuda]'`` was run).

    Returns:
        Module names, in a fixed order.
    """
    return [name for name in _CUDA_EXTRA if importlib.util.find_spec(name) is None]


def resolve_device(spec: str | torch.device = "auto") -> torch.device:
    """The torch device that ``spec`` names, checked against this machine.

    Args:
        spec: ``"auto"``, ``"cpu"``, ``"cuda"`` or ``"cuda:N"`` (a ``torch.device`` is checked the same way).

    Returns:
        ``torch.device("cpu")`` or ``torch.device("cuda", N)``.

    Raises:
        DeviceError: a malformed name, ``cuda`` without a CUDA device or without the CUDA extra, or an index past
            the devices torch sees.
    """
    import torch

    text = str(spec).strip().lower()
    match = _SPEC.match(text)
    if match is None:
        raise DeviceError(f"device {str(spec)!r}: not one of auto, cpu, cuda, cuda:N")
    if text == "cpu":
        return torch.device("cpu")
    if text == "auto":
        usable = torch.cuda.is_available() and not cuda_extra_missing()
        return torch.device("cuda", 0) if usable else torch.device("cpu")
    if not torch.cuda.is_available():
        build = "a CPU-only torch build" if torch.version.cuda is None else f"torch built for CUDA {torch.version.cuda}"
        raise DeviceError(f"device {text!r}: no CUDA device here ({build}, torch.cuda.is_available() is False); "
                          "use --device cpu")
    missing = cuda_extra_missing()
    if missing:
        raise DeviceError(f"device {text!r}: the CUDA extra is not installed (missing {', '.join(missing)}); "
                          "pip install 'parksim[cuda]'")
    index = int(match.group(2) or 0)
    count = torch.cuda.device_count()
    if index >= count:
        raise DeviceError(f"device {text!r}: torch sees {count} CUDA device(s), cuda:0 to cuda:{count - 1}")
    return torch.device("cuda", index)


def describe_device(device: torch.device) -> str:
    """A one-line name for logs: ``"cpu"`` or ``"cuda:0 (NVIDIA H100 80GB HBM3)"``.

    Args:
        device: a device ``resolve_device`` returned.

    Returns:
        The device and, for CUDA, the card's name.
    """
    import torch

    if device.type != "cuda":
        return str(device)
    index = device.index if device.index is not None else torch.cuda.current_device()
    return f"cuda:{index} ({torch.cuda.get_device_name(index)})"
