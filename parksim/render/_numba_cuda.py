"""``numba.cuda`` (from numba-cuda), importable under numpy 2.5.

numba-cuda 0.30.4, the newest release, registers an overload for ``np.row_stack`` when it is imported; numpy 2.5
removed that alias of ``np.vstack``, so the import fails there (it does on the GPU machines we test on). The alias is
put back only when it is missing, before the import. Nothing else in ParkSim reads it.
"""

from __future__ import annotations

import numpy as np

if not hasattr(np, "row_stack"):
    np.row_stack = np.vstack

from numba import cuda  # noqa: E402

__all__ = ["cuda"]
