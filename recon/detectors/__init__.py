"""Parking-slot detectors (DMPR-PS-style and GCN-Parking-style) trained on ground-truth BEVs.

They serve ParkGaussian twice: frozen, as teacher/student inside the slot-aware losses
(``confidence`` / ``edges``, differentiable with respect to the input BEV), and as the
downstream evaluation of reconstructed BEVs (``detect`` + ``evaluate``).
"""

from .decode import Detections, DecodeOptions, MarkingPoint, Slot
from .dmpr import DMPRDetector, PointMaps, load_detector
from .gcn import GCNDetector
from .labels_ps2 import LabelError, SlotLabels, read_ps2_labels

__all__ = ["DMPRDetector", "GCNDetector", "PointMaps", "load_detector", "Detections", "DecodeOptions",
           "MarkingPoint", "Slot", "SlotLabels", "LabelError", "read_ps2_labels"]
