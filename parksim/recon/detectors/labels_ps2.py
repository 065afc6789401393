"""Slot labels in one form for all sources: ParkSim label dicts and ps2.0 label files (JSON or MATLAB ``.mat``).

A ps2.0 file holds ``marks`` and ``slots`` (``.mat`` as saved by the ps2.0 / DMPR-PS labelling tool, JSON as its
``mat2json``): 1-based MATLAB pixel coordinates in a 600x600 image covering 10 m x 10 m. DMPR-PS' directional
relabel has ``marks`` rows ``[x, y, x_dir, y_dir, shape]``, ``(x_dir, y_dir)`` a second point along the marking
point's direction and ``shape`` 0 = T, 1 = L; ps2.0's original labels have ``[x, y]`` rows only (no direction
or shape: slot scores only). ``slots`` rows are ``[p1, p2, type, angle]`` with 1-based point indices.
"""

from __future__ import annotations

import json
import math
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

__all__ = ["SlotLabels", "LabelError", "read_ps2_labels", "slot_angle_deg", "PS2_METRES"]

PS2_METRES = 10.0
"""Side of a ps2.0 image in metres (600 px = 10 m)."""
ANGLE_TOLERANCE_DEG = 20.0
"""Largest gap between a ParkSim slot's labelled angle and the angle its entrance points make (labels are exact)."""


class LabelError(ValueError):
    """A label file is malformed or holds impossible values; the message names the file and the entry."""

    def __init__(self, path: str | Path, message: str) -> None:
        super().__init__(f"{path}: {message}")


@dataclass
class SlotLabels:
    """Marking points ``[N, 4]`` (x, y in px with centres at integers, direction rad, 1 = L / 0 = T) and slots."""

    marks: np.ndarray        # [N, 4] float64; direction and shape NaN where the source has positions only
    slots: np.ndarray        # [M, 2] int64, ordered entrance points (the slot lies right of p1 -> p2)
    slot_angles: np.ndarray  # [M] float64, degrees between entrance p1 -> p2 and the separators
    width: int
    height: int
    m_per_px: float

    @classmethod
    def from_parksim(cls, data: Mapping[str, Any], width: int, height: int, m_per_px: float,
                     source: str | Path = "labels") -> SlotLabels:
        """From a ParkSim label dict (``DatasetReader.labels``, which checks the values) read from ``source``;
        slot angles must agree with the entrance points (``LabelError`` names ``source`` otherwise)."""
        marks = np.array([[m["x"], m["y"], m["direction"], 1.0 if m["shape"] == "L" else 0.0] for m in data["marks"]],
                         dtype=np.float64).reshape(-1, 4)
        slots = np.array([[s["p1"], s["p2"]] for s in data["slots"]], dtype=np.int64).reshape(-1, 2)
        angles = np.array([float(s.get("angle", math.nan)) for s in data["slots"]], dtype=np.float64)
        labels = cls(marks, slots, angles, width, height, m_per_px)
        labels.fill_angles()
        labels.check_angles(source)
        return labels

    @property
    def directional(self) -> bool:
        """Whether every marking point has a direction and shape (ps2.0's original labels have neither)."""
        return bool(np.isfinite(self.marks[:, 2:]).all())

    def fill_angles(self) -> None:
        """Replace missing slot angles by the angle between the entrance and p1's direction."""
        for k in np.flatnonzero(~np.isfinite(self.slot_angles)):
            a, b = self.marks[self.slots[k, 0]], self.marks[self.slots[k, 1]]
            self.slot_angles[k] = slot_angle_deg(a[0], a[1], a[2], b[0], b[1], b[2])

    def check_angles(self, source: str | Path, tolerance_deg: float = ANGLE_TOLERANCE_DEG) -> None:
        """Reject slots whose angle disagrees with the one from their entrance p1 -> p2 to their points' directions
        (a convention error such as a slanted slot labelled ``a`` instead of ``180 - a``; it fails every match)."""
        for k, ((i, j), angle) in enumerate(zip(self.slots, self.slot_angles)):
            a, b = self.marks[i], self.marks[j]
            geometric = slot_angle_deg(a[0], a[1], a[2], b[0], b[1], b[2])
            if abs(angle - geometric) > tolerance_deg:
                raise LabelError(source, f"slot {k} has angle {angle:g} deg but its entrance p1 -> p2 and its "
                                         f"points' directions make {geometric:.0f} deg (labels from before the "
                                         f"synth fix of slanted slot angles? regenerate them)")


