"""Training curves from a metrics JSONL file: loss, train/test PSNR and Gaussian count per iteration."""

from __future__ import annotations

import json
from pathlib import Path

from parksim.fileio import atomic_write

__all__ = ["read_metrics", "plot_metrics"]


def read_metrics(path: str | Path) -> list[dict]:
    """All records of a metrics JSONL file."""
    return [json.loads(line) for line in Path(path).read_text().splitlines() if line.strip()]


def _series(records: list[dict], key: str) -> tuple[list[float], list[float]]:
    rows = [(r["iteration"], r[key]) for r in records if r.get(key) is not None]
    return [x for x, _ in rows], [y for _, y in rows]


def plot_metrics(metrics: str | Path, png: str | Path) -> None:
    """Three panels: loss, PSNR (train batch and test views), Gaussian count; written atomically."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    records = read_metrics(metrics)
    fig, axes = plt.subplots(1, 3, figsize=(15, 4))
    axes[0].plot(*_series(records, "loss"), lw=0.8)
    axes[0].set(title="loss", xlabel="iteration", yscale="log")
    axes[1].plot(*_series(records, "psnr"), lw=0.8, label="train view")
    test = _series(records, "test_psnr")
    if test[0]:
        axes[1].plot(*test, "o-", label="test views")
    axes[1].set(title="PSNR (dB)", xlabel="iteration")
    axes[1].legend()
    axes[2].plot(*_series(records, "gaussians"), lw=0.8)
    axes[2].set(title="Gaussians", xlabel="iteration")
    fig.tight_layout()
    atomic_write(png, lambda p: fig.savefig(p, dpi=100))
    plt.close(fig)
