"""The paper's slot-aware experiments on CPU: one shared photometric phase, each variant's slot-aware phase, tables.

For each scene: train the photometric bundle with the ``cpu_fast`` preset (or reuse it), start every run's
slot-aware phase from it (the ``cpu_slot_aware`` preset with the run's variant and guide detector), then
``parksim.recon.paper_eval`` scores all of them and this writes ``benchmarks/RESULTS_slot_aware.md``: the schedule,
timings, the paper-style tables and the issue's targets with the numbers that decide them.

Runs: the full variant guided by each detector, the ablation variants guided by ``--guide``, and a control
("Photometric only, continued": the same slot-aware iterations with every slot term off, i.e. L_rgb on all four
cameras of a frame), so that a variant is also compared with what the extra iterations alone give.

    python benchmarks/bench_slot_aware.py --scene data/scene1_320 scenes/scene1_320 \\
        --detector dmpr=detectors/dmpr --detector gcn=detectors/gcn --iterations 100
"""

from __future__ import annotations

import argparse
import datetime
import json
import os
import sys
import time
from dataclasses import dataclass
from pathlib import Path

import torch

from parksim.commands.eval import parse_detector
from parksim.recon.config import TrainConfig, dump_config, load_config
from parksim.recon.detectors import DecodeOptions
from parksim.recon.paper_eval import VARIANT_TITLES, evaluate_runs
from parksim.recon.paper_tables import DETECTOR_TITLES, tables_markdown
from parksim.recon.reconstruct import reconstruct
from parksim.recon.slot_aware import DetectorRef, Variant

ROOT = Path(__file__).resolve().parents[1]
ABLATION = (Variant.DIRECT_IPM, Variant.FEATURE_ONLY, Variant.TEACHER_ONLY, Variant.STUDENT_ONLY)
CONTROL = "Photometric only, continued"
TOLERANCE = 0.05


@dataclass(frozen=True)
class Run:
    """One slot-aware run: folder name, table label, variant, guide detector kind (None: none), slot terms on."""

    name: str
    label: str | None
    variant: Variant
    guide: str | None
    slot_terms: bool = True


def plan(detectors: list[str], guide: str, variants: list[Variant], control: bool) -> list[Run]:
    """Full variant per detector first (the headline), then the control, then the ablation variants."""
    runs = [Run(f"full_{kind}", None, Variant.FULL, kind) for kind in detectors]
    if control:
        runs.append(Run("photometric_continued", CONTROL, Variant.DIRECT_IPM, None, slot_terms=False))
    runs += [Run(f"{v.value}_{guide}", None, v, None if v == Variant.DIRECT_IPM else guide) for v in variants]
    return runs


def train_run(run: Run, data: Path, photometric: Path, folder: Path, base: TrainConfig, iterations: int,
              detectors: dict[str, Path]) -> bool:
    """Write the run's config next to it and train its slot-aware phase from the photometric run; False when the
    run was already done (its bundle is kept and reused)."""
    if (folder / "bundle.json").is_file():
        print(f"reusing {folder}")
        return False
    update = {"iterations": iterations, "variant": run.variant,
              "detector": DetectorRef(kind=run.guide, path=str(detectors[run.guide])) if run.guide else None}
    if not run.slot_terms:
        update.update(lambda_align=0.0, lambda_ipm=0.0, lambda_cam=0.0)
    config = base.model_copy(update={"slot_aware": base.slot_aware.model_copy(update=update)})
    path = folder.parent / "configs" / f"{run.name}.yaml"
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(dump_config(config))
    start = time.perf_counter()
    reconstruct(data, folder, path, start_from=photometric)
    print(f"{run.name}: {time.perf_counter() - start:.0f} s")
    return True


def shorter_photometric(config: TrainConfig, iterations: int | None) -> TrainConfig:
    """``config`` with an ``iterations``-long photometric phase, densification (both strategies) stopping 100
    iterations before its end as in cpu_fast.yaml; None leaves it as it is."""
    if iterations is None:
        return config
    stop = max(0, iterations - 100)
    densify = config.densify.model_copy(update={
        "mcmc": config.densify.mcmc.model_copy(update={"refine_stop": min(config.densify.mcmc.refine_stop, stop)}),
        "adc": config.densify.adc.model_copy(update={"refine_stop": min(config.densify.adc.refine_stop, stop)})})
    return config.model_copy(update={"photometric": config.photometric.model_copy(update={"iterations": iterations}),
                                     "densify": densify})


def _slot_seconds(run_dir: Path, photometric: Path) -> float:
    """Training seconds of the slot-aware phase alone (the bundle's total minus the shared photometric phase)."""
    total = json.loads((run_dir / "bundle.json").read_text())["train_seconds"]
    return total - json.loads((photometric / "bundle.json").read_text())["train_seconds"]


def _by_label(result: dict, label: str) -> dict | None:
    return next((r for r in result["runs"] if r["label"] == label), None)


