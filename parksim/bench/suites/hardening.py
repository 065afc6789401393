"""``parksim bench hardening``: the reliability figures of the hardening issues, re-measured on the code as it is.

Six probes, each with its goal stated here before anything is measured:

1. Malformed requests: a fixed corpus of hand-made bad ``/render`` requests (poses NaN, infinite, 1e308, 1e29, with
   too few or many values or text; bad cameras, scales, formats, scenes; POST bodies malformed, nested 10,000 deep,
   with a 5,000-digit integer, invalid UTF-8, wrong types, empty, 2 MiB; a foreign ``Host``; a missing, wrong or
   whitespace-only API key) plus ``--random-probes`` seeded ones, each sent as raw bytes on its own loopback socket
   to ``parksim serve`` started with an API key. Goals: every one answered 4xx (so 0 5xx), every reply JSON with a
   ``detail``, no ``Traceback`` on the server's stderr.
2. schemathesis (only where ``import schemathesis`` works; the record says when it was skipped): property-based
   requests generated from ``/openapi.json``, ``--schemathesis-examples`` per operation. Goal: 0 5xx.
3. Wrong API keys take the same time: ``--key-requests`` ``GET /render`` with each of three wrong keys of the right
   key's length that share 0, half and all but one of its leading characters, in turn (the order rotated every
   round), on one kept-alive connection. Goal: the largest ratio between their median latencies <=
   ``KEY_RATIO_GOAL``, beside it the same ratio of the server's CPU time per request (every thread's
   ``/proc/PID/task/*/schedstat``, nanoseconds); and the same goal for their 10th percentiles, the reading a loaded
   machine leaves alone (a cost that depends on the key shifts the whole distribution; load stretches its upper part,
   and moved the medians of identical requests by up to 1.5x at a load average of 5).
4. Clients that never read their replies: measured by ``parksim bench server-memory`` (its peak RSS against the
   reply budget's bound), not repeated here.
5. Env soak: ``--env-steps`` seeded random steps of one in-process ``ParkingEnv`` on the CPU, state only and with one
   camera at scale 0.25, a new episode after a collision, parking or ``MAX_EPISODE_STEPS``; this process's RSS
   sampled every ``--rss-every`` steps. Every ``--nan-every`` steps a non-finite action (NaN or infinite, in turn in
   either component) is tried. Goals: RSS growth over the last half <= ``RSS_GROWTH_GOAL_MIB``; 0 non-finite
   observations or rewards; every non-finite action refused with ``ValueError`` and the vehicle state unchanged.
6. Kill and re-run: ``parksim import nerfstudio`` of the tiny garage killed with SIGKILL while it writes its temp
   folder, then the same import re-run, ``--kills`` times. Goal: no ``.NAME.tmp-*`` folder left after the re-run.

The scene is ``--gaussians`` Gaussians sampled on the surfaces of synth ``--preset``'s garage with its rig and map
(``parksim.bench.serving.garage_bundle``; the tiny garage under --quick), not trained: no probe depends on the picture.
"""

from __future__ import annotations

import contextlib
import os
import shutil
import signal
import statistics
import subprocess
import sys
import time
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from ...checked_options import CheckedOptions
from ..common import pyplot, save_figure
from ..record import Figure
from ..suite import Context, Outcome, Suite

__all__ = ["HardeningSuite", "HardeningOptions", "wrong_keys", "KEY_RATIO_GOAL", "RSS_GROWTH_GOAL_MIB"]

KEY_RATIO_GOAL = 1.1
"""Largest allowed ratio between the wrong keys' median (and 10th-percentile) latencies."""
RSS_GROWTH_GOAL_MIB = 16.0
"""Largest allowed RSS growth (MiB) over the last half of an env soak."""
MIB = 2**20
_TIMEOUT_S = 60.0


