"""Helpers every ``parksim bench`` subcommand shares: thread control, medians after a warm-up,
run metadata (machine, threads, commit, date, load), and writing a result as JSON + Markdown + PNG.

Only the CLI reaches this package (``parksim bench``); it may import ``recon`` and ``server`` lazily.
"""

from __future__ import annotations

import datetime
import json
import os
import platform
import re
import shutil
import statistics
import subprocess
import time
from collections.abc import Callable, Iterable, Sequence
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

import numpy as np

__all__ = ["ROOT", "RESULTS_MD", "Timing", "Written", "set_threads", "time_medians", "fit_exponent", "load_average",
           "cpu_model", "metadata", "meta_lines", "md_table", "progress", "write_result", "refresh_results_md",
           "pyplot", "save_figure"]

ROOT = Path(__file__).resolve().parents[2]
"""The checkout (benchmarks/, tests/, configs/ live here)."""

RESULTS_MD = ROOT / "benchmarks" / "RESULTS.md"


@dataclass(frozen=True)
class Timing:
    """Median wall-clock and process-CPU milliseconds of repeated calls (CPU sums threads, excludes waiting)."""

    wall_ms: float
    cpu_ms: float
    repeats: int


def set_threads(n: int) -> None:
    """Use ``n`` threads in numba kernels and torch ops (numba resets the count torch reads, so set both)."""
    import numba
    import torch

    numba.set_num_threads(min(n, numba.config.NUMBA_NUM_THREADS))  # type: ignore[attr-defined]  # set at import
    torch.set_num_threads(n)


def time_medians(fns: Sequence[Callable[[], Any]], repeats: int, warmup: int = 1,
                 tick: Callable[[], Any] = lambda: None) -> list[Timing]:
    """Median time of each closure, called in turn per round so a change of load hits all of them alike, in
    reverse order every other round (the first of a round was measured to read up to 10 % slower);
    ``warmup`` untimed rounds first; ``tick`` is called after every round (progress)."""
    for _ in range(warmup):
        for fn in fns:
            fn()
        tick()
    samples: list[list[tuple[float, float]]] = [[] for _ in fns]
    for r in range(repeats):
        for k in range(len(fns)) if r % 2 == 0 else reversed(range(len(fns))):
            t0, c0 = time.perf_counter(), time.process_time()
            fns[k]()
            samples[k].append((1e3 * (time.perf_counter() - t0), 1e3 * (time.process_time() - c0)))
        tick()
    return [Timing(statistics.median(w for w, _ in ts), statistics.median(c for _, c in ts), repeats) for ts in samples]


def fit_exponent(xs: Sequence[float], ys: Sequence[float]) -> float:
    """Slope of log y against log x (least squares): y ~ x^slope."""
    return float(np.polyfit(np.log(np.asarray(xs, float)), np.log(np.asarray(ys, float)), 1)[0])


def _commit() -> str:
    """Short commit of the checkout, with ``+dirty`` when tracked files differ from it ('unknown' outside git)."""
    try:
        head = subprocess.run(["git", "rev-parse", "--short", "HEAD"], cwd=ROOT, capture_output=True, text=True,
                              check=True).stdout.strip()
        dirty = subprocess.run(["git", "diff", "--quiet", "HEAD", "--", "parksim", "recon", "server"],
                               cwd=ROOT).returncode != 0
    except (OSError, subprocess.CalledProcessError):
        return "unknown"
    return head + ("+dirty" if dirty else "")


def cpu_model() -> str:
    """The CPU's model name (/proc/cpuinfo), else what platform knows."""
    cpuinfo = Path("/proc/cpuinfo")
    lines = cpuinfo.read_text().splitlines() if cpuinfo.is_file() else []
    return next((ln.split(":", 1)[1].strip() for ln in lines if ln.startswith("model name")),
                platform.processor() or platform.machine())


def load_average() -> list[float]:
    """1, 5 and 15 minute load averages (the machine may be shared: state them with every timing)."""
    return [round(x, 2) for x in os.getloadavg()]


def metadata(command: str) -> dict[str, Any]:
    """What every figure records: command, machine, threads, versions, commit, date and load at the start."""
    import numba
    import torch

    return {"command": command, "date": datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="seconds"),
            "commit": _commit(), "machine": f"{platform.node()}: {cpu_model()}, {os.cpu_count()} cores",
            "python": platform.python_version(), "torch": torch.__version__, "numba": numba.__version__,
            "torch_threads": torch.get_num_threads(), "numba_threads": numba.get_num_threads(),
            "load_start": load_average()}


