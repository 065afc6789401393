"""float32 tolerances as counts of float32 spacings (ulps) at the magnitude compared.

A fixed constant such as 1e-4 is 3 ulps at 300 px but 1.6 at 800 px, and Intel and AMD CPUs round fused
kernels differently, so bounds are stated as "k roundings at this scale" instead.
"""

from __future__ import annotations

from typing import Any

import numpy as np
import torch


def f32_ulp(x: Any) -> Any:
    """np.spacing of float32 at |x|, elementwise: one ulp, twice the most one rounding to float32 moves a value.

    Returns a float64 tensor for a tensor, a float for a scalar, else a float64 array.
    """
    if isinstance(x, torch.Tensor):
        return torch.from_numpy(np.asarray(f32_ulp(x.detach().cpu().double().numpy()), dtype=np.float64))
    ulp = np.spacing(np.abs(np.asarray(x, dtype=np.float64)).astype(np.float32)).astype(np.float64)
    return float(ulp) if ulp.ndim == 0 else ulp


def f32_tol(reference: Any, ulps: float, dim: int | None = None) -> Any:
    """``ulps`` float32 spacings at the largest |reference|: over all of it, or along ``dim`` (kept, to broadcast).

    The largest magnitude sets the scale because rounding errors come from the largest intermediates:
    u = fx x / z + cx is rounded at the scale of cx and fx x / z even where u itself is near 0.
    """
    if isinstance(reference, torch.Tensor):
        t = reference.detach().abs().double()
        return ulps * f32_ulp(t.amax() if dim is None else t.amax(dim, keepdim=True))
    a = np.abs(np.asarray(reference, dtype=np.float64))
    return ulps * f32_ulp(a.max() if dim is None else a.max(axis=dim, keepdims=True))
