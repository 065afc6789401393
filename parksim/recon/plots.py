"""Plots: training curves from a metrics JSONL file (loss, train/test PSNR, Gaussian count per iteration) and
rendering quality off the recorded path (``parksim eval`` with an off-path split)."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

from parksim.fileio import atomic_write

__all__ = ["read_metrics", "plot_metrics", "plot_offpath"]


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


def _offset_curve(ax: Any, off: dict[str, Any], kind: str, unit: str) -> None:
    """PSNR (solid) and slot PSNR (dashed) against the offset size of ``kind``, starting on the path at 0."""
    ref = off["on_path"]
    groups = [g for g in off["groups"] if g["kind"] == kind]
    x = [0.0] + [g["offset"] for g in groups]
    for key, style, name in (("psnr", "o-", "whole image"), ("slot_psnr", "s--", "slot regions")):
        points = [(xi, s[key]) for xi, s in zip(x, [ref, *groups]) if s[key] is not None]
        line = ax.plot([p[0] for p in points], [p[1] for p in points], style, label=name)[0]
        if ref[key] is not None:
            ax.axhline(ref[key], color=line.get_color(), ls=":", lw=0.8)
    ax.set(xlabel=f"{kind} offset from the recorded path, either side ({unit})", ylabel="PSNR (dB)",
           title=f"{kind} offset (dotted: on the recorded path)")
    ax.set_xticks(x)
    ax.grid(alpha=0.3)
    ax.legend()


def plot_offpath(off: dict[str, Any], png: str | Path) -> None:
    """PSNR against lateral offset, against yaw offset, and along parking manoeuvres (per view, against the
    distance from the path); ``off`` is eval.json's ``offpath``. Written atomically."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 3, figsize=(16, 4.5))
    _offset_curve(axes[0], off, "lateral", "m")
    _offset_curve(axes[1], off, "yaw", "deg")
    ax = axes[2]
    ref = off["on_path"]
    manoeuvre = [v for v in off["views"] if v["kind"] == "manoeuvre"]
    ax.plot([v["offset"] for v in manoeuvre], [v["psnr"] for v in manoeuvre], "o", alpha=0.6, label="whole image")
    slots = [v for v in manoeuvre if v.get("slot_psnr") is not None]
    ax.plot([v["offset"] for v in slots], [v["slot_psnr"] for v in slots], "s", mfc="none", alpha=0.6,
            label="slot regions")
    if ref["psnr"] is not None:
        ax.axhline(ref["psnr"], color="C0", ls=":", lw=0.8)
    if ref["slot_psnr"] is not None:
        ax.axhline(ref["slot_psnr"], color="C1", ls=":", lw=0.8)
    ax.set(xlabel="distance of the ego from the recorded path (m)", ylabel="PSNR (dB)",
           title="parking manoeuvres into slots (one point per view)")
    ax.grid(alpha=0.3)
    if manoeuvre:
        ax.legend()
    fig.tight_layout()
    atomic_write(png, lambda p: fig.savefig(p, dpi=100))
    plt.close(fig)
