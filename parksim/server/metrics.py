"""Prometheus metrics of one app (request counts, errors, latency, the render time split, pool and reply budget),
kept in the app's own ``CollectorRegistry`` so several apps in one process never share or clash."""

from __future__ import annotations

from collections.abc import Callable, Iterator

from prometheus_client import CollectorRegistry, Counter, Histogram, generate_latest
from prometheus_client.exposition import CONTENT_TYPE_PLAIN_0_0_4
from prometheus_client.metrics_core import CounterMetricFamily, GaugeMetricFamily, Metric
from prometheus_client.registry import Collector

__all__ = ["Metrics", "CONTENT_TYPE"]

CONTENT_TYPE = CONTENT_TYPE_PLAIN_0_0_4
_BUCKETS = (0.005, 0.01, 0.025, 0.05, 0.1, 0.25, 0.5, 1.0, 2.5, 5.0, 10.0, 30.0)
Stats = Callable[[], dict[str, int]]


class _StateCollector(Collector):
    """Gauges and counters read at scrape time from the render pool and the reply budget."""

    def __init__(self, pool: Stats, replies: Stats) -> None:
        self._pool, self._replies = pool, replies

    def collect(self) -> Iterator[Metric]:
        pool, replies = self._pool(), self._replies()
        yield GaugeMetricFamily("parksim_render_in_flight", "Render jobs running or queued.", value=pool["in_flight"])
        yield GaugeMetricFamily("parksim_render_capacity", "Render jobs admitted at most (workers + queue).",
                                value=pool["capacity"])
        yield CounterMetricFamily("parksim_render_rejected", "Requests answered 503 because the queue was full.",
                                  value=pool["rejected"])
        yield GaugeMetricFamily("parksim_reply_bytes_in_flight", "Reply bytes reserved by requests being rendered "
                                "or sent.", value=replies["in_flight_bytes"])
        yield GaugeMetricFamily("parksim_reply_budget_bytes", "Reply bytes that may be in flight at once.",
                                value=replies["budget_bytes"])
        yield CounterMetricFamily("parksim_reply_rejected", "Requests answered 503 because the reply budget was "
                                  "full.", value=replies["rejected"])


class Metrics:
    """The app's metrics; ``pool`` and ``replies`` give the render pool's and reply budget's ``stats()``."""

    def __init__(self, pool: Stats, replies: Stats) -> None:
        self.registry = CollectorRegistry()
        r = self.registry
        self._requests = Counter("parksim_requests", "HTTP requests answered, by route, method and status.",
                                 ["route", "method", "status"], registry=r)
        self._errors = Counter("parksim_errors", "HTTP requests answered with a 4xx or 5xx status, by status.",
                               ["status"], registry=r)
        self._latency = Histogram("parksim_request_seconds", "Request latency (to the start of the reply), by route.",
                                  ["route"], buckets=_BUCKETS, registry=r)
        self._stages = Histogram("parksim_render_stage_seconds", "Render job time split: queue wait, fisheye views, "
                                 "BEV, encoding.", ["stage"], buckets=_BUCKETS, registry=r)
        self._images = Counter("parksim_images", "Images returned (views and BEVs).", registry=r)
        r.register(_StateCollector(pool, replies))

    def request(self, route: str, method: str, status: int, seconds: float) -> None:
        """Count one answered request and its latency."""
        self._requests.labels(route, method, str(status)).inc()
        if status >= 400:
            self._errors.labels(str(status)).inc()
        self._latency.labels(route).observe(seconds)

    def render(self, timings: dict[str, float], images: int) -> None:
        """Record one render job's stage times (queue, views, bev, encode) and how many images it returned."""
        for stage, seconds in timings.items():
            self._stages.labels(stage).observe(seconds)
        self._images.inc(images)

    def text(self) -> bytes:
        """The exposition in the Prometheus text format 0.0.4."""
        return generate_latest(self.registry)
