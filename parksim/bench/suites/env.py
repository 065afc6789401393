"""``parksim bench env``: env steps/s of vector ParkSim-v0 for 1, 2 and 4 envs: sub-envs in Ray actors, batch renders
against ``parksim serve`` and ``parksim serve --ray``, and gymnasium's in-process SyncVectorEnv as the reference.

Each run: reset(seed=0), ``--warmup`` steps, then ``--steps`` timed vector steps of seeded random actions. Wall time,
and the CPU time of this process's whole tree (this process, Ray's daemons and actors, the server subprocess and its
replicas, read from /proc), so a loaded machine shows in wall time but not in CPU time. Ray is this process's
instance (``parksim.bench.procs.local_ray``: 2 CPUs and a small object store unless one is running); ``parksim
serve --ray`` joins it.
"""

from __future__ import annotations

import statistics
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

from ..record import Figure
from ..suite import Context, Outcome, Suite

__all__ = ["EnvSuite", "EnvOptions", "BACKENDS", "RAY_CPUS"]

BACKENDS = {"sync": "in-process SyncVectorEnv", "ray": "Ray actors (RayVectorEnv)",
            "serve": "batch POST /render, serve", "serve-ray": "batch POST /render, serve --ray"}
"""Vectorisations: name -> label; ``sync`` is the reference."""
RAY_CPUS = 2
"""CPUs of the Ray instance the suite starts when none is running."""


@dataclass(frozen=True)
class EnvOptions:
    """Options of ``parksim bench env``."""

    envs: list[int] = field(default_factory=lambda: [1, 2, 4], metadata={"help": "numbers of envs", "low": 1,
                                                                         "quick": [2]})
    steps: int = field(default=40, metadata={"help": "timed vector steps per run", "low": 1, "quick": 3})
    warmup: int = field(default=5, metadata={"help": "untimed vector steps first", "low": 0, "quick": 1})
    repeats: int = field(default=3, metadata={"help": "timed runs per setting (median)", "low": 1, "quick": 1})
    preset: str = field(default="tiny", metadata={"help": "synth preset whose garage the bundle samples"})
    gaussians: int = field(default=3000, metadata={"help": "Gaussians of the bundle", "low": 1, "quick": 2000})
    scale: float = field(default=1.0, metadata={"help": "resolution factor of the camera views", "low": 0.05,
                                                "high": 2.0})
    backends: list[str] = field(default_factory=lambda: list(BACKENDS), metadata={
        "help": f"vectorisations to measure, of {', '.join(BACKENDS)} (sync, the reference, always runs)",
        "quick": ["sync", "ray", "serve-ray"]})
    device: str = field(default="cpu", metadata={
        "help": "where sync's envs and serve's server render: cpu, cuda[:N] or auto (resolved here; Ray actors see no "
                "GPU, so a CUDA device measures sync and serve only)"})

    def __post_init__(self) -> None:
        unknown = [b for b in self.backends if b not in BACKENDS]
        if unknown:
            raise ValueError(f"--backends: unknown {', '.join(unknown)}; choose from {', '.join(BACKENDS)}")


def measure(envs: Any, steps: int, warmup: int) -> tuple[float, float]:
    """(env steps/s by wall time, CPU ms of the process tree per env step) over ``steps`` vector steps.

    Args:
        envs: a vector env.
        steps: timed vector steps.
        warmup: untimed vector steps after the reset.

    Returns:
        Env steps per second and CPU milliseconds per env step.
    """
    import os
    import time

    import numpy as np

    from ..procs import tree_cpu_seconds

    rng = np.random.default_rng(0)
    envs.reset(seed=0)
    for _ in range(warmup):
        envs.step(rng.uniform(-1, 1, envs.action_space.shape).astype(np.float32))
    actions = rng.uniform(-1, 1, (steps, *envs.action_space.shape)).astype(np.float32)
    cpu0, t0 = tree_cpu_seconds(os.getpid()), time.perf_counter()
    for a in actions:
        envs.step(a)
    wall, cpu = time.perf_counter() - t0, tree_cpu_seconds(os.getpid()) - cpu0
    n = envs.num_envs * steps
    return n / wall, 1000 * cpu / n


