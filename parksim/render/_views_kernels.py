"""Numba kernel of the inference path: every camera of a rig projected and coloured in one pass over the scene.

Per Gaussian: its rotation and scales are read once, then for each camera the world -> camera transform,
the cull test, the UT footprint (the same inline steps as ``_project_kernels.forward``) and the SH colour
along the camera's view direction. Outputs are dense ``[cameras, N]`` rows; a Gaussian a camera does not
draw gets opacity 0, which the rasterizer's binning skips. No autograd: training uses ``project_fast``.
"""

from __future__ import annotations

import math

import numba
import numpy as np

from . import _project_kernels as pk
from ._sh_kernels import TINY_DISTANCE, sh_basis

__all__ = ["project_views"]


@numba.njit(cache=True, fastmath=pk.FASTMATH, error_model="numpy")
def _views_range(start: int, stop: int, means: np.ndarray, quats: np.ndarray, log_scales: np.ndarray,
                 opacities: np.ndarray, sh: np.ndarray, sh_degree: int, rots: np.ndarray, trans: np.ndarray,
                 centres: np.ndarray, models: np.ndarray, lenses: np.ndarray, opts: np.ndarray, z7: np.ndarray,
                 wm7: np.ndarray, wc7: np.ndarray, z19: np.ndarray, wm19: np.ndarray, wc19: np.ndarray,
                 out_means: np.ndarray, out_conics: np.ndarray, out_colors: np.ndarray, out_opacities: np.ndarray,
                 out_depths: np.ndarray) -> None:
    """``project_views`` for the Gaussians ``start:stop`` (one thread's chunk), all cameras.

    Per camera: cull and gather the visible Gaussians; their footprints (``_project_kernels.footprints``:
    the sigma points of all of them projected in one vectorised loop); the SH colour of the drawn ones.
    """
    m_max = stop - start
    uv19, basis = np.empty((z19.shape[0], 8)), np.empty(16)
    R, s = np.empty((m_max, 3, 3)), np.empty((m_max, 3))     # per Gaussian, shared by the cameras
    vis, xyz, L, sig = np.empty(m_max, np.int64), np.empty((m_max, 3)), np.empty((m_max, 3, 3)), np.empty(m_max)
    pts, uv = np.empty((3, pk.N_UT * m_max)), np.empty((2, pk.N_UT * m_max))
    mom, foot, valid = np.empty((3, 5)), np.empty((7, m_max)), np.empty(m_max, np.bool_)
    for k in range(m_max):
        qw, qx, qy, qz, _ = pk._unit_quaternion(quats[start + k])
        pk._rotation(qw, qx, qy, qz, R[k])
        for j in range(3):
            s[k, j] = math.exp(float(log_scales[start + k, j]))
    for cam in range(rots.shape[0]):
        rot, lens, opt = rots[cam], lenses[cam], opts[cam]
        m = 0
        for k in range(m_max):
            g = start + k
            out_opacities[cam, g] = 0.0
            mx, my, mz = float(means[g, 0]), float(means[g, 1]), float(means[g, 2])
            x = rot[0, 0] * mx + rot[0, 1] * my + rot[0, 2] * mz + trans[cam, 0]
            y = rot[1, 0] * mx + rot[1, 1] * my + rot[1, 2] * mz + trans[cam, 1]
            z = rot[2, 0] * mx + rot[2, 1] * my + rot[2, 2] * mz + trans[cam, 2]
            if not pk._visible(lens, opt, x, y, z, log_scales[g]):
                continue
            vis[m], sig[m] = k, max(s[k, 0], s[k, 1], s[k, 2])
            xyz[m, 0], xyz[m, 1], xyz[m, 2] = x, y, z
            pk._rotate_scaled(rot, R[k], s[k], L[m])
            m += 1
        pk.footprints(models[cam], lens, opt, m, xyz, L, sig, z7, wm7, wc7, z19, wm19, wc19, pts, uv, uv19, mom,
                      foot, valid)
        for i in range(m):
            if not valid[i]:
                continue
            g = start + vis[i]
            a, b, c = foot[2, i], foot[3, i], foot[4, i]
            det = a * c - b * b
            out_means[cam, g, 0], out_means[cam, g, 1] = foot[0, i], foot[1, i]
            out_conics[cam, g, 0], out_conics[cam, g, 1], out_conics[cam, g, 2] = c / det, -b / det, a / det
            out_depths[cam, g] = foot[5, i]
            dx, dy, dz = means[g, 0] - centres[cam, 0], means[g, 1] - centres[cam, 1], means[g, 2] - centres[cam, 2]
            inv = 1.0 / max(math.sqrt(dx * dx + dy * dy + dz * dz), TINY_DISTANCE)  # at the camera: any direction
            n_basis = sh_basis(sh_degree, dx * inv, dy * inv, dz * inv, basis)
            for ch in range(3):
                acc = 0.0
                for j in range(n_basis):
                    acc += basis[j] * sh[g, j, ch]
                out_colors[cam, g, ch] = max(acc + 0.5, 0.0)
            out_opacities[cam, g] = opacities[g]


@numba.njit(parallel=True, cache=True)
def project_views(means: np.ndarray, quats: np.ndarray, log_scales: np.ndarray, opacities: np.ndarray,
                  sh: np.ndarray, sh_degree: int, rots: np.ndarray, trans: np.ndarray, centres: np.ndarray,
                  models: np.ndarray, lenses: np.ndarray, opts: np.ndarray, z7: np.ndarray, wm7: np.ndarray,
                  wc7: np.ndarray, z19: np.ndarray, wm19: np.ndarray, wc19: np.ndarray, out_means: np.ndarray,
                  out_conics: np.ndarray, out_colors: np.ndarray, out_opacities: np.ndarray,
                  out_depths: np.ndarray) -> None:
    """World Gaussians -> per-camera 2D means, conics, colours, opacities (0: not drawn) and distances.

    Camera ``c`` has ``T_camera_world = [rots[c] | trans[c]]``, centre ``centres[c]`` in the world, lens model
    ``models[c]`` with ``lenses[c]`` and ``opts[c]`` as ``_project_kernels``; ``sh`` is ``[N, K, 3]``.
    """
    n = means.shape[0]
    for ch in numba.prange((n + pk.CHUNK - 1) // pk.CHUNK):
        _views_range(ch * pk.CHUNK, min(n, (ch + 1) * pk.CHUNK), means, quats, log_scales, opacities, sh,
                     sh_degree, rots, trans, centres, models, lenses, opts, z7, wm7, wc7, z19, wm19, wc19,
                     out_means, out_conics, out_colors, out_opacities, out_depths)
