"""``parksim detector``: train slot detectors (DMPR-PS-style, GCN-Parking-style) on GT BEVs and evaluate them."""

from __future__ import annotations

import argparse
from pathlib import Path

from .argtypes import integer, number

__all__ = ["add_parser", "run"]


def add_parser(subparsers: argparse._SubParsersAction) -> argparse.ArgumentParser:
    """Register ``detector train`` and ``detector eval`` (cheap: no heavy imports)."""
    p = subparsers.add_parser(
        "detector", help="train and evaluate parking-slot detectors on ground-truth BEVs",
        description="Parking-slot detectors for the slot-aware losses and the downstream evaluation: "
                    "DMPR-PS-style (marking points on a 1/32 grid, slots by pairing rules) and GCN-Parking-style "
                    "(plus an attentional graph scoring ordered point pairs).")
    sub = p.add_subparsers(dest="detector_command", metavar="ACTION")
    sub.required = True

    t = sub.add_parser("train", help="train a detector on the train frames of dataset folders",
                       description="Train on the ground-truth BEVs (ipm/) and slot labels (labels/) of the train "
                                   "frames of ParkSim dataset folders, or on every image of ps2.0-style folders "
                                   "(NAME.json + NAME.jpg). Rotation, mirror and photometric augmentation.")
    t.add_argument("arch", choices=["dmpr", "gcn"], help="detector architecture")
    t.add_argument("data", nargs="+", type=Path, help="dataset or ps2.0 folders")
    t.add_argument("-o", "--output", type=Path, required=True, help="output folder (model.pt, train.json)")
    t.add_argument("--width", type=number(0, open_low=True), default=0.25, help="channel width multiplier")
    t.add_argument("--input-size", type=integer(32), default=256, help="network input side in px, multiple of 32")
    t.add_argument("--steps", type=integer(1), default=1200, help="optimiser steps")
    t.add_argument("--batch-size", type=integer(1), default=8, help="BEVs per step")
    t.add_argument("--lr", type=number(0, open_low=True), default=2e-3, help="peak learning rate (one-cycle)")
    t.add_argument("--seed", type=int, default=0, help="seed for weights, sampling and augmentation")
    t.add_argument("--threads", type=integer(1), default=2, help="torch CPU threads")
    t.add_argument("--init", type=Path, help="start from a trained detector's matching weights (GCN from DMPR)")
    t.add_argument("--device", default="cpu", help="cpu, or cuda[:N] to train on a GPU (checkpoints load on CPU)")
    t.add_argument("--quiet", action="store_true", help="no progress bar")

    e = sub.add_parser("eval", help="precision, recall and AP of a detector on a data folder",
                       description="--protocol parksim (default): a marking point is true when within "
                                   "--distance-px (at 600 px = 10 m, converted to the BEV's scale) of a labelled "
                                   "point and its direction within --direction-deg; a slot when both ordered "
                                   "entrance points match and its angle agrees within --slot-angle-deg. "
                                   "--protocol dmpr-ps: DMPR-PS' published rules with their fixed thresholds "
                                   "(docs/detection_protocol.md).")
    e.add_argument("model", type=Path, help="trained detector (folder or model.pt)")
    e.add_argument("data", type=Path, help="dataset or ps2.0 folder")
    e.add_argument("--split", choices=["test", "train", "all"], default="test",
                   help="frames of a dataset folder (ps2.0 folders: all images)")
    e.add_argument("--threshold", type=number(0, 1, open_low=True, open_high=True), default=0.5,
                   help="marking-point confidence threshold, in (0, 1)")
    e.add_argument("--distance-px", type=number(0, open_low=True), default=10.0,
                   help="point distance at DMPR-PS scale")
    e.add_argument("--direction-deg", type=number(0, 180, open_low=True), default=30.0,
                   help="point direction tolerance")
    e.add_argument("--slot-angle-deg", type=number(0, 180, open_low=True), default=10.0, help="slot angle tolerance")
    e.add_argument("--protocol", choices=["parksim", "dmpr-ps"], default="parksim", help="detection scoring rules")
    e.add_argument("--json", type=Path, help="also write the metrics here")
    e.add_argument("--threads", type=integer(1), default=2, help="torch CPU threads")
    return p


def _train(args: argparse.Namespace) -> int:
    from parksim.recon.detectors.train import TrainOptions, train_detector

    from .outputs import check_output_folder

    check_output_folder(args.output)
    opts = TrainOptions(arch=args.arch, width=args.width, input_size=args.input_size, steps=args.steps,
                        batch_size=args.batch_size, lr=args.lr, seed=args.seed, threads=args.threads,
                        init=str(args.init) if args.init else None, device=args.device)
    path = train_detector(args.data, args.output, opts, progress=not args.quiet)
    print(f"wrote {path}")
    return 0


def _eval(args: argparse.Namespace) -> int:
    import torch

    from parksim.recon.detectors import DecodeOptions, load_detector
    from parksim.recon.detectors.evaluate import MatchOptions, evaluate_folder
    from parksim.recon.detectors.protocols import get_protocol

    from ..fileio import write_json
    from .outputs import check_output_file

    protocol = get_protocol(args.protocol, MatchOptions(args.distance_px, args.direction_deg, args.slot_angle_deg))
    if args.json:
        check_output_file(args.json)
    torch.set_num_threads(args.threads)
    model = load_detector(args.model)
    result = evaluate_folder(model, args.data, args.split, DecodeOptions(threshold=args.threshold), protocol)
    print(f"{args.data} ({result['split']}, {result['images']} BEVs, {result['ms_per_bev']:.1f} ms/BEV, "
          f"{protocol.name} protocol)")
    for name in ("points", "slots"):
        m = result[name]
        print(f"  {name:6s} precision {m['precision']:.3f}  recall {m['recall']:.3f}  AP {m['ap']:.3f}  "
              f"(TP {m['tp']}, FP {m['fp']}, labelled {m['labelled']})")
    if args.json:
        write_json(args.json, result)
    return 0


def run(args: argparse.Namespace) -> int:
    """Dispatch to ``train`` or ``eval``."""
    return _train(args) if args.detector_command == "train" else _eval(args)
