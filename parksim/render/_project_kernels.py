"""Numba kernels of the fused UT projection: culling, forward, and the hand-written backward.

The same steps as the torch reference in ``projection.py``: quaternion -> ``L = R_cw R(q) S``, sigma
points ``mu + L z_p`` through the lens model (centre, axis and rim handled as ``CameraModel.project``),
weighted 2D moments, the adaptive fifth-degree blend, blur, eigenvalue clamp, conic. Gaussians are dealt
to threads in chunks, each chunk with its own scratch arrays; within a chunk the 7-point sigma points of
all its Gaussians go through the lens in one branch-free loop that vectorises (``footprints``), the rest
runs Gaussian by Gaussian. The backward recomputes its chunk's sigma points (with Jacobians, in the same
kind of loop) and applies the chain rule in reverse, so nothing per sigma point is kept between passes.

Arrays in and out keep the caller's dtype (float32 in the renderer); arithmetic inside is float64, which
keeps float32 outputs within rounding of exact.

The per-Gaussian helpers (``_project``, ``_sigma_points``, ``_moments``, ``_ut_blend``, ``_clamped``, the backward
steps) are also compiled for the GPU by numba-cuda (``_device_bodies``, ``_cuda_kernels``): they use only what that
target has (``math.isfinite``, not ``np.isfinite``; no allocation; scratch arrays passed in).
"""

from __future__ import annotations

import math

import numba
import numpy as np

OPENCV_FISHEYE, RADIAL_POLY, PINHOLE, OCAM = 0, 1, 2, 3
"""Lens model ids: rho = theta (1 + k1 t^2 + ...), rho = k1 t + k2 t^2 + ..., rho = tan(theta), and OCamCalib's
polynomial with its affine (``camera.ocam``; served by the device kernels only)."""

FX, FY, CX, CY, THETA_MAX, RHO_MAX, Q0, K1 = range(8)
COS_MAX, SIN_MAX = K1 + 4, K1 + 5
"""Slots of the float64 ``lens`` array; k1..k4 sit at ``K1 .. K1 + 3``, then cos and sin of ``theta_max``."""
AFF_D, AFF_E, RHO_HI, N_SS, N_SERIES, POLY = range(SIN_MAX + 1, SIN_MAX + 7)
"""OCam slots after those: the affine's off-diagonal ``d, e``, the sensor radius of ``theta_max`` (ss models), the
lengths of the two polynomials, then their coefficients from ``POLY`` on, lowest degree first: ``ss`` (``N_SS``
terms, 0 for invpol models), then the series (``N_SERIES`` terms): for an invpol model ``rho(theta) = sum_j
a_j theta^(j+1)`` (``invpol`` expanded about the axis, its constant dropped), for an ss model ``invpol``, Newton's
starting guess (0 terms: none)."""
NEWTON_STEPS = 40
"""Most Newton steps of the ss models' radius solve (it stops at rounding level, in a handful)."""
LensSlots = np.ndarray | tuple[float, ...]
"""The ``lens`` array, or a tuple of its leading slots (which ``_project_loop`` reads into registers)."""

(AXIS_EPS, TINY, ADAPTIVE, THETA_MIN, BLEND, REL_SIZE, BLUR, LO, HI, EXTENT, WIDTH, HEIGHT, NEAR, FAR, CULL,
 EWA) = range(16)
"""Slots of the float64 ``opts`` array: dtype limits, adaptive rule, 2D blur and clamps, image size, culling
(``CULL`` 0 keeps every Gaussian: only for measuring what culling saves), and ``EWA`` 1 for the first-order
footprint instead of the UT (read by the device kernels only)."""
N_OPTS = 16

N_ROT_GRAD = 9
"""Columns of the per-chunk partial gradient of ``R_cam_world`` (row major)."""

CHUNK = 256
"""Gaussians per parallel work item (one scratch allocation each)."""

N_UT = 7
"""Points of the 3D unscented transform's set (2n + 1); the inference kernel's loops are unrolled for it."""

FASTMATH = {"contract", "arcp", "nsz", "reassoc"}
"""LLVM fast-math flags of the per-chunk loops: FMA contraction, reciprocals and reassociation (~1.6x faster
here), but not ``nnan``/``ninf``, so the kernels' NaN guards and ``isfinite`` tests keep their meaning.
The loops also use numpy's error model: a division by zero gives inf/NaN (which the guards handle) instead of
a Python exception, so divisions carry no test-and-raise branch and loops over points can vectorise."""


_ATAN_P = (0.9999999999999895, -0.33333333331568515, 0.19999999682583666, -0.14285693667669663,
           0.11110453922288738, -0.090792021172482, 0.07569048052026542, -0.05893025346657178, 0.03092476390190522)
"""``atan(t) ~ t P(t^2)`` on ``[0, tan(pi/8)]`` (least squares on Chebyshev nodes; max error 1.2e-14 rad)."""
_TAN_PI_8 = 0.41421356237309503


@numba.njit(inline="always", cache=True)
def _atan2(r: float, z: float) -> float:
    """``atan2(r, z)`` for ``r >= 0`` within 2e-14 rad (0 at the origin): octant reduction and ``_ATAN_P``.

    About four times cheaper than libm's atan2 here, and every sigma point of every Gaussian calls it.
    Selects only, no branches, so a loop over many points vectorises.
    """
    az = abs(z)
    swap = r > az
    den = r if swap else az
    t = (az if swap else r) / (den if den > 0 else 1.0)
    big = t > _TAN_PI_8
    t = (t - 1.0) / (t + 1.0) if big else t
    t2 = t * t
    p = _ATAN_P[8]
    for k in range(7, -1, -1):
        p = p * t2 + _ATAN_P[k]
    a = t * p + (0.25 * math.pi if big else 0.0)
    a = 0.5 * math.pi - a if swap else a
    return math.pi - a if z < 0 else a


@numba.njit(inline="always", cache=True)
def _horner(lens: LensSlots, start: int, count: int, x: float) -> tuple[float, float]:
    """``sum_i c_i x^i`` and its derivative in ``x`` for the coefficients ``lens[start:start + count]``."""
    p = dp = 0.0
    for i in range(start + count - 1, start - 1, -1):
        dp = dp * x + p
        p = p * x + lens[i]
    return p, dp