class EnvSuite(Suite):
    """Vector-env throughput and CPU per env step of each vectorisation against in-process SyncVectorEnv."""

    name = "env"
    help = "vector ParkSim-v0 env steps/s: Ray actors, batch renders via parksim serve (--ray) vs SyncVectorEnv"
    description = ("Vector ParkSim-v0 over a bundle sampled on a synth garage (every camera at --scale, no BEV), for "
                   "each of --envs: gymnasium's in-process SyncVectorEnv (the reference), RayVectorEnv (one Ray "
                   "actor per env), and batch POST /render against `parksim serve` and `parksim serve --ray`. Median "
                   "of --repeats runs of --steps vector steps after --warmup. Figures: wall ms per env step (cpu: CPU "
                   "ms of the whole process tree per env step) of each vectorisation and env count, against "
                   "SyncVectorEnv with as many envs. Data: env steps/s and CPU ms per env step of every run.")
    Options = EnvOptions

    def run(self, options: EnvOptions, context: Context) -> Outcome:
        """Every vectorisation for every env count; Ray and the servers are up only while they are measured."""
        import gymnasium as gym

        import parksim.env  # noqa: F401  (registers ParkSim-v0)

        from ...bundle import load
        from ...device import resolve_device
        from ..procs import local_ray, serve_bundle
        from ..serving import garage_bundle

        device = resolve_device(options.device)   # a bad name or a missing GPU: refused before any work
        cuda = device.type == "cuda"
        if cuda and {"ray", "serve-ray"} & set(options.backends):
            raise ValueError(f"--device {options.device}: the Ray backends render in actors that see no GPU; "
                             "measure --backends sync,serve on CUDA")
        bundle = garage_bundle(context, options.preset, None, options.gaussians)
        rig = load(bundle).rig
        view: dict[str, Any] = {"cameras": rig.names, "bev": False, "scale": options.scale}
        sizes = sorted({(round(c.model.width * options.scale), round(c.model.height * options.scale))
                        for c in rig.cameras.values()})
        where = (f"ParkSim-v0 on {bundle.name}, {options.gaussians:,} Gaussians, {len(rig.names)} views at "
                 + ", ".join(f"{w}x{h}" for w, h in sizes) + (", on CUDA" if cuda else ""))
        rows: dict[str, dict[int, dict[str, Any]]] = {}

        def measure_all(name: str, make: Callable[[int], Any]) -> None:
            for n in options.envs:
                envs = make(n)
                try:
                    results = [measure(envs, options.steps, options.warmup) for _ in range(options.repeats)]
                finally:
                    envs.close()
                rows.setdefault(name, {})[n] = {
                    "steps_per_s": statistics.median(r[0] for r in results),
                    "cpu_ms_per_step": statistics.median(r[1] for r in results),
                    "runs": [{"steps_per_s": r[0], "cpu_ms_per_step": r[1]} for r in results]}

        def vector(n: int, **source: Any) -> Any:
            return gym.make_vec("ParkSim-v0", n, **source, **view)

        measure_all("sync", lambda n: vector(n, vectorization_mode="sync", bundle=bundle, device=str(device)))
        if "serve" in options.backends:   # one POST /render carries every env's pose: --max-batch covers them
            with serve_bundle(bundle, ["--device", str(device), "--max-batch", str(max(options.envs))]) as server:
                measure_all("serve", lambda n: vector(n, backend="batch", server=server.base))
        if {"ray", "serve-ray"} & set(options.backends):
            import ray
            from ray import serve

            with local_ray(RAY_CPUS):
                if "ray" in options.backends:
                    measure_all("ray", lambda n: vector(n, bundle=str(bundle)))
                if "serve-ray" in options.backends:
                    try:   # parksim serve --ray joins this instance; Serve, which it starts, goes down after
                        address = ray.get_runtime_context().gcs_address
                        with serve_bundle(bundle, ["--ray", "--address", address]) as server:
                            measure_all("serve-ray", lambda n: vector(n, backend="batch", server=server.base))
                    finally:
                        serve.shutdown()
        return Outcome(_figures(rows, where), {"bundle": str(bundle), "view": view, "device": str(device),
                                               "rows": rows})


def _figures(rows: dict[str, dict[int, dict[str, Any]]], where: str) -> list[Figure]:
    """Wall and CPU ms per env step of each vectorisation and env count, against SyncVectorEnv's."""
    figures = []
    for name in BACKENDS:
        for n, row in rows.get(name, {}).items():
            target = f"{BACKENDS[name]}, {n} env{'s' * (n > 1)}: ms per env step, {where}"
            wall, cpu = 1000 / row["steps_per_s"], row["cpu_ms_per_step"]
            if name == "sync":
                figures.append(Figure(target, wall, "ms", cpu=cpu))
            else:
                ref = rows["sync"][n]
                figures.append(Figure(target, wall, "ms", cpu=cpu, reference=1000 / ref["steps_per_s"],
                                      reference_label=BACKENDS["sync"], reference_cpu=ref["cpu_ms_per_step"]))
    return figures
