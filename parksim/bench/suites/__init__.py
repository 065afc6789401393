"""The benchmark suites, one module each, registered in ``parksim.bench.suite.SUITES``.

Suite modules keep their top level light (dataclasses and constants); torch, numba and the renderer are
imported inside ``run``, so ``parksim bench --help`` stays fast.
"""

__all__: list[str] = []
