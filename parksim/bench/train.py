"""``parksim bench train``: test PSNR against training wall-clock for shipped configs on synthetic garages.

For each (scene, config): synthesise the scene if missing, train with periodic test-frame evaluation
(every ``eval_every`` iterations; set to a fifth of the run where the config has none), evaluate the final
bundle on all test views, and plot test PSNR/SSIM against training wall-clock time. The machine may be
shared: CPU minutes (process time of the iterations) show how much of the wall-clock the run got.
"""

from __future__ import annotations

import argparse
import subprocess
import sys
from pathlib import Path
from typing import Any

from .common import md_table, metadata, progress, pyplot, save_figure, write_result

__all__ = ["run", "train_one", "ensure_dataset", "TARGET_DB"]

TARGET_DB = 28.0


def ensure_dataset(scene: str, data_root: Path, resolution: str | None) -> Path:
    """``data_root/<scene>_<width>`` (``<scene>`` without a resolution), made by ``parksim synth`` if missing."""
    data = data_root / (f"{scene}_{resolution.split('x')[0]}" if resolution else scene)
    if not data.is_dir():
        cmd = [sys.executable, "-m", "parksim.cli", "synth", scene, "-o", str(data), "--quiet"]
        subprocess.run(cmd + (["--resolution", resolution] if resolution else []), check=True)
    return data


def _config_with_eval(config: str, out: Path) -> Path:
    """``config`` with periodic evaluation switched on (a fifth of the run) and no progress bar, written to ``out``."""
    from recon.config import dump_config, load_config

    cfg = load_config(config)
    every = cfg.run.eval_every or max(1, cfg.photometric.iterations // 5)
    cfg = cfg.model_copy(update={"run": cfg.run.model_copy(update={"eval_every": every, "progress": False})})
    out.mkdir(parents=True, exist_ok=True)
    path = out / "bench_config.yaml"
    path.write_text(dump_config(cfg))
    return path


def train_one(scene: str, data: Path, config: str, out: Path) -> dict[str, Any]:
    """Train and evaluate one scene with one config; returns its curve and final numbers."""
    import os
    import shutil

    from recon.evaluate import evaluate_views, projection_of
    from recon.plots import read_metrics
    from recon.reconstruct import reconstruct
    from recon.response import CameraResponse

    from ..bundle import load
    from ..data import DatasetReader

    shutil.rmtree(out, ignore_errors=True)
    reconstruct(data, out, _config_with_eval(config, out.parent / f"{out.name}_config"), log=lambda _: None)
    records = read_metrics(out / "metrics.jsonl")
    curve = [r for r in records if r.get("test_psnr") is not None]
    bundle, reader = load(out), DatasetReader(data)
    response = CameraResponse(reader.rig, 0.0)
    response.load_dict(bundle.meta["camera_response"])
    report = evaluate_views(bundle.scene, reader, [(f, c) for f in reader.split["test"] for c in reader.rig.names],
                            response, method=projection_of(bundle))
    reached = next((r["elapsed_s"] for r in curve if r["test_psnr"] >= TARGET_DB), None)
    return {"scene": scene, "config": Path(config).stem, "curve": curve, "iterations": bundle.meta["iterations"],
            "cpu_s": max((r.get("cpu_s", 0.0) for r in records), default=0.0), "load_end": os.getloadavg()[0],
            "gaussians": bundle.meta["gaussians"], "train_s": bundle.meta["train_seconds"],
            "psnr": report.mean("psnr"), "ssim": report.mean("ssim"), "slot_psnr": report.mean("slot_psnr"),
            "reached_s": reached}


def _fmt(v: float | None, digits: int) -> str:
    return "-" if v is None else f"{v:.{digits}f}"


def run(args: argparse.Namespace) -> Any:
    """Train every (scene, config) pair in turn; write ``train.json/md/png``."""
    meta = metadata(args.command_line)
    pairs = [(s, c) for s in args.scenes for c in args.configs]
    results = []
    with progress(len(pairs), "bench train", args.quiet) as bar:
        for scene, config in pairs:
            data = ensure_dataset(scene, args.data_root, args.resolution)
            results.append(train_one(scene, data, config, args.work / f"{scene}_{Path(config).stem}"))
            bar.update(1)
    rows = [(r["scene"], r["config"], r["iterations"], r["gaussians"], f"{r['train_s'] / 60:.1f}",
             f"{r['cpu_s'] / 60:.1f}", f"{r['load_end']:.1f}", _fmt(r["psnr"], 2), _fmt(r["ssim"], 3),
             _fmt(r["slot_psnr"], 2), "-" if r["reached_s"] is None else f"{r['reached_s'] / 60:.1f}") for r in results]
    body = ["Test frames: the dataset's test split, all cameras; time axis: training wall-clock, periodic "
            "evaluation excluded.", "",
            *md_table(["scene", "config", "iterations", "Gaussians", "train min", "CPU min", "load at end",
                       "test PSNR", "test SSIM", "slot PSNR", f"min to {TARGET_DB:g} dB"], rows), "",
            "Curve points (minutes, test PSNR):", "",
            *(f"- {r['scene']} / {r['config']}: " + ", ".join(f"({c['elapsed_s'] / 60:.1f}, {c['test_psnr']:.2f})"
                                                              for c in r["curve"]) for r in results)]
    return write_result(args.out, "train", meta, {"runs": results}, body, lambda png: _plot(results, meta, png))


def _plot(results: list[dict[str, Any]], meta: dict[str, Any], png: Path) -> None:
    """Test PSNR and SSIM against training minutes, one line per (scene, config)."""
    plt = pyplot()
    fig, (a, b) = plt.subplots(1, 2, figsize=(11, 4.3))
    for r in results:
        t = [c["elapsed_s"] / 60 for c in r["curve"]]
        a.plot(t, [c["test_psnr"] for c in r["curve"]], "o-", label=f"{r['scene']} / {r['config']}")
        b.plot(t, [c["test_ssim"] for c in r["curve"]], "o-", label=f"{r['scene']} / {r['config']}")
    a.axhline(TARGET_DB, color="grey", ls="--", lw=0.8)
    a.set(xlabel="training wall-clock (min)", ylabel="test PSNR (dB)")
    b.set(xlabel="training wall-clock (min)", ylabel="test SSIM")
    for ax in (a, b):
        ax.grid(True, alpha=0.3)
        ax.legend(fontsize=8)
    save_figure(fig, meta, png)
