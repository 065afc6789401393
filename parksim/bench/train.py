"""``parksim bench train``: test PSNR against training time for shipped configs on synthetic garages.

For each (scene, config): synthesise the scene (and its off-path split) if missing, train with periodic test-frame
evaluation (every ``eval_every`` iterations; set to a fifth of the run where the config has none), evaluate the
final bundle as ``parksim eval`` does (recorded test views, slot regions, the off-path split grouped by offset), and
plot test PSNR/SSIM against training CPU minutes (process time of the iterations: on a shared machine, or for a
run paused and resumed, wall-clock says more about the other jobs than about the run; the table gives both) and
PSNR against the offset from the recorded path.
The configs' rows also form the paper-shaped table (methods x scenes), with the paper's row names for the
30-minute presets.
"""

from __future__ import annotations

import argparse
import subprocess
import sys
from pathlib import Path
from typing import Any

from .common import md_table, metadata, progress, pyplot, save_figure, write_result

__all__ = ["run", "train_one", "finished", "ensure_dataset", "TARGET_DB"]

TARGET_DB = 28.0


def ensure_dataset(scene: str, data_root: Path, resolution: str | None) -> Path:
    """``data_root/<scene>_<width>`` (``<scene>`` without a resolution or with ``native``), made by ``parksim synth``
    if missing."""
    resolution = None if resolution == "native" else resolution
    data = data_root / (f"{scene}_{resolution.split('x')[0]}" if resolution else scene)
    if not data.is_dir():
        cmd = [sys.executable, "-m", "parksim.cli", "synth", scene, "-o", str(data), "--quiet"]
        subprocess.run(cmd + (["--resolution", resolution] if resolution else []), check=True)
    return data


