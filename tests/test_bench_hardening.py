"""``parksim bench hardening``: the malformed-request corpus holds what the hardening issue names, and the --quick run
through the real CLI, against a real ``parksim serve`` with an API key, a real ``ParkingEnv`` and a real killed
``parksim import``, writes a record whose figures meet their goals (no timing is asserted)."""

from __future__ import annotations

import importlib.util
from urllib.parse import parse_qs, urlsplit

import pytest
from test_bench_serving import figures

from parksim.bench.malformed import corpus
from parksim.bench.record import Figure, Record, read_record
from parksim.bench.suites.hardening import KEY_RATIO_GOAL, RSS_GROWTH_GOAL_MIB, wrong_keys
from parksim.cli import main

PNG_MAGIC = b"\x89PNG\r\n\x1a\n"
KEY = "0123456789abcdef0123456789abcdef"


def test_the_corpus_is_fixed_ascii_and_holds_each_attack_the_issue_names():
    probes = corpus(KEY, 17.0, 30, seed=3)
    assert probes == corpus(KEY, 17.0, 30, seed=3) != corpus(KEY, 17.0, 30, seed=4)
    assert len({p.name for p in probes}) == len(probes)
    assert sum(p.group == "random" for p in probes) == 30
    for p in probes:
        p.target.encode("ascii")   # valid HTTP: a non-ASCII request line never reaches the app
    poses = {parse_qs(urlsplit(p.target).query).get("pose", [""])[0] for p in probes if p.method == "GET"}
    assert {"nan,0,0", "inf,0,0", "1e308,0,0", "1e29,0,0", "1,2", "1,2,3,4", "a,b,c"} <= poses
    bodies = [p.body or b"" for p in probes if p.method == "POST"]
    assert any(b.startswith(b"[" * 10_000) for b in bodies)
    assert any(b"9" * 5000 in b for b in bodies)
    assert any(b"\xff" in b for b in bodies)
    assert any(len(b) > 2 * 2**20 for b in bodies)
    assert b"" in bodies
    hosts = {p.host for p in probes if p.group == "host"}
    assert "evil.example" in hosts and "" in hosts
    keys = [p for p in probes if p.group == "key"]
    assert {dict(p.headers).get("X-API-Key") for p in keys} >= {None, "wrong", "   ", KEY[:-1]}
    unkeyed = [p for p in probes if not p.keyed]
    assert len(unkeyed) == 10 and all(p.group == "key" for p in unkeyed)


def test_the_wrong_keys_share_0_half_and_all_but_one_leading_characters():
    found = wrong_keys(KEY)
    assert len(found) == 3
    for label, wrong in found.items():
        shared = next(i for i, (a, b) in enumerate(zip(wrong, KEY)) if a != b)
        assert len(wrong) == len(KEY) and wrong[shared + 1:] == KEY[shared + 1:]
        assert label.startswith(f"{shared} of 32 ")
    assert sorted(int(label.split()[0]) for label in found) == [0, 16, 31]


@pytest.fixture(scope="module")
def record(tmp_path_factory: pytest.TempPathFactory) -> Record:
    work = tmp_path_factory.mktemp("bench-hardening")
    results = work / "results"
    assert main(["bench", "hardening", "--quick", "--quiet", "--work", str(work), "--results", str(results)]) == 0
    (path,) = (results / "hardening").glob("*.json")
    found = read_record(path)
    assert found.plot is not None and (path.parent / found.plot).read_bytes()[:8] == PNG_MAGIC
    return found


def one(found: dict[str, Figure], ending: str, start: str = "") -> Figure:
    (figure,) = [f for t, f in found.items() if t.endswith(ending) and t.startswith(start)]
    return figure


def test_every_malformed_request_is_answered_4xx_with_a_json_detail_and_no_traceback(record):
    found = figures(record)
    malformed = record.data["malformed"]
    assert malformed["sent"] == len(corpus(KEY, 0.0, 20, 0)) and malformed["odd"] == []
    assert all(status.startswith("4") for status in malformed["statuses"]), malformed["statuses"]
    assert {"400", "401", "404", "405", "411", "413", "421", "422"} <= set(malformed["statuses"])
    assert malformed["groups"]["host"] == {"421": 6}
    assert "server-memory" in record.data["slow_clients"]
    assert malformed["groups"]["key"] == {"401": 9, "400": 2}
    assert one(found, ": sent", "malformed").value == malformed["sent"]
    for start, ending in (("malformed", ": 5xx replies"), ("malformed", ": replies other than 4xx"),
                          ("malformed", ": replies not JSON with a detail"),
                          ("parksim serve", ": lines with Traceback")):
        figure = one(found, ending, start)
        assert figure.goal == "0" and figure.value == 0, figure
    assert record.data["server_stderr_tracebacks"] == 0


def test_schemathesis_is_measured_or_its_absence_noted(record):
    fuzz = record.data["schemathesis"]
    if importlib.util.find_spec("schemathesis") is None:
        assert "not installed" in fuzz["skipped"]
        assert not any("schemathesis" in f.target for f in record.figures if "Traceback" not in f.target)
    else:
        assert fuzz["requests"] > 0 and fuzz["server_errors"] == 0
        assert one(figures(record), ": 5xx replies", "schemathesis").value == 0


def test_the_wrong_keys_are_timed_with_the_servers_cpu(record):
    found = figures(record)
    keys = record.data["wrong_keys"]
    assert len(keys) == 3 and all(k["n"] == 20 and 0 < k["wall_p10_ms"] <= k["wall_ms"] for k in keys.values())
    assert all(k["server_cpu_ms"] > 0 for k in keys.values())
    median, p10 = one(found, " median latencies"), one(found, " 10th-percentile latencies")
    assert median.goal == p10.goal == f"<= {KEY_RATIO_GOAL:g} x" and median.unit == "x"
    assert median.value == pytest.approx(max(k["wall_ms"] for k in keys.values())
                                         / min(k["wall_ms"] for k in keys.values()))
    assert median.cpu is not None and median.cpu >= 1 and p10.value >= 1


def test_the_env_soak_stays_finite_and_refuses_every_non_finite_action(record):
    found = figures(record)
    soaks = record.data["env"]
    assert list(soaks) == ["state only", "one camera (front) at scale 0.25"]
    for soak in soaks.values():
        assert soak["steps"] == 100 and len(soak["log"]) == 10 and soak["episodes"] >= 1
        assert soak["nonfinite_steps"] == 0
        assert soak["nonfinite_actions_tried"] == soak["nonfinite_actions_refused"] == 10
    growth = [f for t, f in found.items() if t.endswith("RSS growth over the last half")]
    assert len(growth) == 2 and all(f.goal == f"<= {RSS_GROWTH_GOAL_MIB:g} MiB" for f in growth)
    assert one(found, "non-finite observations or rewards").value == 0
    assert one(found, "not refused with ValueError, state unchanged").value == 0


def test_a_killed_import_leaves_nothing_once_re_run(record):
    found = figures(record)
    (round_,) = record.data["kill_and_rerun"]["rounds"]
    assert round_["left_by_kill"] == 1, "the kill did not catch the import mid-write"
    assert round_["rerun_wrote_dataset"] and round_["left_after_rerun"] == 0
    figure = one(found, "temp folders left")
    assert figure.goal == "0" and figure.value == 0

