"""``parksim bench slot-aware``: the paper's slot-aware experiments on CPU: one shared photometric phase per dataset,
each variant's slot-aware phase started from it, all scored by ``parksim.recon.paper_eval``.

Runs: the full variant guided by each detector (the headline), a control ("Photometric only, continued": the same
slot-aware iterations with every slot term off, i.e. L_rgb on all four cameras of a frame) so that a variant is also
compared with what the extra iterations alone give, and the ablation variants guided by ``--guide``. Finished runs
are reused from the runs folder when their config is the one asked for.

The issue's targets for each full run: slot recall on rendered BEVs and slot-region PSNR above photometric only
(and above the control), and rendered-BEV slot precision and recall within 0.05 of the same detector on the
ground-truth BEVs.
"""

from __future__ import annotations

import json
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any, Literal

from ..datasets import ensure_dataset
from ..record import Figure
from ..suite import Context, Outcome, Suite

if TYPE_CHECKING:
    from ...recon.config import TrainConfig

__all__ = ["SlotAwareSuite", "SlotAwareOptions", "Run", "plan", "shorter_photometric", "ABLATION", "CONTROL",
           "TOLERANCE"]

ABLATION = ("direct_ipm", "feature_only", "teacher_only", "student_only")
"""The ablation variants (``parksim.recon.slot_aware.Variant`` values) run by default."""
CONTROL = "Photometric only, continued"
"""Row label of the control run."""
TOLERANCE = 0.05
"""How close rendered-BEV slot precision and recall must come to the ground-truth BEV's."""
_VARIANTS = (*ABLATION, "full")


@dataclass(frozen=True)
class SlotAwareOptions:
    """Options of ``parksim bench slot-aware``."""

    dataset: list[Path] = field(default_factory=list, metadata={
        "help": "datasets to run on (default: synth scene1 at 320x240 under --work; synth tiny under --quick)"})
    photometric: list[Path] = field(default_factory=list, metadata={
        "help": "each dataset's photometric run, in --dataset order; trained here with --photometric-config where "
                "missing (default: RUNS/<dataset>/photometric_<config>)"})
    detector: dict[str, Path] = field(default_factory=dict, metadata={
        "help": "KIND=PATH: detectors that guide and score the runs, repeated (default: the `detectors` suite's "
                "DMPR-PS-style and GCN-style models, trained under --work when missing)", "metavar": "KIND=PATH"})
    guide: Literal["dmpr", "gcn"] = field(default="gcn", metadata={"help": "detector guiding the ablation variants"})
    variants: list[str] = field(default_factory=lambda: list(ABLATION), metadata={
        "help": f"ablation variants to run, of {', '.join(_VARIANTS)} (empty: none)", "quick": []})
    control: bool = field(default=True, metadata={
        "help": "run the 'photometric only, continued' control (same iterations, slot terms off)"})
    config: str = field(default="cpu_slot_aware", metadata={
        "help": "slot-aware config (preset name or YAML path) each run starts from (variant, detector and "
                "iterations set per run)", "quick": "tiny"})
    photometric_config: str = field(default="cpu_fast", metadata={
        "help": "config (preset name or YAML path) of a photometric run trained here", "quick": "tiny"})
    iterations: int | None = field(default=None, metadata={
        "help": "slot-aware iterations per run (default: --config's)", "low": 1, "quick": 2})
    photometric_iterations: int | None = field(default=None, metadata={
        "help": "photometric iterations of both configs (default: theirs); densification stops 100 before",
        "low": 1})
    runs: Path | None = field(default=None, metadata={
        "help": "where the runs go, a folder per dataset (default: WORK/slot_aware)"})
    threshold: float = field(default=0.5, metadata={"help": "detectors' operating threshold", "low": 0.0,
                                                    "high": 1.0, "open_low": True})

    def __post_init__(self) -> None:
        unknown = [v for v in self.variants if v not in _VARIANTS]
        if unknown:
            raise ValueError(f"--variants: unknown {', '.join(unknown)}; choose from {', '.join(_VARIANTS)}")
        if self.photometric and len(self.photometric) != len(self.dataset):
            raise ValueError(f"--photometric names {len(self.photometric)} runs for {len(self.dataset)} datasets")
        if not set(self.detector) <= {"dmpr", "gcn"}:
            raise ValueError(f"--detector: kinds are dmpr and gcn, got {', '.join(self.detector)}")


@dataclass(frozen=True)
class Run:
    """One slot-aware run: folder name, table label (None: the variant's), variant, guide detector kind (None: none),
    slot terms on."""

    name: str
    label: str | None
    variant: str
    guide: str | None
    slot_terms: bool = True


