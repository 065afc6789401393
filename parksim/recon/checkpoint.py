"""Training checkpoints: everything a resumed run needs to continue exactly where a killed one stopped.

One file, ``checkpoints/last.pt``, replaced atomically; it holds the parameters, Adam moments,
the strategy's and camera response's state (and the per-image exposure corrections' when learned), the RNG state,
the iteration and the wall-clock and CPU time spent.
Its tensors are always CPU tensors, whatever device the run trains on, so a checkpoint written on a GPU resumes on
the CPU and the other way round (the trainer moves them to its device).
"""

from __future__ import annotations

import pickle
import warnings
import zipfile
from pathlib import Path
from typing import Any

import torch

from parksim.fileio import atomic_write

__all__ = ["CheckpointError", "save_checkpoint", "load_checkpoint", "checkpoint_path", "tensors_to", "FORMAT"]

FORMAT = "parksim-recon-checkpoint/1"
_REQUIRED = ("format", "iteration", "params", "optimizer", "response", "strategy", "rng", "config", "elapsed", "cpu")


class CheckpointError(ValueError):
    """A run's saved state (its checkpoint, or the metrics log a resume continues) is missing, truncated, corrupt
    or from another format; the message names the file."""


def checkpoint_path(out_dir: str | Path) -> Path:
    """Where a run in ``out_dir`` keeps its checkpoint."""
    return Path(out_dir) / "checkpoints" / "last.pt"


def tensors_to(value: Any, device: torch.device) -> Any:
    """``value`` with every tensor inside it (dicts, lists, tuples) moved to ``device`` (ones already there are kept).

    Args:
        value: a state (``Trainer.state()``, a strategy's ``state_dict()``) or any plain value.
        device: where the tensors go.

    Returns:
        The same structure.
    """
    if isinstance(value, torch.Tensor):
        return value.to(device)
    if isinstance(value, dict):
        return {k: tensors_to(v, device) for k, v in value.items()}
    if type(value) in (list, tuple):   # exactly: a named tuple would not rebuild from one iterable
        return type(value)(tensors_to(v, device) for v in value)
    return value


def save_checkpoint(path: str | Path, state: dict[str, Any]) -> None:
    """Write ``state`` (must hold the required keys) atomically, its tensors moved to the CPU."""
    missing = [k for k in _REQUIRED if k not in state and k != "format"]
    if missing:
        raise ValueError(f"checkpoint state lacks {missing}")
    atomic_write(path, lambda p: torch.save({"format": FORMAT, **tensors_to(state, torch.device("cpu"))}, p))


def load_checkpoint(path: str | Path) -> dict[str, Any]:
    """Read and check a checkpoint (tensors only: no code is unpickled)."""
    path = Path(path)
    if not path.is_file():
        raise CheckpointError(f"{path}: checkpoint not found")
    try:
        with warnings.catch_warnings():   # torch warns about legacy (pickle) files before refusing them: one line
            warnings.simplefilter("ignore")
            state = torch.load(path, map_location="cpu", weights_only=True)
    except pickle.UnpicklingError:
        raise CheckpointError(f"{path}: a pickled object, not a {FORMAT} checkpoint (refused: only tensors and "
                              "plain values are loaded)") from None
    except (RuntimeError, EOFError, OSError, zipfile.BadZipFile, ValueError) as e:
        first = str(e).strip().splitlines()[0][:200] if str(e).strip() else ""
        raise CheckpointError(f"{path}: corrupt or truncated checkpoint ({type(e).__name__}: {first})") from None
    if not isinstance(state, dict) or state.get("format") != FORMAT:
        found = state.get("format") if isinstance(state, dict) else type(state).__name__
        raise CheckpointError(f"{path}: not a {FORMAT} checkpoint (found {found!r})")
    missing = [k for k in _REQUIRED if k not in state]
    if missing:
        raise CheckpointError(f"{path}: checkpoint lacks {missing}")
    return state