@numba.njit(inline="always", cache=True)
def _ocam_rho(lens: LensSlots, t: float) -> tuple[float, float]:
    """``rho(theta)`` and ``d rho / d theta`` of an OCam lens, as ``OCamFisheye.q`` and ``.drho``.

    invpol models: the series ``sum_j a_j theta^(j+1)``. ss models: the root of ``rho cos(theta) + ss(rho)
    sin(theta)`` on ``[0, rho_hi]`` by Newton kept in the sign bracket (bisection where a step leaves it), from
    ``invpol`` when the file has it; then ``d rho / d theta = (rho^2 + ss^2) / (rho ss' - ss)``.
    """
    n_ss, n_series = int(lens[N_SS]), int(lens[N_SERIES])
    if n_ss == 0:
        a, da = _horner(lens, POLY, n_series, t)
        return t * a, a + t * da
    hi = lens[RHO_HI]
    lo = 0.0
    rho = _horner(lens, POLY + n_ss, n_series, t - 0.5 * math.pi)[0] if n_series > 0 else t * hi / lens[THETA_MAX]
    rho = min(max(rho, lo), hi)
    cos, sin = math.cos(t), math.sin(t)
    tol = 8 * 2.220446049250313e-16 * hi
    for _ in range(NEWTON_STEPS):
        p, dp = _horner(lens, POLY, n_ss, rho)
        f = rho * cos + p * sin
        lo = rho if f <= 0 else lo
        hi = rho if f >= 0 else hi
        step = rho - f / (cos + dp * sin)
        new = step if (lo <= step <= hi and math.isfinite(step)) else 0.5 * (lo + hi)
        done = abs(new - rho) <= tol
        rho = new
        if done:
            break
    p, dp = _horner(lens, POLY, n_ss, rho)
    return rho, (rho * rho + p * p) / (rho * dp - p)


@numba.njit(inline="always", cache=True)
def _rho(model: int, lens: LensSlots, t: float) -> tuple[float, float]:
    """``rho(theta)`` and ``d rho / d theta`` of the lens model ``model``."""
    if model == OCAM:
        return _ocam_rho(lens, t)
    k1, k2, k3, k4 = lens[K1], lens[K1 + 1], lens[K1 + 2], lens[K1 + 3]
    if model == OPENCV_FISHEYE:
        t2 = t * t
        return (t * (1.0 + t2 * (k1 + t2 * (k2 + t2 * (k3 + t2 * k4)))),
                1.0 + t2 * (3.0 * k1 + t2 * (5.0 * k2 + t2 * (7.0 * k3 + t2 * 9.0 * k4))))
    if model == RADIAL_POLY:
        return t * (k1 + t * (k2 + t * (k3 + t * k4))), k1 + t * (2.0 * k2 + t * (3.0 * k3 + t * 4.0 * k4))
    c = math.cos(t)
    return math.tan(t), 1.0 / (c * c)


@numba.njit(inline="always", cache=True)
def _direction(x: float, y: float, z: float, n2: float) -> tuple[float, float, float, float]:
    """``(c x, c y, c z, c)``: the point ``(x, y, z)`` with ``|p|^2 = n2`` (overflowed or not) scaled by a
    power of two ``c`` that brings ``|p|`` into ``[2^-300, 2^424]``, where ``|p|^3`` (the on-axis Jacobian's
    denominator) neither overflows nor underflows.

    ``c`` is 1 for any ordinary point (bit-identical results) and exact otherwise, as
    ``camera.base._pow2_normalised``; NaN for a point with an infinite or NaN coordinate (no direction to
    trust), which the footprint's NaN guard then drops. Selects only: it vectorises.
    """
    finite = math.isfinite(x) & math.isfinite(y) & math.isfinite(z)
    c = 2.0 ** -600 if n2 > 2.0 ** 600 else (2.0 ** 600 if n2 < 2.0 ** -600 else 1.0)
    c = c if finite else math.nan
    return x * c, y * c, z * c, c


@numba.njit(inline="always", cache=True)
def _project(model: int, lens: LensSlots, axis_eps: float, tiny: float, x: float, y: float, z: float
             ) -> tuple[float, float, float, float, float, float, float, float]:
    """``(u, v)`` of a camera-frame point and the Jacobian rows ``du/dp, dv/dp``, as ``CameraModel.project``.

    ``u = fx s x + cx`` with the radial scale ``s = rho(theta) / r``, computed on the point's
    ``_direction`` so that no magnitude overflows; the camera centre (``|p|^2 <= tiny``) maps to the
    principal point, points within ``axis_eps`` of the axis use ``s = q(0) / |p|`` (front) or the rim
    (back), points past ``theta_max`` land on the rim in their own direction. Every case is computed
    (with safe denominators) and picked by selects, so a loop of projections vectorises.
    """
    n2 = x * x + y * y + z * z        # inf past 1e154: read only by the centre test and _direction
    centre = n2 <= tiny
    x, y, z, c = _direction(x, y, z, n2)
    n2 = x * x + y * y + z * z
    r2 = x * x + y * y
    n2s = n2 if n2 > 0 else 1.0
    r = math.sqrt(r2)
    rs = r if r > 0 else 1.0
    theta = _atan2(r, z)
    rim = theta > lens[THETA_MAX]
    rho, drho = _rho(model, lens, theta)
    s_side = (lens[RHO_MAX] if rim else rho) / rs        # off the axis
    sr = (-s_side if rim else drho * z / n2s - s_side) / rs
    s_front = lens[Q0] / math.sqrt(n2s)                  # on the axis, in front
    k = -s_front / n2s
    axis, front = r2 <= (axis_eps * axis_eps) * n2, z > 0
    s = (s_front if front else lens[RHO_MAX]) if axis else s_side
    sx = (k * x if front else 0.0) if axis else sr * x / rs
    sy = (k * y if front else 0.0) if axis else sr * y / rs
    sz = (k * z if front else 0.0) if axis else (0.0 if rim else -drho / n2s)
    fx, fy = lens[FX], lens[FY]
    if centre:   # a select too once inlined into a loop
        return lens[CX], lens[CY], 0.0, 0.0, 0.0, 0.0, 0.0, 0.0
    if model == OCAM:   # the affine [[fx, e], [d, fy]] on (s x, s y)
        d, e = lens[AFF_D], lens[AFF_E]
        ax, ay, az = c * (s + x * sx), c * x * sy, c * x * sz     # d(s x)/dp
        bx, by, bz = c * y * sx, c * (s + y * sy), c * y * sz     # d(s y)/dp
        return (fx * s * x + e * s * y + lens[CX], d * s * x + fy * s * y + lens[CY],
                fx * ax + e * bx, fx * ay + e * by, fx * az + e * bz, d * ax + fy * bx, d * ay + fy * by,
                d * az + fy * bz)
    gx, gy = fx * c, fy * c     # d/dp of a function of c p
    return (fx * s * x + lens[CX], fy * s * y + lens[CY],
            gx * (s + x * sx), gx * x * sy, gx * x * sz, gy * y * sx, gy * (s + y * sy), gy * y * sz)