def plan(detectors: list[str], guide: str, variants: list[str], control: bool) -> list[Run]:
    """The full variant per detector first (the headline), then the control, then the ablation variants.

    Args:
        detectors: detector kinds, each guiding one full run.
        guide: the kind guiding the ablation variants.
        variants: ablation variants (``Variant`` values).
        control: whether to run the control.

    Returns:
        The runs in that order.
    """
    runs = [Run(f"full_{kind}", None, "full", kind) for kind in detectors]
    if control:
        runs.append(Run("photometric_continued", CONTROL, "direct_ipm", None, slot_terms=False))
    return runs + [Run(f"{v}_{guide}", None, v, None if v == "direct_ipm" else guide) for v in variants]


def shorter_photometric(config: TrainConfig, iterations: int | None) -> TrainConfig:
    """``config`` with an ``iterations``-long photometric phase, densification (both strategies) stopping 100
    iterations before its end as in cpu_fast.yaml.

    Args:
        config: a training config.
        iterations: photometric iterations, or None to leave ``config`` as it is.

    Returns:
        The config.
    """
    if iterations is None:
        return config
    stop = max(0, iterations - 100)
    densify = config.densify.model_copy(update={
        "mcmc": config.densify.mcmc.model_copy(update={"refine_stop": min(config.densify.mcmc.refine_stop, stop)}),
        "adc": config.densify.adc.model_copy(update={"refine_stop": min(config.densify.adc.refine_stop, stop)})})
    return config.model_copy(update={"photometric": config.photometric.model_copy(update={"iterations": iterations}),
                                     "densify": densify})


def _train(data: Path, folder: Path, config: TrainConfig, start_from: Path | None) -> dict[str, Any]:
    """Train ``folder`` with ``config`` (from the photometric run ``start_from``), or reuse it when it holds a
    finished run of that config; its training seconds from ``bundle.json`` and what this call spent (wall, CPU)."""
    from ...recon.config import dump_config
    from ...recon.reconstruct import CONFIG_FILE, reconstruct

    text = dump_config(config)
    wall, cpu = time.perf_counter(), time.process_time()
    trained = not (folder / "bundle.json").is_file()
    if trained:
        path = folder.parent / "configs" / f"{folder.name}.yaml"
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_text(text)
        reconstruct(data, folder, path, start_from=start_from, log=lambda _: None)
    elif (folder / CONFIG_FILE).read_text() != text:
        raise ValueError(f"{folder}: holds a run of another config; remove it or choose another --runs folder")
    return {"train_seconds": _train_seconds(folder), "trained_here": trained,
            "here": {"wall_s": time.perf_counter() - wall, "cpu_s": time.process_time() - cpu}}


def _train_seconds(folder: Path) -> float:
    """Training seconds of the bundle in ``folder`` (a slot-aware run's include its photometric phase)."""
    return float(json.loads((folder / "bundle.json").read_text())["train_seconds"])


def _slot_config(base: TrainConfig, run: Run, iterations: int, detectors: dict[str, Path]) -> TrainConfig:
    """``base`` with the run's slot-aware section: iterations, variant, guide detector, slot terms."""
    from ...recon.slot_aware import DetectorRef, Variant

    update: dict[str, Any] = {"iterations": iterations, "variant": Variant(run.variant),
                              "detector": DetectorRef(kind=run.guide, path=str(detectors[run.guide]))
                              if run.guide else None}
    if not run.slot_terms:
        update.update(lambda_align=0.0, lambda_ipm=0.0, lambda_cam=0.0)
    return base.model_copy(update={"slot_aware": base.slot_aware.model_copy(update=update)})


@dataclass(frozen=True)
class _Check:
    """One of the issue's targets for one full run."""

    target: str
    value: float
    unit: str
    reference: float
    reference_label: str
    goal: str
    met: bool


def _checks(result: dict[str, Any]) -> list[_Check]:
    """The issue's targets for each full run of one dataset's result, with the numbers that decide them; the two
    comparisons against photometric only are repeated against the control (same iterations, slot terms off), which
    says whether a gain comes from the slot terms."""
    from ...recon.paper_tables import DETECTOR_TITLES

    rows = {r["label"]: r for r in result["runs"]}
    photometric = rows["Photometric only"]
    references = [(n, rows[n]) for n in ("Photometric only", CONTROL) if n in rows]
    checks = []
    for run in (r for r in result["runs"] if r["variant"] == "full"):
        kind = run["detector"]
        title = DETECTOR_TITLES[kind]
        slot_iterations = run["iterations"] - photometric["iterations"]
        where = f"{result['scene']}, {photometric['iterations']} + {slot_iterations} it., {run['label']}: "
        mine, gt = run["detection"][kind]["slots"], result["gt"][kind]["slots"]
        for name, ref in references:
            versus = "" if ref is photometric else " (vs the control)"
            base = ref["detection"][kind]["slots"]
            checks += [
                _Check(f"{where}{title} slot recall on rendered BEVs{versus}", mine["recall"], "fraction",
                       base["recall"], name, f"> {name}", mine["recall"] > base["recall"]),
                _Check(f"{where}slot-region PSNR{versus}", run["slot_psnr"], "dB", ref["slot_psnr"], name,
                       f"> {name}", run["slot_psnr"] > ref["slot_psnr"])]
        for metric in ("precision", "recall"):
            checks.append(_Check(f"{where}{title} slot {metric} on rendered BEVs vs GT BEVs", mine[metric], "fraction",
                                 gt[metric], f"GT BEVs, {title}", f"within {TOLERANCE} of the reference",
                                 abs(mine[metric] - gt[metric]) <= TOLERANCE))
    return checks


