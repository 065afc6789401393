"""Dataset directories: the layout (paths, names), a writer and a lazy, validating reader."""

from .layout import DEPTH_SCALE, DatasetError, DatasetLayout, frame_name
from .reader import DatasetReader
from .writer import DatasetWriter, atomic_dir

__all__ = ["DatasetLayout", "DatasetReader", "DatasetWriter", "DatasetError", "atomic_dir", "frame_name",
           "DEPTH_SCALE"]
