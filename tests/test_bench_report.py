"""``parksim bench report``: the committed dashboard is exactly what the committed records give, every link in it
resolves, and the latest record of a target wins with its same-run reference beside it."""

from __future__ import annotations

import re
import shutil
from pathlib import Path

import pytest

from parksim.bench.record import Figure, Machine, Record, read_record, records_in, write_record
from parksim.bench.report import render_dashboard, render_details, write_dashboard
from parksim.cli import main

ROOT = Path(__file__).resolve().parents[1]
BENCH = ROOT / "benchmarks"


def test_committed_dashboard_regenerates_byte_identically(tmp_path):
    copy = tmp_path / "benchmarks"
    shutil.copytree(BENCH / "results", copy / "results")
    assert main(["bench", "report", "--results", str(copy / "results"), "-o", str(copy / "RESULTS.md")]) == 0
    for page in sorted(p.name for p in copy.glob("RESULTS*.md")) + sorted(p.name for p in BENCH.glob("RESULTS*.md")):
        assert (BENCH / page).is_file() and (copy / page).is_file() and \
            (copy / page).read_bytes() == (BENCH / page).read_bytes(), \
            f"benchmarks/{page} differs from what the records give: run `parksim bench report` and commit it"


def test_every_committed_record_loads_and_every_dashboard_link_resolves():
    records = records_in(BENCH / "results")
    assert records, "no records under benchmarks/results"
    for path, rec in records:
        assert rec.figures or rec.legacy, f"{path}: a non-legacy record without figures"
        if rec.plot:
            assert (path.parent / rec.plot).is_file(), f"{path}: plot {rec.plot} missing"
    text = (BENCH / "RESULTS.md").read_text()
    links = re.findall(r"\]\(([^)#]+)\)", text)
    assert links
    for link in links:
        assert (BENCH / link).is_file(), f"RESULTS.md links {link}, which is not there"


def _record(date: str, value: float, target: str = "latency", reference: float | None = None) -> Record:
    figure = Figure(target, value, "ms", cpu=2 * value, reference=reference,
                    reference_label=None if reference is None else "old code",
                    reference_cpu=None if reference is None else 2 * reference)
    return Record(suite="demo", command=f"parksim bench demo # {date}", commit="abc1234", date=date,
                  machine=Machine("host", "Test CPU", 2), figures=[figure])


def test_latest_record_of_a_target_wins_and_shows_its_reference(tmp_path):
    results = tmp_path / "results"
    write_record(_record("2026-01-01T00:00:00+00:00", 10.0, reference=20.0), results)
    newest = write_record(_record("2026-02-01T00:00:00+00:00", 5.0, reference=20.0), results)
    write_record(_record("2026-01-15T00:00:00+00:00", 7.0, target="other"), results)
    text = render_dashboard(results, tmp_path)
    rows = [line for line in text.splitlines() if line.startswith("| latency")]
    assert len(rows) == 1
    assert "5 ms (CPU 10)" in rows[0] and "20 ms (CPU 40): old code" in rows[0] and "0.25x" in rows[0]
    assert f"results/demo/{newest.name}" in rows[0]
    assert any(line.startswith("| other | 7 ms") for line in text.splitlines())   # an older target is kept
    assert render_dashboard(results, tmp_path) == text                            # same records, same bytes


def test_record_round_trips_non_finite_values_and_refuses_what_is_not_a_record(tmp_path):
    rec = _record("2026-03-01T00:00:00+00:00", float("inf"))
    path = write_record(rec, tmp_path)
    back = read_record(path)
    assert back.figures[0].value == float("inf") and back.machine == rec.machine
    bad = tmp_path / "demo" / "bad.json"
    bad.write_text('{"suite": "demo"}')
    with pytest.raises(ValueError, match="bad.json: not a benchmark record"):
        read_record(bad)
    with pytest.raises(ValueError, match="reference needs its label"):
        Figure("x", 1.0, "ms", reference=2.0)


def test_goals_in_the_figures_unit_are_checked_and_others_shown_as_written(tmp_path):
    figures = [Figure("fast", 5.0, "ms", goal="<= 10 ms"), Figure("slow", 50.0, "ms", goal="<= 10 ms (target)"),
               Figure("none failed", 0.0, "count", goal="0"), Figure("relative", 5.0, "ms", goal="<= 1.5x the other"),
               Figure("psnr", 27.0, "dB", goal=">= 28 dB", better="higher")]
    write_record(Record(suite="demo", command="parksim bench demo", commit="abc1234", date="2026-01-01T00:00:00+00:00",
                        machine=Machine("host", "Test CPU", 2), figures=figures), tmp_path / "results")
    rows = {line.split(" | ")[0][2:]: line for line in render_dashboard(tmp_path / "results", tmp_path).splitlines()
            if line.startswith("| ") and any(unit in line for unit in (" ms", " dB", " count"))}
    assert "<= 10 ms: met" in rows["fast"] and "<= 10 ms (target): not met" in rows["slow"]
    assert "| 0: met |" in rows["none failed"] and ">= 28 dB: not met" in rows["psnr"]
    assert "| <= 1.5x the other |" in rows["relative"]


def test_a_records_details_become_a_linked_page_of_the_latest_one(tmp_path):
    results = tmp_path / "results"
    for date, table in (("2026-01-01T00:00:00+00:00", "| old |"), ("2026-02-01T00:00:00+00:00", "| new |")):
        rec = _record(date, 5.0)
        rec.details = f"## table\n\n{table}\n"
        write_record(rec, results)
    write_record(_record("2026-03-01T00:00:00+00:00", 4.0), results)   # a later run without details keeps the page
    pages = render_details(results, tmp_path)
    assert list(pages) == ["RESULTS_demo.md"]
    assert "| new |" in pages["RESULTS_demo.md"] and "| old |" not in pages["RESULTS_demo.md"]
    assert "Full tables of the latest run that wrote them: [RESULTS_demo.md](RESULTS_demo.md)" in \
        render_dashboard(results, tmp_path)
    write_dashboard(results, tmp_path / "RESULTS.md")
    assert (tmp_path / "RESULTS_demo.md").read_text() == pages["RESULTS_demo.md"]
