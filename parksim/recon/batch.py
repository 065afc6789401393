"""Many scenes at once: each dataset is one Ray task that trains its own bundle into ``SCENES/<dataset name>/``.

The driver plans every scene before it submits one (a finished bundle is skipped, a run with a checkpoint resumes,
anything else starts fresh), gives each task ``cpus`` Ray CPUs, ``gpus`` Ray GPUs (fractions share one GPU among
tasks) and ``retries`` retries (Ray's ``max_retries`` with ``retry_exceptions``: a retry resumes from the failed
attempt's last checkpoint), and relays each task's progress (its metrics log, read as the trainer writes it) and
failed attempts through a Ray queue while it waits. Each task trains on the config's ``run.device`` or the batch's
``device``, resolved on the task's node, where a task's reserved GPUs are numbered from ``cuda:0``.
"""

from __future__ import annotations

import contextlib
import json
import math
import threading
import time
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Literal

import ray
from ray.util.queue import Queue

from .checkpoint import checkpoint_path
from .config import TrainConfig, load_config, resolve_config
from .metrics_log import METRICS_FILE
from .reconstruct import CONFIG_FILE, reconstruct

__all__ = ["Scene", "Outcome", "SceneFailed", "one_line", "plan_scenes", "ray_session", "default_cpus_per_task",
           "check_gpus", "run_batch"]

BUNDLE_META = "bundle.json"
"""Written last by ``parksim.bundle.save``: its presence means the scene's bundle is finished."""


class SceneFailed(RuntimeError):
    """A scene's task failed; the message is the error as one line (the original may not survive pickling)."""


@dataclass(frozen=True)
class Scene:
    """One dataset and the bundle folder it trains into (absolute paths: Ray workers do not share the cwd)."""

    name: str
    data: Path
    out: Path


@dataclass
class Outcome:
    """How one scene ended: ``trained``, ``resumed``, ``skipped`` or ``failed``, after ``attempts`` task runs."""

    name: str
    status: Literal["trained", "resumed", "skipped", "failed"]
    attempts: int = 0
    iterations: int | None = None
    gaussians: int | None = None
    seconds: float | None = None
    psnr: float | None = None
    detail: str = ""


def plan_scenes(datasets: Sequence[Path], scenes_dir: Path) -> list[Scene]:
    """A scene per dataset, named after its folder; two datasets of the same name are a ValueError."""
    scenes: dict[str, Scene] = {}
    for data in (Path(d).resolve() for d in datasets):
        if not data.name:
            raise ValueError(f"{data}: a dataset folder needs a name to name its scene")
        if data.name in scenes:
            raise ValueError(f"datasets {scenes[data.name].data} and {data} would both write "
                             f"{scenes[data.name].out}: rename one folder")
        scenes[data.name] = Scene(data.name, data, (scenes_dir / data.name).resolve())
    return list(scenes.values())


def one_line(error: BaseException, limit: int = 400) -> str:
    """An error as one line: its type and its message, whitespace folded, at most ``limit`` characters."""
    text = " ".join(str(error).split())
    line = f"{type(error).__name__}: {text}" if text else type(error).__name__
    return line if len(line) <= limit else line[:limit - 3] + "..."


def _worker_config(spec: str) -> str:
    """The config as workers can find it: a preset by name (each node has the package), a file by absolute path."""
    return str(Path(spec).resolve()) if Path(spec).is_file() else resolve_config(spec).stem


class _MetricsTail:
    """Sends each new record of a run's ``metrics.jsonl`` to ``send`` while the trainer appends to it.

    Reads only whole lines; a file that shrinks (a resume cuts it back, a fresh start deletes it) is read again
    from the start, and records at or before the last one sent are not sent twice.
    """

    def __init__(self, path: Path, send: Callable[[dict[str, Any]], None], every: float = 0.5) -> None:
        self.path, self.send, self.every = path, send, every
        self.offset, self.last = 0, 0
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._loop, daemon=True)

    def __enter__(self) -> _MetricsTail:
        self._thread.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self._stop.set()
        self._thread.join()
        self.poll()

    def _loop(self) -> None:
        while not self._stop.wait(self.every):
            self.poll()

    def poll(self) -> None:
        """Send the records appended since the last poll."""
        try:
            size = self.path.stat().st_size
        except FileNotFoundError:
            return
        if size < self.offset:
            self.offset = 0
        with open(self.path, "rb") as f:
            f.seek(self.offset)
            chunk = f.read(size - self.offset)
        whole = chunk[:chunk.rfind(b"\n") + 1]
        self.offset += len(whole)
        for line in whole.splitlines():
            try:
                record = json.loads(line)
            except json.JSONDecodeError:
                continue
            step = record.get("iteration") if isinstance(record, dict) else None
            if isinstance(step, int) and step > self.last:
                self.last = step
                self.send(record)