@numba.njit(inline="always", cache=True)
def _project_loop(model: int, lens: np.ndarray, axis_eps: float, tiny: float, pts: np.ndarray, uv: np.ndarray,
                  n: int, jac: bool) -> None:
    """``uv[:, :n]``: pixels of the camera-frame points ``pts[:, :n]`` (one branch-free loop: it vectorises),
    and with ``jac`` the Jacobian rows ``du/dp, dv/dp`` in ``uv[2:8]``.

    The lens slots are read into a tuple first: loads from the array could alias ``uv`` and would keep
    LLVM from vectorising. An OCam lens reads its polynomials from the array (its solve has a loop anyway).
    """
    values = (lens[FX], lens[FY], lens[CX], lens[CY], lens[THETA_MAX], lens[RHO_MAX], lens[Q0], lens[K1],
              lens[K1 + 1], lens[K1 + 2], lens[K1 + 3])
    for i in range(n):
        out = (_project(model, lens, axis_eps, tiny, pts[0, i], pts[1, i], pts[2, i]) if model == OCAM
               else _project(model, values, axis_eps, tiny, pts[0, i], pts[1, i], pts[2, i]))
        uv[0, i] = out[0]
        uv[1, i] = out[1]
        if jac:
            uv[2, i], uv[3, i], uv[4, i], uv[5, i], uv[6, i], uv[7, i] = out[2], out[3], out[4], out[5], out[6], out[7]


@numba.njit(inline="always", cache=True)
def project_batch(model: int, lens: np.ndarray, axis_eps: float, tiny: float, pts: np.ndarray, uv: np.ndarray,
                  n: int, jac: bool) -> None:
    """``_project_loop`` with the lens model a constant in each branch, so the model test leaves the loop."""
    if model == OPENCV_FISHEYE:
        _project_loop(OPENCV_FISHEYE, lens, axis_eps, tiny, pts, uv, n, jac)
    elif model == RADIAL_POLY:
        _project_loop(RADIAL_POLY, lens, axis_eps, tiny, pts, uv, n, jac)
    elif model == PINHOLE:
        _project_loop(PINHOLE, lens, axis_eps, tiny, pts, uv, n, jac)
    else:
        _project_loop(OCAM, lens, axis_eps, tiny, pts, uv, n, jac)


@numba.njit(cache=True, fastmath=FASTMATH, error_model="numpy")
def project_pixels(model: int, lens: np.ndarray, axis_eps: float, tiny: float, pts: np.ndarray, uv: np.ndarray,
                   n: int) -> None:
    """``project_batch`` without Jacobians, as a function of its own (not inlined into its callers).

    The four lens loops are what takes longest to compile; compiled once here, they serve the inference and
    the differentiable forward kernels alike (about a third of their first-use compile time), and calling them
    once per chunk costs nothing measurable. The same fast-math flags as the chunk loops: the same bits.
    """
    project_batch(model, lens, axis_eps, tiny, pts, uv, n, False)


@numba.njit(cache=True, fastmath=FASTMATH, error_model="numpy")
def project_pixels_jacobians(model: int, lens: np.ndarray, axis_eps: float, tiny: float, pts: np.ndarray,
                             uv: np.ndarray, n: int) -> None:
    """``project_batch`` with the Jacobian rows, on its own for the backward kernel (see ``project_pixels``)."""
    project_batch(model, lens, axis_eps, tiny, pts, uv, n, True)


@numba.njit(inline="always", cache=True)
def _unit_quaternion(q: np.ndarray) -> tuple[float, float, float, float, float]:
    """``(w, x, y, z)`` normalised and the input norm; a zero quaternion acts as the identity (norm 0)."""
    w, x, y, z = float(q[0]), float(q[1]), float(q[2]), float(q[3])
    norm = math.sqrt(w * w + x * x + y * y + z * z)
    if not norm > 0:
        return 1.0, 0.0, 0.0, 0.0, 0.0
    return w / norm, x / norm, y / norm, z / norm, norm


@numba.njit(inline="always", cache=True)
def _rotation(qw: float, qx: float, qy: float, qz: float, R: np.ndarray) -> None:
    """``R = R(q)`` of a unit quaternion into the 3x3 scratch array."""
    R[0, 0] = 1 - 2 * (qy * qy + qz * qz)
    R[0, 1] = 2 * (qx * qy - qw * qz)
    R[0, 2] = 2 * (qx * qz + qw * qy)
    R[1, 0] = 2 * (qx * qy + qw * qz)
    R[1, 1] = 1 - 2 * (qx * qx + qz * qz)
    R[1, 2] = 2 * (qy * qz - qw * qx)
    R[2, 0] = 2 * (qx * qz - qw * qy)
    R[2, 1] = 2 * (qy * qz + qw * qx)
    R[2, 2] = 1 - 2 * (qx * qx + qy * qy)


@numba.njit(inline="always", cache=True)
def _rotate_scaled(rot: np.ndarray, R: np.ndarray, s: np.ndarray, L: np.ndarray) -> None:
    """``L = rot R diag(s)``: a world-frame covariance factor seen from a camera with rotation ``rot``."""
    for i in range(3):
        for j in range(3):
            L[i, j] = (rot[i, 0] * R[0, j] + rot[i, 1] * R[1, j] + rot[i, 2] * R[2, j]) * s[j]


@numba.njit(inline="always", cache=True)
def _covariance_sqrt(qw: float, qx: float, qy: float, qz: float, s: np.ndarray, rot: np.ndarray,
                     R: np.ndarray, L: np.ndarray) -> None:
    """``R = R(q)`` and ``L = rot R(q) diag(s)`` into the 3x3 scratch arrays."""
    _rotation(qw, qx, qy, qz, R)
    _rotate_scaled(rot, R, s, L)


