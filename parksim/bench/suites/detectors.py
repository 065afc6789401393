"""``parksim bench detectors``: train (or reuse) the DMPR-PS-style and GCN-style slot detectors on the train frames
of synthetic garages and score them on their test frames' ground-truth BEVs.

Scoring is the ParkSim protocol (``docs/detection_protocol.md``): a marking point within 10 px at 600 px = 10 m and
its direction within 30 deg; a slot when both ordered entrance points match and its angle within 10 deg. Precision
and recall at confidence 0.5, AP over the confidence sweep, pooled over the datasets; the slot figures without the
angle condition (DMPR-PS' and GCN-Parking's own criterion) are kept in the data. Training is staged: each stage a
one-cycle schedule from the previous stage's weights; the GCN starts from the finished DMPR model (backbone and
point head), so its training time includes the DMPR's.
"""

from __future__ import annotations

import json
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

from ..common import Timing, set_threads, time_medians
from ..datasets import ensure_dataset
from ..record import Figure
from ..suite import Context, Outcome, Suite

if TYPE_CHECKING:
    from ...recon.detectors.train import TrainOptions

__all__ = ["DetectorsSuite", "DetectorsOptions", "train_stages", "default_models", "SCENES", "STEPS", "QUICK_STEPS",
           "TITLES"]

SCENES = ("scene1", "scene2", "scene3", "scene4")
"""Synth presets the detectors are trained and scored on by default (each at its own resolution)."""
STEPS = {"dmpr": [1200], "gcn": [600]}
"""Training steps per stage of each architecture (the GCN continues from the DMPR model)."""
QUICK_STEPS = {"dmpr": [4], "gcn": [2]}
"""The same under ``--quick``: a few steps on the tiny garage, enough to run every code path."""
TITLES = {"dmpr": "DMPR-PS-style", "gcn": "GCN-style"}
"""How figures name each architecture."""
_SAME_MODEL = ("arch", "width", "input_size", "steps", "batch_size", "lr", "seed")
"""Training options that make a stored model the one asked for (paths, device and threads do not)."""


@dataclass(frozen=True)
class DetectorsOptions:
    """Options of ``parksim bench detectors``."""

    data: list[Path] = field(default_factory=list, metadata={
        "help": "ParkSim dataset folders: their train frames train, their test frames score (default: synth "
                "scene1-4 at their own resolution under --work; synth tiny under --quick)"})
    models: Path | None = field(default=None, metadata={
        "help": "folder of the models (dmpr/, gcn/ and the earlier stages), reused where it holds a stage trained "
                "with the same options (default: WORK/detectors/<dataset names>)"})
    dmpr_steps: list[int] = field(default_factory=lambda: list(STEPS["dmpr"]), metadata={
        "help": "DMPR steps per training stage (each stage restarts the one-cycle schedule)", "low": 1,
        "quick": QUICK_STEPS["dmpr"]})
    gcn_steps: list[int] = field(default_factory=lambda: list(STEPS["gcn"]), metadata={
        "help": "GCN steps per stage; its backbone and point head start from the DMPR model", "low": 1,
        "quick": QUICK_STEPS["gcn"]})
    device: str = field(default="cpu", metadata={
        "help": "training device: cpu, or cuda[:N] (scoring and timing run on the CPU)"})
    threads: int = field(default=2, metadata={"help": "torch CPU threads (training, scoring, timing)", "low": 1})
    repeats: int = field(default=20, metadata={"help": "timed detections of one test BEV (median)", "low": 1,
                                               "quick": 3})


def _same_model(meta: dict[str, Any], options: TrainOptions) -> bool:
    """Whether a stored ``train.json`` describes a model trained with ``options``."""
    stored, wanted = meta.get("options", {}), asdict(options)
    return all(stored.get(k) == wanted[k] for k in _SAME_MODEL) and meta.get("step") == options.steps