@dataclass(frozen=True)
class HardeningOptions(CheckedOptions):
    """Options of ``parksim bench hardening``."""

    preset: str = field(default="tiny", metadata={"help": "synth preset whose garage the bundle samples"})
    gaussians: int = field(default=20_000, metadata={"help": "Gaussians of the bundle", "low": 1, "quick": 2_000})
    random_probes: int = field(default=200, metadata={
        "help": "seeded random malformed requests besides the hand-made ones", "low": 0, "quick": 20})
    schemathesis_examples: int = field(default=100, metadata={
        "help": "schemathesis examples per API operation (when schemathesis is installed)", "low": 1, "quick": 5})
    key_requests: int = field(default=200, metadata={"help": "requests per wrong API key", "low": 1, "quick": 20})
    env_steps: int = field(default=2000, metadata={"help": "random steps of each env soak", "low": 2, "quick": 100})
    rss_every: int = field(default=50, metadata={"help": "env steps between RSS samples", "low": 1, "quick": 10})
    nan_every: int = field(default=50, metadata={"help": "env steps between non-finite actions tried", "low": 1,
                                                 "quick": 10})
    kills: int = field(default=3, metadata={"help": "imports killed mid-write and re-run", "low": 1, "quick": 1})

    def __post_init__(self) -> None:
        super().__post_init__()
        if self.env_steps < 2 * self.rss_every:
            raise ValueError(f"--env-steps ({self.env_steps}) must be at least twice --rss-every ({self.rss_every}), "
                             "or the last half holds no RSS sample to compare")


def _schemathesis(base: str, key: str, examples: int, seed: int) -> dict[str, Any] | None:
    """Property-based requests from ``/openapi.json`` (schemathesis' hypothesis strategies), ``examples`` per
    operation; None when schemathesis (>= 4) is not installed. Counts the requests and the 5xx replies."""
    try:
        import schemathesis
    except ImportError:
        return None
    from hypothesis import HealthCheck, given, settings
    from hypothesis import seed as hypothesis_seed

    schema = schemathesis.openapi.from_url(f"{base}/openapi.json")   # schemathesis >= 4 (the dev extra's)
    counts: dict[str, int] = {}
    for result in schema.get_all_operations():
        operation = result.ok()   # type: ignore[union-attr]  # an Err here (a schema it cannot read) raises

        @hypothesis_seed(seed)
        @settings(max_examples=examples, deadline=None, database=None, suppress_health_check=list(HealthCheck))
        @given(case=operation.as_strategy())
        def call(case: Any) -> None:
            status = str(case.call(base_url=base, headers={"X-API-Key": key}, timeout=_TIMEOUT_S).status_code)
            counts[status] = counts.get(status, 0) + 1

        call()
    return {"version": getattr(schemathesis, "__version__", "?"), "requests": sum(counts.values()),
            "statuses": dict(sorted(counts.items())),
            "server_errors": sum(n for s, n in counts.items() if s.startswith("5"))}


# --- wrong keys --------------------------------------------------------------------------------------------------


def _server_cpu_ns(pid: int) -> int:
    """CPU nanoseconds every thread of ``pid`` has run so far (``/proc/PID/task/*/schedstat``; a thread that exits
    between the listing and the read counts 0)."""
    total = 0
    for task in os.listdir(f"/proc/{pid}/task"):
        with contextlib.suppress(OSError):
            total += int(Path(f"/proc/{pid}/task/{task}/schedstat").read_text().split()[0])
    return total