class SlotAwareSuite(Suite):
    """The slot-aware variants against photometric only and the same-iterations control."""

    name = "slot-aware"
    help = "slot-aware variants vs photometric only and a same-iterations control (paper tables)"
    description = ("Per dataset: train (or reuse) the photometric run (--photometric-config), start each run's "
                   "slot-aware phase from it (--config with the run's variant and guide detector): the full variant "
                   "per --detector, the control (same iterations, slot terms off) and the ablation --variants "
                   "guided by --guide; then score every bundle as `parksim eval` does (novel views, slot regions, "
                   "detection on rendered vs ground-truth BEVs). Figures: the issue's targets for each full run. "
                   "Data: the paper tables' numbers, training and evaluation times. Plot: ground-truth vs rendered "
                   "BEVs of the first dataset with the guide detector's detections.")
    Options = SlotAwareOptions

    def run(self, options: SlotAwareOptions, context: Context) -> Outcome:
        """Train what is missing, evaluate every run of every dataset, check the targets."""
        from ...recon.config import load_config
        from ...recon.detectors import DecodeOptions
        from ...recon.paper_eval import evaluate_runs
        from ...recon.slot_aware import DetectorRef
        from .detectors import default_models

        datasets = options.dataset or [ensure_dataset(context, "scene1", "320x240")]
        if options.detector:
            detectors = dict(options.detector)
        else:
            trained = default_models(context)
            detectors = {"dmpr": trained / "dmpr", "gcn": trained / "gcn"}
        if options.variants and options.guide not in detectors:
            raise ValueError(f"--guide {options.guide}: no such --detector (given: {', '.join(detectors)})")
        base = shorter_photometric(load_config(options.config), options.photometric_iterations)
        photometric_config = shorter_photometric(load_config(options.photometric_config),
                                                 options.photometric_iterations)
        iterations = options.iterations or base.slot_aware.iterations
        models = {kind: DetectorRef(kind=kind, path=str(path)).load() for kind, path in detectors.items()}
        runs = plan(list(detectors), options.guide, options.variants, options.control)
        shown = options.guide if options.guide in detectors else next(iter(detectors))   # the plot's detector
        runs_root = options.runs or context.work / "slot_aware"
        stem = Path(options.photometric_config).stem + (f"_p{options.photometric_iterations}"
                                                         if options.photometric_iterations else "")
        results, timings, panels = [], [], []
        for k, data in enumerate(datasets):
            root = runs_root / data.name
            photometric = options.photometric[k] if options.photometric else root / f"photometric_{stem}"
            if not options.photometric or not (photometric / "bundle.json").is_file():   # a given run is taken as is
                timings.append({"scene": data.name, "run": "photometric",
                                **_train(data, photometric, photometric_config, None)})
            schedule = root / f"from_{photometric.name}_{Path(options.config).stem}_{iterations}it"
            for run in runs:
                done = _train(data, schedule / run.name, _slot_config(base, run, iterations, detectors), photometric)
                timings.append({"scene": data.name, "run": run.name, **done,
                                "slot_aware_seconds": done["train_seconds"] - _train_seconds(photometric)})
            wall, cpu = time.perf_counter(), time.process_time()
            entries = [(photometric, "Photometric only")] + [(schedule / r.name, r.label) for r in runs]
            results.append(evaluate_runs(entries, data, models, schedule / "eval",
                                         decode=DecodeOptions(threshold=options.threshold)))
            timings.append({"scene": data.name, "run": f"evaluation of {len(entries)} bundles",
                            "here": {"wall_s": time.perf_counter() - wall, "cpu_s": time.process_time() - cpu}})
            panels.append(schedule / "eval" / f"panel_{shown}.png")
        checks = [c for r in results for c in _checks(r)]
        figures = [Figure(c.target, c.value, c.unit, reference=c.reference, reference_label=c.reference_label,
                          goal=c.goal, better="higher") for c in checks]
        data_out = {"datasets": [str(d) for d in datasets], "detectors": {k: str(p) for k, p in detectors.items()},
                    "schedule": {"photometric_config": options.photometric_config, "config": options.config,
                                 "photometric_iterations": photometric_config.photometric.iterations,
                                 "slot_aware_iterations": iterations},
                    "runs": [asdict(r) for r in runs], "timings": timings, "results": results,
                    "targets": [asdict(c) for c in checks]}
        return Outcome(figures, data_out, lambda png: _copy_panel(panels[0], png))


def _copy_panel(panel: Path, png: Path) -> None:
    """The evaluation's panel of ground-truth vs rendered BEVs, as the record's plot."""
    import shutil

    shutil.copyfile(panel, png)