def train_stages(data: list[Path], out: Path, stages: list[int], options: TrainOptions,
                 progress: bool = False) -> dict[str, Any]:
    """Train the detector ``out`` in stages; a stage whose folder already holds it is reused.

    Stage ``k`` of ``n`` is written to ``out`` when it is the last, else beside it as ``<out>_stage<k>``; it trains
    ``stages[k-1]`` steps with seed ``options.seed + k - 1``, the first from ``options.init`` (or fresh), each later
    one from the stage before.

    Args:
        data: dataset or ps2.0 folders whose train frames train the model.
        out: the final model's folder (``model.pt``, ``train.json``).
        stages: steps per stage.
        options: architecture, size and schedule of every stage (``steps``, ``seed`` and ``init`` set per stage).
        progress: show a progress bar.

    Returns:
        The last stage's ``train.json`` (options, folders, images, steps, training seconds including the stages
        and the model it started from).

    Raises:
        ValueError: a stage's folder holds a model trained with other options (remove it or choose another folder).
    """
    from dataclasses import replace

    from ...recon.detectors.train import train_detector

    init = options.init
    for k, steps in enumerate(stages, 1):
        stage = out if k == len(stages) else out.with_name(f"{out.name}_stage{k}")
        opts = replace(options, steps=steps, seed=options.seed + k - 1, init=init)
        meta_path = stage / "train.json"
        if not meta_path.is_file():
            train_detector(list(data), stage, opts, progress=progress)
        elif not _same_model(json.loads(meta_path.read_text()), opts):
            raise ValueError(f"{stage}: holds a detector trained with other options than {opts}; "
                             "remove it or choose another models folder")
        init = str(stage)
    return json.loads((out / "train.json").read_text())


def _default_data(context: Context) -> list[Path]:
    """Synth scene1-4 under the work folder (made if missing), or the tiny garage under ``--quick``."""
    return list(dict.fromkeys(ensure_dataset(context, scene, None) for scene in SCENES))


def _models_folder(context: Context, data: list[Path]) -> Path:
    """Where the models trained on ``data`` go by default: one folder per set of datasets."""
    return context.work / "detectors" / "+".join(d.name for d in data)


def default_models(context: Context) -> Path:
    """The detectors this suite trains by default, made if missing: DMPR-PS-style then GCN-style on synth scene1-4
    (``--quick``: a few steps on the tiny garage); other suites take them as their default detectors.

    Args:
        context: the run's context (work folder, seed, quick, quiet).

    Returns:
        The models folder, holding ``dmpr/`` and ``gcn/``.
    """
    from ...recon.detectors.train import TrainOptions

    data = _default_data(context)
    models = _models_folder(context, data)
    steps = QUICK_STEPS if context.quick else STEPS
    _train_both(data, models, steps["dmpr"], steps["gcn"], TrainOptions(seed=context.seed), not context.quiet)
    return models


def _train_both(data: list[Path], models: Path, dmpr_steps: list[int], gcn_steps: list[int], base: TrainOptions,
                progress: bool) -> dict[str, dict[str, Any]]:
    """Train (or reuse) ``models/dmpr``, then ``models/gcn`` from it; the ``train.json`` of each."""
    from dataclasses import replace

    metas = {"dmpr": train_stages(data, models / "dmpr", dmpr_steps, replace(base, arch="dmpr"), progress)}
    metas["gcn"] = train_stages(data, models / "gcn", gcn_steps,
                                replace(base, arch="gcn", init=str(models / "dmpr")), progress)
    return metas


def _pooled(results: list[dict[str, Any]]) -> dict[str, Any]:
    """Pooled precision/recall (and label-weighted AP) over several folders' ``evaluate_folder`` results."""
    total: dict[str, Any] = {"images": sum(r["images"] for r in results)}
    for key in ("points", "slots"):
        tp = sum(r[key]["tp"] for r in results)
        fp = sum(r[key]["fp"] for r in results)
        labelled = sum(r[key]["labelled"] for r in results)
        total[key] = {"precision": tp / max(tp + fp, 1), "recall": tp / max(labelled, 1), "labelled": labelled,
                      "ap": sum(r[key]["ap"] * r[key]["labelled"] for r in results) / max(labelled, 1)}
    return total


