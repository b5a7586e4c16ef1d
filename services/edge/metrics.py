"""Prometheus metrics of one daemon, served on ``--metrics-port`` (``GET /metrics``).

Every daemon (vehicle, RSU, monitor, router) can serve its own registry
(``prometheus-client``) over HTTP: ``metrics_port`` in its config or
``--metrics-port PORT``, on ``metrics_host`` (default ``0.0.0.0``, as every
Prometheus exporter; the router's ``--metrics-host``); port 0 picks a free one,
logged. Without a port nothing listens.

Nothing is counted twice: the values are read at scrape time from the counters
the daemon keeps anyway (``services.edge.stats.NodeStats`` per V2X stream, the
receive policies' ``ReceiveStats``, the pure core's ``counters``), so the
metrics and the stats reports on ``{prefix}/stats/{node}`` always agree. Only
tick lateness is observed here (:meth:`DaemonMetrics.on_tick`: a histogram, where
the stats keep a count and a maximum).

Decisions where the issue is silent:

- The stats are per run (the shell starts fresh counters at each run's start and
  end), but Prometheus counters must never go down: a counter here is the sum
  over every run since the daemon started. :class:`Carry` remembers the counter
  object it read last per slot; once another object has taken its place, the old
  one's final values (still referenced, no longer written) join the slot's base.
  Reads happen at every scrape, at every stats report (every ``stats_period_s``,
  at a run's start and before its end) and just before a run's start replaces the
  counters kept between runs; the pure core's (the car's agent, the RSU's core:
  one per run) also at every tick of the control loop. Nothing is lost.
- Gauges are of *now*: ``crosspath_run_active``, the car's mode, the reservation
  table's size, and the peak receive-queue depth of the current run (the inbox
  keeps only its peak between scrapes: a queue that fills and drains within one
  scrape interval would be invisible as a current depth).
- Latency histograms are re-bucketed from the stats' log-spaced histograms (50
  buckets per decade) onto :data:`LATENCY_BUCKETS_S`: a source bucket counts
  below a bound only when it lies wholly below it, so a bound may undercount by
  samples within 4.7 % below it.
- Every ``crosspath_*`` series carries a ``node`` label (the daemon's id), so a
  dashboard groups by node whatever the scrape job calls its targets;
  ``crosspath_daemon_info`` adds ``service`` and ``version``. Process metrics
  (CPU, memory, open files) come from prometheus-client's own collectors.
- The endpoint is served by the daemon's event loop (``asyncio`` streams), not a
  thread: a scrape reads the counters on the thread that writes them, and a
  daemon whose loop is stuck does not answer, which is what an operator wants
  to see. A scrape of a car (about 300 series) takes 4 ms of loop time to collect
  and 8 more to format (measured on a loaded 2-core machine): well inside a
  tick period, and once per scrape interval (typically 15 s).
- A port that cannot be bound ends the daemon at start with one line and exit
  status 78 (``EXIT_CONFIG``), like any endpoint (``services.edge.shell``).
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import math
from collections.abc import Callable, Iterable, Iterator, Mapping
from dataclasses import dataclass
from typing import Any, Final, Protocol, TypeVar

from prometheus_client import (
    CONTENT_TYPE_LATEST,
    CollectorRegistry,
    Counter,
    Histogram,
    generate_latest,
)
from prometheus_client.core import (
    CounterMetricFamily,
    GaugeMetricFamily,
    HistogramMetricFamily,
    Metric,
)
from prometheus_client.gc_collector import GCCollector
from prometheus_client.platform_collector import PlatformCollector
from prometheus_client.process_collector import ProcessCollector

from services.edge.lifecycle import EXIT_CONFIG, ServiceExit
from services.edge.provenance import package_version
from services.edge.stats import BUCKETS_PER_DECADE, LATENCY_FLOOR_S, LatencyHistogram, NodeStats
from services.edge.transport import TransportError, ZenohTransport

__all__ = [
    "LATENCY_BUCKETS_S",
    "METRICS",
    "TICK_LAG_BUCKETS_S",
    "Carry",
    "CoreView",
    "DaemonMetrics",
    "MetricsServer",
    "zenoh_links",
]

log = logging.getLogger("crosspath.metrics")

LATENCY_BUCKETS_S: Final = (
    0.0001,
    0.00025,
    0.0005,
    0.001,
    0.0025,
    0.005,
    0.01,
    0.025,
    0.05,
    0.1,
    0.25,
    0.5,
    1.0,
    2.5,
)
"""Upper bounds of the exported one-way and queueing latency histograms [s]."""

TICK_LAG_BUCKETS_S: Final = (0.001, 0.0025, 0.005, 0.01, 0.025, 0.05, 0.1, 0.25, 0.5, 1.0)
"""Upper bounds of the tick-lag histogram [run s]."""

METRICS: Final[Mapping[str, str]] = {
    "crosspath_daemon_info": "this daemon: node id, service and package version (value 1)",
    "crosspath_v2x_sent_messages_total": "V2X datagrams handed to the transport, per stream",
    "crosspath_v2x_sent_bytes_total": "V2X payload bytes sent (encoded message), per stream",
    "crosspath_v2x_received_messages_total": "V2X datagrams received, decoded and accepted",
    "crosspath_v2x_received_bytes_total": "V2X payload bytes received and accepted",
    "crosspath_v2x_latency_seconds": "one-way V2X latency, generation to handling [wall s]",
    "crosspath_dropped_messages_total": (
        "messages dropped, by stream (V2X stream or subscription) and reason: malformed, "
        "stale, refused (sender not in the run), duplicate (a replayed copy), rate_limited, "
        "coalesced (replaced by a newer one before handled), overflow (inbox full)"
    ),
    "crosspath_receive_offered_messages_total": "datagrams the network offered a subscription",
    "crosspath_receive_delivered_messages_total": "datagrams a subscription's handler took",
    "crosspath_receive_latency_seconds": "arrival to end of the handler (queueing) [wall s]",
    "crosspath_receive_queue_peak_lanes": "most senders queued at once in this run's inbox",
    "crosspath_receive_queue_peak_bytes": "most bytes queued at once in this run's inbox",
    "crosspath_internal_errors_total": "exceptions out of our own handlers (bugs)",
    "crosspath_ticks_total": "control-loop ticks run",
    "crosspath_ticks_late_total": "ticks run more than one period behind the run clock",
    "crosspath_tick_lag_seconds": "how far a tick ran behind its due time [run s]",
    "crosspath_run_active": "1 while a run is active",
    "crosspath_run_time_seconds": "run time of the active run [run s]",
    "crosspath_zenoh_links": "Zenoh links (transport sessions) open now",
    "crosspath_core_events_total": "every counter of the pure core (agent or RSU core)",
    "crosspath_mode_changes_total": "a car's mode changes, by the mode entered",
    "crosspath_vehicle_mode": "a car's mode now (1 for the current mode)",
    "crosspath_rsu_decisions_total": "RSU evaluations of a car's path, by outcome",
    "crosspath_rsu_actions_total": "RSU commands and plans: initiations, terminations, ...",
    "crosspath_rsu_conflicts_total": "RSU evaluations that found a conflict within T_free",
    "crosspath_rsu_table_vehicles": "cars in the RSU's reservation table now",
}
"""Every ``crosspath_*`` metric name this module exports, with its help text (the
dashboard in ``deploy/grafana/`` uses only these and prometheus-client's
``process_*`` and ``python_*``)."""

_RSU_ACTIONS: Final = {
    "initiations": "initiation",
    "reinitiations": "reinitiation",
    "terminations": "termination",
    "coordinated_paths": "coordinated_path",
    "given_way": "given_way",
    "order_kept": "order_kept",
    "expired": "expired",
}
"""RSU core counters exported as ``crosspath_rsu_actions_total{action}``."""

_STREAM_FIELDS: Final = ("msgs_tx", "bytes_tx", "msgs_rx", "bytes_rx", "malformed", "dropped_stale")
_RECEIVE_DROPS: Final = ("refused", "duplicate", "rate_limited", "coalesced", "overflow")

T = TypeVar("T")


@dataclass(frozen=True, slots=True)
class CoreView:
    """What the daemon's pure core shows the metrics now.

    ``counters`` must be a new object for every run (a fresh core has fresh
    counters): :class:`Carry` tells runs apart by it.
    """

    counters: Mapping[str, int]
    mode: str | None = None
    """A car's mode name (``AUTO``, ``C_SLOW``, ``C_FAST``)."""
    table_size: int | None = None
    """An RSU's reservation table size."""


