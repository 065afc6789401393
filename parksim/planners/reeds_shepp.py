"""Reeds-Shepp curves: the shortest paths of a car that drives forward and backward with a minimum turning radius.

Reeds and Shepp (1990) showed that a shortest path is one of 48 words of at most five segments: arcs left (L)
or right (R) at the minimum radius and straight runs (S), each driven forward or backward. The words come from
eight base formulas (their sections 8.1-8.11: CSC, CCC, CCCC, CCSC, CCSCC) in the goal's frame scaled to a unit
radius, each applied to the goal as given and as seen by three symmetries: time flip (drive the word backward:
``(x, y, phi) -> (-x, y, -phi)``, lengths negated), reflection (mirror left and right: ``(x, -y, -phi)``, L and
R swapped) and reversal (the word read from the goal back to the start). A formula answers only where its word
exists (its sign conditions); tests/test_reeds_shepp.py integrates every answer and checks that it ends on the goal.

A segment's signed length is metres travelled, negative when driving backward; an arc turns by length / radius
(left arcs counter-clockwise when driven forward).
"""

from __future__ import annotations

import math
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from typing import Any

import numpy as np

__all__ = ["ReedsSheppPath", "reeds_shepp_paths", "reeds_shepp_path", "reeds_shepp_length"]

_HALF_PI = math.pi / 2
_ZERO = 10 * np.finfo(np.float64).eps
"""Slack of the base formulas' sign conditions; a unit length this small is a zero segment (a -1e-16 rad arc that
rounding left would otherwise add a pose)."""

_Lengths = tuple[float, ...]


def _mod2pi(a: float) -> float:
    """``a`` wrapped to [-pi, pi]."""
    v = math.fmod(a, 2 * math.pi)
    if v < -math.pi:
        return v + 2 * math.pi
    return v - 2 * math.pi if v > math.pi else v


def _polar(x: float, y: float) -> tuple[float, float]:
    """``(r, theta)`` of the point ``(x, y)``."""
    return math.hypot(x, y), math.atan2(y, x)


def _tau_omega(u: float, v: float, xi: float, eta: float, phi: float) -> tuple[float, float]:
    """The first and last arcs of the CCCC words (Reeds-Shepp section 8.7)."""
    delta = _mod2pi(u - v)
    a = math.sin(u) - math.sin(delta)
    b = math.cos(u) - math.cos(delta) - 1.0
    t1 = math.atan2(eta * a - xi * b, xi * a + eta * b)
    t2 = 2.0 * (math.cos(delta) - math.cos(v) - math.cos(u)) + 3.0
    tau = _mod2pi(t1 + math.pi) if t2 < 0 else _mod2pi(t1)
    return tau, _mod2pi(tau - u + v - phi)


def _lsl(x: float, y: float, phi: float) -> _Lengths | None:
    """L+ S+ L+ (8.1)."""
    u, t = _polar(x - math.sin(phi), y - 1.0 + math.cos(phi))
    v = _mod2pi(phi - t)
    return (t, u, v) if t >= -_ZERO and v >= -_ZERO else None


def _lsr(x: float, y: float, phi: float) -> _Lengths | None:
    """L+ S+ R+ (8.2)."""
    r, t1 = _polar(x + math.sin(phi), y - 1.0 - math.cos(phi))
    if r * r < 4.0:
        return None
    u = math.sqrt(r * r - 4.0)
    t = _mod2pi(t1 + math.atan2(2.0, u))
    v = _mod2pi(t - phi)
    return (t, u, v) if t >= -_ZERO and v >= -_ZERO else None


def _lrl(x: float, y: float, phi: float) -> _Lengths | None:
    """L+ R- L (8.3, 8.4)."""
    r, theta = _polar(x - math.sin(phi), y - 1.0 + math.cos(phi))
    if r > 4.0:
        return None
    u = -2.0 * math.asin(0.25 * r)
    t = _mod2pi(theta + 0.5 * u + math.pi)
    v = _mod2pi(phi - t + u)
    return (t, u, v) if t >= -_ZERO and u <= _ZERO else None


