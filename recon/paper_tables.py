"""Markdown versions of the paper's experiment tables from ``recon.paper_eval`` results (one result per scene).

* Novel view synthesis: photometric-only and full slot-aware reconstructions, PSNR/SSIM over the whole valid
  image and over slot regions.
* One detection table per detector: precision/recall of marking points and slots on the ground-truth BEVs
  ("GT-" row) and on each of those reconstructions' rendered BEVs.
* Ablation: every reconstruction, rendering quality plus each detector's slot precision/recall on its BEVs.
Rows are matched across scenes by label; a cell a scene lacks reads "n/a". Each detection table names the
scoring protocol (``recon.detectors.protocols``; results from before protocols were recorded used ParkSim's).
"""

from __future__ import annotations

from collections.abc import Callable, Iterable
from typing import Any

__all__ = ["tables_markdown", "DETECTOR_TITLES"]

DETECTOR_TITLES = {"dmpr": "DMPR-PS", "gcn": "GCN"}


def _f(value: float | None, digits: int) -> str:
    return "n/a" if value is None else f"{value:.{digits}f}"


def _row(cells: Iterable[str]) -> str:
    return "| " + " | ".join(cells) + " |"


def _table(header: list[str], rows: list[list[str]]) -> list[str]:
    return [_row(header), _row(["---"] * len(header)), *(_row(r) for r in rows)]


def _main(run: dict[str, Any]) -> bool:
    """The paper's main rows: photometric only and the full slot-aware variant."""
    return run["variant"] in (None, "full")


def _labels(results: list[dict[str, Any]], keep: Callable[[dict[str, Any]], bool]) -> list[str]:
    """Labels of the runs ``keep`` selects, in order of first appearance over the scenes."""
    seen: dict[str, None] = {}
    for result in results:
        seen.update((run["label"], None) for run in result["runs"] if keep(run))
    return list(seen)


def _run(result: dict[str, Any], label: str) -> dict[str, Any] | None:
    return next((run for run in result["runs"] if run["label"] == label), None)


def _pr(scores: dict[str, Any] | None, what: str) -> list[str]:
    if scores is None:
        return ["n/a", "n/a"]
    return [_f(scores[what]["precision"], 3), _f(scores[what]["recall"], 3)]


def _quality(run: dict[str, Any]) -> list[str]:
    return [str(run["iterations"]), _f(run["psnr"], 2), _f(run["ssim"], 3), _f(run["slot_psnr"], 2),
            _f(run["slot_ssim"], 3)]


def _synthesis(results: list[dict[str, Any]]) -> list[str]:
    rows = [[r["scene"], run["label"], *_quality(run)] for r in results for run in r["runs"] if _main(run)]
    return ["### Novel view synthesis (test frames, all cameras)", "",
            *_table(["Scene", "Reconstruction", "iterations", "PSNR", "SSIM", "slot PSNR", "slot SSIM"], rows)]


def _protocol(results: list[dict[str, Any]]) -> str:
    """The line that names the detection scoring protocol(s) of ``results``."""
    names = dict.fromkeys(r.get("protocol", {}).get("name", "parksim") for r in results)
    return f"Detection scored with the {' / '.join(names)} protocol (docs/detection_protocol.md)."


def _detection(results: list[dict[str, Any]], detector: str) -> list[str]:
    title = DETECTOR_TITLES.get(detector, detector)
    header = ["Variant"] + [f"{r['scene']} {c}" for r in results for c in ("point P", "point R", "slot P", "slot R")]
    rows = [[f"GT-{title}"] + [c for r in results for c in _pr(r["gt"].get(detector), "points")
                               + _pr(r["gt"].get(detector), "slots")]]
    for label in _labels(results, _main):
        cells = []
        for r in results:
            run = _run(r, label)
            scores = run["detection"].get(detector) if run is not None else None
            cells += _pr(scores, "points") + _pr(scores, "slots")
        rows.append([label] + cells)
    counts = "; ".join(f"{r['scene']}: {_count(r, detector)}" for r in results)
    return [f"### {title} on ground-truth vs rendered BEVs of the test frames", "", *_table(header, rows), "",
            f"Labelled: {counts}.", _protocol(results)]


def _count(result: dict[str, Any], detector: str) -> str:
    gt = result["gt"].get(detector)
    if gt is None:
        return "n/a"
    return (f"{gt['points']['labelled']} points, {gt['slots']['labelled']} slots in "
            f"{len(result['test_frames'])} test frames")


def _ablation(results: list[dict[str, Any]], detectors: list[str]) -> list[str]:
    header = ["Variant", "iterations", "PSNR", "SSIM", "slot PSNR", "slot SSIM"]
    header += [f"{DETECTOR_TITLES.get(d, d)} slot {m}" for d in detectors for m in ("P", "R")]
    rows = []
    for r in results:
        rows.append([f"*{r['scene']}*"] + [""] * (len(header) - 1))
        rows += [[run["label"], *_quality(run), *(c for d in detectors for c in _pr(run["detection"].get(d), "slots"))]
                 for run in r["runs"]]
    return ["### Ablation of the slot-aware strategy (rendering quality and rendered-BEV slot detection)", "",
            *_table(header, rows), "", _protocol(results)]


def tables_markdown(results: list[dict[str, Any]]) -> str:
    """All tables for ``results`` (one ``recon.paper_eval.evaluate_runs`` result per scene), as Markdown."""
    detectors = list(dict.fromkeys(d for r in results for d in r["gt"]))
    parts = [_synthesis(results)] + [_detection(results, d) for d in detectors] + [_ablation(results, detectors)]
    return "\n\n".join("\n".join(p) for p in parts) + "\n"
