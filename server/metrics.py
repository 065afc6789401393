"""Prometheus text exposition (format 0.0.4) of request counts, errors, latency and the render time split."""

from __future__ import annotations

import threading
from collections import defaultdict

__all__ = ["Metrics", "CONTENT_TYPE"]

CONTENT_TYPE = "text/plain; version=0.0.4; charset=utf-8"
_BUCKETS = (0.005, 0.01, 0.025, 0.05, 0.1, 0.25, 0.5, 1.0, 2.5, 5.0, 10.0, 30.0)


class _Histogram:
    """Cumulative-bucket histogram of seconds."""

    def __init__(self) -> None:
        self.counts = [0] * (len(_BUCKETS) + 1)
        self.total = 0.0

    def observe(self, seconds: float) -> None:
        i = next((i for i, b in enumerate(_BUCKETS) if seconds <= b), len(_BUCKETS))
        self.counts[i] += 1
        self.total += seconds

    def lines(self, name: str, labels: str) -> list[str]:
        out, running = [], 0
        for bound, count in zip([*map(str, _BUCKETS), "+Inf"], self.counts):
            running += count
            out.append(f'{name}_bucket{{{labels}{"," if labels else ""}le="{bound}"}} {running}')
        suffix = f"{{{labels}}}" if labels else ""
        out += [f"{name}_sum{suffix} {self.total:.6f}", f"{name}_count{suffix} {running}"]
        return out


def _labels(**kv: str) -> str:
    return ",".join(f'{k}="{v}"' for k, v in kv.items())


class Metrics:
    """Thread-safe counters and histograms, rendered on demand by ``text``."""

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self.requests: dict[tuple[str, str, int], int] = defaultdict(int)
        self.latency: dict[str, _Histogram] = defaultdict(_Histogram)
        self.stages: dict[str, _Histogram] = defaultdict(_Histogram)
        self.images = 0

    def request(self, route: str, method: str, status: int, seconds: float) -> None:
        """Count one answered request and its latency."""
        with self._lock:
            self.requests[(route, method, status)] += 1
            self.latency[route].observe(seconds)

    def render(self, timings: dict[str, float], images: int) -> None:
        """Record one render job's stage times (queue, views, bev, encode) and how many images it returned."""
        with self._lock:
            for stage, seconds in timings.items():
                self.stages[stage].observe(seconds)
            self.images += images

    def text(self, pool: dict[str, int]) -> str:
        """The exposition text, with the render pool's gauges."""
        with self._lock:
            out = ["# HELP parksim_requests_total HTTP requests answered, by route, method and status.",
                   "# TYPE parksim_requests_total counter"]
            out += [f"parksim_requests_total{{{_labels(route=r, method=m, status=str(s))}}} {n}"
                    for (r, m, s), n in sorted(self.requests.items())]
            out += ["# HELP parksim_errors_total HTTP requests answered with a 4xx or 5xx status, by status.",
                    "# TYPE parksim_errors_total counter"]
            errors: dict[int, int] = defaultdict(int)
            for (_, _, s), n in self.requests.items():
                if s >= 400:
                    errors[s] += n
            out += [f'parksim_errors_total{{status="{s}"}} {n}' for s, n in sorted(errors.items())]
            out += ["# HELP parksim_request_seconds Request latency, by route.",
                    "# TYPE parksim_request_seconds histogram"]
            for route, h in sorted(self.latency.items()):
                out += h.lines("parksim_request_seconds", _labels(route=route))
            out += ["# HELP parksim_render_stage_seconds Render job time split: queue wait, fisheye views, BEV, "
                    "encoding.", "# TYPE parksim_render_stage_seconds histogram"]
            for stage, h in sorted(self.stages.items()):
                out += h.lines("parksim_render_stage_seconds", _labels(stage=stage))
            out += ["# HELP parksim_images_total Images returned (views and BEVs).",
                    "# TYPE parksim_images_total counter", f"parksim_images_total {self.images}"]
        out += ["# HELP parksim_render_in_flight Render jobs running or queued.",
                "# TYPE parksim_render_in_flight gauge", f"parksim_render_in_flight {pool['in_flight']}",
                "# HELP parksim_render_capacity Render jobs admitted at most (workers + queue).",
                "# TYPE parksim_render_capacity gauge", f"parksim_render_capacity {pool['capacity']}",
                "# HELP parksim_render_rejected_total Requests answered 503 because the queue was full.",
                "# TYPE parksim_render_rejected_total counter", f"parksim_render_rejected_total {pool['rejected']}"]
        return "\n".join(out) + "\n"
