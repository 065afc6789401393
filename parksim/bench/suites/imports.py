"""``parksim bench import``: what an MP4 rig log costs in reconstruction quality, and how long rig-log imports take.

Quality: the tiny garage (``parksim synth tiny``) reconstructed with the tiny schedule stretched to
``--iterations`` (densification from 10 % to 80 % of the run, seed 0; both runs start from ``--random-init`` random
Gaussians, since a rig log has no point cloud, with pose refinement off, since the log carries the synth's exact
poses), once from the dataset and once after a round trip through a rig log of mp4v videos
(``parksim.bench.rig_logs``) imported by ``parksim.importers.import_recording``; both bundles are scored by
``parksim.recon.evaluate.evaluate_bundle`` against the original dataset's test frames, so the codec shows in the
second. Time: a ``--timing-frames`` synth of the tiny garage at ``--timing-width`` x ``--timing-height`` (10 Hz)
written as a rig log of PNG folders and of mp4v videos, each imported ``--repeats`` times in turn in this process
(imports warm): wall and this process's CPU time (the import runs in one thread apart from OpenCV's decoders).
"""

from __future__ import annotations

import dataclasses
import functools
import itertools
import shutil
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from ..common import progress, time_medians
from ..datasets import ensure_dataset
from ..record import Figure
from ..suite import Context, Outcome, Suite

__all__ = ["ImportSuite", "ImportOptions", "psnr_to", "GOAL_DB"]

GOAL_DB = 1.0
"""The requirement: a reconstruction from the mp4v log within this many dB test PSNR of one from the PNGs."""


@dataclass(frozen=True)
class ImportOptions:
    """Options of ``parksim bench import``."""

    repeats: int = field(default=3, metadata={"help": "timed imports per source (median)", "low": 1, "quick": 1})
    iterations: int = field(default=300, metadata={
        "help": "photometric iterations of both reconstructions", "low": 20, "quick": 20})
    random_init: int = field(default=6000, metadata={
        "help": "random Gaussians both reconstructions start from", "low": 1, "quick": 1000})
    timing_frames: int = field(default=100, metadata={"help": "frames of the timed rig logs", "low": 2,
                                                      "quick": 12})
    timing_width: int = field(default=320, metadata={"help": "image width of the timed rig logs", "low": 8,
                                                     "quick": 160})
    timing_height: int = field(default=240, metadata={"help": "image height of the timed rig logs", "low": 8,
                                                      "quick": 120})