def _lrlr_meet(x: float, y: float, phi: float) -> _Lengths | None:
    """L+ R+ L- R- (8.7): the two middle arcs equal and opposite."""
    xi, eta = x + math.sin(phi), y - 1.0 - math.cos(phi)
    rho = 0.25 * (2.0 + math.hypot(xi, eta))
    if rho > 1.0:
        return None
    u = math.acos(rho)
    t, v = _tau_omega(u, -u, xi, eta, phi)
    return (t, u, -u, v) if t >= -_ZERO and v <= _ZERO else None


def _lrlr_same(x: float, y: float, phi: float) -> _Lengths | None:
    """L+ R- L- R+ (8.8): the two middle arcs equal."""
    xi, eta = x + math.sin(phi), y - 1.0 - math.cos(phi)
    rho = (20.0 - xi * xi - eta * eta) / 16.0
    if not 0.0 <= rho <= 1.0:
        return None
    u = -math.acos(rho)
    if u < -_HALF_PI:
        return None
    t, v = _tau_omega(u, u, xi, eta, phi)
    return (t, u, u, v) if t >= -_ZERO and v >= -_ZERO else None


def _lrsl(x: float, y: float, phi: float) -> _Lengths | None:
    """L+ R-(pi/2) S- L- (8.9)."""
    rho, theta = _polar(x - math.sin(phi), y - 1.0 + math.cos(phi))
    if rho < 2.0:
        return None
    r = math.sqrt(rho * rho - 4.0)
    u = 2.0 - r
    t = _mod2pi(theta + math.atan2(r, -2.0))
    v = _mod2pi(phi - _HALF_PI - t)
    return (t, -_HALF_PI, u, v) if t >= -_ZERO and u <= _ZERO and v <= _ZERO else None


def _lrsr(x: float, y: float, phi: float) -> _Lengths | None:
    """L+ R-(pi/2) S- R- (8.10)."""
    xi, eta = x + math.sin(phi), y - 1.0 - math.cos(phi)
    rho, theta = _polar(-eta, xi)
    if rho < 2.0:
        return None
    t, u = theta, 2.0 - rho
    v = _mod2pi(t + _HALF_PI - phi)
    return (t, -_HALF_PI, u, v) if t >= -_ZERO and u <= _ZERO and v <= _ZERO else None


def _lrslr(x: float, y: float, phi: float) -> _Lengths | None:
    """L+ R-(pi/2) S- L-(pi/2) R+ (8.11)."""
    xi, eta = x + math.sin(phi), y - 1.0 - math.cos(phi)
    rho, _ = _polar(xi, eta)
    if rho < 2.0:
        return None
    u = 4.0 - math.sqrt(rho * rho - 4.0)
    if u > _ZERO:
        return None
    t = _mod2pi(math.atan2((4.0 - u) * xi - 2.0 * eta, -2.0 * xi + (u - 4.0) * eta))
    v = _mod2pi(t - phi)
    return (t, -_HALF_PI, u, -_HALF_PI, v) if t >= -_ZERO and v >= -_ZERO else None


_BASE: tuple[tuple[str, Callable[[float, float, float], _Lengths | None]], ...] = (
    ("LSL", _lsl), ("LSR", _lsr), ("LRL", _lrl), ("LRLR", _lrlr_meet), ("LRLR", _lrlr_same),
    ("LRSL", _lrsl), ("LRSR", _lrsr), ("LRSLR", _lrslr))
"""The base words and their formulas (unit radius, goal ``(x, y, phi)`` in the start's frame)."""

_MIRROR = str.maketrans("LR", "RL")


