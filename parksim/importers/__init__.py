"""Importers: bring a recording in as a ParkSim dataset. One module per format, all returning a ``Recording``
that ``write_recording`` writes in the one dataset layout (the way nerfstudio keeps its dataparsers).

A module in ``IMPORTERS`` defines ``HELP`` (one line), ``DESCRIPTION`` (its expected input),
``add_arguments(parser)`` (its options; cheap, no heavy imports) and ``load(args) -> Recording``.
A new format is one new module and one line here. Importer modules are imported to build ``parksim import --help``,
so they import torch, cv2 and the camera models inside ``load``, not at their top.
"""

from __future__ import annotations

import importlib
from types import ModuleType

from .recording import Dropped, Recording, RecordingError, write_recording

__all__ = ["IMPORTERS", "importer", "Recording", "RecordingError", "Dropped", "write_recording"]

IMPORTERS: dict[str, str] = {"nerfstudio": "nerfstudio", "colmap": "colmap", "rig-log": "rig_log"}
"""CLI name -> module name in this package."""


def importer(name: str) -> ModuleType:
    """The importer module registered as ``name``."""
    if name not in IMPORTERS:
        raise ValueError(f"unknown importer {name!r}; known: {sorted(IMPORTERS)}")
    return importlib.import_module(f"{__name__}.{IMPORTERS[name]}")
