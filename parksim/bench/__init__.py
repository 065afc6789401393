"""``parksim bench``: seeded benchmark suites, each run written as one JSON record, and the dashboard built from them.

- ``record``: a run as data (``Figure``, ``Machine``, ``Record``), written once, read by the report.
- ``suite``: the ``Suite`` contract (options dataclass, ``run(options, context) -> Outcome``), the registry
  ``SUITES`` and ``run_suite``, which stamps a run (command, commit, date, machine, load, versions) into a record.
- ``report``: ``benchmarks/RESULTS.md`` generated from the records alone.
- ``suites/``: one module per suite (``scaling``, ``knobs``, ``train``, ``stress``, ``soak-train`` and
  ``soak-server``, ...), each importing torch and the renderer only inside ``run``.
- Inputs the suites share: ``datasets`` (synthetic garages made once under the work folder), ``scenes``
  (garage-like Gaussian scenes from a dataset's points, SH caps), ``bundles`` and ``serving`` (trained and served
  bundles); ``procs`` (processes under measurement: RSS and CPU from /proc, a loopback ``parksim serve``).
- ``common``: timing medians (wall and process CPU, alternating order), thread control, growth exponents,
  progress bars and plots.

Reached from the CLI (``parksim bench``) and the tests; library code elsewhere never imports it.
"""

__all__: list[str] = []