def _words(x: float, y: float, phi: float) -> Iterator[tuple[str, _Lengths]]:
    """Every base formula under the 8 combinations of time flip, reflection and reversal: ``(word, unit lengths)``."""
    xb, yb = x * math.cos(phi) + y * math.sin(phi), x * math.sin(phi) - y * math.cos(phi)
    for word, formula in _BASE:
        for backward, (px, py) in ((False, (x, y)), (True, (xb, yb))):
            for flip in (False, True):
                for mirror in (False, True):
                    lengths = formula(-px if flip else px, -py if mirror else py, -phi if flip != mirror else phi)
                    if lengths is None:
                        continue
                    w = word.translate(_MIRROR) if mirror else word
                    lengths = tuple(0.0 if abs(v) <= _ZERO else -v if flip else v for v in lengths)
                    yield (w[::-1], lengths[::-1]) if backward else (w, lengths)


def _advance(x: float, y: float, yaw: float, kind: str, length: Any, radius: float) -> tuple[Any, Any, Any]:
    """The pose after driving ``length`` metres of segment ``kind`` (L, S or R) from ``(x, y, yaw)``, exact.

    Returns:
        ``(x, y, yaw)``, floats or arrays like ``length`` (a float or an array; negative drives backward).
    """
    if kind == "S":
        return x + length * np.cos(yaw), y + length * np.sin(yaw), yaw + 0.0 * length
    sign = 1.0 if kind == "L" else -1.0
    turn = sign * length / radius
    return (x + sign * radius * (np.sin(yaw + turn) - np.sin(yaw)),
            y + sign * radius * (np.cos(yaw) - np.cos(yaw + turn)), yaw + turn)


@dataclass(frozen=True)
class ReedsSheppPath:
    """One Reeds-Shepp word between two poses.

    Attributes:
        start: ``(x, y, yaw)`` the path leaves from (metres, radians).
        word: the segments' kinds, ``L`` (left arc), ``S`` (straight), ``R`` (right arc), e.g. ``"LSR"``.
        lengths: signed metres per segment, negative where the car drives backward (zero-length segments kept).
        radius: the arcs' radius (m).
    """

    start: tuple[float, float, float]
    word: str
    lengths: tuple[float, ...]
    radius: float

    @property
    def length(self) -> float:
        """Metres driven, forward and backward together."""
        return float(sum(abs(v) for v in self.lengths))

    @property
    def switches(self) -> int:
        """Direction changes (cusps) along the path."""
        signs = [math.copysign(1.0, v) for v in self.lengths if v != 0.0]
        return sum(a != b for a, b in zip(signs, signs[1:]))

    def end(self) -> tuple[float, float, float]:
        """The pose the path ends at, integrated in closed form.

        Returns:
            ``(x, y, yaw)``, yaw unwrapped (the start's yaw plus the turns).
        """
        x, y, yaw = self.start
        for kind, length in zip(self.word, self.lengths):
            x, y, yaw = _advance(x, y, yaw, kind, length, self.radius)
        return float(x), float(y), float(yaw)

    def sample(self, step: float = 0.1) -> np.ndarray:
        """Poses at most ``step`` metres apart along the path, every segment's ends included.

        Args:
            step: largest spacing of the poses along the path (m).

        Returns:
            ``[N, 4]`` float64 ``(x, y, yaw, direction)``: yaw unwrapped (continuous along the path), direction
            +1 or -1, the way the car moves from this pose to the next (the last pose repeats the last segment's).
            A cusp pose appears once, with the direction it leaves in. Zero-length segments add no pose.

        Raises:
            ValueError: ``step`` is not positive.
        """
        if not step > 0:
            raise ValueError(f"step must be positive, got {step}")
        x, y, yaw = self.start
        parts = []
        direction = 1.0
        for kind, length in zip(self.word, self.lengths):
            if length == 0.0:
                continue
            direction = math.copysign(1.0, length)
            n = max(1, math.ceil(abs(length) / step))
            xs, ys, yaws = _advance(x, y, yaw, kind, length * np.arange(n + 1) / n, self.radius)
            parts.append(np.column_stack([xs[:-1], ys[:-1], yaws[:-1], np.full(n, direction)]))
            x, y, yaw = float(xs[-1]), float(ys[-1]), float(yaws[-1])
        parts.append(np.array([[x, y, yaw, direction]]))
        return np.concatenate(parts)


