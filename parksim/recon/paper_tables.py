"""Markdown versions of the paper's experiment tables from ``parksim.recon.paper_eval`` results (one result per scene).

* Novel view synthesis: photometric-only and full slot-aware reconstructions, PSNR/SSIM over the whole valid
  image and over slot regions.
* One detection table per detector: precision/recall of marking points and slots on the ground-truth BEVs
  ("GT-" row) and on each of those reconstructions' rendered BEVs.
* Ablation: every reconstruction, rendering quality plus each detector's slot precision/recall on its BEVs.
* Off the recorded path (datasets with an off-path split, ``parksim offpath``): per scene and detector, slot
  precision/recall on ground-truth and rendered BEVs at the same off-path poses, per offset group.
Rows are matched across scenes by label; a cell a scene lacks reads "n/a". Each detection table names the
scoring protocol (``parksim.recon.detectors.protocols``; results from before protocols were recorded used ParkSim's).
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


def _offpath(result: dict[str, Any], detector: str) -> list[str]:
    """One scene's detection off the recorded path: per pose group, the detector's slot precision/recall on the
    ground-truth BEVs and, for each main reconstruction, PSNR and slot precision/recall on its rendered BEVs at the
    same poses; the first row is the recorded test frames."""
    title = DETECTOR_TITLES.get(detector, detector)
    off = result["offpath"]
    runs = [run for run in result["runs"] if _main(run)]
    header = ["Poses", "frames", "labelled slots", f"GT-{title} slot P", f"GT-{title} slot R"]
    header += [f"{run['label']} {c}" for run in runs for c in ("PSNR", "slot P", "slot R")]

    def cells(gt: dict[str, Any] | None, frames: int, per_run: list[tuple[float | None, dict[str, Any] | None]]
              ) -> list[str]:
        labelled = str(gt["slots"]["labelled"]) if gt is not None else "n/a"
        return [str(frames), labelled, *_pr(gt, "slots"),
                *(c for psnr, scores in per_run for c in [_f(psnr, 2), *_pr(scores, "slots")])]

    rows = [["on path (recorded test frames)", *cells(result["gt"].get(detector), len(result["test_frames"]),
                                                      [(run["psnr"], run["detection"].get(detector)) for run in runs])]]
    for g in off["groups"]:
        name = g["group"]
        per_run = [(run["offpath"]["quality"][name]["psnr"], run["offpath"]["detection"].get(detector, {}).get(name))
                   for run in runs]
        rows.append([name, *cells(off["gt"].get(detector, {}).get(name), g["frames"], per_run)])
    skipped = ", ".join(f"{k} {v}" for k, v in sorted(off["skipped"].items())) or "none"
    return [f"### {title} off the recorded path, {result['scene']}: ground-truth vs rendered BEVs at the same poses",
            "", *_table(header, rows), "",
            f"Lateral and yaw offsets count both sides; skipped poses: {skipped} (docs/offpath.md).",
            _protocol([result])]


def tables_markdown(results: list[dict[str, Any]]) -> str:
    """All tables for ``results`` (one ``parksim.recon.paper_eval.evaluate_runs`` result per scene), as Markdown."""
    detectors = list(dict.fromkeys(d for r in results for d in r["gt"]))
    parts = [_synthesis(results)] + [_detection(results, d) for d in detectors] + [_ablation(results, detectors)]
    parts += [_offpath(r, d) for r in results if "offpath" in r for d in detectors]
    return "\n\n".join("\n".join(p) for p in parts) + "\n"
