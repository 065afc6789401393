"""Numba kernels of the masked D-SSIM loss: its value and its gradient in the prediction, per image plane.

SSIM's five local moments (means of p, g, p^2, g^2, p g) are an 11-tap separable Gaussian blur with reflect
padding (``losses.ssim_map``, kornia's values). The gradient runs the blur's adjoint: the same taps, zero
padded, with the padded border folded back onto the pixels it mirrors. In torch the loss's grouped
convolutions and their backward took a quarter of a training step's CPU; here each pass is a loop over
rows that vectorises across columns.
"""

from __future__ import annotations

import numba
import numpy as np

__all__ = ["dssim_forward", "dssim_backward"]


@numba.njit(inline="always", cache=True)
def _tap(x: int, v: int, i: int, n: int, r: int, adjoint: bool) -> int:
    """Source index of tap i of output x on a line of n (-1: no such tap), in one of three passes v.

    Forward: out[x] = sum_i w[i] src[reflect(x + i - r)], reflected without repeating the end (torch's
    ``reflect`` pad), pass 0 only. Adjoint (w symmetric): Z(p) = sum_i w[i] src[p + i - r] zero padded, and
    out[x] = Z(x) + Z(-x) for 1 <= x <= r + Z(2 (n - 1) - x) for n - 1 - r <= x <= n - 2: the padded border
    folded back onto the pixels it mirrors (passes 1 and 2).
    """
    if not adjoint:
        if v > 0:
            return -1
        q = x + i - r
        return -q if q < 0 else (2 * (n - 1) - q if q >= n else q)
    if v == 1 and not 1 <= x <= r or v == 2 and not n - 1 - r <= x <= n - 2:
        return -1
    q = (x if v == 0 else (-x if v == 1 else 2 * (n - 1) - x)) + i - r
    return q if 0 <= q < n else -1


@numba.njit(cache=True, fastmath=True)
def _blur_cols(src: np.ndarray, dst: np.ndarray, w: np.ndarray, adjoint: bool) -> None:
    """Blur [K, H, W] maps along W (each row) by the taps of ``_tap``."""
    taps, n = w.shape[0], src.shape[2]
    r = taps // 2
    for k in range(src.shape[0]):
        for y in range(src.shape[1]):
            s, d = src[k, y], dst[k, y]
            d[:] = 0.0
            inner, out = n - 2 - 2 * r, d[r + 1:]
            for i in range(taps):   # interior x in [r + 1, n - 1 - r): no reflection, no fold
                wi, src_i = w[i], s[i + 1:]
                for x in range(inner):   # offset views, not x + i - r: indices provably >= 0, so it vectorises
                    out[x] += wi * src_i[x]
            for x in range(n):
                if r + 1 <= x < n - 1 - r:
                    continue
                acc = 0.0
                for v in range(3):
                    for i in range(taps):
                        q = _tap(x, v, i, n, r, adjoint)
                        if q >= 0:
                            acc += w[i] * s[q]
                d[x] = acc


@numba.njit(cache=True, fastmath=True)
def _blur_rows(src: np.ndarray, dst: np.ndarray, w: np.ndarray, adjoint: bool) -> None:
    """Blur [K, H, W] maps along H by the taps of ``_tap``, whole rows at a time (vectorises across W)."""
    taps, n = w.shape[0], src.shape[1]
    r = taps // 2
    for k in range(src.shape[0]):
        for y in range(n):
            d = dst[k, y]
            d[:] = 0.0
            for v in range(3):
                for i in range(taps):
                    q = _tap(y, v, i, n, r, adjoint)
                    if q < 0:
                        continue
                    s, wi = src[k, q], w[i]
                    for x in range(d.shape[0]):
                        d[x] += wi * s[x]


@numba.njit(inline="always", cache=True)
def _terms(mp, mg, pp, gg, pg, consts: np.ndarray) -> tuple:
    """SSIM = (a1 a2) / (b1 b2) at one pixel from its five blurred moments: (a1, a2, b1, b2)."""
    two, c1, c2 = consts[0], consts[1], consts[2]
    return two * mp * mg + c1, two * (pg - mp * mg) + c2, mp * mp + mg * mg + c1, (pp - mp * mp) + (gg - mg * mg) + c2


@numba.njit(parallel=True, cache=True)
def dssim_forward(pred: np.ndarray, gt: np.ndarray, w: np.ndarray, consts: np.ndarray, moments: np.ndarray,
                  ssim: np.ndarray) -> None:
    """Per plane j of ``pred, gt [P, H, W]``: ``moments[j]`` = blurred (p, g, p^2, g^2, p g), ``ssim[j]`` the map.

    ``w`` holds the blur taps and ``consts`` (2, C1, C2), both in the images' dtype so no pass widens to float64.
    """
    for j in numba.prange(pred.shape[0]):
        p, g, m = pred[j], gt[j], moments[j]
        raw = np.empty_like(m)
        for y in range(p.shape[0]):
            for x in range(p.shape[1]):
                pv, gv = p[y, x], g[y, x]
                raw[0, y, x], raw[1, y, x], raw[2, y, x], raw[3, y, x], raw[4, y, x] = pv, gv, pv * pv, gv * gv, pv * gv
        tmp = np.empty_like(m)
        _blur_cols(raw, tmp, w, False)
        _blur_rows(tmp, m, w, False)
        for y in range(p.shape[0]):
            for x in range(p.shape[1]):
                a1, a2, b1, b2 = _terms(m[0, y, x], m[1, y, x], m[2, y, x], m[3, y, x], m[4, y, x], consts)
                ssim[j, y, x] = (a1 * a2) / (b1 * b2)


@numba.njit(parallel=True, cache=True)
def dssim_backward(pred: np.ndarray, gt: np.ndarray, w: np.ndarray, consts: np.ndarray, moments: np.ndarray,
                   ssim: np.ndarray, grad_ssim: np.ndarray, grad_pred: np.ndarray) -> None:
    """``grad_pred[j]`` from ``grad_ssim[j]`` (dL/d ssim map per pixel), by the moments' adjoint blur."""
    two = consts[0]
    for j in numba.prange(pred.shape[0]):
        m, s, t = moments[j], ssim[j], grad_ssim[j]
        d = np.empty((3, s.shape[0], s.shape[1]), pred.dtype)   # dL/d blurred p, p^2, p g
        for y in range(s.shape[0]):
            for x in range(s.shape[1]):
                mp, mg = m[0, y, x], m[1, y, x]
                a1, a2, b1, b2 = _terms(mp, mg, m[2, y, x], m[3, y, x], m[4, y, x], consts)
                tv, sv = t[y, x], s[y, x]
                d_a1, d_a2 = tv * a2 / (b1 * b2), tv * a1 / (b1 * b2)
                d_b1, d_b2 = -tv * sv / b1, -tv * sv / b2
                d[0, y, x] = two * mg * (d_a1 - d_a2) + two * mp * (d_b1 - d_b2)
                d[1, y, x] = d_b2
                d[2, y, x] = two * d_a2
        tmp = np.empty_like(d)
        _blur_rows(d, tmp, w, True)
        _blur_cols(tmp, d, w, True)
        p, g = pred[j], gt[j]
        for y in range(s.shape[0]):
            for x in range(s.shape[1]):
                grad_pred[j, y, x] = d[0, y, x] + two * p[y, x] * d[1, y, x] + g[y, x] * d[2, y, x]