def targets(result: dict) -> list[str]:
    """The issue's targets for each full run, with the numbers that decide them; the same two comparisons against
    the control (same iterations, slot terms off) say whether a gain comes from the slot terms."""
    lines = ["| scene | run | target | value | reference | met |", "| --- | --- | --- | --- | --- | --- |"]
    references = [(name, run) for name, run in (("photometric only", _by_label(result, "Photometric only")),
                                                ("the control", _by_label(result, CONTROL))) if run is not None]
    for run in (r for r in result["runs"] if r["variant"] == "full"):
        kind = run["detector"]
        gt, mine = result["gt"][kind]["slots"], run["detection"][kind]["slots"]
        title = DETECTOR_TITLES[kind]
        checks = []
        for name, ref in references:
            base = ref["detection"][kind]["slots"]
            checks += [(f"{title} slot recall on rendered BEVs > {name}", mine["recall"], base["recall"],
                        mine["recall"] > base["recall"]),
                       (f"slot-region PSNR > {name}", run["slot_psnr"], ref["slot_psnr"],
                        run["slot_psnr"] > ref["slot_psnr"])]
        checks += [(f"{title} slot precision within {TOLERANCE} of GT-BEV", mine["precision"], gt["precision"],
                    abs(mine["precision"] - gt["precision"]) <= TOLERANCE),
                   (f"{title} slot recall within {TOLERANCE} of GT-BEV", mine["recall"], gt["recall"],
                    abs(mine["recall"] - gt["recall"]) <= TOLERANCE)]
        lines += [f"| {result['scene']} | {run['label']} | {what} | {value:.3f} | {ref:.3f} | {'yes' if ok else 'no'} |"
                  for what, value, ref, ok in checks]
    return lines


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--scene", nargs=2, action="append", type=Path, required=True, metavar=("DATA", "PHOTOMETRIC"),
                    help="dataset and its photometric run (trained here with cpu_fast.yaml when missing)")
    ap.add_argument("--detector", action="append", type=parse_detector, required=True, metavar="KIND=PATH")
    ap.add_argument("--guide", choices=["dmpr", "gcn"], default="gcn", help="detector guiding the ablation variants")
    ap.add_argument("--variants", nargs="*", type=Variant, default=list(ABLATION), help="ablation variants to run")
    ap.add_argument("--no-control", action="store_true", help="skip the 'photometric only, continued' control")
    ap.add_argument("--config", default="cpu_slot_aware",
                    help="slot-aware config (preset name or YAML path) each run starts from (variant, detector, "
                         "iterations set per run)")
    ap.add_argument("--photometric-config", default="cpu_fast",
                    help="config (preset name or YAML path) of a photometric run trained here")
    ap.add_argument("--iterations", type=int, help="slot-aware iterations per run (default: --config's)")
    ap.add_argument("--photometric-iterations", type=int,
                    help="photometric iterations of both configs (default: theirs); densification stops 100 before")
    ap.add_argument("--runs", type=Path, default=Path("scenes/slot_aware"), help="where the runs go (per scene)")
    ap.add_argument("--threshold", type=float, default=0.5, help="detectors' operating threshold")
    ap.add_argument("--out", type=Path, default=ROOT / "benchmarks" / "RESULTS_slot_aware.md")
    args = ap.parse_args(argv)
    base = shorter_photometric(load_config(args.config), args.photometric_iterations)
    photometric_config = shorter_photometric(load_config(args.photometric_config), args.photometric_iterations)
    iterations = args.iterations or base.slot_aware.iterations
    detectors = dict(args.detector)
    models = {kind: DetectorRef(kind=kind, path=str(path)).load() for kind, path in detectors.items()}
    runs = plan(list(detectors), args.guide, args.variants, not args.no_control)
    load_before, started = os.getloadavg(), datetime.datetime.now(datetime.timezone.utc)
    results, timings = [], []
    for data, photometric in args.scene:
        if not (photometric / "bundle.json").is_file():
            path = args.runs / "configs" / f"{photometric.name}.yaml"
            path.parent.mkdir(parents=True, exist_ok=True)
            path.write_text(dump_config(photometric_config))
            reconstruct(data, photometric, path)
        root = args.runs / data.name
        for run in runs:
            trained = train_run(run, data, photometric, root / run.name, base, iterations, detectors)
            timings.append(f"| {data.name} | {run.name} | {_slot_seconds(root / run.name, photometric):.0f} | "
                           f"{'this invocation' if trained else 'an earlier invocation (reused)'} |")
        start = time.perf_counter()
        entries = [(photometric, "Photometric only")] + [(root / r.name, r.label) for r in runs]
        results.append(evaluate_runs(entries, data, models, root / "eval",
                                     decode=DecodeOptions(threshold=args.threshold)))
        timings.append(f"| {data.name} | evaluation of {len(entries)} bundles | {time.perf_counter() - start:.0f} | "
                       "this invocation |")
    load_after = os.getloadavg()
    text = "\n".join([
        "# Slot-aware phase: the paper's tables on CPU", "",
        f"`python benchmarks/bench_slot_aware.py {' '.join(sys.argv[1:] if argv is None else argv)}`", "",
        f"Started {started.isoformat(timespec='minutes')}; load average {load_before[0]:.1f} at the start and "
        f"{load_after[0]:.1f} at the end (2 shared cores); torch {torch.__version__}, "
        f"{torch.get_num_threads()} threads.",
        f"Schedule: photometric phase `{Path(args.photometric_config).stem}`"
        + (f" cut to {args.photometric_iterations} iterations" if args.photometric_iterations else "")
        + f" (shared by all runs), then {iterations} "
        f"slot-aware iterations per run (`{Path(args.config).stem}`"
        + (", its photometric section cut the same way" if args.photometric_iterations else "") + "); detectors: "
        + ", ".join(f"{DETECTOR_TITLES[k]} `{p}`" for k, p in detectors.items())
        + f"; operating threshold {args.threshold}; ablation guided by {DETECTOR_TITLES[args.guide]}.", "",
        "| scene | run | slot-aware training (s, wall) | trained by |", "| --- | --- | --- | --- |", *timings, "",
        tables_markdown(results).rstrip(), "",
        "### Targets of the issue", "", *(line for r in results for line in targets(r)), "",
        "Variant names: " + "; ".join(f"{v.value} = {t}" for v, t in VARIANT_TITLES.items()) + ".", ""])
    args.out.write_text(text)
    print(text)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
