"""Importers: bring a recording in as a ParkSim dataset. One module per format, each an ``Importer`` (``base``)
returning a ``Recording`` that ``write_recording`` writes in the one dataset layout (the way nerfstudio keeps its
dataparsers); ``import_recording`` (``pipeline``) is the whole import, for the command line and for Python.
"""

from __future__ import annotations

from .base import IMPORTERS, CheckedOptions, Importer, check_options, importer
from .pipeline import ImportSettings, import_recording
from .recording import Dropped, Recording, RecordingError, write_recording

__all__ = ["Importer", "IMPORTERS", "importer", "ImportSettings", "import_recording", "CheckedOptions",
           "check_options", "Recording", "RecordingError", "Dropped", "write_recording"]