def _detect_timing(model: Any, data: Path, repeats: int) -> tuple[Timing, tuple[int, int]]:
    """Median time to detect (network and decoding at the operating point) on the first test BEV of ``data``."""
    import torch

    from ...recon.detectors.dataset import iter_items

    item = next(iter_items(data, "test"))
    bev = torch.from_numpy(item.image).permute(2, 0, 1).float()[None] / 255.0

    def once() -> None:
        with torch.no_grad():
            model.detect(bev, item.labels.m_per_px)

    return time_medians([once], repeats)[0], (bev.shape[-1], bev.shape[-2])


class DetectorsSuite(Suite):
    """Slot detectors trained on synthetic garages, scored on their test frames' ground-truth BEVs."""

    name = "detectors"
    help = "train or reuse the DMPR-PS-style and GCN-style slot detectors; P/R on GT BEVs"
    description = ("Train the DMPR-PS-style detector (stages --dmpr-steps), then the GCN-style one from it "
                   "(--gcn-steps), on the train frames of --data (models reused when already trained with the same "
                   "options), and score both on the ground-truth BEVs of the test frames under the ParkSim "
                   "protocol. Figures: point and slot precision and recall pooled over the datasets, and the median "
                   "time to detect on one BEV. Data: per-dataset P/R/AP, slots without the angle check, training "
                   "times.")
    Options = DetectorsOptions

    def run(self, options: DetectorsOptions, context: Context) -> Outcome:
        """Train or reuse both models, then score and time them."""
        from ...recon.detectors import load_detector
        from ...recon.detectors.evaluate import MatchOptions, evaluate_folder
        from ...recon.detectors.protocols import ParkSimProtocol
        from ...recon.detectors.train import TrainOptions

        data = options.data or _default_data(context)
        models = options.models or _models_folder(context, data)
        set_threads(options.threads)
        base = TrainOptions(seed=context.seed, threads=options.threads, device=options.device)
        metas = _train_both(data, models, options.dmpr_steps, options.gcn_steps, base, not context.quiet)
        names = "+".join(d.name for d in data)
        no_angle = ParkSimProtocol(MatchOptions(slot_angle_deg=180.0))
        figures: list[Figure] = []
        per_arch: dict[str, Any] = {}
        for arch, meta in metas.items():
            model = load_detector(models / arch)
            results = [evaluate_folder(model, d, "test", protocol=ParkSimProtocol()) for d in data]
            total = _pooled(results)
            loose = _pooled([evaluate_folder(model, d, "test", protocol=no_angle) for d in data])
            timing, (w, h) = _detect_timing(model, data[0], options.repeats)
            steps = options.dmpr_steps + (options.gcn_steps if arch == "gcn" else [])
            per_arch[arch] = {
                "model": str(models / arch), "steps": steps, "options": meta["options"],
                "train_seconds": meta["total_train_seconds"], "folders": results, "all": total,
                "slots_without_angle_check": loose["slots"], "detect": timing,
                "ms_per_bev_mean": sum(r["ms_per_bev"] * r["images"] for r in results) / total["images"]}
            title = f"{TITLES[arch]}: "
            where = f"on GT BEVs of the test frames of {names}"
            for key, what in (("points", "point"), ("slots", "slot")):
                for metric, goal in (("precision", ">= 0.95"), ("recall", ">= 0.90")):
                    figures.append(Figure(f"{title}{what} {metric} {where}", total[key][metric], "fraction",
                                          goal=goal, better="higher"))
            figures.append(Figure(f"{title}detection on one {w}x{h} BEV (input {meta['options']['input_size']} px), "
                                  f"{options.threads} threads", timing.wall_ms, "ms", cpu=timing.cpu_ms))
        data_out = {"datasets": [str(d) for d in data], "models": str(models), "images": per_arch["dmpr"]["all"]
                    ["images"], "protocol": ParkSimProtocol().describe(), "detectors": per_arch}
        return Outcome(figures, data_out)