def _local(start: tuple[float, float, float], goal: tuple[float, float, float], radius: float
           ) -> tuple[np.ndarray, tuple[float, float, float]]:
    """The checked start, and the goal in the start's frame over ``radius``: ``(start [3], (x, y, phi))``."""
    if not (math.isfinite(radius) and radius > 0):
        raise ValueError(f"radius must be positive and finite, got {radius}")
    s, g = np.asarray(start, np.float64), np.asarray(goal, np.float64)
    if s.shape != (3,) or g.shape != (3,) or not (np.isfinite(s).all() and np.isfinite(g).all()):
        raise ValueError(f"start and goal must be (x, y, yaw), 3 finite numbers each, got {start!r} and {goal!r}")
    dx, dy = g[0] - s[0], g[1] - s[1]
    c, si = math.cos(s[2]), math.sin(s[2])
    return s, ((c * dx + si * dy) / radius, (-si * dx + c * dy) / radius, _mod2pi(g[2] - s[2]))


def reeds_shepp_paths(start: tuple[float, float, float], goal: tuple[float, float, float],
                      radius: float) -> list[ReedsSheppPath]:
    """Every Reeds-Shepp word from ``start`` to ``goal`` that the base formulas give, shortest first.

    Args:
        start: ``(x, y, yaw)`` in metres and radians.
        goal: ``(x, y, yaw)`` in metres and radians.
        radius: the minimum turning radius (m).

    Returns:
        The candidate paths (at least one for any two poses), sorted by length and then by word; the first is a
        shortest path.

    Raises:
        ValueError: ``radius`` is not positive and finite, or a pose is not 3 finite numbers.

    Example:
        >>> path = reeds_shepp_paths((0.0, 0.0, 0.0), (-3.0, 0.0, 0.0), radius=4.0)[0]
        >>> path.word.replace("L", "").replace("R", ""), round(path.length, 9), path.sample(1.0)[:, 3].tolist()
        ('S', 3.0, [-1.0, -1.0, -1.0, -1.0])
    """
    s, local = _local(start, goal, radius)
    origin = (float(s[0]), float(s[1]), float(s[2]))
    found: dict[tuple[str, tuple[float, ...]], ReedsSheppPath] = {}
    for word, lengths in _words(*local):
        metres = tuple(v * radius for v in lengths)
        found.setdefault((word, metres), ReedsSheppPath(origin, word, metres, radius))
    return sorted(found.values(), key=lambda p: (p.length, p.word, p.lengths))


def reeds_shepp_path(start: tuple[float, float, float], goal: tuple[float, float, float],
                     radius: float) -> ReedsSheppPath:
    """A shortest Reeds-Shepp path from ``start`` to ``goal`` (the first of ``reeds_shepp_paths``).

    Args:
        start: ``(x, y, yaw)`` in metres and radians.
        goal: ``(x, y, yaw)`` in metres and radians.
        radius: the minimum turning radius (m).

    Returns:
        The shortest path.

    Raises:
        ValueError: as ``reeds_shepp_paths``.
    """
    return reeds_shepp_paths(start, goal, radius)[0]


def reeds_shepp_length(start: tuple[float, float, float], goal: tuple[float, float, float], radius: float) -> float:
    """The length of a shortest Reeds-Shepp path, without building the paths (Hybrid A*'s heuristic calls it).

    Args:
        start: ``(x, y, yaw)`` in metres and radians.
        goal: ``(x, y, yaw)`` in metres and radians.
        radius: the minimum turning radius (m).

    Returns:
        Metres, equal to ``reeds_shepp_path(start, goal, radius).length``.

    Raises:
        ValueError: as ``reeds_shepp_paths``.
    """
    _, local = _local(start, goal, radius)
    return min(sum(abs(v * radius) for v in lengths) for _, lengths in _words(*local))