class ShellView(Protocol):
    """What the metrics read of a ``services.edge.shell.DaemonShell``."""

    @property
    def stats(self) -> NodeStats: ...
    @property
    def receive(self) -> Mapping[str, Any]: ...
    @property
    def run_id(self) -> str | None: ...
    @property
    def plumbing_malformed(self) -> int: ...
    @property
    def internal_errors(self) -> int: ...
    def now(self) -> float | None: ...


class Carry:
    """Monotone totals over counter objects that each run replaces (see the module doc)."""

    def __init__(self) -> None:
        self._base: dict[str, dict[str, float]] = {}
        self._seen: dict[str, object] = {}

    def read(
        self, slot: str, current: T | None, values: Callable[[T], Mapping[str, float]]
    ) -> dict[str, float]:
        """Totals of ``slot``: every earlier object's final values plus ``current``'s."""
        base = self._base.setdefault(slot, {})
        prev = self._seen.get(slot)
        if prev is not None and prev is not current:
            for key, value in values(prev).items():  # type: ignore[arg-type]
                base[key] = base.get(key, 0.0) + value
        self._seen[slot] = current
        out = dict(base)
        if current is not None:
            for key, value in values(current).items():
                out[key] = out.get(key, 0.0) + value
        return out


def bucket_upper_s(index: int) -> float:
    """Upper edge of bucket ``index`` of a ``services.edge.stats.LatencyHistogram`` [s]."""
    return LATENCY_FLOOR_S * math.pow(10.0, index / BUCKETS_PER_DECADE)