@ray.remote
def _train(scene: Scene, config: str, events: Queue, device: str | None) -> dict[str, Any]:
    """One scene as a Ray task: resume from the checkpoint if there is one, else start over, on ``device`` (None: the
    config's); returns the bundle's metadata. A failed attempt is reported on ``events`` before Ray sees the
    exception (and retries)."""
    resume = checkpoint_path(scene.out).is_file()
    if not resume:   # a run killed before its first checkpoint kept nothing to continue: start it over
        (scene.out / CONFIG_FILE).unlink(missing_ok=True)
    psnr: list[float] = []

    def send(record: dict[str, Any]) -> None:
        if "psnr" in record:
            psnr.append(float(record["psnr"]))
        events.put(("record", scene.name, record))

    try:
        with _MetricsTail(scene.out / METRICS_FILE, send):
            reconstruct(scene.data, scene.out, config, resume=resume, log=lambda s: events.put(("log", scene.name, s)),
                        device=device)
    except Exception as e:
        line = one_line(e)
        events.put(("attempt failed", scene.name, line))
        raise SceneFailed(line) from None
    meta = json.loads((scene.out / BUNDLE_META).read_text())
    return {"iterations": meta["iterations"], "gaussians": meta["gaussians"],
            "seconds": meta["train_seconds"], "psnr": psnr[-1] if psnr else None}


@contextlib.contextmanager
def ray_session(address: str | None) -> Iterator[None]:
    """Ray for the batch: the caller's instance if one is up, else a new local one (``address`` None) or the
    cluster at ``address``; what this starts it also shuts down. Worker output stays in Ray's logs: progress
    comes through the batch's queue."""
    if ray.is_initialized():
        yield
        return
    ray.init(address=address, include_dashboard=False, log_to_driver=False, configure_logging=False)
    try:
        yield
    finally:
        ray.shutdown()


def _largest_node(resource: str) -> float:
    """The most of ``resource`` (``CPU``, ``GPU``) one live node of the cluster has."""
    return max(float(n["Resources"].get(resource, 0)) for n in ray.nodes() if n["Alive"])


def _largest_node_cpus() -> int:
    return int(_largest_node("CPU"))


def check_gpus(device: str, gpus_per_task: float) -> None:
    """Refuse GPU settings no task could run with: a CUDA device without reserved GPUs (Ray places a task by what it
    reserves, and older Ray versions show a task that reserves none no GPU), a GPU count Ray does not take (a fraction
    must be below 1) or more GPUs than any node has.

    Args:
        device: the tasks' device name (``run.device`` or ``--device``).
        gpus_per_task: Ray GPUs each task reserves.

    Raises:
        ValueError: one of the above, as one line.
    """
    if device.startswith("cuda") and not gpus_per_task:
        raise ValueError(f"device {device} needs --gpus-per-task > 0 (e.g. 1, or 0.5 for two scenes per GPU): a Ray "
                         "task is placed by the GPUs it reserves")
    if gpus_per_task > 1 and not float(gpus_per_task).is_integer():
        raise ValueError(f"--gpus-per-task {gpus_per_task:g}: Ray takes a fraction below 1 or a whole number")
    if gpus_per_task > _largest_node("GPU"):
        raise ValueError(f"--gpus-per-task {gpus_per_task:g}: no Ray node has that many GPUs "
                         f"(largest: {_largest_node('GPU'):g})")


