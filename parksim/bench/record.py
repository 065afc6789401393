"""A benchmark record: one run of one suite as data (JSON), the only thing ``parksim bench report`` reads.

A record holds what was run (command, options, commit, date), where (host, CPU model, cores, GPU, load at the
start and end, library versions), and its figures: each a value with its unit, beside the reference measured
in the same run where there is one. Records live at ``RESULTS/<suite>/<stamp>-<commit>.json`` (a plot, if any,
beside it as ``.png``); they are written once and never edited.
"""

from __future__ import annotations

import datetime
import json
import math
import os
import platform
import subprocess
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any, Literal

__all__ = ["Figure", "Machine", "Record", "this_machine", "current_commit", "utc_now", "read_record",
           "write_record", "records_in", "SCHEMA"]

SCHEMA = 1
"""Version of the record layout; ``read_record`` refuses others."""


@dataclass(frozen=True)
class Figure:
    """One measured figure against its target.

    Attributes:
        target: what is measured, stable across runs (the dashboard's row key), e.g.
            ``"4 views + BEV at 640x480, 2e5 Gaussians: latency"``.
        value: the figure (wall time for timings).
        unit: ``ms``, ``dB``, ``x``, ``MiB``, ``%``, ``count``, ...
        cpu: process CPU time in ``unit`` beside a wall-time ``value`` (the machines are shared), else None.
        reference: the same quantity measured in the same run for the reference, else None.
        reference_label: what the reference is (``"gsplat 3DGUT"``, ``"commit 5ebf0ca"``, ``"UT"``).
        reference_cpu: the reference's process CPU time, else None.
        goal: the target to meet, as text (``"<= 250 ms"``), else None.
        better: whether lower or higher values are better (for the ratio's reading).
    """

    target: str
    value: float
    unit: str
    cpu: float | None = None
    reference: float | None = None
    reference_label: str | None = None
    reference_cpu: float | None = None
    goal: str | None = None
    better: Literal["lower", "higher"] = "lower"

    def __post_init__(self) -> None:
        if not self.target or not self.unit:
            raise ValueError(f"a figure needs a target and a unit, got {self.target!r}, {self.unit!r}")
        if (self.reference is None) != (self.reference_label is None):
            raise ValueError(f"{self.target}: a reference needs its label and a label its reference")


@dataclass(frozen=True)
class Machine:
    """Where a record was measured: host name, CPU model, logical cores, GPU (name, or None)."""

    host: str
    cpu_model: str
    cores: int
    gpu: str | None = None

    @property
    def label(self) -> str:
        """One line for tables: ``CPU model, N cores`` (+ GPU)."""
        return f"{self.cpu_model}, {self.cores} cores" + (f", {self.gpu}" if self.gpu else "")


@dataclass
class Record:
    """One run of one suite (see the module docstring); ``legacy`` records were converted from old Markdown."""

    suite: str
    command: str
    commit: str
    date: str
    machine: Machine
    figures: list[Figure]
    options: dict[str, Any] = field(default_factory=dict)
    load: dict[str, list[float]] = field(default_factory=dict)
    versions: dict[str, str] = field(default_factory=dict)
    data: dict[str, Any] = field(default_factory=dict)
    plot: str | None = None
    note: str | None = None
    legacy: bool = False
    details: str | None = None
    schema: int = SCHEMA

    def to_json(self) -> str:
        """Indented JSON with a trailing newline (non-finite floats as strings, so any JSON reader takes it)."""
        return json.dumps(_jsonable(asdict(self)), indent=1, ensure_ascii=False) + "\n"


def _jsonable(v: Any) -> Any:
    if isinstance(v, float) and not math.isfinite(v):
        return "nan" if math.isnan(v) else ("inf" if v > 0 else "-inf")
    if isinstance(v, dict):
        return {str(k): _jsonable(x) for k, x in v.items()}
    if isinstance(v, (list, tuple)):
        return [_jsonable(x) for x in v]
    if isinstance(v, Path):
        return str(v)
    if hasattr(v, "__dataclass_fields__"):
        return _jsonable(asdict(v))
    if hasattr(v, "item") and callable(v.item):   # numpy / torch scalars
        return _jsonable(v.item())
    return v