def _histogram_values(hist: LatencyHistogram) -> dict[str, float]:
    """Keys ``b:<bucket index>``, ``sum`` [s] and ``count``."""
    values = {f"b:{i}": float(n) for i, n in list(hist.buckets.items())}
    values["sum"] = hist.sum_s
    values["count"] = float(hist.count)
    return values


def _rebucket(values: Mapping[str, float], bounds: Iterable[float]) -> list[tuple[str, float]]:
    """Cumulative Prometheus buckets from :func:`_histogram_values` (module doc)."""
    counts = sorted((int(k[2:]), n) for k, n in values.items() if k.startswith("b:"))
    out: list[tuple[str, float]] = []
    i = 0
    cumulative = 0.0
    for bound in bounds:
        while i < len(counts) and bucket_upper_s(counts[i][0]) <= bound * (1 + 1e-9):
            cumulative += counts[i][1]
            i += 1
        out.append((_le(bound), cumulative))
    out.append(("+Inf", values.get("count", 0.0)))
    return out


def _le(bound: float) -> str:
    return repr(float(bound))


class _Collector:
    """Reads the daemon's counters at scrape time (a prometheus-client custom collector)."""

    def __init__(self, owner: DaemonMetrics) -> None:
        self.owner = owner

    def collect(self) -> Iterator[Metric]:
        return iter(self.owner.families())

    def describe(self) -> Iterator[Metric]:
        return iter(())  # no registration-time collect (names are not fixed by stream)