def default_cpus_per_task(tasks: int) -> int:
    """The cluster's CPUs shared evenly by ``tasks`` tasks, at least 1 and at most what the largest node has."""
    total = int(ray.cluster_resources().get("CPU", 1))
    return max(1, min(total // max(tasks, 1), _largest_node_cpus()))


def _existing_run(scene: Scene, config: TrainConfig) -> str | None:
    """``finished`` or ``resumable`` for a scene whose folder already holds a run of this config, None for none;
    a run of another config is a ValueError (it is kept, not mixed or replaced)."""
    finished, resumable = (scene.out / BUNDLE_META).is_file(), checkpoint_path(scene.out).is_file()
    if not (finished or resumable):
        return None
    stored = scene.out / CONFIG_FILE
    if stored.is_file() and not load_config(stored).same_run(config):
        raise ValueError(f"{scene.out} holds a run with another config: remove it or choose another output folder")
    return "finished" if finished else "resumable"


def _progress_line(name: str, record: dict[str, Any]) -> str:
    parts = [f"iteration {record['iteration']}"]
    parts += [f"{label} {record[key]:.2f} dB" for key, label in (("psnr", "train PSNR"), ("test_psnr", "test PSNR"))
              if isinstance(record.get(key), float) and math.isfinite(record[key])]
    return f"{name}: {', '.join(parts)}"


class _Relay:
    """Prints the tasks' events as they come: progress at most every ``interval`` s per scene, every failed attempt
    and every line the trainer logs (initialised, resumed, wrote)."""

    def __init__(self, events: Queue, report: Callable[[str], None], retries: int, interval: float) -> None:
        self.events, self.report, self.retries, self.interval = events, report, retries, interval
        self.failed: dict[str, int] = {}
        self._shown: dict[str, float] = {}

    def drain(self) -> None:
        for kind, name, payload in self.events.get_nowait_batch(self.events.qsize()):
            if kind == "record":
                now = time.monotonic()
                if now - self._shown.get(name, -math.inf) >= self.interval:
                    self._shown[name] = now
                    self.report(_progress_line(name, payload))
            elif kind == "attempt failed":
                self.failed[name] = attempt = self.failed.get(name, 0) + 1
                retry = "retrying (from its last checkpoint, if any)" if attempt <= self.retries else "giving up"
                self.report(f"{name}: attempt {attempt} failed: {payload}; {retry}")
            else:
                self.report(f"{name}: {payload}")


def _plan(scenes: Sequence[Scene], config: TrainConfig) -> tuple[dict[str, Outcome], dict[Scene, bool]]:
    """Outcomes known before any task (skipped, refused) and the scenes to train, each with whether it resumes."""
    known: dict[str, Outcome] = {}
    todo: dict[Scene, bool] = {}
    for scene in scenes:
        try:
            existing = _existing_run(scene, config)
        except ValueError as e:
            known[scene.name] = Outcome(scene.name, "failed", detail=one_line(e))
            continue
        if existing == "finished":
            known[scene.name] = Outcome(scene.name, "skipped", detail="bundle already written")
        else:
            todo[scene] = existing == "resumable"
    return known, todo


def run_batch(scenes: Sequence[Scene], config: str, cpus_per_task: int | None = None,
              retries: int = 1, report: Callable[[str], None] = print, progress_every: float = 10.0,
              device: str | None = None, gpus_per_task: float = 0.0) -> list[Outcome]:
    """Train every scene (``plan_scenes``) whose bundle is not yet written as a Ray task (Ray must be up, see
    ``ray_session``); returns one outcome per scene, in order. A failed scene does not stop the others. ``device``
    overrides the config's ``run.device`` in every task (a run started on another device resumes on this one);
    ``gpus_per_task`` is each task's Ray ``num_gpus`` (with 0 the task is shown no GPU at all)."""
    train_config = load_config(config)
    if device is not None:
        train_config = train_config.on_device(device)
    outcomes, todo = _plan(scenes, train_config)
    if not todo:
        return [outcomes[s.name] for s in scenes]
    cpus = cpus_per_task or default_cpus_per_task(len(todo))
    if cpus > _largest_node_cpus():
        raise ValueError(f"--cpus-per-task {cpus}: no Ray node has that many CPUs (largest: {_largest_node_cpus()})")
    check_gpus(train_config.run.device, gpus_per_task)
    gpus = f" and {gpus_per_task:g} GPU(s)" if gpus_per_task else ""
    report(f"training {len(todo)} of {len(scenes)} scene(s) as Ray tasks on {train_config.run.device}, "
           f"{cpus} CPU(s){gpus} each")
    events = Queue(actor_options={"num_cpus": 0})
    relay = _Relay(events, report, retries, progress_every)
    env = {"OMP_NUM_THREADS": str(cpus), "NUMBA_NUM_THREADS": str(cpus)}   # torch's and numba's pools
    if not gpus_per_task:   # Ray leaves every GPU visible to a task that reserved none: auto would take one
        env["CUDA_VISIBLE_DEVICES"] = ""
    options = {"num_cpus": cpus, "num_gpus": gpus_per_task, "max_retries": retries, "retry_exceptions": True,
               "runtime_env": {"env_vars": env}}
    pending = {_train.options(**options, name=f"reconstruct {s.name}").remote(s, _worker_config(config), events,
                                                                              device): s
               for s in todo}
    try:
        while pending:
            done, _ = ray.wait(list(pending), num_returns=1, timeout=0.5)
            relay.drain()
            for ref in done:
                scene = pending.pop(ref)
                outcomes[scene.name] = _outcome(scene, ref, todo[scene], relay.failed.get(scene.name, 0))
    finally:
        events.shutdown()
    return [outcomes[s.name] for s in scenes]


def _outcome(scene: Scene, ref: ray.ObjectRef, resumed: bool, failed_attempts: int) -> Outcome:
    """The outcome of a finished task: its bundle's numbers, or its error as one line."""
    try:
        result = ray.get(ref)
    except ray.exceptions.RayTaskError as e:
        cause = e.cause
        return Outcome(scene.name, "failed", failed_attempts,
                       detail=str(cause) if isinstance(cause, SceneFailed) else one_line(cause))
    except ray.exceptions.RayError as e:   # the worker or its node died: Ray's own error
        return Outcome(scene.name, "failed", failed_attempts, detail=one_line(e))
    return Outcome(scene.name, "resumed" if resumed else "trained", failed_attempts + 1, result["iterations"],
                   result["gaussians"], result["seconds"], result["psnr"])