def _config_with_eval(config: str, out: Path) -> Path:
    """``config`` with periodic evaluation switched on (a fifth of the run) and no progress bar, written to ``out``."""
    from parksim.recon.config import dump_config, load_config

    cfg = load_config(config)
    every = cfg.run.eval_every or max(1, cfg.photometric.iterations // 5)
    cfg = cfg.model_copy(update={"run": cfg.run.model_copy(update={"eval_every": every, "progress": False})})
    out.mkdir(parents=True, exist_ok=True)
    path = out / "bench_config.yaml"
    path.write_text(dump_config(cfg))
    return path


PAPER_ROWS = {"cpu_30min": "UT, photometric only (3DGUT row)",
              "cpu_30min_ewa": "Jacobian / EWA projection (FisheyeGS row)"}
"""The paper's Table 1 row each 30-minute preset stands for (docs/training.md)."""


def ensure_offpath(data: Path) -> None:
    """Write the dataset's off-path split (``parksim offpath``) when a synthetic dataset has none."""
    from ..synth.offpath import OFFPATH_DIR, OFFPATH_FILE, write_offpath

    if not (data / OFFPATH_DIR / OFFPATH_FILE).is_file():
        write_offpath(data)


def finished(out: Path) -> bool:
    """Whether ``out`` holds a finished run (its bundle written)."""
    return (out / "bundle.json").is_file()


def _evaluation(out: Path, data: Path, reuse: bool) -> dict[str, Any]:
    """``parksim eval``'s result for the bundle in ``out``: read from ``out/eval/eval.json`` when reusing one made on
    this dataset (and, if the dataset has an off-path split, with it), else computed and written there."""
    import json

    from parksim.recon.evaluate import evaluate_bundle

    from ..synth.offpath import OFFPATH_DIR, OFFPATH_FILE

    saved = out / "eval" / "eval.json"
    if reuse and saved.is_file():
        result: dict[str, Any] = json.loads(saved.read_text())
        wants_offpath = (data / OFFPATH_DIR / OFFPATH_FILE).is_file()
        if Path(result["dataset"]).resolve() == data.resolve() and (result.get("offpath") or not wants_offpath):
            return result
    return evaluate_bundle(out, data, out / "eval")


def train_one(scene: str, data: Path, config: str, out: Path, reuse: bool = False) -> dict[str, Any]:
    """Train and evaluate one scene with one config; returns its curve, final numbers and off-path groups.

    With ``reuse`` a finished run in ``out`` (and its evaluation) is taken as it is instead of being redone."""
    import os
    import shutil

    from parksim.recon.plots import read_metrics
    from parksim.recon.reconstruct import reconstruct

    from ..bundle import load

    if not (reuse and finished(out)):
        shutil.rmtree(out, ignore_errors=True)
        reconstruct(data, out, _config_with_eval(config, out.parent / f"{out.name}_config"), log=lambda _: None)
    records = read_metrics(out / "metrics.jsonl")
    curve = [r for r in records if r.get("test_psnr") is not None]
    meta = load(out).meta
    result = _evaluation(out, data, reuse)
    reached = next((r for r in curve if r["test_psnr"] >= TARGET_DB), None)
    return {"scene": scene, "config": Path(config).stem, "curve": curve, "iterations": meta["iterations"],
            "cpu_s": max((r.get("cpu_s", 0.0) for r in records), default=0.0), "load_end": os.getloadavg()[0],
            "gaussians": meta["gaussians"], "train_s": meta["train_seconds"], **result["overall"],
            "reached_s": reached and reached["elapsed_s"], "reached_cpu_s": reached and reached["cpu_s"],
            "offpath": result.get("offpath")}


def _fmt(v: float | None, digits: int) -> str:
    return "-" if v is None else f"{v:.{digits}f}"


def _minutes(seconds: float | None) -> str:
    return "-" if seconds is None else f"{seconds / 60:.1f}"


def _offpath_rows(results: list[dict[str, Any]]) -> tuple[list[str], list[list[str]]]:
    """PSNR (slot PSNR) per off-path group, one row per run that has an off-path split."""
    runs = [r for r in results if r["offpath"]]
    labels = list(dict.fromkeys(g["group"] for r in runs for g in r["offpath"]["groups"]))
    rows = []
    for r in runs:
        cells = {g["group"]: g for g in r["offpath"]["groups"]}
        on = r["offpath"]["on_path"]
        rows.append([r["scene"], r["config"], f"{_fmt(on['psnr'], 2)} ({_fmt(on['slot_psnr'], 2)})",
                     *(f"{_fmt(cells[k]['psnr'], 2)} ({_fmt(cells[k]['slot_psnr'], 2)})" if k in cells else "-"
                       for k in labels)])
    return ["scene", "config", "on path", *labels], rows


def _paper_table(results: list[dict[str, Any]]) -> list[str]:
    """Methods (configs) as rows, scenes as column pairs (PSNR, SSIM), in the shape of the paper's Table 1."""
    scenes = list(dict.fromkeys(r["scene"] for r in results))
    by = {(r["config"], r["scene"]): r for r in results}
    rows = [[PAPER_ROWS.get(c, c), *(x for s in scenes for x in ((_fmt(by[c, s]["psnr"], 2), _fmt(by[c, s]["ssim"], 3))
                                                                if (c, s) in by else ("-", "-")))]
            for c in dict.fromkeys(r["config"] for r in results)]
    return md_table(["method", *(f"{s} {k}" for s in scenes for k in ("PSNR", "SSIM"))], rows)


def run(args: argparse.Namespace) -> Any:
    """Train every (scene, config) pair in turn; write ``train.json/md/png``."""
    meta = metadata(args.command_line)
    pairs = [(s, c) for s in args.scenes for c in args.configs]
    skipped = [p for p in pairs if args.only_finished and not finished(_run_dir(args.work, *p))]
    pairs = [p for p in pairs if p not in skipped]
    results = []
    with progress(len(pairs), "bench train", args.quiet) as bar:
        for scene, config in pairs:
            data = ensure_dataset(scene, args.data_root, args.resolution)
            ensure_offpath(data)
            results.append(train_one(scene, data, config, _run_dir(args.work, scene, config),
                                     args.reuse or args.only_finished))
            bar.update(1)
    rows = [(r["scene"], r["config"], r["iterations"], r["gaussians"], _minutes(r["train_s"]), _minutes(r["cpu_s"]),
             f"{r['load_end']:.1f}", _fmt(r["psnr"], 2), _fmt(r["ssim"], 3), _fmt(r["slot_psnr"], 2),
             _minutes(r["reached_s"]), _minutes(r["reached_cpu_s"])) for r in results]
    headers, off_rows = _offpath_rows(results)
    body = ["Test frames: the dataset's test split, all cameras; time axis: training CPU minutes (process time of "
            "the iterations, periodic evaluation excluded).", "",
            *md_table(["scene", "config", "iterations", "Gaussians", "train min", "CPU min", "load at end",
                       "test PSNR", "test SSIM", "slot PSNR", f"min to {TARGET_DB:g} dB",
                       f"CPU min to {TARGET_DB:g} dB"], rows), "",
            "In the shape of the paper's Table 1 (recorded test views; LPIPS needs weights this machine cannot "
            "download, so it is not reported):", "", *_paper_table(results), "",
            "Off the recorded path (`parksim offpath`; docs/offpath.md): PSNR (slot-region PSNR) per group, both "
            "signs of each offset together:", "",
            *(md_table(headers, off_rows) if off_rows else ["(no off-path split)"]),
            *(["", "Not run (no finished run in the work folder): "
                + ", ".join(f"{sc} / {Path(c).stem}" for sc, c in skipped)] if skipped else []),
            "", "Curve points (CPU minutes, test PSNR):", "",
            *(f"- {r['scene']} / {r['config']}: " + ", ".join(f"({c['cpu_s'] / 60:.1f}, {c['test_psnr']:.2f})"
                                                              for c in r["curve"]) for r in results)]
    return write_result(args.out, "train", meta, {"runs": results}, body, lambda png: _plot(results, meta, png))


def _run_dir(work: Path, scene: str, config: str) -> Path:
    """Where the run of ``config`` on ``scene`` lives: ``work/<scene>_<config stem>``."""
    return work / f"{scene}_{Path(config).stem}"


def _offset_points(r: dict[str, Any], kind: str) -> tuple[list[float], list[float]]:
    """(offset, PSNR) of one run's groups of ``kind``, with the on-path reference at 0."""
    off = r["offpath"]
    points = [(0.0, off["on_path"]["psnr"])] + [(g["offset"], g["psnr"]) for g in off["groups"] if g["kind"] == kind]
    return [p[0] for p in points], [p[1] for p in points]


def _plot(results: list[dict[str, Any]], meta: dict[str, Any], png: Path) -> None:
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
    save_figure(fig, meta, png)
