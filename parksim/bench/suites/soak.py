"""``parksim bench soak-train`` and ``soak-server``: the soaks of the stability campaign, bounded in count and time,
logging as they go.

``soak-train``: a long training run on a tiny synthetic scene (densification on until the end), checking
every logged step that the loss and every parameter are finite and recording the Gaussian count and RSS.
``soak-server``: a fixed number of GET /render to ``parksim serve`` on 127.0.0.1 only, the server's RSS
logged from warm-up to the end, every non-200 counted.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from ...checked_options import CheckedOptions
from ..common import progress, pyplot, save_figure
from ..datasets import ensure_dataset
from ..procs import rss_mib, serve_bundle
from ..record import Figure
from ..suite import Context, Outcome, Suite

__all__ = ["SoakTrainSuite", "SoakTrainOptions", "SoakServerSuite", "SoakServerOptions"]


@dataclass(frozen=True)
class SoakTrainOptions(CheckedOptions):
    """Options of ``parksim bench soak-train``."""

    steps: int = field(default=20_000, metadata={"help": "training iterations", "low": 1, "quick": 30})
    max_seconds: float = field(default=3600.0, metadata={"help": "stop after this long", "low": 0.0,
                                                         "open_low": True, "quick": 120.0})
    log_every: int = field(default=100, metadata={"help": "steps between log lines", "low": 1, "quick": 10})
    config: str = field(default="tiny", metadata={
        "help": "training config to stretch (packaged preset name or YAML path)"})
    dataset: Path | None = field(default=None, metadata={"help": "dataset (default: synth tiny under --work)"})


@dataclass(frozen=True)
class SoakServerOptions(CheckedOptions):
    """Options of ``parksim bench soak-server``."""

    requests: int = field(default=500, metadata={"help": "requests to send", "low": 1, "quick": 5})
    gaussians: int = field(default=20_000, metadata={"help": "Gaussians of the served scene", "low": 1,
                                                     "quick": 500})
    max_seconds: float = field(default=1800.0, metadata={"help": "stop after this long", "low": 0.0,
                                                         "open_low": True, "quick": 120.0})
    log_every: int = field(default=25, metadata={"help": "requests between RSS samples", "low": 1, "quick": 1})
    dataset: Path | None = field(default=None, metadata={
        "help": "dataset for the scene and poses (default: synth tiny under --work)"})


def _soak_config(config: str, steps: int) -> Any:
    """``config`` stretched to ``steps`` photometric iterations with densification running to the end."""
    from ...recon.config import load_config

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
    import torch

    snap = trainer.params.snapshot()
    return all(bool(torch.isfinite(t).all()) for t in (snap.means, snap.quats, snap.log_scales,
                                                       snap.opacity_logits, snap.sh))


class SoakTrainSuite(Suite):
    """A long training run: finiteness, Gaussian count and memory over time."""

    name = "soak-train"
    help = "long training on a tiny scene: NaN checks, Gaussian count, RSS"
    description = ("Train a tiny synthetic scene for --steps iterations with densification on to the end (bounded by "
                   "--max-seconds), logging loss, Gaussian count and RSS and checking loss and parameters are finite "
                   "every --log-every steps. Figures: steps done, RSS growth over the second half, non-finite checks "
                   "failed (goal 0).")
    Options = SoakTrainOptions

    def run(self, options: SoakTrainOptions, context: Context) -> Outcome:
        """Train ``options.steps`` iterations (or until ``options.max_seconds``), checking as it goes."""
        from ...data import DatasetReader
        from ...recon.trainer import Trainer

        data = options.dataset or ensure_dataset(context, "tiny", None)
        cfg = _soak_config(options.config, options.steps)
        cap = cfg.densify.mcmc.cap_max if cfg.densify.strategy == "mcmc" else None
        trainer = Trainer(DatasetReader(data), cfg, context.work / "soak_train", log=lambda _: None)
        trainer.initialise()
        log: list[dict[str, Any]] = []
        nan_steps: list[int] = []
        start = time.monotonic()
        with progress(options.steps, "soak-train", context.quiet) as bar:
            while trainer.step < options.steps and time.monotonic() - start < options.max_seconds:
                record = trainer.iteration()
                if not math.isfinite(record["loss"]):
                    nan_steps.append(trainer.step)
                if trainer.step % options.log_every == 0 or trainer.step == options.steps:
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
        where = f"{Path(options.config).stem} stretched to {options.steps} steps on {data.name}"
        figures = [Figure(f"{where}: steps done", trainer.step, "steps", better="higher"),
                   Figure(f"{where}: RSS growth over the second half", summary["rss_growth_second_half_mib"], "MiB"),
                   Figure(f"{where}: non-finite checks failed", len(nan_steps), "checks", goal="0")]
        data_out = {"dataset": str(data), "config": options.config, "strategy": cfg.densify.strategy,
                    "summary": summary, "log": log}
        return Outcome(figures, data_out, lambda png: _plot_log(log, "step", ("gaussians", "rss_mib", "loss"), png))


def _bundle_for(data: Path, n: int, out: Path, seed: int) -> Path:
    """A bundle of ``n`` garage-like Gaussians on ``data``'s surfaces with its rig (not trained)."""
    from ...bundle import Bundle, save
    from ...rig import Rig
    from ..scenes import garage_scene

    return save(out, Bundle(garage_scene(data, n, seed), Rig.load(data / "rig.json"),
                            meta={"source": f"garage-like scene from {data} (not trained)", "gaussians": n}))