def slot_angle_deg(xa: float, ya: float, da: float, xb: float, yb: float, db: float) -> float:
    """Angle (deg, 0..180) between the entrance a -> b and the mean direction of the two separators."""
    entrance = math.atan2(yb - ya, xb - xa)
    sep = math.atan2(math.sin(da) + math.sin(db), math.cos(da) + math.cos(db))
    return abs(math.degrees(math.remainder(sep - entrance, 2 * math.pi)))


def _rows(path: Path, data: Mapping[str, Any], key: str, full: int, short: int | None = None) -> np.ndarray:
    """``data[key]`` as a float array ``[K, full]``, or ``[K, short]`` where rows have exactly ``short`` numbers
    (ps2.0 stores a single row unnested, MATLAB an empty table as 0x0)."""
    if key not in data:
        raise LabelError(path, f"missing {key!r}")
    try:
        arr = np.asarray(data[key], dtype=np.float64)
    except (TypeError, ValueError):
        raise LabelError(path, f"{key!r} must be a list of number rows") from None
    if arr.size == 0:
        return np.zeros((0, full))
    if arr.ndim == 1:
        arr = arr[None]
    if arr.ndim != 2 or not (arr.shape[1] >= full or arr.shape[1] == short):
        either = f"{short} or " if short else ""
        raise LabelError(path, f"each {key!r} row needs {either}at least {full} numbers, got shape {list(arr.shape)}")
    if not np.isfinite(arr).all():
        raise LabelError(path, f"{key!r} holds non-finite values")
    return arr if arr.shape[1] == short else arr[:, :full]


def _load(path: Path) -> Mapping[str, Any]:
    """The label file's variables: ``.mat`` through scipy, anything else as JSON."""
    if path.suffix.lower() == ".mat":
        from scipy.io import loadmat
        from scipy.io.matlab import MatReadError

        try:
            data: Any = loadmat(path)
        except FileNotFoundError:
            raise LabelError(path, "file not found") from None
        except (MatReadError, ValueError, TypeError, OSError, IndexError, EOFError) as e:  # scipy's, by file
            raise LabelError(path, f"not a readable MATLAB file: {e}") from None
    else:
        try:
            data = json.loads(path.read_text())
        except FileNotFoundError:
            raise LabelError(path, "file not found") from None
        except (json.JSONDecodeError, UnicodeDecodeError) as e:
            raise LabelError(path, f"not valid JSON: {e}") from None
    if not isinstance(data, dict):
        raise LabelError(path, "expected an object with 'marks' and 'slots'")
    return data


def _mark(path: Path, i: int, row: np.ndarray, width: int, height: int) -> tuple[float, float, float, float]:
    """One checked ``marks`` row as ``(x, y, direction, shape)`` in ParkSim pixels (NaN direction and shape for
    a position-only row)."""
    x, y = row[0], row[1]
    u, v = x - 1.0, y - 1.0
    if not (-0.5 <= u <= width - 0.5 and -0.5 <= v <= height - 0.5):
        raise LabelError(path, f"mark {i + 1} at ({x:.1f}, {y:.1f}) lies outside the {width}x{height} image")
    if len(row) == 2:
        return u, v, math.nan, math.nan
    xd, yd, shape = row[2:5]
    if xd == x and yd == y:
        raise LabelError(path, f"mark {i + 1} has no direction (its direction point equals the point)")
    if shape not in (0.0, 1.0):
        raise LabelError(path, f"mark {i + 1} has shape {shape:g}; expected 0 (T) or 1 (L)")
    return u, v, math.atan2(yd - y, xd - x), shape


def read_ps2_labels(path: str | Path, width: int = 600, height: int = 600) -> SlotLabels:
    """Read and check one ps2.0 label file (``.mat`` or JSON) for a ``width`` x ``height`` image of 10 m x 10 m."""
    path = Path(path)
    data = _load(path)
    marks = _rows(path, data, "marks", 5, short=2)
    slots = _rows(path, data, "slots", 4)
    out = np.array([_mark(path, i, row, width, height) for i, row in enumerate(marks)]).reshape(-1, 4)
    pairs = np.zeros((len(slots), 2), dtype=np.int64)
    for j, (p1, p2, _kind, angle) in enumerate(slots):
        for p in (p1, p2):
            if p != int(p) or not 1 <= p <= len(marks):
                raise LabelError(path, f"slot {j + 1} refers to mark {p:g}; marks are numbered 1..{len(marks)}")
        if p1 == p2:
            raise LabelError(path, f"slot {j + 1} uses mark {int(p1)} twice")
        if not 0.0 < angle < 180.0:
            raise LabelError(path, f"slot {j + 1} has angle {angle:g}; expected degrees in (0, 180)")
        pairs[j] = (int(p1) - 1, int(p2) - 1)
    return SlotLabels(out, pairs, slots[:, 3].copy(), width, height, PS2_METRES / width)