class DaemonMetrics:
    """The registry of one daemon and what feeds it.

    ``shell`` gives the V2X and receive counters (None for the router), ``core`` the
    pure core's view (None outside a run, or for daemons without one), ``links`` the
    number of Zenoh links now.
    """

    def __init__(
        self,
        node: str,
        service: str,
        shell: ShellView | None = None,
        core: Callable[[], CoreView | None] | None = None,
        links: Callable[[], int] | None = None,
    ) -> None:
        self.node = node
        self.service = service
        self.shell = shell
        self.core = core
        self.links = links
        self.carry = Carry()
        self.registry = CollectorRegistry(auto_describe=False)
        labels = ["node"]
        self._ticks = Counter(
            "crosspath_ticks", METRICS["crosspath_ticks_total"], labels, registry=self.registry
        ).labels(node)
        self._late = Counter(
            "crosspath_ticks_late",
            METRICS["crosspath_ticks_late_total"],
            labels,
            registry=self.registry,
        ).labels(node)
        self._lag = Histogram(
            "crosspath_tick_lag_seconds",
            METRICS["crosspath_tick_lag_seconds"],
            labels,
            buckets=TICK_LAG_BUCKETS_S,
            registry=self.registry,
        ).labels(node)
        self.registry.register(_Collector(self))
        ProcessCollector(registry=self.registry)
        PlatformCollector(registry=self.registry)
        GCCollector(registry=self.registry)

    # -- feeding

    def on_tick(self, lag_s: float, period_s: float) -> None:
        """A control-loop tick ran ``lag_s`` behind its due time [run s]."""
        self._ticks.inc()
        self._lag.observe(max(0.0, lag_s))
        if lag_s > period_s:
            self._late.inc()
        if self.core is not None:  # see this run's core (a few microseconds; module doc)
            view = self.core()
            self.carry.read("core", None if view is None else view.counters, _as_floats)

    def observe(self) -> None:
        """Read the per-run counters now (before the shell replaces them; module doc)."""
        self.families()

    # -- reading

    def render(self) -> bytes:
        """The registry in Prometheus' text format."""
        return generate_latest(self.registry)

    def families(self) -> list[Metric]:
        """Every custom metric family now (the carried counters are read on the way)."""
        node = self.node
        out: list[Metric] = []
        info = GaugeMetricFamily(
            "crosspath_daemon_info",
            METRICS["crosspath_daemon_info"],
            labels=["node", "service", "version"],
        )
        info.add_metric([node, self.service, package_version()], 1.0)
        out.append(info)
        if self.shell is not None:
            out.extend(self._shell_families(self.shell))
        if self.links is not None:
            links = GaugeMetricFamily(
                "crosspath_zenoh_links", METRICS["crosspath_zenoh_links"], labels=["node"]
            )
            links.add_metric([node], float(self.links()))
            out.append(links)
        if self.core is not None:
            out.extend(self._core_families(self.core()))
        return out

    def _counter(self, name: str, labels: list[str]) -> CounterMetricFamily:
        return CounterMetricFamily(name.removesuffix("_total"), METRICS[name], labels=labels)

    def _shell_families(self, shell: ShellView) -> list[Metric]:
        node = self.node
        streams = self.carry.read("streams", shell.stats, _stream_values)
        sent = self._counter("crosspath_v2x_sent_messages_total", ["node", "stream"])
        sent_b = self._counter("crosspath_v2x_sent_bytes_total", ["node", "stream"])
        recv = self._counter("crosspath_v2x_received_messages_total", ["node", "stream"])
        recv_b = self._counter("crosspath_v2x_received_bytes_total", ["node", "stream"])
        dropped = self._counter("crosspath_dropped_messages_total", ["node", "stream", "reason"])
        latency = HistogramMetricFamily(
            "crosspath_v2x_latency_seconds",
            METRICS["crosspath_v2x_latency_seconds"],
            labels=["node", "stream"],
        )
        names = sorted({k.split("|", 1)[0] for k in streams})
        for stream in names:
            get = streams.get
            sent.add_metric([node, stream], get(f"{stream}|msgs_tx", 0.0))
            sent_b.add_metric([node, stream], get(f"{stream}|bytes_tx", 0.0))
            recv.add_metric([node, stream], get(f"{stream}|msgs_rx", 0.0))
            recv_b.add_metric([node, stream], get(f"{stream}|bytes_rx", 0.0))
            dropped.add_metric([node, stream, "malformed"], get(f"{stream}|malformed", 0.0))
            dropped.add_metric([node, stream, "stale"], get(f"{stream}|dropped_stale", 0.0))
            lat = f"{stream}|lat|"
            hist = {k.removeprefix(lat): v for k, v in streams.items() if k.startswith(lat)}
            latency.add_metric(
                [node, stream], _rebucket(hist, LATENCY_BUCKETS_S), hist.get("sum", 0.0)
            )
        dropped.add_metric([node, "plumbing", "malformed"], float(shell.plumbing_malformed))
        offered = self._counter("crosspath_receive_offered_messages_total", ["node", "stream"])
        delivered = self._counter("crosspath_receive_delivered_messages_total", ["node", "stream"])
        queue_latency = HistogramMetricFamily(
            "crosspath_receive_latency_seconds",
            METRICS["crosspath_receive_latency_seconds"],
            labels=["node", "stream"],
        )
        peak_lanes = GaugeMetricFamily(
            "crosspath_receive_queue_peak_lanes",
            METRICS["crosspath_receive_queue_peak_lanes"],
            labels=["node", "stream"],
        )
        peak_bytes = GaugeMetricFamily(
            "crosspath_receive_queue_peak_bytes",
            METRICS["crosspath_receive_queue_peak_bytes"],
            labels=["node", "stream"],
        )
        for label, policy in sorted(shell.receive.items()):
            stats = getattr(policy, "stats", None)
            if stats is None:
                continue
            counts = self.carry.read(f"receive:{label}", stats.counts, _as_floats)
            offered.add_metric([node, label], counts.get("offered", 0.0))
            delivered.add_metric([node, label], counts.get("delivered", 0.0))
            for reason in _RECEIVE_DROPS:
                dropped.add_metric([node, label, reason], counts.get(reason, 0.0))
            hist = self.carry.read(f"receive_latency:{label}", stats.latency, _histogram_values)
            queue_latency.add_metric(
                [node, label], _rebucket(hist, LATENCY_BUCKETS_S), hist.get("sum", 0.0)
            )
            peak_lanes.add_metric([node, label], float(stats.max_lanes))
            peak_bytes.add_metric([node, label], float(stats.max_bytes))
        errors = self._counter("crosspath_internal_errors_total", ["node"])
        errors.add_metric([node], float(shell.internal_errors))
        active = GaugeMetricFamily(
            "crosspath_run_active", METRICS["crosspath_run_active"], labels=["node"]
        )
        active.add_metric([node], 0.0 if shell.run_id is None else 1.0)
        run_time = GaugeMetricFamily(
            "crosspath_run_time_seconds", METRICS["crosspath_run_time_seconds"], labels=["node"]
        )
        now = shell.now()
        run_time.add_metric([node], 0.0 if now is None or not math.isfinite(now) else now)
        return [
            sent,
            sent_b,
            recv,
            recv_b,
            latency,
            dropped,
            offered,
            delivered,
            queue_latency,
            peak_lanes,
            peak_bytes,
            errors,
            active,
            run_time,
        ]

    def _core_families(self, view: CoreView | None) -> list[Metric]:
        node = self.node
        counters = self.carry.read("core", None if view is None else view.counters, _as_floats)
        events = self._counter("crosspath_core_events_total", ["node", "event"])
        modes = self._counter("crosspath_mode_changes_total", ["node", "mode"])
        decisions = self._counter("crosspath_rsu_decisions_total", ["node", "decision"])
        actions = self._counter("crosspath_rsu_actions_total", ["node", "action"])
        conflicts = self._counter("crosspath_rsu_conflicts_total", ["node"])
        rsu = self.service == "rsu"
        for name, value in sorted(counters.items()):
            events.add_metric([node, name], value)
            if name.startswith("mode_"):
                modes.add_metric([node, name.removeprefix("mode_").upper()], value)
            elif name.startswith("event_"):
                decisions.add_metric([node, name.removeprefix("event_")], value)
            elif name in _RSU_ACTIONS:
                actions.add_metric([node, _RSU_ACTIONS[name]], value)
        out: list[Metric] = [events, modes]
        if rsu:
            conflicts.add_metric([node], counters.get("conflicts", 0.0))
            table = GaugeMetricFamily(
                "crosspath_rsu_table_vehicles",
                METRICS["crosspath_rsu_table_vehicles"],
                labels=["node"],
            )
            size = None if view is None else view.table_size
            table.add_metric([node], float(size or 0))
            out.extend([decisions, actions, conflicts, table])
        else:
            mode = GaugeMetricFamily(
                "crosspath_vehicle_mode", METRICS["crosspath_vehicle_mode"], labels=["node", "mode"]
            )
            current = None if view is None else view.mode
            for name in ("AUTO", "C_SLOW", "C_FAST"):
                mode.add_metric([node, name], 1.0 if current == name else 0.0)
            out.append(mode)
        return out

    # -- serving

    async def serve(self, host: str, port: int) -> MetricsServer:
        """Listen on ``host:port``; ``ServiceExit`` (status 78) when it cannot be bound."""
        server = MetricsServer(self)
        await server.start(host, port)
        return server


