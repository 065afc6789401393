"""Dataset directories: the layout (paths, names), a writer and a lazy, validating reader."""

from .layout import DEPTH_SCALE, DatasetError, DatasetLayout, frame_name
from .reader import DatasetReader
from .writer import DatasetWriter

__all__ = ["DatasetLayout", "DatasetReader", "DatasetWriter", "DatasetError", "frame_name",
           "DEPTH_SCALE"]