@numba.njit(inline="always", cache=True)
def _load_row(g: int, means: np.ndarray, quats: np.ndarray, log_scales: np.ndarray, rot: np.ndarray, k: int,
              xyz: np.ndarray, q: np.ndarray, s: np.ndarray, R: np.ndarray, L: np.ndarray, sig: np.ndarray) -> None:
    """Row ``k`` of a chunk's per-Gaussian state from Gaussian ``g``: centre ``xyz``, unit quaternion and its input
    norm ``q``, scales ``s``, ``R(q)``, ``L = rot R(q) diag(s)`` and the largest scale ``sig``."""
    xyz[k, 0], xyz[k, 1], xyz[k, 2] = float(means[g, 0]), float(means[g, 1]), float(means[g, 2])
    q[k, 0], q[k, 1], q[k, 2], q[k, 3], q[k, 4] = _unit_quaternion(quats[g])
    for j in range(3):
        s[k, j] = math.exp(float(log_scales[g, j]))
    sig[k] = max(s[k, 0], s[k, 1], s[k, 2])
    _covariance_sqrt(q[k, 0], q[k, 1], q[k, 2], q[k, 3], s[k], rot, R[k], L[k])


@numba.njit(inline="always", cache=True)
def _sigma_points(model: int, lens: np.ndarray, opts: np.ndarray, x: float, y: float, z: float,
                  L: np.ndarray, zs: np.ndarray, uvj: np.ndarray, jac: bool) -> None:
    """Project ``mu + L z_p`` for every row of ``zs``: ``uvj[p] = (u, v[, du/dp, dv/dp])``."""
    for p in range(zs.shape[0]):
        z0, z1, z2 = zs[p, 0], zs[p, 1], zs[p, 2]
        out = _project(model, lens, opts[AXIS_EPS], opts[TINY],
                       x + (L[0, 0] * z0 + L[0, 1] * z1 + L[0, 2] * z2),
                       y + (L[1, 0] * z0 + L[1, 1] * z1 + L[1, 2] * z2),
                       z + (L[2, 0] * z0 + L[2, 1] * z1 + L[2, 2] * z2))
        uvj[p, 0], uvj[p, 1] = out[0], out[1]
        if jac:
            for k in range(6):
                uvj[p, 2 + k] = out[2 + k]


@numba.njit(inline="always", cache=True)
def _moments(us: np.ndarray, vs: np.ndarray, base: int, stride: int, wm, wc
             ) -> tuple[float, float, float, float, float]:
    """``(mean u, mean v, cov a, b, c)`` of projected points, relative to the centre point.

    Point ``p`` is at ``(us, vs)[base + p * stride]``: rows of one Gaussian, or one Gaussian of a point-major
    batch. With weight tuples (a constant count) the point loops unroll and a loop over Gaussians vectorises.
    """
    u0, v0 = us[base], vs[base]
    mu = mv = 0.0
    for p in range(len(wm)):
        mu += wm[p] * (us[base + p * stride] - u0)
        mv += wm[p] * (vs[base + p * stride] - v0)
    a = b = c = 0.0
    for p in range(len(wm)):
        du, dv = us[base + p * stride] - u0 - mu, vs[base + p * stride] - v0 - mv
        a += wc[p] * du * du
        b += wc[p] * du * dv
        c += wc[p] * dv * dv
    return u0 + mu, v0 + mv, a, b, c


@numba.njit(inline="always", cache=True)
def _adaptive_weight(opts: np.ndarray, x: float, y: float, z: float, sigma: float
                     ) -> tuple[bool, float, float, float, float, float]:
    """``(rich, w, dw/dx, dw/dy, dw/dz, dw/dsigma)`` of the blend into the fifth-degree set."""
    rc2 = x * x + y * y
    n = math.sqrt(rc2 + z * z)
    rel = opts[REL_SIZE]
    if not (opts[ADAPTIVE] > 0 and sigma > rel * n):
        return False, 0.0, 0.0, 0.0, 0.0, 0.0
    rc = math.sqrt(rc2)
    theta = _atan2(rc, z)
    if not theta > opts[THETA_MIN]:
        return False, 0.0, 0.0, 0.0, 0.0, 0.0
    a_raw = (theta - opts[THETA_MIN]) / opts[BLEND]
    b_raw = sigma / (rel * n) - 1.0
    a, b = min(a_raw, 1.0), min(b_raw, 1.0)
    da = 1.0 / opts[BLEND] if a_raw <= 1.0 else 0.0
    db = 1.0 / (rel * n) if b_raw <= 1.0 else 0.0
    gt = b * da                    # dw/dtheta
    gn = -a * db * sigma / n       # dw/d|mu|
    den = rc2 + z * z
    gr = gt * z / den              # dw/drc through theta
    return (True, a * b, gr * x / rc + gn * x / n, gr * y / rc + gn * y / n,
            -gt * rc / den + gn * z / n, a * db)


@numba.njit(inline="always", cache=True)
def _ut_blend(model: int, lens: np.ndarray, opts: np.ndarray, x: float, y: float, z: float, sigma: float,
              L: np.ndarray, m7: tuple[float, float, float, float, float], z19: np.ndarray, wm19: np.ndarray,
              wc19: np.ndarray, uv19: np.ndarray, mom: np.ndarray, jac: bool
              ) -> tuple[bool, float, float, float, float, float]:
    """The UT moments from the 7-point ones ``m7`` into ``mom`` (rows: 7-point, fifth-degree, blended), projecting
    the fifth-degree set into ``uv19`` where ``_adaptive_weight`` asks for it; returns that weight."""
    aw = _adaptive_weight(opts, x, y, z, sigma)
    m19 = m7
    if aw[0]:
        _sigma_points(model, lens, opts, x, y, z, L, z19, uv19, jac)
        m19 = _moments(uv19[:, 0], uv19[:, 1], 0, 1, wm19, wc19)
    for k in range(5):
        mom[0, k], mom[1, k] = m7[k], m19[k]
        mom[2, k] = m7[k] + aw[1] * (m19[k] - m7[k]) if aw[0] else m7[k]
    return aw