def meta_lines(meta: dict[str, Any]) -> list[str]:
    """The metadata as Markdown bullet lines."""
    return [f"- command: `{meta['command']}`",
            f"- machine: {meta['machine']}; python {meta['python']}, torch {meta['torch']}, numba {meta['numba']}",
            f"- commit {meta['commit']}, {meta['date']}; threads: numba {meta['numba_threads']}, "
            f"torch {meta['torch_threads']}",
            f"- load average (1/5/15 min) at start {meta['load_start']}, at end {meta.get('load_end', '?')}"]


def md_table(headers: Sequence[str], rows: Iterable[Sequence[Any]]) -> list[str]:
    """A Markdown table; floats get 4 significant digits."""
    def cell(v: Any) -> str:
        return f"{v:.4g}" if isinstance(v, float) else str(v)

    return ["| " + " | ".join(headers) + " |", "|" + " --- |" * len(headers),
            *("| " + " | ".join(cell(v) for v in row) + " |" for row in rows)]


def progress(total: int, desc: str, quiet: bool) -> Any:
    """A tqdm bar on stderr (hidden with ``quiet``)."""
    from tqdm import tqdm

    return tqdm(total=total, desc=desc, unit="pt", disable=quiet, dynamic_ncols=True)


def _jsonable(v: Any) -> Any:
    if isinstance(v, float) and not np.isfinite(v):
        return None if np.isnan(v) else ("inf" if v > 0 else "-inf")
    if isinstance(v, dict):
        return {k: _jsonable(x) for k, x in v.items()}
    if isinstance(v, (list, tuple)):
        return [_jsonable(x) for x in v]
    if hasattr(v, "__dataclass_fields__"):
        return _jsonable(asdict(v))
    return v


@dataclass(frozen=True)
class Written:
    """Paths of one subcommand's outputs."""

    json: Path
    markdown: Path
    figure: Path | None


def write_result(out_dir: Path, name: str, meta: dict[str, Any], data: dict[str, Any], body: list[str],
                 figure: Callable[[Path], None] | None = None) -> Written:
    """Write ``name.json`` (meta + data), ``name.md`` (title, metadata, ``body``) and ``name.png`` (``figure``)."""
    out_dir.mkdir(parents=True, exist_ok=True)
    meta = {**meta, "load_end": load_average()}
    png: Path | None = None
    if figure is not None:
        png = out_dir / f"{name}.png"
        figure(png)
    js = out_dir / f"{name}.json"
    js.write_text(json.dumps(_jsonable({"meta": meta, **data}), indent=1) + "\n")
    md = out_dir / f"{name}.md"
    picture = [f"![{name}](figures/{png.name})", ""] if png is not None else []
    md.write_text("\n".join([*meta_lines(meta), "", *picture, *body]) + "\n")
    return Written(js, md, png)


def refresh_results_md(written: Written, title: str, results_md: Path = RESULTS_MD) -> None:
    """Put ``written``'s Markdown into ``results_md`` between this result's markers (replacing an older copy,
    else appended) and copy its figure to ``figures/`` beside it, where the Markdown links it."""
    name = written.markdown.stem
    begin, end = f"<!-- parksim bench {name}: begin -->", f"<!-- parksim bench {name}: end -->"
    block = f"{begin}\n## {title}\n\n{written.markdown.read_text().rstrip()}\n{end}"
    text = results_md.read_text() if results_md.is_file() else "# ParkSim benchmark results\n"
    pattern = re.compile(re.escape(begin) + ".*?" + re.escape(end), re.S)
    text = pattern.sub(lambda _: block, text) if pattern.search(text) else text.rstrip() + "\n\n" + block + "\n"
    results_md.write_text(text)
    if written.figure is not None:
        (results_md.parent / "figures").mkdir(exist_ok=True)
        shutil.copyfile(written.figure, results_md.parent / "figures" / written.figure.name)


def pyplot() -> Any:
    """matplotlib's pyplot on the Agg backend (no display)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def save_figure(fig: Any, meta: dict[str, Any], png: Path) -> None:
    """Write machine, threads, commit, date and load into the figure's footer, save it as ``png`` and close it."""
    fig.text(0.01, 0.005, f"{meta['machine']} | threads numba {meta['numba_threads']} torch {meta['torch_threads']} | "
             f"commit {meta['commit']} | {meta['date']} | load {meta['load_start']}", fontsize=6, color="grey",
             ha="left", va="bottom")
    fig.tight_layout(rect=(0, 0.04, 1, 1))
    fig.savefig(png, dpi=110)
    pyplot().close(fig)
