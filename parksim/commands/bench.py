"""``parksim bench``: render / train / scaling / stress / soak-train / soak-server benchmarks.

Each writes ``<out>/<name>.json``, ``.md`` and ``.png`` and, unless ``--quick`` or ``--no-results-md``,
refreshes its section of ``benchmarks/RESULTS.md`` (figure copied to ``benchmarks/figures/``).
Options whose default differs under ``--quick`` default to None here and are filled in by ``_resolve``.
"""

from __future__ import annotations

import argparse
import os
from collections.abc import Callable
from pathlib import Path
from typing import Any

__all__ = ["add_parser", "run"]

OUT = Path("benchmarks/results")
WORK = Path("out/bench")


def _floats(text: str) -> list[float]:
    return [float(v) for v in text.split(",") if v]


def _ints(text: str) -> list[int]:
    return [int(float(v)) for v in text.split(",") if v]


def _words(text: str) -> list[str]:
    return [v for v in text.split(",") if v]


def _option(p: argparse.ArgumentParser, name: str, full: Any, quick: Any, help: str,
            type: Callable[[str], Any] | None = None) -> None:
    """An option whose default is ``full``, or ``quick`` under ``--quick``."""
    def shown(v: Any) -> str:
        return ",".join(f"{x:g}" if isinstance(x, float) else str(x) for x in v) if isinstance(v, list) else str(v)

    p.add_argument(name, type=type or str, default=None,
                   help=f"{help} (default {shown(full)}; --quick: {shown(quick)})")
    p.set_defaults(**{f"_default_{name.lstrip('-').replace('-', '_')}": (full, quick)})


def _common(p: argparse.ArgumentParser) -> None:
    p.add_argument("--out", type=Path, default=OUT, help="where JSON/Markdown/PNG go")
    p.add_argument("--work", type=Path, default=WORK, help="scratch folder for datasets, bundles and runs it makes")
    p.add_argument("--quick", action="store_true", help="a small run (seconds) for tests; never refreshes RESULTS.md")
    p.add_argument("--results-md", type=Path, default=Path("benchmarks/RESULTS.md"),
                   help="Markdown file whose section for this benchmark is refreshed")
    p.add_argument("--no-results-md", action="store_true", help="do not refresh --results-md")
    p.add_argument("--seed", type=int, default=0, help="seed of the scenes, poses and hypothesis")
    p.add_argument("--quiet", action="store_true", help="no progress bar")