@numba.njit(inline="always", cache=True)
def _sigma_batch(xyz: np.ndarray, L: np.ndarray, zs: np.ndarray, m: int, pts: np.ndarray) -> None:
    """``pts[:, p * m + i] = xyz[i] + L[i] z_p`` for the first ``m`` Gaussians: point-major, so that one
    ``project_batch`` loop over every sigma point of a chunk vectorises."""
    for p in range(zs.shape[0]):
        z0, z1, z2 = zs[p, 0], zs[p, 1], zs[p, 2]
        for i in range(m):
            for d in range(3):
                pts[d, p * m + i] = xyz[i, d] + (L[i, d, 0] * z0 + L[i, d, 1] * z1 + L[i, d, 2] * z2)


@numba.njit(cache=True, fastmath=FASTMATH, error_model="numpy")
def footprints(model: int, lens: np.ndarray, opts: np.ndarray, m: int, xyz: np.ndarray, L: np.ndarray,
               sig: np.ndarray, z7: np.ndarray, wm7: np.ndarray, wc7: np.ndarray, z19: np.ndarray,
               wm19: np.ndarray, wc19: np.ndarray, pts: np.ndarray, uv: np.ndarray, uv19: np.ndarray,
               mom: np.ndarray, foot: np.ndarray, valid: np.ndarray) -> None:
    """Image footprints of the first ``m`` camera-frame Gaussians (centres ``xyz``, covariance factors ``L``,
    largest scales ``sig``): ``foot[:, i] = (u, v, a, b, c, depth, radius)`` and ``valid[i]`` as ``_clamped``.

    Their 7-point sigma points go through the lens in one vectorised loop (``pts``, ``uv``: 7 m columns), the
    moments in another; the fifth-degree blend runs Gaussian by Gaussian (``_ut_blend``, ``uv19``, ``mom``).
    A function of its own, called once per chunk: the inference and the differentiable forward kernels share one
    compile of it, with their fast-math flags (the same bits as inlined).
    """
    wm = (wm7[0], wm7[1], wm7[2], wm7[3], wm7[4], wm7[5], wm7[6])   # tuples: constant point count, no aliasing
    wc = (wc7[0], wc7[1], wc7[2], wc7[3], wc7[4], wc7[5], wc7[6])
    _sigma_batch(xyz, L, z7, m, pts)
    project_pixels(model, lens, opts[AXIS_EPS], opts[TINY], pts, uv, N_UT * m)
    for i in range(m):
        foot[0, i], foot[1, i], foot[2, i], foot[3, i], foot[4, i] = _moments(uv[0], uv[1], i, m, wm, wc)
    for i in range(m):   # the fifth-degree blend, for the few Gaussians that need it
        x, y, z = xyz[i, 0], xyz[i, 1], xyz[i, 2]
        if _adaptive_weight(opts, x, y, z, sig[i])[0]:
            m7 = (foot[0, i], foot[1, i], foot[2, i], foot[3, i], foot[4, i])
            _ut_blend(model, lens, opts, x, y, z, sig[i], L[i], m7, z19, wm19, wc19, uv19, mom, False)
            for j in range(5):
                foot[j, i] = mom[2, j]
    for i in range(m):
        u, v, a, b, c, depth, radius, ok = _clamped(foot[0, i], foot[1, i], foot[2, i], foot[3, i], foot[4, i],
                                                    xyz[i, 0], xyz[i, 1], xyz[i, 2], opts)
        foot[0, i], foot[1, i], foot[2, i], foot[3, i], foot[4, i], foot[5, i], foot[6, i] = (
            u, v, a, b, c, depth, radius)
        valid[i] = ok


@numba.njit(inline="always", cache=True)
def _eig_clamp(a: float, b: float, c: float, lo: float, hi: float, tiny: float
               ) -> tuple[bool, bool, float, float, float, float, float, float, float]:
    """Eigenvalues of ``[[a, b], [b, c]]`` clamped to ``[lo, hi]`` via ``f(A) = f2 I + s (A - l2 I)``.

    Returns ``(need, pos, r, l1, l2, s, a', b', c')``; ``need`` False leaves the matrix untouched.
    Selects only, so a loop of clamps vectorises.
    """
    mid, half = 0.5 * (a + c), 0.5 * (a - c)
    disc = half * half + b * b
    r0 = math.sqrt(disc)
    need = (mid - r0 < lo) | (mid + r0 > hi)
    pos = (disc > tiny) & need
    r = r0 if pos else 0.0
    l1, l2 = mid + r, mid - r
    f1, f2 = min(max(l1, lo), hi), min(max(l2, lo), hi)
    s = (f1 - f2) / (2 * r if pos else 1.0) if pos else 0.0
    if not need:
        return False, False, 0.0, mid, mid, 0.0, a, b, c
    return True, pos, r, l1, l2, s, f2 + s * (a - l2), s * b, f2 + s * (c - l2)


@numba.njit(inline="always", cache=True)
def _eig_clamp_backward(a: float, b: float, c: float, lo: float, hi: float, tiny: float,
                        ga: float, gb: float, gc: float) -> tuple[float, float, float]:
    """Gradient of ``_eig_clamp``'s output w.r.t. ``(a, b, c)``."""
    need, pos, r, l1, l2, s, _, _, _ = _eig_clamp(a, b, c, lo, hi, tiny)
    if not need:
        return ga, gb, gc
    gs = ga * (a - l2) + gb * b + gc * (c - l2)
    gf2 = ga + gc
    gl2 = -s * (ga + gc)
    gr = gl1 = 0.0
    if pos:
        gf1 = gs / (2 * r)
        gf2 -= gf1
        gr = -gs * s / r
        gl1 = gf1 if lo <= l1 <= hi else 0.0
    gl2 += gf2 if lo <= l2 <= hi else 0.0
    gmid = gl1 + gl2
    gr += gl1 - gl2
    ghalf = gdisc_b = 0.0
    if pos:
        gdisc = gr / (2 * r)
        ghalf = 2 * 0.5 * (a - c) * gdisc
        gdisc_b = 2 * b * gdisc
    return s * ga + 0.5 * (gmid + ghalf), s * gb + gdisc_b, s * gc + 0.5 * (gmid - ghalf)


@numba.njit(inline="always", cache=True)
def _point_backward(uvj: np.ndarray, p: int, gu: float, gv: float, z_set: np.ndarray,
                    g_mu: np.ndarray, g_L: np.ndarray) -> None:
    """Pixel gradient of sigma point ``p`` -> its 3D point ``mu + L z_p`` -> ``g_mu``, ``g_L``."""
    for i in range(3):
        gp = uvj[p, 2 + i] * gu + uvj[p, 5 + i] * gv
        g_mu[i] += gp
        for j in range(3):
            g_L[i, j] += gp * z_set[p, j]


