"""Training benchmark: reconstruct synthetic garages at 320x240 with ``configs/cpu_fast.yaml`` on this machine.

For each scene: synthesise it if missing, train with periodic test-frame evaluation (every 10th frame, all
four cameras), evaluate the final bundle, then plot test PSNR/SSIM against training wall-clock time
(``benchmarks/figures/train_psnr_vs_time.png``) and write ``benchmarks/RESULTS_train.md``.

    .venv/bin/python benchmarks/bench_train.py [--scenes scene1 scene3] [--config configs/cpu_fast.yaml]
"""

from __future__ import annotations

import argparse
import datetime
import json
import os
import platform
import shutil
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
TARGET_DB = 28.0


def _machine() -> str:
    """CPU model, core count and load at the start (the machine is shared: timings are noisy)."""
    model = next((line.split(":", 1)[1].strip() for line in Path("/proc/cpuinfo").read_text().splitlines()
                  if line.startswith("model name")), platform.processor())
    return f"{model}, {os.cpu_count()} cores, load average {os.getloadavg()[0]:.1f} at start"


def _ensure_dataset(scene: str, data_root: Path, resolution: str) -> Path:
    data = data_root / f"{scene}_{resolution.split('x')[0]}"
    if not data.is_dir():
        subprocess.run([sys.executable, "-m", "parksim.cli", "synth", scene, "--resolution", resolution,
                        "-o", str(data), "--quiet"], check=True, cwd=ROOT)
    return data


def _run(scene: str, data: Path, config: Path, out_root: Path) -> dict:
    """Train and evaluate one scene; returns its curve and final numbers."""
    from recon.evaluate import evaluate_views
    from recon.plots import read_metrics
    from recon.reconstruct import reconstruct
    from recon.response import CameraResponse

    from parksim.bundle import load
    from parksim.data import DatasetReader

    out = out_root / scene
    shutil.rmtree(out, ignore_errors=True)
    reconstruct(data, out, config)
    records = read_metrics(out / "metrics.jsonl")
    curve = [r for r in records if r.get("test_psnr") is not None]
    bundle, reader = load(out), DatasetReader(data)
    response = CameraResponse(reader.rig, 0.0)
    response.load_dict(bundle.meta["camera_response"])
    views = [(f, c) for f in reader.split["test"] for c in reader.rig.names]
    report = evaluate_views(bundle.scene, reader, views, response)
    reached = next((r["elapsed_s"] for r in curve if r["test_psnr"] >= TARGET_DB), None)
    cpu = max((r.get("cpu_s", 0.0) for r in records), default=0.0)
    return {"scene": scene, "curve": curve, "iterations": bundle.meta["iterations"], "cpu_s": cpu,
            "load_end": os.getloadavg()[0],
            "gaussians": bundle.meta["gaussians"], "train_s": bundle.meta["train_seconds"],
            "psnr": report.mean("psnr"), "ssim": report.mean("ssim"), "slot_psnr": report.mean("slot_psnr"),
            "slot_ssim": report.mean("slot_ssim"), "reached_s": reached}


def _plot(results: list[dict], png: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, (a, b) = plt.subplots(1, 2, figsize=(11, 4))
    for r in results:
        t = [c["elapsed_s"] / 60 for c in r["curve"]]
        a.plot(t, [c["test_psnr"] for c in r["curve"]], "o-", label=r["scene"])
        b.plot(t, [c["test_ssim"] for c in r["curve"]], "o-", label=r["scene"])
    a.axhline(TARGET_DB, color="grey", ls="--", lw=0.8)
    a.set(xlabel="training wall-clock (min)", ylabel="test PSNR (dB)", title="test frames, 320x240, 2 CPU cores")
    b.set(xlabel="training wall-clock (min)", ylabel="test SSIM")
    a.legend()
    b.legend()
    fig.tight_layout()
    png.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(png, dpi=100)


def _fmt(v: float | None, digits: int) -> str:
    return "not computed" if v is None else f"{v:.{digits}f}"


def _markdown(results: list[dict], command: str, machine: str, config: Path) -> str:
    lines = ["# Training benchmark (photometric phase, CPU)", "",
             f"- command: `{command}`", f"- config: `{config.relative_to(ROOT)}`", f"- machine: {machine}",
             f"- date: {datetime.datetime.now().isoformat(timespec='minutes')}",
             "- time axis: training wall-clock, periodic evaluation excluded; test frames = every 10th frame, 4 cameras",
             "- the machine is shared: CPU min (process CPU time of the training iterations, both cores) shows how much",
             "  of the wall-clock the run actually got; load average at the end of each scene is in the table",
             "", "![curve](figures/train_psnr_vs_time.png)", "",
             "| scene | iterations | Gaussians | train min | CPU min | load at end | test PSNR | test SSIM | slot PSNR | "
             "slot SSIM | min to 28 dB |", "| --- | --- | --- | --- | --- | --- | --- | --- | --- | --- | --- |"]
    for r in results:
        reached = "not reached" if r["reached_s"] is None else f"{r['reached_s'] / 60:.1f}"
        lines.append(f"| {r['scene']} | {r['iterations']} | {r['gaussians']} | {r['train_s'] / 60:.1f} | "
                     f"{r['cpu_s'] / 60:.1f} | {r['load_end']:.1f} | "
                     f"{_fmt(r['psnr'], 2)} | {_fmt(r['ssim'], 3)} | {_fmt(r['slot_psnr'], 2)} | "
                     f"{_fmt(r['slot_ssim'], 3)} | {reached} |")
    lines += ["", "Curve points (minutes, test PSNR, test SSIM):", ""]
    for r in results:
        pts = ", ".join(f"({c['elapsed_s'] / 60:.1f}, {c['test_psnr']:.2f}, {c['test_ssim']:.3f})" for c in r["curve"])
        lines.append(f"- {r['scene']}: {pts}")
    return "\n".join(lines) + "\n"


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--scenes", nargs="+", default=["scene1", "scene3"])
    parser.add_argument("--config", type=Path, default=ROOT / "configs" / "cpu_fast.yaml")
    parser.add_argument("--resolution", default="320x240")
    parser.add_argument("--data-root", type=Path, default=ROOT / "data")
    parser.add_argument("--out", type=Path, default=ROOT / "out" / "bench_train")
    args = parser.parse_args()
    machine = _machine()
    previous = args.out / "results.json"
    # Scenes measured earlier and not re-run now stay in the table (each row records its own load).
    results = [r for r in (json.loads(previous.read_text()) if previous.is_file() else [])
               if r["scene"] not in args.scenes]
    for scene in args.scenes:
        data = _ensure_dataset(scene, args.data_root, args.resolution)
        results.append(_run(scene, data, args.config.resolve(), args.out))
        json.dump(results, open(args.out / "results.json", "w"), indent=1)
        _plot(results, ROOT / "benchmarks" / "figures" / "train_psnr_vs_time.png")
        command = "python benchmarks/bench_train.py " + " ".join(sys.argv[1:])
        (ROOT / "benchmarks" / "RESULTS_train.md").write_text(_markdown(results, command, machine, args.config.resolve()))
    return 0


if __name__ == "__main__":
    sys.exit(main())