def _stream_values(stats: NodeStats) -> dict[str, float]:
    """Keys ``<stream>|<counter>`` and ``<stream>|lat|<histogram key>``."""
    values: dict[str, float] = {}
    for name, s in list(stats.streams.items()):
        for field in _STREAM_FIELDS:
            values[f"{name}|{field}"] = float(getattr(s, field))
        for key, value in _histogram_values(s.latency).items():
            values[f"{name}|lat|{key}"] = value
    return values


def _as_floats(counts: Mapping[str, int]) -> dict[str, float]:
    return {k: float(v) for k, v in list(counts.items())}


def zenoh_links(transport: object) -> Callable[[], int] | None:
    """The number of links of ``transport`` now (0 while closed); None for a transport
    that is not Zenoh (the in-memory bus of the tests)."""
    if not isinstance(transport, ZenohTransport):
        return None
    zenoh = transport

    def count() -> int:
        if not zenoh.is_open:
            return 0
        try:
            return len(zenoh.links())
        except TransportError:
            return 0

    return count


_REQUEST_TIMEOUT_S: Final = 5.0
_MAX_REQUEST: Final = 8192


class MetricsServer:
    """The HTTP endpoint: ``GET /metrics`` answers the registry, ``/`` a pointer to it."""

    def __init__(self, metrics: DaemonMetrics) -> None:
        self.metrics = metrics
        self._server: asyncio.Server | None = None
        self.port: int | None = None
        """The port listened on (the one picked when 0 was asked)."""

    async def start(self, host: str, port: int) -> None:
        try:
            self._server = await asyncio.start_server(self._handle, host, port, reuse_address=True)
        except (OSError, OverflowError) as exc:  # in use, not on this host; bad port
            reason = exc.strerror if isinstance(exc, OSError) and exc.strerror else str(exc)
            raise ServiceExit(f"metrics endpoint {host}:{port}: {reason}", EXIT_CONFIG) from None
        self.port = self._server.sockets[0].getsockname()[1]
        log.info("metrics on http://%s:%d/metrics", host, self.port)

    async def close(self) -> None:
        server, self._server = self._server, None
        if server is not None:
            server.close()
            with contextlib.suppress(Exception):
                await asyncio.wait_for(server.wait_closed(), 1.0)

    async def _handle(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        try:
            head = await asyncio.wait_for(reader.readuntil(b"\r\n\r\n"), _REQUEST_TIMEOUT_S)
            status, ctype, body = self._answer(head)
        except (asyncio.IncompleteReadError, asyncio.LimitOverrunError, TimeoutError):
            status, ctype, body = "400 Bad Request", "text/plain", b"bad request\n"
        except ConnectionError:
            writer.close()
            return
        header = (
            f"HTTP/1.1 {status}\r\nContent-Type: {ctype}\r\n"
            f"Content-Length: {len(body)}\r\nConnection: close\r\n\r\n"
        )
        try:
            writer.write(header.encode() + body)
            await writer.drain()
        except ConnectionError:
            pass
        finally:
            writer.close()

    def _answer(self, head: bytes) -> tuple[str, str, bytes]:
        if len(head) > _MAX_REQUEST:
            return "400 Bad Request", "text/plain", b"request too large\n"
        parts = head.split(b"\r\n", 1)[0].split()
        if len(parts) != 3 or parts[0] != b"GET":
            return "405 Method Not Allowed", "text/plain", b"only GET\n"
        path = parts[1].split(b"?", 1)[0]
        if path == b"/metrics":
            return "200 OK", CONTENT_TYPE_LATEST, self.metrics.render()
        if path == b"/":
            return "200 OK", "text/plain", b"crosspath metrics: GET /metrics\n"
        return "404 Not Found", "text/plain", b"not found\n"