@numba.njit(inline="always", cache=True)
def _moments_backward(uvj: np.ndarray, wm: np.ndarray, wc: np.ndarray, gmu: float, gmv: float,
                      ga: float, gb: float, gc: float, scale: float, z_set: np.ndarray,
                      g_mu: np.ndarray, g_L: np.ndarray) -> None:
    """Back through ``_moments`` and ``_sigma_points``: adds ``scale *`` the gradient to ``g_mu`` and ``g_L``."""
    npts = wm.shape[0]
    u0, v0 = uvj[0, 0], uvj[0, 1]
    mu = mv = 0.0
    for p in range(npts):
        mu += wm[p] * (uvj[p, 0] - u0)
        mv += wm[p] * (uvj[p, 1] - v0)
    sgu = sgv = 0.0                  # sum over points of dLoss/d(d_p), d_p = rel_p - m
    for p in range(npts):
        du, dv = uvj[p, 0] - u0 - mu, uvj[p, 1] - v0 - mv
        sgu += wc[p] * (2 * ga * du + gb * dv)
        sgv += wc[p] * (gb * du + 2 * gc * dv)
    gu0, gv0 = gmu, gmv              # the centre point enters as uv_0 + m and through rel_p = uv_p - uv_0
    for p in range(1, npts):
        du, dv = uvj[p, 0] - u0 - mu, uvj[p, 1] - v0 - mv
        gu = wc[p] * (2 * ga * du + gb * dv) + wm[p] * (gmu - sgu)
        gv = wc[p] * (gb * du + 2 * gc * dv) + wm[p] * (gmv - sgv)
        gu0 -= gu
        gv0 -= gv
        _point_backward(uvj, p, gu * scale, gv * scale, z_set, g_mu, g_L)
    _point_backward(uvj, 0, gu0 * scale, gv0 * scale, z_set, g_mu, g_L)


@numba.njit(inline="always", cache=True)
def _scale_rotation_backward(g: int, qw: float, qx: float, qy: float, qz: float, qn: float, s: np.ndarray,
                             sigma: float, g_sigma: float, rot: np.ndarray, R: np.ndarray, g_L: np.ndarray,
                             G: np.ndarray, grad_quats: np.ndarray, grad_log_scales: np.ndarray,
                             g_rot: np.ndarray) -> None:
    """Back through ``L = rot R(q) diag(exp(log_scales))`` and ``sigma = exp(max log_scales)``; ``G`` is scratch."""
    for j in range(3):
        g_s = 0.0
        for i in range(3):
            g_m = rot[0, i] * g_L[0, j] + rot[1, i] * g_L[1, j] + rot[2, i] * g_L[2, j]   # (rot^T g_L)[i, j]
            g_s += R[i, j] * g_m
            G[i, j] = g_m * s[j]     # dLoss/dR(q)
        grad_log_scales[g, j] = s[j] * g_s + (g_sigma * sigma if s[j] == sigma else 0.0)
    for i in range(3):
        for k in range(3):
            g_rot[3 * i + k] += (g_L[i, 0] * R[k, 0] * s[0] + g_L[i, 1] * R[k, 1] * s[1]
                                 + g_L[i, 2] * R[k, 2] * s[2])
    gw = 2 * (-qz * G[0, 1] + qy * G[0, 2] + qz * G[1, 0] - qx * G[1, 2] - qy * G[2, 0] + qx * G[2, 1])
    gx = 2 * (qy * G[0, 1] + qz * G[0, 2] + qy * G[1, 0] - 2 * qx * G[1, 1] - qw * G[1, 2] + qz * G[2, 0]
              + qw * G[2, 1] - 2 * qx * G[2, 2])
    gy = 2 * (-2 * qy * G[0, 0] + qx * G[0, 1] + qw * G[0, 2] + qx * G[1, 0] + qz * G[1, 2] - qw * G[2, 0]
              + qz * G[2, 1] - 2 * qy * G[2, 2])
    gz = 2 * (-2 * qz * G[0, 0] - qw * G[0, 1] + qx * G[0, 2] + qw * G[1, 0] - 2 * qz * G[1, 1] + qy * G[1, 2]
              + qx * G[2, 0] + qy * G[2, 1])
    if qn > 0:
        dot = qw * gw + qx * gx + qy * gy + qz * gz
        grad_quats[g, 0] = (gw - qw * dot) / qn
        grad_quats[g, 1] = (gx - qx * dot) / qn
        grad_quats[g, 2] = (gy - qy * dot) / qn
        grad_quats[g, 3] = (gz - qz * dot) / qn
    else:
        for k in range(4):
            grad_quats[g, k] = 0.0


@numba.njit(inline="always", cache=True)
def _visible(lens: np.ndarray, opts: np.ndarray, x: float, y: float, z: float, log_scales: np.ndarray) -> bool:
    """Distance in ``[near, far]`` and the 3-sigma cone reaches within ``theta_max``.

    ``theta - asin(ratio) <= theta_max`` is tested as ``cos theta >= cos(theta_max + asin(ratio))``
    (cos falls on [0, pi]), which needs no inverse trigonometry; always true once that sum reaches pi.
    """
    if opts[CULL] == 0.0:
        return True
    dist = math.sqrt(x * x + y * y + z * z)
    if not opts[NEAR] <= dist <= opts[FAR]:
        return False
    cos_max, sin_max = lens[COS_MAX], lens[SIN_MAX]
    if z >= dist * cos_max:
        return True
    sigma = math.exp(max(float(log_scales[0]), float(log_scales[1]), float(log_scales[2])))
    ratio = min(opts[EXTENT] * sigma / max(dist, opts[NEAR]), 1.0)
    cos_a = math.sqrt(1.0 - ratio * ratio)
    if cos_max * cos_a - sin_max * ratio <= -1.0 or (sin_max * cos_a + cos_max * ratio < 0.0):
        return True   # theta_max + asin(ratio) >= pi: every direction is within reach
    return z >= dist * (cos_max * cos_a - sin_max * ratio)


@numba.njit(parallel=True, cache=True)
def cull(means: np.ndarray, log_scales: np.ndarray, lens: np.ndarray, opts: np.ndarray, keep: np.ndarray) -> None:
    """``keep[i]``: Gaussian ``i`` (camera frame) may be visible, as ``_visible``."""
    for i in numba.prange(means.shape[0]):
        keep[i] = _visible(lens, opts, float(means[i, 0]), float(means[i, 1]), float(means[i, 2]), log_scales[i])


