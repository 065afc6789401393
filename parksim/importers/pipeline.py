"""What every import does around its importer's ``load``: the settings all formats share (``ImportSettings``) and
``import_recording``, which loads, fits per-image poses to a rig, writes the dataset and returns the report.

``parksim import FORMAT`` builds its command line from the importer's ``Options`` and ``ImportSettings`` and
calls ``import_recording``; a Python user calls it the same way::

    from parksim.importers import ImportSettings, import_recording, importer

    ngp = importer("instant-ngp")
    report = import_recording(ngp, ngp.Options(Path("fox")), ImportSettings(Path("data/fox"), test_every=8))
"""

from __future__ import annotations

import errno
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any, Literal

from .base import CheckedOptions, Importer, importer
from .recording import Recording, write_recording

if TYPE_CHECKING:
    from ..rig import Rig

__all__ = ["ImportSettings", "import_recording"]


@dataclass(frozen=True)
class ImportSettings(CheckedOptions):
    """Options of ``parksim import FORMAT`` that every format shares."""

    output: Path = field(metadata={"help": "dataset folder to write (must not exist unless --overwrite)",
                                   "flag": "-o"})
    test_every: int = field(default=10, metadata={
        "help": "every n-th frame is a test frame when the source has no split (0: none)", "low": 0})
    scale: float | None = field(default=None, metadata={
        "help": "metric scale for per-image poses (SfM has none); default: from --rig's camera baselines, else 1",
        "low": 0, "open_low": True})
    rig: Path | None = field(default=None, metadata={
        "help": "a known rig (rig.json/yaml, or a dataset folder holding one): names the vehicle frame and gives "
                "the scale of per-image poses by its camera baselines", "metavar": "RIG"})
    rig_tolerance: tuple[float, float] | None = field(default=None, metadata={
        "help": "largest spread of a camera's pose relative to the first camera across frames for the poses to "
                "count as one fixed rig (default: 0.02,0.5)", "metavar": "M,DEG", "low": 0})
    camera_height: float | None = field(default=None, metadata={
        "help": "without --rig: how far the ground lies below the cameras' centroid (for the BEV)", "metavar": "M",
        "low": 0})
    downscale: int = field(default=1, metadata={
        "help": "store the images N times smaller (cv2.INTER_AREA) with the rig's intrinsics scaled to match "
                "(focal lengths / N, principal point by the pixel-centre rule); N must divide every camera's width "
                "and height", "metavar": "N", "low": 1})
    strict: bool = field(default=False, metadata={
        "help": "refuse the recording at its first absent, cut short, unreadable or wrong-size image instead of "
                "dropping that frame"})
    points: Literal["sfm"] | None = field(default=None, metadata={
        "help": "sfm: triangulate points3d.ply from the imported poses once the dataset is written, as `parksim "
                "points` does (SIFT, each camera's own lens, poses held fixed); replaces the recording's points"})
    overwrite: bool = field(default=False, metadata={"help": "replace an existing output folder"})
    quiet: bool = field(default=False, metadata={"help": "no progress bar"})

    def __post_init__(self) -> None:
        super().__post_init__()
        if self.rig_tolerance is not None and len(self.rig_tolerance) != 2:
            raise ValueError(f"rig_tolerance must be two numbers (metres, degrees), got {self.rig_tolerance}")


def _known_rig(path: Path | None) -> Rig | None:
    """The known rig given as a rig file or a dataset folder, or None."""
    from ..rig import Rig

    if path is None:
        return None
    return Rig.load(path / "rig.json" if path.is_dir() else path)


def _fit(rec: Recording, settings: ImportSettings, known: Rig | None) -> Recording:
    """Per-image poses fitted to a rig at metric scale; a recording with ego poses refuses the SfM settings."""
    from .rig_fit import TOLERANCE_DEG, TOLERANCE_M, fit_rig

    if rec.poses is not None or rec.camera_poses is None:
        given = [flag for flag, value in (("--rig", settings.rig), ("--scale", settings.scale),
                                          ("--rig-tolerance", settings.rig_tolerance),
                                          ("--camera-height", settings.camera_height)) if value is not None]
        if given:
            raise ValueError(f"{', '.join(given)} apply to per-image (SfM) poses fitted to a rig; this recording "
                             "has ego poses")
        return rec
    if known is not None and not set(rec.rig.names) <= set(known.names):
        raise ValueError(f"--rig {settings.rig} has cameras {known.names}; the recording has {rec.rig.names}")
    tol_m, tol_deg = settings.rig_tolerance or (TOLERANCE_M, TOLERANCE_DEG)
    fit = fit_rig(rec.camera_poses, rec.rig.names, known, settings.scale, tol_m, tol_deg, settings.camera_height)
    return fit.apply(rec)


def import_recording(chosen: Importer | str, options: Any, settings: ImportSettings) -> dict[str, Any]:
    """Import a recording as a dataset, all or nothing.

    Args:
        chosen: an importer, or its name in ``IMPORTERS``.
        options: an instance of the importer's ``Options``.
        settings: the output folder and what every format shares.

    Returns:
        The import report (also saved as ``import_report.json`` in the dataset).

    Raises:
        RecordingError: the input is unusable (one line naming the file or option at fault).
        FileExistsError: ``settings.output`` exists and ``settings.overwrite`` is off (checked before reading).
        SfmError: ``settings.points`` is ``"sfm"`` and the images give too few points (the dataset stays, without).
    """
    chosen = importer(chosen) if isinstance(chosen, str) else chosen
    if not isinstance(options, chosen.Options):
        raise TypeError(f"importer {chosen.name}: options must be {chosen.Options.__name__}, "
                        f"got {type(options).__name__}")
    if settings.output.exists() and not settings.overwrite:
        raise FileExistsError(errno.EEXIST, "already exists; pass --overwrite to replace it", str(settings.output))
    known = _known_rig(settings.rig)
    rec = _fit(chosen.load(options), settings, known)
    report = write_recording(rec, settings.output, chosen.name, settings.test_every, settings.overwrite,
                             not settings.quiet, strict=settings.strict, downscale=settings.downscale)
    if settings.points == "sfm":
        from .points_sfm import add_to_import

        report.update(add_to_import(settings.output, not settings.quiet))
    return report