class SoakServerSuite(Suite):
    """A fixed number of renders from a loopback server: replies and the server's memory."""

    name = "soak-server"
    help = "fixed request count to a loopback server, its memory before and after"
    description = ("Serve a garage-like bundle with `parksim serve` on 127.0.0.1 only and send --requests sequential "
                   "GET /render (all cameras + BEV) at random poses of the dataset's trajectory, logging the "
                   "server's RSS. Figures: requests sent, non-200 replies (goal 0), RSS growth after warm-up.")
    Options = SoakServerOptions

    def run(self, options: SoakServerOptions, context: Context) -> Outcome:
        """Send ``options.requests`` requests (or until ``options.max_seconds``) and sample the server's RSS."""
        import httpx
        import numpy as np

        from ...data import DatasetReader

        data = options.dataset or ensure_dataset(context, "tiny", None)
        bundle = _bundle_for(data, options.gaussians, context.work / "soak_server_bundle", context.seed)
        poses = DatasetReader(data).poses.numpy()
        rng = np.random.default_rng(context.seed)
        log: list[dict[str, Any]] = []
        statuses: dict[str, int] = {}
        start = time.monotonic()
        with serve_bundle(bundle) as server, httpx.Client(base_url=server.base, timeout=120) as client:
            client.get("/render", params={"pose": "0,0,0", "bev": "on"}).raise_for_status()   # warm-up: JIT, IPM
            rss_warm = rss_mib(server.pid)
            with progress(options.requests, "soak-server", context.quiet) as bar:
                for i in range(1, options.requests + 1):
                    T = poses[rng.integers(len(poses))]
                    pose = f"{T[0, 3]:.3f},{T[1, 3]:.3f},{math.atan2(T[1, 0], T[0, 0]):.4f}"
                    code = str(client.get("/render", params={"pose": pose, "bev": "on"}).status_code)
                    statuses[code] = statuses.get(code, 0) + 1
                    if i % options.log_every == 0 or i == options.requests:
                        log.append({"request": i, "seconds": time.monotonic() - start,
                                    "rss_mib": rss_mib(server.pid)})
                    bar.update(1)
                    if time.monotonic() - start > options.max_seconds:
                        break
        requests = sum(statuses.values())
        summary = {"requests": requests, "statuses": statuses, "rss_after_warmup_mib": rss_warm,
                   "rss_end_mib": log[-1]["rss_mib"], "rss_max_mib": max(r["rss_mib"] for r in log),
                   "seconds": time.monotonic() - start}
        where = f"{options.requests} renders of {options.gaussians:,} Gaussians, all cameras + BEV"
        figures = [Figure(f"{where}: requests sent", requests, "requests", better="higher"),
                   Figure(f"{where}: non-200 replies", requests - statuses.get("200", 0), "replies", goal="0"),
                   Figure(f"{where}: server RSS growth after warm-up", summary["rss_end_mib"] - rss_warm, "MiB")]
        data_out = {"dataset": str(data), "gaussians": options.gaussians, "summary": summary, "log": log}
        return Outcome(figures, data_out, lambda png: _plot_log(log, "request", ("rss_mib",), png))


def _plot_log(log: list[dict[str, Any]], x: str, keys: tuple[str, ...], png: Path) -> None:
    """One panel per logged quantity against ``x``."""
    plt = pyplot()
    fig, axes = plt.subplots(1, len(keys), figsize=(4.2 * len(keys), 3.6), squeeze=False)
    for ax, key in zip(axes[0], keys):
        ax.plot([r[x] for r in log], [r[key] for r in log], ".-")
        ax.set(xlabel=x, ylabel=key)
        ax.grid(True, alpha=0.3)
    save_figure(fig, png)