@numba.njit(inline="always", cache=True)
def _clamped(mean_u: float, mean_v: float, a: float, b: float, c: float, x: float, y: float, z: float,
             opts: np.ndarray) -> tuple[float, float, float, float, float, float, float, bool]:
    """UT moments -> ``(u, v, a, b, c, depth, radius, valid)``: NaN guard, blur, eigenvalue clamp, 3-sigma box.

    ``(a, b, c)`` is the clamped 2D covariance, ``valid`` whether it is finite and its box overlaps the image.
    """
    finite = math.isfinite(mean_u) & math.isfinite(mean_v) & math.isfinite(a) & math.isfinite(b) & math.isfinite(c)
    mean_u, mean_v = (mean_u, mean_v) if finite else (0.0, 0.0)
    a, b, c = (a, b, c) if finite else (0.0, 0.0, 0.0)
    blur = opts[BLUR]
    _, _, _, _, _, _, a, b, c = _eig_clamp(a + blur, b, c + blur, opts[LO], opts[HI], opts[TINY])
    half = 0.5 * (a - c)
    radius = math.ceil(opts[EXTENT] * math.sqrt(0.5 * (a + c) + math.sqrt(max(half * half + b * b, 0.0))))
    valid = finite & (mean_u + radius > -0.5) & (mean_u - radius < opts[WIDTH] - 0.5) \
        & (mean_v + radius > -0.5) & (mean_v - radius < opts[HEIGHT] - 0.5)
    return mean_u, mean_v, a, b, c, math.sqrt(x * x + y * y + z * z), radius, valid


@numba.njit(cache=True, fastmath=FASTMATH, error_model="numpy")
def _forward_range(start: int, stop: int, index: np.ndarray, means: np.ndarray, quats: np.ndarray,
                   log_scales: np.ndarray, rot: np.ndarray, model: int, lens: np.ndarray, opts: np.ndarray,
                   z7: np.ndarray, wm7: np.ndarray, wc7: np.ndarray, z19: np.ndarray, wm19: np.ndarray,
                   wc19: np.ndarray, out_means: np.ndarray, out_conics: np.ndarray, out_cov: np.ndarray,
                   out_depths: np.ndarray, out_radii: np.ndarray, out_valid: np.ndarray) -> None:
    """``forward`` for the rows ``start:stop`` of ``index`` (one thread's chunk), through ``footprints``."""
    m = stop - start
    xyz, q, s, R, L, sig = (np.empty((m, 3)), np.empty((m, 5)), np.empty((m, 3)), np.empty((m, 3, 3)),
                            np.empty((m, 3, 3)), np.empty(m))
    pts, uv, uv19 = np.empty((3, N_UT * m)), np.empty((2, N_UT * m)), np.empty((z19.shape[0], 8))
    mom, foot, valid = np.empty((3, 5)), np.empty((7, m)), np.empty(m, np.bool_)
    for i in range(m):
        _load_row(index[start + i], means, quats, log_scales, rot, i, xyz, q, s, R, L, sig)
    footprints(model, lens, opts, m, xyz, L, sig, z7, wm7, wc7, z19, wm19, wc19, pts, uv, uv19, mom, foot, valid)
    for i in range(m):
        a, b, c = foot[2, i], foot[3, i], foot[4, i]
        det = a * c - b * b
        out_means[start + i, 0], out_means[start + i, 1] = foot[0, i], foot[1, i]
        out_conics[start + i, 0], out_conics[start + i, 1], out_conics[start + i, 2] = c / det, -b / det, a / det
        out_cov[start + i, 0], out_cov[start + i, 1], out_cov[start + i, 2] = a, b, c
        out_depths[start + i] = foot[5, i]
        out_radii[start + i] = foot[6, i]
        out_valid[start + i] = valid[i]


