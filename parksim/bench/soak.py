"""The soaks of the stability campaign, bounded in count and time, logging as they go.

``soak-train``: a long training run on a tiny synthetic scene (densification on until the end), checking
every logged step that the loss and every parameter are finite and recording the Gaussian count and RSS.
``soak-server``: a fixed number of GET /render to ``parksim serve`` on 127.0.0.1 only, the server's RSS
logged from warm-up to the end, every non-200 counted.
"""

from __future__ import annotations

import argparse
import math
import time
from pathlib import Path
from typing import Any

import numpy as np
import torch

from .common import md_table, metadata, progress, pyplot, save_figure, write_result
from .procs import rss_mib, serve_bundle
from .train import ensure_dataset

__all__ = ["soak_train", "soak_server"]


def _soak_config(config: str, steps: int) -> Any:
    """``config`` stretched to ``steps`` photometric iterations with densification running to the end."""
    from parksim.recon.config import load_config

    cfg = load_config(config)
    d = cfg.densify
    densify = d.model_copy(update={"mcmc": d.mcmc.model_copy(update={"refine_stop": steps}),
                                   "adc": d.adc.model_copy(update={"refine_stop": steps})})
    return cfg.model_copy(update={
        "photometric": cfg.photometric.model_copy(update={"iterations": steps}), "densify": densify,
        "slot_aware": cfg.slot_aware.model_copy(update={"iterations": 0}),
        "run": cfg.run.model_copy(update={"eval_every": 0, "progress": False})})


def _finite_params(trainer: Any) -> bool:
    """Whether every parameter tensor of the trainer is finite."""
    snap = trainer.params.snapshot()
    return all(bool(torch.isfinite(t).all()) for t in (snap.means, snap.quats, snap.log_scales,
                                                       snap.opacity_logits, snap.sh))


