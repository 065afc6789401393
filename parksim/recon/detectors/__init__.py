"""Parking-slot detectors (DMPR-PS-style and GCN-Parking-style) trained on ground-truth BEVs.

They serve ParkGaussian twice: frozen, as teacher/student inside the slot-aware losses
(``confidence`` / ``edges``, differentiable with respect to the input BEV), and as the
downstream evaluation of reconstructed BEVs (``detect`` + ``evaluate``).
"""

from .backbone import PointMaps
from .base import Detector
from .decode import DecodeOptions, Detections, MarkingPoint, Slot
from .dmpr import DMPRDetector
from .gcn import GCNDetector
from .labels_ps2 import LabelError, SlotLabels, read_ps2_labels
from .registry import DETECTORS, load_detector

__all__ = ["Detector", "DMPRDetector", "GCNDetector", "DETECTORS", "PointMaps", "load_detector", "Detections",
           "DecodeOptions", "MarkingPoint", "Slot", "SlotLabels", "LabelError", "read_ps2_labels"]
