"""``parksim bench train``: test PSNR against training time for shipped configs on synthetic garages.

For each (scene, config): synthesise the scene (and its off-path split) if missing, train with periodic test-frame
evaluation (every ``eval_every`` iterations; set to a fifth of the run where the config has none), evaluate the
final bundle as ``parksim eval`` does (recorded test views, slot regions, the off-path split grouped by offset), and
plot test PSNR/SSIM against training CPU minutes (process time of the iterations: on a shared machine, or for a
run paused and resumed, wall-clock says more about the other jobs than about the run; the record keeps both) and
PSNR against the offset from the recorded path. Runs live in ``WORK/<scene>_<config>``, so they can be trained one
at a time (``parksim reconstruct``) and tabulated together with ``--reuse`` or ``--only-finished``.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from ...checked_options import CheckedOptions
from ..bundles import finished
from ..common import progress, pyplot, save_figure
from ..datasets import synth_dataset
from ..record import Figure
from ..suite import Context, Outcome, Suite

__all__ = ["TrainSuite", "TrainOptions", "train_one", "TARGET_DB", "PAPER_ROWS"]

TARGET_DB = 28.0
"""Test PSNR a run should reach (the figures' goal; minutes to it are recorded per run)."""

DATA_ROOT = Path("data")
"""Where a full run finds or synthesises its datasets, relative to the working folder (``--data-root``)."""

PAPER_ROWS = {"cpu_30min": "UT, photometric only (3DGUT row)",
              "cpu_30min_ewa": "Jacobian / EWA projection (FisheyeGS row)"}
"""The paper's Table 1 row each 30-minute preset stands for (docs/training.md)."""


@dataclass(frozen=True)
class TrainOptions(CheckedOptions):
    """Options of ``parksim bench train``."""

    scenes: list[str] = field(default_factory=lambda: ["scene1"], metadata={
        "help": "synth presets to train", "quick": ["tiny"]})
    configs: list[str] = field(default_factory=lambda: ["cpu_fast", "demo"], metadata={
        "help": "training configs (packaged preset names or YAML paths)", "quick": ["tiny"]})
    resolution: str = field(default="320x240", metadata={
        "help": "synth resolution WxH, or native: the preset's own (640x480; the 30-minute presets train at native)",
        "quick": "native"})
    data_root: Path | None = field(default=None, metadata={
        "help": f"where datasets are found or synthesised (default: {DATA_ROOT} in the working folder; "
                "--quick: WORK/data)"})
    reuse: bool = field(default=False, metadata={
        "help": "take finished runs in --work (WORK/<scene>_<config>) and their eval/eval.json as they are instead "
                "of retraining; pairs without one are trained"})
    only_finished: bool = field(default=False, metadata={
        "help": "leave out the pairs with no finished run in --work (listed as not run); implies --reuse"})


def _config_with_eval(config: str, out: Path) -> Path:
    """``config`` with periodic evaluation switched on (a fifth of the run) and no progress bar, written to ``out``."""
    from ...recon.config import dump_config, load_config

    cfg = load_config(config)
    every = cfg.run.eval_every or max(1, cfg.photometric.iterations // 5)
    cfg = cfg.model_copy(update={"run": cfg.run.model_copy(update={"eval_every": every, "progress": False})})
    out.mkdir(parents=True, exist_ok=True)
    path = out / "bench_config.yaml"
    path.write_text(dump_config(cfg))
    return path


def _ensure_offpath(data: Path) -> None:
    """Write the dataset's off-path split (``parksim offpath``) when a synthetic dataset has none."""
    from ...synth.offpath import OFFPATH_DIR, OFFPATH_FILE, write_offpath

    if not (data / OFFPATH_DIR / OFFPATH_FILE).is_file():
        write_offpath(data)


def _evaluation(out: Path, data: Path, reuse: bool) -> dict[str, Any]:
    """``parksim eval``'s result for the bundle in ``out``: read from ``out/eval/eval.json`` when reusing one made on
    this dataset (and, if the dataset has an off-path split, with it), else computed and written there."""
    import json

    from ...recon.evaluate import evaluate_bundle
    from ...synth.offpath import OFFPATH_DIR, OFFPATH_FILE

    saved = out / "eval" / "eval.json"
    if reuse and saved.is_file():
        result: dict[str, Any] = json.loads(saved.read_text())
        wants_offpath = (data / OFFPATH_DIR / OFFPATH_FILE).is_file()
        if Path(result["dataset"]).resolve() == data.resolve() and (result.get("offpath") or not wants_offpath):
            return result
    return evaluate_bundle(out, data, out / "eval")


def train_one(scene: str, data: Path, config: str, out: Path, reuse: bool = False) -> dict[str, Any]:
    """Train and evaluate one scene with one config.

    Args:
        scene: the scene's name (recorded).
        data: its dataset folder.
        config: a packaged preset name or a YAML path.
        out: the run folder.
        reuse: take a finished run in ``out`` (and its evaluation) as it is instead of redoing it.

    Returns:
        The run's test curve, final numbers (``parksim eval``'s overall scores), time and CPU seconds to
        ``TARGET_DB``, and off-path groups.
    """
    import os
    import shutil

    from ...bundle import load
    from ...recon.plots import read_metrics
    from ...recon.reconstruct import reconstruct

    if not (reuse and finished(out)):
        shutil.rmtree(out, ignore_errors=True)
        reconstruct(data, out, _config_with_eval(config, out.parent / f"{out.name}_config"), log=lambda _: None)
    records = read_metrics(out / "metrics.jsonl")
    curve = [r for r in records if r.get("test_psnr") is not None]
    meta = load(out).meta
    result = _evaluation(out, data, reuse)
    reached = next((r for r in curve if r["test_psnr"] >= TARGET_DB), None)
    stem = Path(config).stem
    return {"scene": scene, "config": stem, "paper_row": PAPER_ROWS.get(stem), "curve": curve,
            "iterations": meta["iterations"], "cpu_s": max((r.get("cpu_s", 0.0) for r in records), default=0.0),
            "load_end": os.getloadavg()[0], "gaussians": meta["gaussians"], "train_s": meta["train_seconds"],
            **result["overall"], "reached_s": reached and reached["elapsed_s"],
            "reached_cpu_s": reached and reached["cpu_s"], "offpath": result.get("offpath")}


def _run_dir(work: Path, scene: str, config: str) -> Path:
    """Where the run of ``config`` on ``scene`` lives: ``work/<scene>_<config stem>``."""
    return work / f"{scene}_{Path(config).stem}"


class TrainSuite(Suite):
    """Test PSNR against training time, per (scene, config)."""

    name = "train"
    help = "test PSNR against training CPU minutes for the shipped configs"
    description = ("Synthesise each scene if missing (with its off-path split), train it with each config (periodic "
                   "test evaluation on), evaluate the bundle as `parksim eval` does, plot test PSNR/SSIM against "
                   "training CPU minutes and PSNR against the offset from the path. Figures: per (scene, config) "
                   f"the final test PSNR (goal >= {TARGET_DB:g} dB) and the training CPU minutes.")
    Options = TrainOptions

    def run(self, options: TrainOptions, context: Context) -> Outcome:
        """Train (or, with ``reuse``, take) every (scene, config) pair in turn."""
        root = options.data_root or (context.work / "data" if context.quick else DATA_ROOT)
        reuse = options.reuse or options.only_finished
        pairs = [(s, c) for s in options.scenes for c in options.configs]
        skipped = [p for p in pairs if options.only_finished and not finished(_run_dir(context.work, *p))]
        pairs = [p for p in pairs if p not in skipped]
        results = []
        with progress(len(pairs), "bench train", context.quiet) as bar:
            for scene, config in pairs:
                dataset = synth_dataset(scene, root, options.resolution)
                _ensure_offpath(dataset)
                results.append(train_one(scene, dataset, config, _run_dir(context.work, scene, config), reuse))
                bar.update(1)
        figures: list[Figure] = []
        for r in results:
            where = f"{r['scene']} ({options.resolution}), {r['config']}"
            figures += [Figure(f"{where}: final test PSNR", r["psnr"], "dB", goal=f">= {TARGET_DB:g} dB",
                               better="higher"),
                        Figure(f"{where}: training CPU time", r["cpu_s"] / 60, "min")]
        data = {"target_db": TARGET_DB, "data_root": str(root), "runs": results,
                "not_run": [{"scene": s, "config": Path(c).stem} for s, c in skipped]}
        return Outcome(figures, data, lambda png: _plot(results, png))


def _offset_points(r: dict[str, Any], kind: str) -> tuple[list[float], list[float]]:
    """(offset, PSNR) of one run's groups of ``kind``, with the on-path reference at 0."""
    off = r["offpath"]
    points = [(0.0, off["on_path"]["psnr"])] + [(g["offset"], g["psnr"]) for g in off["groups"] if g["kind"] == kind]
    return [p[0] for p in points], [p[1] for p in points]


def _plot(results: list[dict[str, Any]], png: Path) -> None:
    """Test PSNR and SSIM against training CPU minutes, and PSNR against the lateral and yaw offset from the recorded
    path, one line per (scene, config)."""
    plt = pyplot()
    fig, ((a, b), (c, d)) = plt.subplots(2, 2, figsize=(11, 8.6))
    for r in results:
        label = f"{r['scene']} / {r['config']}"
        t = [p["cpu_s"] / 60 for p in r["curve"]]
        a.plot(t, [p["test_psnr"] for p in r["curve"]], "o-", label=label)
        b.plot(t, [p["test_ssim"] for p in r["curve"]], "o-", label=label)
        if r["offpath"]:
            c.plot(*_offset_points(r, "lateral"), "o-", label=label)
            d.plot(*_offset_points(r, "yaw"), "o-", label=label)
    a.axhline(TARGET_DB, color="grey", ls="--", lw=0.8)
    a.set(xlabel="training CPU (min)", ylabel="test PSNR (dB)")
    b.set(xlabel="training CPU (min)", ylabel="test SSIM")
    c.set(xlabel="lateral offset from the recorded path, both sides (m)", ylabel="PSNR (dB)")
    d.set(xlabel="yaw offset from the recorded heading, both ways (deg)", ylabel="PSNR (dB)")
    for ax in (a, b, c, d):
        ax.grid(True, alpha=0.3)
        if ax.lines:
            ax.legend(fontsize=8)
    save_figure(fig, png)
