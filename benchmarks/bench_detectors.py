"""Train the DMPR-PS-style and GCN-Parking-style detectors on synthetic train frames; evaluate on test frames.

Writes a markdown table (command, machine, date, training time, ms per BEV, precision/recall/AP of
marking points and slots per scene and overall) to ``benchmarks/RESULTS_detectors.md``.

    python benchmarks/bench_detectors.py --data data/det_scene1 data/det_scene2 data/det_scene3 data/det_scene4
"""

from __future__ import annotations

import argparse
import datetime
import json
import os
import sys
from pathlib import Path

import torch

from parksim.bench.common import cpu_model
from parksim.recon.detectors import load_detector
from parksim.recon.detectors.evaluate import MatchOptions, evaluate_folder
from parksim.recon.detectors.protocols import ParkSimProtocol
from parksim.recon.detectors.train import TrainOptions, train_detector


def _train(arch: str, data: list[Path], models: Path, stages: list[int], init: Path | None, seed: int,
           device: str) -> dict:
    """Train ``models/arch`` in stages (each a one-cycle schedule starting from the previous stage's weights;
    the first from ``init``), reusing finished stages; returns the last stage's train.json metadata."""
    for k, steps in enumerate(stages, 1):
        out = models / (arch if k == len(stages) else f"{arch}_stage{k}")
        if not (out / "train.json").is_file():
            train_detector(data, out, TrainOptions(arch=arch, steps=steps, seed=seed + k - 1,
                                                   init=str(init) if init else None, device=device))
        init = out
    return json.loads((models / arch / "train.json").read_text())


def _total(results: list[dict]) -> dict:
    """Pooled precision/recall (and label-weighted AP) over several folders' results."""
    total: dict = {"images": sum(r["images"] for r in results)}
    for key in ("points", "slots"):
        tp = sum(r[key]["tp"] for r in results)
        fp = sum(r[key]["fp"] for r in results)
        lab = sum(r[key]["labelled"] for r in results)
        total[key] = {"precision": tp / max(tp + fp, 1), "recall": tp / max(lab, 1),
                      "ap": sum(r[key]["ap"] * r[key]["labelled"] for r in results) / max(lab, 1)}
    return total


def _row(name: str, r: dict) -> str:
    p, s = r["points"], r["slots"]
    return (f"| {name} | {r['images']} | {p['precision']:.3f} | {p['recall']:.3f} | {p['ap']:.3f} | "
            f"{s['precision']:.3f} | {s['recall']:.3f} | {s['ap']:.3f} |")


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--data", type=Path, nargs="+", required=True,
                    help="ParkSim scene folders: train frames train, test frames evaluate")
    ap.add_argument("--models", type=Path, default=Path("data/detectors"), help="where the models go (reused if there)")
    ap.add_argument("--dmpr-steps", type=int, nargs="+", default=[TrainOptions().steps],
                    help="DMPR steps per training stage (each stage restarts the one-cycle schedule)")
    ap.add_argument("--gcn-steps", type=int, nargs="+", default=[TrainOptions().steps // 2],
                    help="GCN steps per stage; its backbone and point head start from the DMPR model")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--device", default="cpu", help="cpu, or cuda to train on a GPU (evaluation runs on the CPU)")
    ap.add_argument("--out", type=Path, default=Path("benchmarks/RESULTS_detectors.md"))
    args = ap.parse_args(argv)
    torch.set_num_threads(2)

    metas = {"dmpr": _train("dmpr", args.data, args.models, args.dmpr_steps, None, args.seed, args.device)}
    metas["gcn"] = _train("gcn", args.data, args.models, args.gcn_steps, args.models / "dmpr", args.seed, args.device)
    gpu = f", trained on {torch.cuda.get_device_name()}" if args.device.startswith("cuda") else ""
    lines = ["# Parking-slot detectors on ground-truth BEVs", "",
             f"Command: `python {' '.join(sys.argv)}`  ",
             f"Machine: {cpu_model()}, {os.cpu_count()} cores, torch {torch.__version__} with 2 threads{gpu}, "
             f"load average at the end: {os.getloadavg()[0]:.1f}  ",
             f"Date: {datetime.datetime.now().isoformat(timespec='minutes')}", "",
             "Trained on the train frames, evaluated on the test frames (every 10th) of: "
             + ", ".join(f"`{d}`" for d in args.data) + ". Matching (ParkSim protocol, docs/detection_protocol.md): "
             "point within 10 px at 600 px = 10 m and direction within 30 deg; slot: both ordered entrance points "
             "match and angle within 10 deg. "
             "Precision/recall at confidence 0.5; AP over the confidence sweep. The last two columns drop the slot "
             "angle condition (DMPR-PS' and GCN-Parking's own slot criterion: both entrance points only).", ""]
    summary = ["| detector | width | input px | train steps | train time (s) | ms per BEV | point P | point R | "
               "slot P | slot R | slot P, no angle check | slot R, no angle check |",
               "| --- | --- | --- | --- | --- | --- | --- | --- | --- | --- | --- | --- |"]
    details = []
    for arch, meta in metas.items():
        model = load_detector(args.models / arch)
        results = [evaluate_folder(model, d, "test", protocol=ParkSimProtocol()) for d in args.data]
        no_angle = ParkSimProtocol(MatchOptions(slot_angle_deg=180.0))
        loose = _total([evaluate_folder(model, d, "test", protocol=no_angle) for d in args.data])
        total = _total(results)
        ms = sum(r["ms_per_bev"] * r["images"] for r in results) / total["images"]
        opts = meta["options"]
        seconds = meta["total_train_seconds"]
        steps = "+".join(str(n) for n in (args.dmpr_steps if arch == "dmpr" else args.dmpr_steps + args.gcn_steps))
        note = " (incl. the DMPR model it starts from)" if arch == "gcn" else ""
        summary.append(f"| {arch} | {opts['width']} | {opts['input_size']} | {steps} | {seconds:.0f}{note} | "
                       f"{ms:.1f} | {total['points']['precision']:.3f} | {total['points']['recall']:.3f} | "
                       f"{total['slots']['precision']:.3f} | {total['slots']['recall']:.3f} | "
                       f"{loose['slots']['precision']:.3f} | {loose['slots']['recall']:.3f} |")
        details += ["", f"### {arch}", "",
                    "| scene | BEVs | point P | point R | point AP | slot P | slot R | slot AP |",
                    "| --- | --- | --- | --- | --- | --- | --- | --- |"]
        details += [_row(Path(r["folder"]).name, r) for r in results] + [_row("all", total)]
    lines += summary + details + [""]
    args.out.write_text("\n".join(lines))
    print("\n".join(lines))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