def wrong_keys(key: str) -> dict[str, str]:
    """Three wrong keys of ``key``'s length sharing 0, half and all but one of its leading characters.

    Args:
        key: the right key (at least 2 characters).

    Returns:
        Label -> wrong key.
    """
    def differ(k: int) -> str:
        return key[:k] + ("a" if key[k] != "a" else "b") + key[k + 1:]

    return {f"{k} of {len(key)} leading characters right": differ(k) for k in (0, len(key) // 2, len(key) - 1)}


def _key_latency(base: str, pid: int, key: str, pose: str, n: int) -> dict[str, Any]:
    """``n`` ``GET /render`` with each wrong key, in turn per round (the order rotated every round, so each key
    is first, middle and last as often), after 10 untimed rounds: per key the median, 10th percentile and quartiles
    of the wall ms, and the median server CPU ms."""
    import httpx

    keys = wrong_keys(key)
    wall: dict[str, list[float]] = {label: [] for label in keys}
    cpu: dict[str, list[float]] = {label: [] for label in keys}
    labels = list(keys)
    with httpx.Client(base_url=base, timeout=_TIMEOUT_S) as client:
        for r in range(n + 10):
            for label in labels[r % len(labels):] + labels[:r % len(labels)]:
                c0 = _server_cpu_ns(pid)
                t0 = time.perf_counter()
                status = client.get("/render", params={"pose": pose}, headers={"X-API-Key": keys[label]}).status_code
                t1 = time.perf_counter()
                c1 = _server_cpu_ns(pid)
                if status != 401:
                    raise RuntimeError(f"a wrong API key ({label}) was answered {status}, not 401")
                if r >= 10:
                    wall[label].append(1e3 * (t1 - t0))
                    cpu[label].append((c1 - c0) / 1e6)
    out = {}
    for label in labels:
        p10, p25, p50, p75, p90 = (float(v) for v in np.percentile(wall[label], [10, 25, 50, 75, 90]))
        out[label] = {"wall_ms": p50, "wall_p10_ms": p10, "wall_quartiles_ms": [p25, p75], "wall_p90_ms": p90,
                      "server_cpu_ms": statistics.median(cpu[label]), "n": n}
    return out


def _ratio(values: list[float]) -> float:
    """Largest over smallest (1.0 when the smallest is 0 and so is the largest)."""
    low, high = min(values), max(values)
    return high / low if low > 0 else (1.0 if high == 0 else float("inf"))


# --- env soak ----------------------------------------------------------------------------------------------------

_NON_FINITE_ACTIONS = ((float("nan"), 0.0), (0.0, float("nan")), (float("inf"), 0.0), (0.0, float("-inf")))


def _env_soak(bundle: Path, cameras: list[str], options: HardeningOptions, seed: int) -> dict[str, Any]:
    """``options.env_steps`` seeded random steps of one ``ParkingEnv`` showing ``cameras`` at scale 0.25 (a new
    episode after a collision, parking or ``MAX_EPISODE_STEPS``), this process's RSS sampled every
    ``options.rss_every`` steps, a non-finite action tried every ``options.nan_every`` steps."""
    from ...env import MAX_EPISODE_STEPS, ParkingEnv
    from ..procs import rss_mib

    env = ParkingEnv(bundle=bundle, cameras=cameras, scale=0.25, device="cpu")
    rng = np.random.default_rng(seed)
    env.reset(seed=seed)
    for _ in range(10):   # warm-up: kernels, caches
        env.step(rng.uniform(-1, 1, 2).astype(np.float32))
    env.reset()
    nonfinite, episodes, in_episode, tried, refused = 0, 1, 0, 0, 0
    log = []
    start = time.perf_counter()
    for i in range(1, options.env_steps + 1):
        if i % options.nan_every == 0:
            before = env.state
            tried += 1
            try:
                env.step(np.array(_NON_FINITE_ACTIONS[tried % len(_NON_FINITE_ACTIONS)], np.float32))
            except ValueError:
                refused += env.state == before
        obs, reward, terminated, _, _ = env.step(rng.uniform(-1, 1, 2).astype(np.float32))
        finite = np.isfinite(reward) and all(np.isfinite(v).all() for v in obs.values())
        nonfinite += not finite
        in_episode += 1
        if terminated or in_episode >= MAX_EPISODE_STEPS:
            env.reset()
            episodes, in_episode = episodes + 1, 0
        if i % options.rss_every == 0:
            log.append({"step": i, "rss_mib": rss_mib()})
    env.close()
    rss = [r["rss_mib"] for r in log]
    return {"cameras": cameras, "steps": options.env_steps, "episodes": episodes, "nonfinite_steps": nonfinite,
            "nonfinite_actions_tried": tried, "nonfinite_actions_refused": refused,
            "rss_first_mib": rss[0], "rss_max_mib": max(rss), "rss_end_mib": rss[-1],
            "rss_growth_last_half_mib": rss[-1] - rss[len(rss) // 2], "seconds": time.perf_counter() - start,
            "log": log}


# --- kill and re-run ---------------------------------------------------------------------------------------------


def _temps(out: Path) -> list[Path]:
    """The temp folders of writers of ``out`` beside it."""
    return sorted(out.parent.glob(f".{out.name}.tmp-*"))


def _writing(out: Path) -> bool:
    """Whether a temp folder of ``out`` holds a file yet (the writer is mid-write)."""
    return out.parent.is_dir() and any(f.is_file() for t in _temps(out) for f in t.rglob("*"))


def _kill_mid_write(exported: Path, out: Path, tries: int = 5) -> int:
    """Start ``parksim import nerfstudio EXPORTED -o OUT`` and SIGKILL it once its temp folder holds a file (polled
    every millisecond: a tiny import writes for about 0.1 s); a fresh try when it finished first. Returns the tries
    used; ``RuntimeError`` when every try finished before it was caught writing."""
    for attempt in range(1, tries + 1):
        if out.exists():
            shutil.rmtree(out)
        proc = subprocess.Popen([sys.executable, "-m", "parksim.cli", "import", "nerfstudio", str(exported),
                                 "-o", str(out), "--quiet"], stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
        deadline = time.monotonic() + 300
        while not _writing(out) and proc.poll() is None and time.monotonic() < deadline:
            time.sleep(0.001)
        if proc.poll() is None:
            proc.send_signal(signal.SIGKILL)
            proc.wait()
            return attempt
    raise RuntimeError(f"{tries} imports each finished before they were caught writing")


def _kill_and_rerun(context: Context, kills: int) -> dict[str, Any]:
    """``kills`` rounds of an import killed mid-write and re-run in this process into the same folder."""
    from ...importers import ImportSettings, import_recording, importer
    from ...importers.nerfstudio import export
    from ..datasets import ensure_dataset

    work = context.work / "hardening"
    exported = work / "nerfstudio_tiny"
    if not (exported / "transforms.json").is_file():
        export(ensure_dataset(context, "tiny", None), exported, overwrite=True)
    nerfstudio = importer("nerfstudio")
    rounds = []
    for _ in range(kills):
        out = work / "imports" / "out"
        tries = _kill_mid_write(exported, out)
        left_by_kill = _temps(out)
        size = sum(f.stat().st_size for t in left_by_kill for f in t.rglob("*") if f.is_file())
        import_recording(nerfstudio, nerfstudio.Options(transforms=exported), ImportSettings(out, quiet=True))
        rounds.append({"tries": tries, "left_by_kill": len(left_by_kill), "left_by_kill_mib": size / MIB,
                       "rerun_wrote_dataset": (out / "meta.json").is_file(), "left_after_rerun": len(_temps(out))})
    return {"exported": str(exported), "rounds": rounds}


# --- the suite ---------------------------------------------------------------------------------------------------


@contextlib.contextmanager
def _keyed_server(bundle: Path, work: Path, seed: int) -> Iterator[tuple[Any, str, Path]]:
    """``parksim serve`` of ``bundle`` on loopback with a seeded 32-character API key from a file; yields
    (server, key, stderr log)."""
    from ..procs import serve_bundle

    work.mkdir(parents=True, exist_ok=True)
    key = "".join(np.random.default_rng(seed).choice(list("0123456789abcdef"), 32))
    key_file, log = work / "api_key", work / "server_stderr.log"
    key_file.write_text(key + "\n")
    key_file.chmod(0o600)
    with serve_bundle(bundle, ["--api-key-file", str(key_file)], log=log) as server:
        yield server, key, log


class HardeningSuite(Suite):
    """The reliability probes of the hardening issues: malformed requests, wrong keys, env soak, kill and re-run."""

    name = "hardening"
    help = "reliability: malformed requests, schemathesis, wrong-key timing, env soak, killed imports"
    description = ("`parksim serve` with an API key on loopback: a fixed corpus of hand-made malformed /render "
                   "requests plus --random-probes seeded ones as raw HTTP (goals: 0 5xx, every reply a 4xx JSON with "
                   "a detail, no Traceback on the server's stderr); schemathesis from /openapi.json when installed "
                   "(goal: 0 5xx); --key-requests requests with each of three wrong keys (goal: their median "
                   f"and 10th-percentile latencies within {KEY_RATIO_GOAL:g}x; cpu: the same ratio of the server's CPU "
                   "per request). "
                   "Clients that never read: see the server-memory suite. Then --env-steps random steps of one "
                   "ParkingEnv, state only and with one camera at scale 0.25 (goals: RSS growth over the last half "
                   f"<= {RSS_GROWTH_GOAL_MIB:g} MiB, 0 non-finite observations or rewards, every non-finite action "
                   "refused with the state unchanged), and `parksim import nerfstudio` killed with SIGKILL mid-write "
                   "then re-run, --kills times (goal: 0 temp folders left).")
    Options = HardeningOptions

    def run(self, options: HardeningOptions, context: Context) -> Outcome:
        """Serve and probe, soak the env, kill and re-run imports."""
        from ...bundle import load
        from ..malformed import corpus, probe_all
        from ..serving import scene_bundle

        served = scene_bundle(None, context, options.preset, None, options.gaussians)
        bundle, x = served.bundle, round(served.length / 2, 1)   # mid-aisle: a valid x for the probes
        with _keyed_server(bundle, context.work / "hardening", context.seed) as (server, key, log):
            port = int(server.base.rsplit(":", 1)[1])
            malformed = probe_all(port, corpus(key, x, options.random_probes, context.seed), key)
            fuzz = _schemathesis(server.base, key, options.schemathesis_examples, context.seed)
            keys = _key_latency(server.base, server.pid, key, f"{x:g},0,0", options.key_requests)
        tracebacks = sum("Traceback" in line for line in log.read_text(errors="replace").splitlines())
        camera = load(bundle).rig.names[0]
        soaks = {"state only": _env_soak(bundle, [], options, context.seed),
                 f"one camera ({camera}) at scale 0.25": _env_soak(bundle, [camera], options, context.seed)}
        kills = _kill_and_rerun(context, options.kills)

        where = f"malformed /render requests, the hand-made corpus + {options.random_probes} seeded"
        figures = [Figure(f"{where}: sent", malformed["sent"], "requests", better="higher"),
                   Figure(f"{where}: 5xx replies", malformed["server_errors"], "replies", goal="0"),
                   Figure(f"{where}: replies other than 4xx", malformed["not_4xx"], "replies", goal="0"),
                   Figure(f"{where}: replies not JSON with a detail", malformed["not_json_detail"], "replies",
                          goal="0"),
                   Figure("parksim serve stderr after the malformed requests"
                          + (" and schemathesis" if fuzz else "") + ": lines with Traceback", tracebacks, "lines",
                          goal="0")]
        if fuzz is not None:
            target = f"schemathesis from /openapi.json, {options.schemathesis_examples} examples per operation"
            figures += [Figure(f"{target}: requests", fuzz["requests"], "requests", better="higher"),
                        Figure(f"{target}: 5xx replies", fuzz["server_errors"], "replies", goal="0")]
        wrong = (f"3 wrong API keys sharing 0, 16, 31 of 32 leading characters, {options.key_requests} GET /render "
                 "each: largest ratio of their")
        figures += [Figure(f"{wrong} median latencies", _ratio([k["wall_ms"] for k in keys.values()]), "x",
                           cpu=_ratio([k["server_cpu_ms"] for k in keys.values()]), goal=f"<= {KEY_RATIO_GOAL:g} x"),
                    Figure(f"{wrong} 10th-percentile latencies", _ratio([k["wall_p10_ms"] for k in keys.values()]),
                           "x", goal=f"<= {KEY_RATIO_GOAL:g} x")]
        for label, soak in soaks.items():
            figures.append(Figure(f"ParkingEnv, {label}, {options.env_steps} random steps: RSS growth over the last "
                                  "half", soak["rss_growth_last_half_mib"], "MiB",
                                  goal=f"<= {RSS_GROWTH_GOAL_MIB:g} MiB"))
        total = sum(s["steps"] for s in soaks.values())
        tried = sum(s["nonfinite_actions_tried"] for s in soaks.values())
        figures += [Figure(f"ParkingEnv, {total} random steps: non-finite observations or rewards",
                           sum(s["nonfinite_steps"] for s in soaks.values()), "steps", goal="0"),
                    Figure(f"ParkingEnv, {tried} non-finite actions: not refused with ValueError, state unchanged",
                           tried - sum(s["nonfinite_actions_refused"] for s in soaks.values()), "actions", goal="0"),
                    Figure(f"parksim import nerfstudio killed mid-write (SIGKILL) and re-run, {options.kills} "
                           "times: temp folders left", sum(r["left_after_rerun"] for r in kills["rounds"]),
                           "folders", goal="0")]
        if fuzz is None:
            fuzz = {"skipped": "schemathesis is not installed (pip install schemathesis to add its figures)"}
        data = {"bundle": str(bundle), "scene": served.label, "malformed": malformed, "schemathesis": fuzz,
                "wrong_keys": keys, "server_stderr_tracebacks": tracebacks, "env": soaks, "kill_and_rerun": kills,
                "slow_clients": "measured by the server-memory suite (parksim bench server-memory)"}
        return Outcome(figures, data, lambda png: _plot_rss(soaks, png))


def _plot_rss(soaks: dict[str, dict[str, Any]], png: Path) -> None:
    """This process's RSS against the step of each env soak."""
    plt = pyplot()
    fig, ax = plt.subplots(figsize=(6, 3.6))
    for label, soak in soaks.items():
        ax.plot([r["step"] for r in soak["log"]], [r["rss_mib"] for r in soak["log"]], ".-", label=label)
    ax.set(xlabel="env step", ylabel="RSS (MiB)", title="ParkingEnv soak")
    ax.grid(True, alpha=0.3)
    ax.legend()
    save_figure(fig, png)