@numba.njit(parallel=True, cache=True)
def forward(index: np.ndarray, means: np.ndarray, quats: np.ndarray, log_scales: np.ndarray, rot: np.ndarray,
            model: int, lens: np.ndarray, opts: np.ndarray, z7: np.ndarray, wm7: np.ndarray, wc7: np.ndarray,
            z19: np.ndarray, wm19: np.ndarray, wc19: np.ndarray, out_means: np.ndarray, out_conics: np.ndarray,
            out_cov: np.ndarray, out_depths: np.ndarray, out_radii: np.ndarray, out_valid: np.ndarray) -> None:
    """Project the Gaussians ``index``: 2D means, conics, clamped covariances, distances, radii, validity."""
    m = index.shape[0]
    for ch in numba.prange((m + CHUNK - 1) // CHUNK):
        _forward_range(ch * CHUNK, min(m, (ch + 1) * CHUNK), index, means, quats, log_scales, rot, model, lens,
                       opts, z7, wm7, wc7, z19, wm19, wc19, out_means, out_conics, out_cov, out_depths,
                       out_radii, out_valid)


@numba.njit(cache=True, fastmath=FASTMATH, error_model="numpy")
def _backward_range(start: int, stop: int, index: np.ndarray, means: np.ndarray, quats: np.ndarray,
                    log_scales: np.ndarray, rot: np.ndarray, model: int, lens: np.ndarray, opts: np.ndarray,
                    z7: np.ndarray, wm7: np.ndarray, wc7: np.ndarray, z19: np.ndarray, wm19: np.ndarray,
                    wc19: np.ndarray, g_means2d: np.ndarray, g_conics: np.ndarray, g_cov2d: np.ndarray,
                    g_depths: np.ndarray, grad_means: np.ndarray, grad_quats: np.ndarray,
                    grad_log_scales: np.ndarray, g_rot: np.ndarray) -> None:
    """``backward`` for the rows ``start:stop`` of ``index``; adds the ``rot`` gradient into ``g_rot``.

    The rows with an incoming gradient are gathered first and their 7-point sigma points projected, with
    Jacobians, in one vectorised loop (``_sigma_batch``, ``project_batch``); the chain rule runs row by row.
    """
    cap = stop - start
    rows, xyz, L, sig = np.empty(cap, np.int64), np.empty((cap, 3)), np.empty((cap, 3, 3)), np.empty(cap)
    R, s, q = np.empty((cap, 3, 3)), np.empty((cap, 3)), np.empty((cap, 5))
    pts, uvj = np.empty((3, N_UT * cap)), np.empty((8, N_UT * cap))
    uv7, uv19, mom = np.empty((N_UT, 8)), np.empty((z19.shape[0], 8)), np.empty((3, 5))
    g_mu, g_L, G = np.empty(3), np.empty((3, 3)), np.empty((3, 3))
    m = 0
    for i in range(start, stop):
        if (g_means2d[i, 0] == 0.0 and g_means2d[i, 1] == 0.0 and g_conics[i, 0] == 0.0 and g_conics[i, 1] == 0.0
                and g_conics[i, 2] == 0.0 and g_cov2d[i, 0] == 0.0 and g_cov2d[i, 1] == 0.0
                and g_cov2d[i, 2] == 0.0 and g_depths[i] == 0.0):
            continue   # drawn nowhere (occluded, or culled by the rasterizer): its gradients stay 0, as zeroed
        rows[m] = i
        _load_row(index[i], means, quats, log_scales, rot, m, xyz, q, s, R, L, sig)
        m += 1
    _sigma_batch(xyz, L, z7, m, pts)
    project_pixels_jacobians(model, lens, opts[AXIS_EPS], opts[TINY], pts, uvj, N_UT * m)
    for k in range(m):
        i, g = rows[k], index[rows[k]]
        x, y, z, sigma = xyz[k, 0], xyz[k, 1], xyz[k, 2], sig[k]
        for p in range(N_UT):
            for col in range(8):
                uv7[p, col] = uvj[col, p * m + k]
        m7 = _moments(uv7[:, 0], uv7[:, 1], 0, 1, wm7, wc7)
        rich, w, dwx, dwy, dwz, dws = _ut_blend(model, lens, opts, x, y, z, sigma, L[k], m7, z19, wm19, wc19,
                                                uv19, mom, True)
        n = math.sqrt(x * x + y * y + z * z)
        gd = float(g_depths[i])
        g_mu[0], g_mu[1], g_mu[2] = gd * x / n, gd * y / n, gd * z / n
        for r in range(3):
            for j in range(3):
                g_L[r, j] = 0.0
        mean_u, mean_v, a, b, c = mom[2, 0], mom[2, 1], mom[2, 2], mom[2, 3], mom[2, 4]
        finite = np.isfinite(mean_u) and np.isfinite(mean_v) and np.isfinite(a) and np.isfinite(b) \
            and np.isfinite(c)
        gs = 0.0
        if finite:
            blur, lo, hi, tiny = opts[BLUR], opts[LO], opts[HI], opts[TINY]
            _, _, _, _, _, _, ca, cb, cc = _eig_clamp(a + blur, b, c + blur, lo, hi, tiny)
            det = ca * cc - cb * cb
            g0, g1, g2 = float(g_conics[i, 0]), float(g_conics[i, 1]), float(g_conics[i, 2])
            gdet = -(g0 * cc - g1 * cb + g2 * ca) / (det * det)
            gca = g2 / det + gdet * cc + float(g_cov2d[i, 0])
            gcb = -g1 / det - 2 * gdet * cb + float(g_cov2d[i, 1])
            gcc = g0 / det + gdet * ca + float(g_cov2d[i, 2])
            ga, gb, gc = _eig_clamp_backward(a + blur, b, c + blur, lo, hi, tiny, gca, gcb, gcc)
            gmu, gmv = float(g_means2d[i, 0]), float(g_means2d[i, 1])
            _moments_backward(uv7, wm7, wc7, gmu, gmv, ga, gb, gc, 1.0 - w, z7, g_mu, g_L)
            if rich:
                _moments_backward(uv19, wm19, wc19, gmu, gmv, ga, gb, gc, w, z19, g_mu, g_L)
                gw = (gmu * (mom[1, 0] - mom[0, 0]) + gmv * (mom[1, 1] - mom[0, 1])
                      + ga * (mom[1, 2] - mom[0, 2]) + gb * (mom[1, 3] - mom[0, 3])
                      + gc * (mom[1, 4] - mom[0, 4]))
                g_mu[0] += gw * dwx
                g_mu[1] += gw * dwy
                g_mu[2] += gw * dwz
                gs = gw * dws
        for j in range(3):
            grad_means[g, j] = g_mu[j]
        # sigma = exp(max log-scale): torch's amax splits the gradient evenly between ties
        ties = (s[k, 0] == sigma) + (s[k, 1] == sigma) + (s[k, 2] == sigma)
        _scale_rotation_backward(g, q[k, 0], q[k, 1], q[k, 2], q[k, 3], q[k, 4], s[k], sigma, gs / ties, rot, R[k],
                                 g_L, G, grad_quats, grad_log_scales, g_rot)


@numba.njit(parallel=True, cache=True)
def backward(index: np.ndarray, means: np.ndarray, quats: np.ndarray, log_scales: np.ndarray, rot: np.ndarray,
             model: int, lens: np.ndarray, opts: np.ndarray, z7: np.ndarray, wm7: np.ndarray, wc7: np.ndarray,
             z19: np.ndarray, wm19: np.ndarray, wc19: np.ndarray, g_means2d: np.ndarray, g_conics: np.ndarray,
             g_cov2d: np.ndarray, g_depths: np.ndarray, grad_means: np.ndarray, grad_quats: np.ndarray,
             grad_log_scales: np.ndarray, grad_rot: np.ndarray) -> None:
    """Gradients of ``forward``'s means, conics, covariances and depths w.r.t. means, quats, log-scales, rot.

    Rows ``index`` of ``grad_means/quats/log_scales`` with a nonzero incoming gradient are written (the
    caller zeroes the rest: a Gaussian drawn nowhere, most often an occluded one, has zero gradients);
    ``grad_rot[chunk]`` (zeroed by the caller) gets each chunk's partial sum of the ``rot`` gradient.
    """
    m = index.shape[0]
    for ch in numba.prange((m + CHUNK - 1) // CHUNK):
        _backward_range(ch * CHUNK, min(m, (ch + 1) * CHUNK), index, means, quats, log_scales, rot, model, lens,
                        opts, z7, wm7, wc7, z19, wm19, wc19, g_means2d, g_conics, g_cov2d, g_depths, grad_means,
                        grad_quats, grad_log_scales, grad_rot[ch])
