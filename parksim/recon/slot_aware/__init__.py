"""ParkGaussian's slot-aware phase: detector-guided weights and losses on top of the photometric fit."""

from .config import DetectorError, DetectorRef, SlotAwareConfig
from .losses import align_loss, cam_loss, ipm_loss, total_loss, weighted_l1
from .step import SlotAwareStep, SlotAwareTerms, SlotFrame, frame_has_slots, freeze
from .variants import Variant, VariantSpec, spec_of
from .weights import edge_tubes, edge_weights, mix, shape_confidence, top_edges, upsample

__all__ = ["SlotAwareConfig", "DetectorRef", "DetectorError", "SlotAwareStep", "SlotAwareTerms", "SlotFrame",
           "Variant", "VariantSpec", "spec_of",
           "align_loss", "cam_loss", "ipm_loss", "total_loss", "weighted_l1", "freeze", "frame_has_slots",
           "edge_tubes", "edge_weights", "mix", "shape_confidence", "top_edges", "upsample"]
