"""The importer contract, its registry, and the checks every importer's options get on construction.

An importer is an ``Importer`` subclass in its own module of this package: a ``name`` (the ``parksim import``
sub-command), a one-line ``help``, a ``description`` of its expected input, an ``Options`` dataclass and
``load(options) -> Recording``. ``Options`` fields carry ``metadata`` (``help``, ``flag``, ``positional``,
``metavar``, ``low``/``high``/``open_low``, ``nargs``; see ``parksim.commands.options``, which builds the command
line from it), so an importer never sees argparse. What every import shares (output folder, split, scale, known
rig, rig fit, writing) is ``ImportSettings`` and ``import_recording`` in ``pipeline``.

A new format is one module and one line in ``IMPORTERS`` (docs/import.md, "Add an importer"). Importer modules
are imported to build ``parksim import --help``: they import torch, cv2 and the camera models inside ``load``.
"""

from __future__ import annotations

from abc import abstractmethod
from typing import Any

from ..checked_options import CheckedOptions, check_options
from ..plugins import Plugin, instantiate
from .recording import Recording

__all__ = ["Importer", "IMPORTERS", "importer", "CheckedOptions", "check_options"]


class Importer(Plugin):
    """A recording format (see the module docstring)."""

    @abstractmethod
    def load(self, options: Any) -> Recording:
        """Read and check the input; write nothing.

        Args:
            options: an instance of ``self.Options``.

        Returns:
            The recording: rig, frames, timestamps, image sources, ego and/or per-image poses, notes for the report.
        """


IMPORTERS: dict[str, str] = {
    "nerfstudio": "nerfstudio:NerfstudioImporter",
    "instant-ngp": "instant_ngp:InstantNgpImporter",
    "colmap": "colmap:ColmapImporter",
    "rig-log": "rig_log:RigLogImporter",
}
"""``parksim import`` name -> ``module:Class`` in this package (the order of ``parksim import --help``)."""


def importer(name: str) -> Importer:
    """The registered importer ``name``, instantiated (imports its module)."""
    return instantiate(IMPORTERS, name, __package__ or "parksim.importers", Importer, "importer")