def add_parser(sub: argparse._SubParsersAction) -> argparse.ArgumentParser:
    p = sub.add_parser(
        "bench", help="benchmarks: render knobs, training, scaling, stress campaign, soaks",
        description="Seeded benchmarks. Each writes OUT/NAME.json, NAME.md and NAME.png (machine, threads, commit, "
                    "date and load recorded; timings are medians after a warm-up) and refreshes its section of "
                    "benchmarks/RESULTS.md. Use --quick for a seconds-long smoke run.")
    cmds = p.add_subparsers(dest="bench", metavar="BENCHMARK")
    cmds.required = True
    cpus = os.cpu_count() or 1

    r = cmds.add_parser("render", help="latency vs error over the knobs a user can turn (Pareto plot)",
                        description="Change one knob at a time from full quality (first input, scale 1, full SH, UT, "
                                    "all cameras, no BEV, auto backend, most threads) and record the median latency, "
                                    "the error against the full-quality render (PSNR, max abs) and, for trained "
                                    "bundles, the PSNR against the dataset's ground truth at one test frame.")
    r.add_argument("--bundle", type=Path, action="append", default=[],
                   help="a scene bundle; repeat to compare several (e.g. compaction levels); the first is the "
                        "reference")
    r.add_argument("--dataset", type=Path,
                   help="dataset giving pose, rig and ground truth (default: the first bundle's, else "
                        "data/scene1_320, or synth tiny under --quick; with no bundle a garage-like scene of "
                        "--gaussians is built from its points)")
    _option(r, "--gaussians", 200_000, 500, "Gaussians of the built scene when no --bundle is given", int)
    r.add_argument("--frame", type=int, help="dataset frame whose pose is rendered (default: first test frame)")
    _option(r, "--scales", [1.0, 0.75, 0.5, 0.25], [1.0, 0.5], "resolution scales of the fisheye views", _floats)
    _option(r, "--sh-degrees", [0, 1, 2], [0], "SH degree caps (values >= the scene's degree are skipped)", _ints)
    _option(r, "--methods", ["ut", "ewa"], ["ut", "ewa"], "projections: ut (unscented) or ewa (Jacobian)", _words)
    _option(r, "--camera-sets", ["front", "front+rear", "all+bev"], ["front", "all+bev"],
            "camera subsets requested ('+'-joined names or all; suffix +bev adds the BEV)", _words)
    _option(r, "--backends", ["auto"], ["auto", "torch"],
            "rasterizer backends (auto, numba, torch = dense reference: small scenes only, gsplat: CUDA)", _words)
    _option(r, "--threads", sorted({1, cpus}), [1], "numba/torch thread counts", _ints)
    _option(r, "--repeats", 5, 1, "timed renders per point (median), after --warmup", int)
    r.add_argument("--warmup", type=int, default=1, help="untimed renders first (JIT, caches)")
    _common(r)

    t = cmds.add_parser("train", help="test PSNR against training wall-clock for the shipped configs",
                        description="Synthesise each scene if missing, train it with each config (periodic test "
                                    "evaluation on), evaluate the bundle, plot test PSNR/SSIM against wall-clock.")
    _option(t, "--scenes", ["scene1"], ["tiny"], "synth presets to train", _words)
    _option(t, "--configs", ["cpu_fast", "demo"], ["tiny"],
            "training configs (packaged preset names or YAML paths)", _words)
    _option(t, "--resolution", "320x240", "native", "synth resolution WxH, or native: the preset's own "
            "(640x480; the 30-minute presets train at native)")
    t.add_argument("--data-root", type=Path, default=Path("data"), help="where datasets are found or synthesised")
    t.add_argument("--reuse", action="store_true",
                   help="take finished runs in --work (WORK/<scene>_<config>) and their eval/eval.json as they are "
                        "instead of retraining; pairs without one are trained")
    t.add_argument("--only-finished", action="store_true",
                   help="leave out the pairs with no finished run in --work (listed as not run); implies --reuse")
    _common(t)

    s = cmds.add_parser("scaling", help="latency vs number of Gaussians and of pixels, fitted growth exponents",
                        description="Forward latency of one camera over N Gaussians (garage-like scenes from the "
                                    "dataset's points) at --base-width, and over widths at --base-gaussians; "
                                    "exponents of time ~ N^a and ~ pixels^b fitted on CPU time.")
    s.add_argument("--dataset", type=Path, help="dataset (default data/scene1_320; synth tiny under --quick)")
    _option(s, "--gaussians", [1_000, 3_000, 10_000, 30_000, 100_000, 300_000, 1_000_000], [500, 1_000, 2_000],
            "scene sizes of the N sweep", _ints)
    _option(s, "--widths", [160, 320, 640, 1280], [40, 80, 160], "image widths of the pixel sweep", _ints)
    _option(s, "--base-width", 320, 80, "width during the N sweep", int)
    _option(s, "--base-gaussians", 100_000, 1_000, "Gaussians during the pixel sweep", int)
    _option(s, "--repeats", 5, 1, "timed renders per point (median)", int)
    s.add_argument("--warmup", type=int, default=1, help="untimed renders first")
    s.add_argument("--threads", type=int, default=cpus, help="numba/torch threads")
    _common(s)

    st = cmds.add_parser("stress", help="the hypothesis stress suite at many examples: cases tried, failures found",
                         description="Run tests/test_stress.py (projection, rasterizer, IPM, losses, render at the "
                                     "scene edge; float32 finiteness and float64 agreement) with --examples per "
                                     "property instead of CI's default, counting cases and failures.")
    _option(st, "--examples", 500, 3, "hypothesis examples per property", int)
    st.add_argument("--tests", type=Path, default=None, help="test file (default tests/test_stress.py of the checkout)")
    _common(st)

    k = cmds.add_parser("soak-train", help="long training on a tiny scene: NaN checks, Gaussian count, RSS",
                        description="Train a tiny synthetic scene for --steps iterations with densification on to "
                                    "the end (bounded by --max-seconds), logging loss, Gaussian count and RSS and "
                                    "checking loss and parameters are finite every --log-every steps.")
    _option(k, "--steps", 20_000, 30, "training iterations", int)
    _option(k, "--max-seconds", 3600.0, 120.0, "stop after this long", float)
    _option(k, "--log-every", 100, 10, "steps between log lines", int)
    k.add_argument("--config", default="tiny", help="training config to stretch (packaged preset name or YAML path)")
    k.add_argument("--dataset", type=Path, help="dataset (default: synth tiny under --work)")
    _common(k)

    v = cmds.add_parser("soak-server", help="fixed request count to a loopback server, its memory before and after",
                        description="Serve a garage-like bundle with `parksim serve` on 127.0.0.1 only and send "
                                    "--requests sequential GET /render (all cameras + BEV), logging the server's RSS.")
    _option(v, "--requests", 500, 5, "requests to send", int)
    _option(v, "--gaussians", 20_000, 500, "Gaussians of the served scene", int)
    _option(v, "--max-seconds", 1800.0, 120.0, "stop after this long", float)
    _option(v, "--log-every", 25, 1, "requests between RSS samples", int)
    v.add_argument("--dataset", type=Path, help="dataset for the scene and poses (default: synth tiny under --work)")
    _common(v)
    return p