def soak_train(args: argparse.Namespace) -> Any:
    """Train ``--steps`` iterations (or until ``--max-seconds``); write ``soak_train.json/md/png``."""
    from parksim.recon.trainer import Trainer

    from ..data import DatasetReader

    data = args.dataset or ensure_dataset("tiny", args.work, None)
    cfg = _soak_config(args.config, args.steps)
    cap = cfg.densify.mcmc.cap_max if cfg.densify.strategy == "mcmc" else None
    meta = {**metadata(args.command_line), "dataset": str(data), "config": str(args.config),
            "strategy": cfg.densify.strategy, "cap_max": cap}
    trainer = Trainer(DatasetReader(data), cfg, args.work / "soak_train", log=lambda _: None)
    trainer.initialise()
    log: list[dict[str, Any]] = []
    nan_steps: list[int] = []
    start = time.monotonic()
    with progress(args.steps, "soak-train", args.quiet) as bar:
        while trainer.step < args.steps and time.monotonic() - start < args.max_seconds:
            record = trainer.iteration()
            if not math.isfinite(record["loss"]):
                nan_steps.append(trainer.step)
            if trainer.step % args.log_every == 0 or trainer.step == args.steps:
                finite = _finite_params(trainer)
                if not finite:
                    nan_steps.append(trainer.step)
                log.append({"step": trainer.step, "seconds": time.monotonic() - start, "loss": record["loss"],
                            "psnr": record["psnr"], "gaussians": record["gaussians"], "rss_mib": rss_mib(),
                            "finite": finite})
            bar.update(1)
    counts = [r["gaussians"] for r in log]
    rss = [r["rss_mib"] for r in log]
    summary = {"steps": trainer.step, "seconds": time.monotonic() - start, "nan_steps": nan_steps,
               "gaussians_max": max(counts), "gaussians_end": counts[-1], "cap_max": cap,
               "rss_first_mib": rss[0], "rss_max_mib": max(rss), "rss_end_mib": rss[-1],
               "rss_growth_second_half_mib": rss[-1] - rss[len(rss) // 2]}
    body = [f"Training `{args.config}` stretched to {args.steps} photometric iterations on `{data}` "
            f"(densification to the end, {cfg.densify.strategy}); every {args.log_every} steps: loss and parameters "
            "checked finite, Gaussian count and RSS logged.", "",
            *md_table(["steps", "seconds", "non-finite steps", "Gaussians max / end (cap)", "RSS first / max / end MiB",
                       "RSS growth over 2nd half MiB"],
                      [(summary["steps"], f"{summary['seconds']:.0f}", len(nan_steps),
                        f"{summary['gaussians_max']} / {summary['gaussians_end']} ({cap})",
                        f"{rss[0]:.0f} / {max(rss):.0f} / {rss[-1]:.0f}",
                        f"{summary['rss_growth_second_half_mib']:+.1f}")])]
    return write_result(args.out, "soak_train", meta, {"summary": summary, "log": log}, body,
                        lambda png: _plot_log(log, "step", ("gaussians", "rss_mib", "loss"), meta, png))


def _bundle_for(data: Path, n: int, out: Path, seed: int) -> Path:
    """A bundle of ``n`` garage-like Gaussians on ``data``'s surfaces with its rig (not trained)."""
    from ..bundle import Bundle, save
    from ..rig import Rig
    from .scenes import garage_scene

    return save(out, Bundle(garage_scene(data, n, seed), Rig.load(data / "rig.json"),
                            meta={"source": f"garage-like scene from {data} (not trained)", "gaussians": n}))


def soak_server(args: argparse.Namespace) -> Any:
    """``--requests`` sequential GET /render at the dataset's poses; write ``soak_server.json/md/png``."""
    import httpx

    from ..data import DatasetReader

    data = args.dataset or ensure_dataset("tiny", args.work, None)
    bundle = _bundle_for(data, args.gaussians, args.work / "soak_server_bundle", args.seed)
    poses = DatasetReader(data).poses.numpy()
    rng = np.random.default_rng(args.seed)
    meta = {**metadata(args.command_line), "dataset": str(data), "gaussians": args.gaussians}
    log: list[dict[str, Any]] = []
    statuses: dict[str, int] = {}
    start = time.monotonic()
    with serve_bundle(bundle) as server, httpx.Client(base_url=server.base, timeout=120) as client:
        client.get("/render", params={"pose": "0,0,0", "bev": "on"}).raise_for_status()   # warm-up: JIT, IPM grids
        rss_warm = rss_mib(server.pid)
        with progress(args.requests, "soak-server", args.quiet) as bar:
            for i in range(1, args.requests + 1):
                T = poses[rng.integers(len(poses))]
                pose = f"{T[0, 3]:.3f},{T[1, 3]:.3f},{math.atan2(T[1, 0], T[0, 0]):.4f}"
                code = str(client.get("/render", params={"pose": pose, "bev": "on"}).status_code)
                statuses[code] = statuses.get(code, 0) + 1
                if i % args.log_every == 0 or i == args.requests:
                    log.append({"request": i, "seconds": time.monotonic() - start, "rss_mib": rss_mib(server.pid)})
                bar.update(1)
                if time.monotonic() - start > args.max_seconds:
                    break
    summary = {"requests": sum(statuses.values()), "statuses": statuses, "rss_after_warmup_mib": rss_warm,
               "rss_end_mib": log[-1]["rss_mib"], "rss_max_mib": max(r["rss_mib"] for r in log),
               "seconds": time.monotonic() - start}
    body = [f"`parksim serve` on 127.0.0.1 with {args.gaussians:,} garage-like Gaussians on `{data}`; sequential "
            "GET /render (all cameras + BEV) at random poses of the dataset's trajectory.", "",
            *md_table(["requests", "HTTP statuses", "seconds", "RSS after warm-up / max / end MiB"],
                      [(summary["requests"], ", ".join(f"{k}: {v}" for k, v in sorted(statuses.items())),
                        f"{summary['seconds']:.0f}",
                        f"{rss_warm:.0f} / {summary['rss_max_mib']:.0f} / {summary['rss_end_mib']:.0f}")])]
    return write_result(args.out, "soak_server", meta, {"summary": summary, "log": log}, body,
                        lambda png: _plot_log(log, "request", ("rss_mib",), meta, png))


def _plot_log(log: list[dict[str, Any]], x: str, keys: tuple[str, ...], meta: dict[str, Any], png: Path) -> None:
    """One panel per logged quantity against ``x``."""
    plt = pyplot()
    fig, axes = plt.subplots(1, len(keys), figsize=(4.2 * len(keys), 3.6), squeeze=False)
    for ax, key in zip(axes[0], keys):
        ax.plot([r[x] for r in log], [r[key] for r in log], ".-")
        ax.set(xlabel=x, ylabel=key)
        ax.grid(True, alpha=0.3)
    save_figure(fig, meta, png)

