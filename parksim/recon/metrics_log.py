"""A run's metrics log (``metrics.jsonl``, one JSON record per line): append, and cut back on resume.

A run killed mid-write (or on a full disk) leaves a torn last line; a resume drops it rather than refuse to go on.
"""

from __future__ import annotations

import json
import sys
from pathlib import Path
from typing import Any

from parksim.fileio import atomic_write

from .checkpoint import CheckpointError

__all__ = ["METRICS_FILE", "append_record", "cut_back"]

METRICS_FILE = "metrics.jsonl"


def append_record(path: Path, record: dict[str, Any]) -> None:
    """Add one record as a line."""
    with open(path, "a") as f:
        f.write(json.dumps(record) + "\n")


def _iteration(path: Path, number: int, line: str) -> int | None:
    """The record's iteration, or None when the line is not JSON (a torn write)."""
    try:
        record = json.loads(line)
    except json.JSONDecodeError:
        return None
    if not isinstance(record, dict) or not isinstance(record.get("iteration"), int):
        raise CheckpointError(f"{path} line {number}: a metrics record without an integer 'iteration'")
    return record["iteration"]


def cut_back(path: Path, step: int) -> None:
    """Keep the records up to ``step`` (the checkpoint's), replacing the file atomically.

    A torn last line is dropped with a note on stderr; a line that is not JSON anywhere else is a CheckpointError.
    """
    if not path.is_file():
        return
    numbered = [(n, ln) for n, ln in enumerate(path.read_text(errors="replace").split("\n"), 1) if ln.strip()]
    kept = []
    for i, (number, line) in enumerate(numbered):
        iteration = _iteration(path, number, line)
        if iteration is None and i < len(numbered) - 1:
            raise CheckpointError(f"{path} line {number}: not a JSON record (only a torn last line can be dropped)")
        if iteration is None:
            print(f"{path}: dropped its torn last line {number} (the run was killed while writing it)", file=sys.stderr)
        elif iteration <= step:
            kept.append(line)
    atomic_write(path, lambda p: p.write_text("".join(ln + "\n" for ln in kept)))
