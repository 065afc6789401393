"""The paper's five slot-aware ablation variants ("Ablation on Slot-aware Strategy", reference lines 549-555).

Each variant is a set of switches on the full step (``step.SlotAwareStep``):
(1) ``direct_ipm``: plain IPM L1 (uniform weights), no detector, no alignment, no camera term;
(2) ``feature_only``: the detector's alignment loss L_align only, no weighted reconstruction terms;
(3) ``teacher_only``: W_mix = W^t (alpha = beta = 1), L_ipm + L_cam, no alignment;
(4) ``student_only``: W_mix = sg(W^s) (alpha = beta = 0), L_ipm + L_cam, no alignment;
(5) ``full``: the teacher-student mix with alpha, beta from the config, L_align + L_ipm + L_cam.
"""

from __future__ import annotations

from dataclasses import dataclass
from enum import Enum
from typing import Literal

__all__ = ["Variant", "VariantSpec", "spec_of"]


class Variant(str, Enum):
    """Selectable ablation variant (``slot_aware.variant`` in the config)."""

    DIRECT_IPM = "direct_ipm"
    FEATURE_ONLY = "feature_only"
    TEACHER_ONLY = "teacher_only"
    STUDENT_ONLY = "student_only"
    FULL = "full"


@dataclass(frozen=True)
class VariantSpec:
    """How a variant changes the step: weighting of L_ipm/L_cam, teacher share, which terms are on."""

    weights: Literal["uniform", "slot"] | None  # None: no weighted reconstruction terms
    teacher_share: float | None                  # overrides alpha and beta; None keeps the config's values
    align: bool
    ipm: bool
    cam: bool

    @property
    def uses_detector(self) -> bool:
        """Whether the frozen detector runs at all (and slot-less frames must be skipped)."""
        return self.align or self.weights == "slot"


_SPECS = {
    Variant.DIRECT_IPM: VariantSpec("uniform", None, align=False, ipm=True, cam=False),
    Variant.FEATURE_ONLY: VariantSpec(None, None, align=True, ipm=False, cam=False),
    Variant.TEACHER_ONLY: VariantSpec("slot", 1.0, align=False, ipm=True, cam=True),
    Variant.STUDENT_ONLY: VariantSpec("slot", 0.0, align=False, ipm=True, cam=True),
    Variant.FULL: VariantSpec("slot", None, align=True, ipm=True, cam=True),
}


def spec_of(variant: Variant) -> VariantSpec:
    """The switches of ``variant``."""
    return _SPECS[Variant(variant)]