def _config(options: ImportOptions, path: Path) -> Path:
    """The packaged tiny schedule at ``iterations`` photometric iterations, densifying from 10 % to 80 % of the run,
    from ``random_init`` random Gaussians with pose refinement off (on by default for imported data, it would
    also move the poses; the rig log's poses are the synth's exact ones); written to ``path``."""
    from ...recon.config import dump_config, load_config, parse_config

    n = options.iterations
    cfg = load_config("tiny").model_dump(mode="json")
    cfg["init"].update(source="random", random_count=options.random_init)
    cfg["pose_opt"]["enabled"] = False
    cfg["photometric"].update(iterations=n, sh_degree_interval=n // 3)
    cfg["run"]["checkpoint_every"] = n
    for strategy in ("mcmc", "adc"):
        cfg["densify"][strategy].update(refine_start=n // 10, refine_stop=n * 8 // 10, refine_every=n // 20)
    cfg["densify"]["adc"]["reset_every"] = n // 2
    path.write_text(dump_config(parse_config(cfg, str(path))))
    return path


def _import(log: dict[str, Any], out: Path) -> None:
    """``parksim import rig-log`` of the log written by ``write_rig_log`` into the dataset ``out``."""
    from ...importers import ImportSettings, import_recording, importer

    rig_log = importer("rig-log")
    import_recording(rig_log, rig_log.Options(**log), ImportSettings(out, quiet=True))


def _reconstruct_and_score(data: Path, original: Path, out: Path, config: Path) -> dict[str, float]:
    """Reconstruct ``data`` into ``out`` and score the bundle on ``original``'s test frames.

    Returns:
        ``psnr`` (dB), ``ssim`` and ``train_s`` (wall seconds of the reconstruction).
    """
    from ...recon.evaluate import evaluate_bundle
    from ...recon.reconstruct import reconstruct

    start = time.perf_counter()
    reconstruct(data, out, config, log=lambda _: None)
    wall = time.perf_counter() - start
    result = evaluate_bundle(out, original, out / "eval_original")
    return {"psnr": result["overall"]["psnr"], "ssim": result["overall"]["ssim"], "train_s": wall}


def psnr_to(a: Path, b: Path) -> float:
    """Mean PSNR of one dataset's images against another's (e.g. decoded video frames against the PNGs).

    Args:
        a: the reference dataset.
        b: a dataset with the same cameras and frames.

    Returns:
        The mean over every frame and camera of ``a`` of each image's PSNR (dB, peak 1).
    """
    import numpy as np

    from ...data import DatasetReader

    ra, rb = DatasetReader(a), DatasetReader(b)
    mse = [float(((ra.image(c, f) - rb.image(c, f)) ** 2).mean()) for c in ra.rig.names for f in ra.frames]
    return float(np.mean([10 * np.log10(1.0 / m) for m in mse]))


class ImportSuite(Suite):
    """An mp4v rig log's cost in reconstruction PSNR, and the import time of PNG folders against videos."""

    name = "import"
    help = "rig-log import: mp4v quality cost in reconstruction PSNR, import time of folders and videos"
    description = ("The tiny garage reconstructed from itself and from its mp4v rig log, both scored on the original "
                   "test frames; a rig log of --timing-frames frames imported from PNG folders and from mp4v videos "
                   "in turn, in this process. Figures: the mp4v run's test PSNR beside the PNG run's (goal: within "
                   f"{GOAL_DB:g} dB), the decoded frames' PSNR, the video import's time beside the folders'.")
    Options = ImportOptions

    def run(self, options: ImportOptions, context: Context) -> Outcome:
        """Reconstruct from both sources, then time the imports."""
        import yaml

        from ...data import DatasetReader
        from ...synth import generate, get_preset
        from ..rig_logs import FOURCC, write_rig_log

        work = context.work / "import"
        shutil.rmtree(work, ignore_errors=True)
        work.mkdir(parents=True)
        tiny = ensure_dataset(context, "tiny", None)
        with progress(3 + options.repeats, "bench import", context.quiet) as bar:
            _import(write_rig_log(tiny, work / "tiny_log", video=True), work / "tiny_mp4")
            config = _config(options, work / "config.yaml")
            quality = {"original": _reconstruct_and_score(tiny, tiny, work / "run_original", config)}
            bar.update(1)
            quality["mp4"] = _reconstruct_and_score(work / "tiny_mp4", tiny, work / "run_mp4", config)
            bar.update(1)
            codec_psnr = psnr_to(tiny, work / "tiny_mp4")

            big = generate(dataclasses.replace(get_preset("tiny"), frames=options.timing_frames,
                                               width=options.timing_width, height=options.timing_height), work / "big")
            logs = {"image folders (PNG)": write_rig_log(big, work / "big_png", video=False),
                    f"videos ({FOURCC})": write_rig_log(big, work / "big_mp4", video=True)}
            bar.update(1)
            outputs, count = work / "imported", itertools.count()

            def import_once(log: dict[str, Any]) -> None:   # a fresh output folder per import
                _import(log, outputs / str(next(count)))

            def clean() -> None:   # after every round, untimed
                shutil.rmtree(outputs, ignore_errors=True)
                bar.update(1)

            timings = time_medians([functools.partial(import_once, log) for log in logs.values()], options.repeats,
                                   warmup=0, tick=clean)
        cameras = len(DatasetReader(big).rig.names)
        images = options.timing_frames * cameras
        timing = {name: {"wall_ms": t.wall_ms, "cpu_ms": t.cpu_ms, "images_per_s": images / (t.wall_ms / 1e3)}
                  for name, t in zip(logs, timings)}
        folders, videos = timings
        condition = (f"{options.timing_frames} frames x {cameras} cameras at "
                     f"{options.timing_width}x{options.timing_height}")
        figures = [
            Figure(f"test PSNR of the tiny garage reconstructed from its {FOURCC} rig log, {options.iterations} "
                   "iterations", quality["mp4"]["psnr"], "dB", reference=quality["original"]["psnr"],
                   reference_label="reconstructed from the dataset's PNGs", goal=f"within {GOAL_DB:g} dB of the PNGs'",
                   better="higher"),
            Figure(f"{FOURCC} frames decoded against the PNGs, tiny garage", codec_psnr, "dB", better="higher"),
            Figure(f"rig-log import, {condition}, {FOURCC} videos", videos.wall_ms, "ms", cpu=videos.cpu_ms,
                   reference=folders.wall_ms, reference_label="PNG image folders", reference_cpu=folders.cpu_ms)]
        data = {"fourcc": FOURCC, "quality": quality, "codec_psnr_db": codec_psnr, "timing": timing,
                "config": yaml.safe_load(config.read_text())}
        return Outcome(figures, data)