def _resolve(args: argparse.Namespace) -> None:
    """Fill options left unset with their full or --quick default, and record the effective command line."""
    for key in [k for k in vars(args) if k.startswith("_default_")]:
        name = key.removeprefix("_default_")
        if getattr(args, name) is None:
            full, quick = getattr(args, key)
            setattr(args, name, quick if args.quick else full)
        delattr(args, key)
    shown = {k: v for k, v in vars(args).items() if not k.startswith("_") and k not in ("command", "bench")}
    parts = [f"--{k.replace('_', '-')}" if v is True else
             " ".join(f"--bundle {b}" for b in v) if k == "bundle" else   # the one repeatable option
             f"--{k.replace('_', '-')} {','.join(map(str, v)) if isinstance(v, list) else v}"
             for k, v in shown.items() if v not in (None, False, [])]
    args.command_line = " ".join(["parksim bench", args.bench, *parts])


def _dataset(args: argparse.Namespace) -> Path:
    """``--dataset``, else tiny (synthesised under --work) with --quick, else data/scene1_320 (made if missing)."""
    from ..bench.train import ensure_dataset

    if args.dataset is not None:
        return args.dataset
    return ensure_dataset("tiny", args.work, None) if args.quick else ensure_dataset("scene1", Path("data"), "320x240")


# subcommand -> (module in parksim.bench, its entry function, RESULTS.md section title)
SUBCOMMANDS = {
    "render": ("render", "run", "Render: latency vs error over the user's knobs (`parksim bench render`)"),
    "train": ("train", "run", "Training: test PSNR vs CPU minutes (`parksim bench train`)"),
    "scaling": ("scaling", "run", "Scaling: latency vs Gaussians and pixels (`parksim bench scaling`)"),
    "stress": ("stress", "run", "Stress campaign (`parksim bench stress`)"),
    "soak-train": ("soak", "soak_train", "Soak: long training run (`parksim bench soak-train`)"),
    "soak-server": ("soak", "soak_server", "Soak: server (`parksim bench soak-server`)"),
}


def run(args: argparse.Namespace) -> int:
    import importlib

    from ..bench.common import refresh_results_md
    from ..bench.stress import STRESS_TESTS

    _resolve(args)
    module, function, title = SUBCOMMANDS[args.bench]
    if args.bench == "scaling" or (args.bench == "render" and not args.bundle):
        args.dataset = _dataset(args)
    if args.bench == "stress":
        args.tests = args.tests or STRESS_TESTS
    written = getattr(importlib.import_module(f"parksim.bench.{module}"), function)(args)
    if not (args.quick or args.no_results_md):
        refresh_results_md(written, title, args.results_md)
    print(f"wrote {written.json}, {written.markdown}" + (f", {written.figure}" if written.figure else ""))
    return 0