def _number(v: Any) -> float | None:
    """A JSON value back to float (``"inf"`` etc. included), None stays None."""
    return None if v is None else float(v)


def read_record(path: Path) -> Record:
    """Load a record written by ``write_record``.

    Args:
        path: a ``.json`` record.

    Returns:
        The record. ``ValueError`` names the file when it is not a record of this schema.
    """
    try:
        raw = json.loads(path.read_text())
        if raw.get("schema") != SCHEMA:
            raise ValueError(f"schema {raw.get('schema')!r}, expected {SCHEMA}")
        figures = [Figure(**{**f, **{k: _number(f.get(k)) for k in ("value", "cpu", "reference", "reference_cpu")}})
                   for f in raw.pop("figures")]
        machine = Machine(**raw.pop("machine"))
        return Record(figures=figures, machine=machine, **raw)
    except (OSError, ValueError, TypeError, KeyError) as e:
        raise ValueError(f"{path}: not a benchmark record ({e})") from None


def write_record(record: Record, results: Path, plot: Any = None) -> Path:
    """Write ``record`` as ``results/<suite>/<stamp>-<commit>.json`` (and its plot beside it).

    Args:
        record: the run.
        results: the results folder (``benchmarks/results`` in the repository).
        plot: ``plot(png_path)`` draws the run's figure, or None.

    Returns:
        The record's path. The file is written to a temporary name and renamed, so a reader never sees half.
    """
    stamp = record.date.replace("-", "").replace(":", "").removesuffix("+0000").removesuffix("Z")
    folder = results / record.suite
    folder.mkdir(parents=True, exist_ok=True)
    path = folder / f"{stamp}-{record.commit.replace('+', '_')}.json"
    if plot is not None:
        png = path.with_suffix(".png")
        plot(png)
        record.plot = png.name
    tmp = path.with_suffix(".json.tmp")
    tmp.write_text(record.to_json())
    os.replace(tmp, path)
    return path


def records_in(results: Path) -> list[tuple[Path, Record]]:
    """Every record under ``results`` (``<suite>/*.json``), oldest first (by date, then path)."""
    found = [(p, read_record(p)) for p in sorted(results.glob("*/*.json"))]
    return sorted(found, key=lambda pr: (pr[1].date, str(pr[0])))


def utc_now() -> str:
    """The current UTC time, to the second, ISO 8601 (``2026-11-27T16:30:00+00:00``)."""
    return datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="seconds")


def current_commit(where: Path | None = None) -> str:
    """Short commit of the git work tree at ``where`` (default: the working folder), ``+dirty`` when its tracked
    files differ from it, ``unknown`` outside git. The installed package never looks for its own checkout."""
    cwd = where or Path.cwd()
    try:
        head = subprocess.run(["git", "rev-parse", "--short", "HEAD"], cwd=cwd, capture_output=True, text=True,
                              check=True).stdout.strip()
        dirty = subprocess.run(["git", "diff", "--quiet", "HEAD", "--", "parksim"], cwd=cwd,
                               capture_output=True).returncode != 0
    except (OSError, subprocess.CalledProcessError):
        return "unknown"
    return head + ("+dirty" if dirty else "")


def _cpu_model() -> str:
    cpuinfo = Path("/proc/cpuinfo")
    lines = cpuinfo.read_text().splitlines() if cpuinfo.is_file() else []
    return next((ln.split(":", 1)[1].strip() for ln in lines if ln.startswith("model name")),
                platform.processor() or platform.machine())


def _gpu_name() -> str | None:
    """The first CUDA device's name when torch is loaded and sees one (never imports torch itself)."""
    import sys

    torch = sys.modules.get("torch")
    if torch is None or not torch.cuda.is_available():
        return None
    return str(torch.cuda.get_device_name(0))


def this_machine() -> Machine:
    """The machine this process runs on."""
    return Machine(platform.node(), _cpu_model(), os.cpu_count() or 1, _gpu_name())
