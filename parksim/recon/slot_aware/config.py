"""Pydantic model of the slot-aware phase (``slot_aware:`` in a training config); defaults are the paper's.

Values not given by the paper (marked "ParkSim" below): ``lambda_edge``, the alignment region size
``align_top_k`` and the alignment softmax temperature ``align_temperature``.
"""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING, Literal

from pydantic import BaseModel, ConfigDict, Field

from .variants import Variant

if TYPE_CHECKING:
    from ..detectors import Detector

__all__ = ["SlotAwareConfig", "DetectorRef", "DetectorError"]


class DetectorError(ValueError):
    """A configured detector checkpoint is missing or is not of the configured kind; the message names both."""


class DetectorRef(BaseModel):
    """A trained slot detector: its architecture and its checkpoint (``model.pt`` or the folder holding it)."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    kind: Literal["dmpr", "gcn"]
    path: str

    def checkpoint(self) -> Path:
        """The ``model.pt`` this reference names; a clear error when it is not there."""
        path = Path(self.path)
        path = path / "model.pt" if path.is_dir() else path
        if not path.is_file():
            raise DetectorError(f"detector {self.kind}: {path}: checkpoint not found "
                                f"(train one with `parksim detector train {self.kind} ...`)")
        return path

    def load(self) -> Detector:
        """The detector in eval mode; its checkpoint must hold a detector of ``kind``."""
        from ..detectors import load_detector

        model = load_detector(self.checkpoint())
        if model.kind != self.kind:
            raise DetectorError(f"detector {self.kind}: {self.path} holds a {model.kind!r} detector")
        return model


class SlotAwareConfig(BaseModel):
    """Phase 2 (paper "Training"): alignment + slot-aware losses after the photometric phase."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    iterations: int = Field(10_000, ge=0, description="slot-aware iterations (0: no phase 2)")
    lambda_align: float = Field(0.001, ge=0)
    lambda_ipm: float = Field(0.1, ge=0)
    lambda_cam: float = Field(0.1, ge=0)
    lambda_edge: float = Field(1.0, ge=0, description="ParkSim: weight of the GCN edge tubes in W_mix'")
    tau: float = Field(0.25, description="confidence threshold of the shaping function")
    temperature: float = Field(0.5, gt=0, description="T of the shaping function")
    gamma: float = Field(1.0, gt=0, description="exponent of the shaping function")
    alpha: float = Field(0.8, ge=0, le=1, description="teacher share of the corner weights")
    beta: float = Field(0.8, ge=0, le=1, description="teacher share of the edge weights")
    edge_top_k: int = Field(8, ge=0, description="K_e: edges taken from each edge-score matrix")
    edge_sigma: float = Field(1.5, gt=0, description="Gaussian tube width in BEV pixels")
    edge_samples: int = Field(32, ge=2, description="samples along each edge segment")
    align_top_k: int = Field(16, gt=0, description="ParkSim: K of the teacher's top-K region (grid cells)")
    align_temperature: float = Field(1.0, gt=0, description="ParkSim: softmax temperature of pi^s, pi^t")
    variant: Variant = Variant.FULL
    detector: DetectorRef | None = Field(None, description="the frozen detector: {kind: dmpr|gcn, path: model.pt "
                                         "or its folder}")
