"""Pydantic model of the slot-aware phase (``slot_aware:`` in a training config); defaults are the paper's.

Values not given by the paper (marked "ParkSim" below): ``lambda_edge``, the alignment region size
``align_top_k`` and the alignment softmax temperature ``align_temperature``.
"""

from __future__ import annotations

from pydantic import BaseModel, ConfigDict, Field

from .variants import Variant

__all__ = ["SlotAwareConfig"]


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
    detector: str | None = Field(None, description="frozen detector checkpoint (model.pt or its folder)")
