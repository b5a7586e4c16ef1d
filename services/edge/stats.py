"""Per-stream traffic counters of one node, and the run's ``network`` section.

Pure values: nothing here reads a clock or does I/O; the daemon shells call
``on_send`` / ``on_receive`` / ``on_malformed`` / ``on_stale`` and publish
``NodeStats.snapshot()`` on ``<prefix>/stats/{node}``; the monitor merges the
snapshots of every node into the ``network`` section of the run result.

A *stream* is a short name per kind of traffic (``fp``, ``ap``, ``cmd``,
``beacon``...); the shells choose them, this module does not care.

Latency is one-way: receive time minus the message's generation time, both on
the run's time base, in seconds. Across hosts it includes the clock skew (see
``services.edge.clock``); negative values (skew larger than the latency) are
counted in ``negative`` and recorded as 0.

Latencies go into a fixed log-spaced histogram (50 buckets per decade, from
1 µs up; a bucket spans 4.7 %), so snapshots from many nodes merge exactly and
percentiles are within about 2.5 % of the exact sample percentile (reported as
the bucket's geometric middle, clamped to the observed minimum and maximum).
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any

BUCKETS_PER_DECADE = 50
"""Resolution of the latency histogram."""

LATENCY_FLOOR_S = 1e-6
"""Lower edge of bucket 1; smaller latencies (and 0) fall into bucket 0."""

_LOG_RATIO = math.log(10.0) / BUCKETS_PER_DECADE


def _bucket_of(latency_s: float) -> int:
    if latency_s < LATENCY_FLOOR_S:
        return 0
    return 1 + math.floor(math.log(latency_s / LATENCY_FLOOR_S) / _LOG_RATIO)


def _bucket_middle(index: int) -> float:
    if index == 0:
        return 0.0
    return LATENCY_FLOOR_S * math.exp((index - 0.5) * _LOG_RATIO)


@dataclass(slots=True)
class LatencyHistogram:
    """Counts of one-way latencies in log-spaced buckets (seconds)."""

    count: int = 0
    sum_s: float = 0.0
    min_s: float = math.inf
    max_s: float = 0.0
    negative: int = 0
    buckets: dict[int, int] = field(default_factory=dict)

    def add(self, latency_s: float) -> None:
        """Record one latency; negative (clock skew) counts as 0 and in ``negative``."""
        if not math.isfinite(latency_s):
            raise ValueError(f"latency must be finite, got {latency_s}")
        if latency_s < 0.0:
            self.negative += 1
            latency_s = 0.0
        self.count += 1
        self.sum_s += latency_s
        self.min_s = min(self.min_s, latency_s)
        self.max_s = max(self.max_s, latency_s)
        index = _bucket_of(latency_s)
        self.buckets[index] = self.buckets.get(index, 0) + 1

    def merge(self, other: LatencyHistogram) -> None:
        """Add ``other``'s samples to this histogram."""
        self.count += other.count
        self.sum_s += other.sum_s
        self.min_s = min(self.min_s, other.min_s)
        self.max_s = max(self.max_s, other.max_s)
        self.negative += other.negative
        for index, n in other.buckets.items():
            self.buckets[index] = self.buckets.get(index, 0) + n

    def percentile(self, q: float) -> float | None:
        """The ``q`` quantile (0 < q <= 1) in seconds by nearest rank; None when empty."""
        if not 0.0 < q <= 1.0:
            raise ValueError(f"quantile must be in (0, 1], got {q}")
        if self.count == 0:
            return None
        rank = max(1, math.ceil(q * self.count))
        seen = 0
        for index in sorted(self.buckets):
            seen += self.buckets[index]
            if seen >= rank:
                return min(max(_bucket_middle(index), self.min_s), self.max_s)
        return self.max_s  # unreachable while buckets sum to count

    @property
    def mean_s(self) -> float | None:
        """Mean latency in seconds; None when empty."""
        return self.sum_s / self.count if self.count else None

    def to_json(self) -> dict[str, Any]:
        """JSON-able form (bucket indices as string keys)."""
        return {
            "count": self.count,
            "sum_s": self.sum_s,
            "min_s": self.min_s if self.count else None,
            "max_s": self.max_s,
            "negative": self.negative,
            "buckets": {str(index): n for index, n in sorted(self.buckets.items())},
        }

    @classmethod
    def from_json(cls, data: Mapping[str, Any]) -> LatencyHistogram:
        """Inverse of :meth:`to_json`; raises ValueError on malformed input."""
        try:
            buckets = {int(k): int(v) for k, v in dict(data.get("buckets", {})).items()}
            count = int(data.get("count", 0))
            min_s = data.get("min_s")
            hist = cls(
                count=count,
                sum_s=float(data.get("sum_s", 0.0)),
                min_s=math.inf if min_s is None else float(min_s),
                max_s=float(data.get("max_s", 0.0)),
                negative=int(data.get("negative", 0)),
                buckets=buckets,
            )
        except (TypeError, ValueError, AttributeError) as exc:
            raise ValueError(f"malformed latency histogram: {exc}") from None
        if any(i < 0 or n < 0 for i, n in buckets.items()) or sum(buckets.values()) != count:
            raise ValueError("malformed latency histogram: bucket counts do not add up")
        return hist


_COUNTERS = ("msgs_rx", "bytes_rx", "msgs_tx", "bytes_tx", "malformed", "dropped_stale")


@dataclass(slots=True)
class StreamStats:
    """Counters of one stream at one node; bytes are datagram payload bytes."""

    msgs_rx: int = 0
    bytes_rx: int = 0
    msgs_tx: int = 0
    bytes_tx: int = 0
    malformed: int = 0
    dropped_stale: int = 0
    latency: LatencyHistogram = field(default_factory=LatencyHistogram)

    def merge(self, other: StreamStats) -> None:
        """Add ``other``'s counts to these."""
        for name in _COUNTERS:
            setattr(self, name, getattr(self, name) + getattr(other, name))
        self.latency.merge(other.latency)

    def to_json(self) -> dict[str, Any]:
        """JSON-able form."""
        data: dict[str, Any] = {name: getattr(self, name) for name in _COUNTERS}
        data["latency"] = self.latency.to_json()
        return data

    @classmethod
    def from_json(cls, data: Mapping[str, Any]) -> StreamStats:
        """Inverse of :meth:`to_json`; raises ValueError on malformed input."""
        try:
            counts = {name: int(data.get(name, 0)) for name in _COUNTERS}
        except (TypeError, ValueError, AttributeError) as exc:
            raise ValueError(f"malformed stream stats: {exc}") from None
        if any(v < 0 for v in counts.values()):
            raise ValueError("malformed stream stats: negative counter")
        latency = LatencyHistogram.from_json(data.get("latency") or {})
        return cls(latency=latency, **counts)


class NodeStats:
    """Every stream's counters at one node."""

    __slots__ = ("node", "streams")

    def __init__(self, node: str) -> None:
        self.node = node
        self.streams: dict[str, StreamStats] = {}

    def stream(self, name: str) -> StreamStats:
        """The counters of ``name`` (e.g. a ``protocol.keys.Stream``), created on first use."""
        key = str(name)
        stats = self.streams.get(key)
        if stats is None:
            stats = self.streams[key] = StreamStats()
        return stats

    def on_send(self, stream: str, nbytes: int) -> None:
        """One datagram of ``nbytes`` handed to the transport."""
        stats = self.stream(stream)
        stats.msgs_tx += 1
        stats.bytes_tx += nbytes

    def on_receive(self, stream: str, nbytes: int, latency_s: float | None = None) -> None:
        """One datagram received and decoded; ``latency_s`` = receive minus generation time."""
        stats = self.stream(stream)
        stats.msgs_rx += 1
        stats.bytes_rx += nbytes
        if latency_s is not None:
            stats.latency.add(latency_s)

    def on_malformed(self, stream: str) -> None:
        """One datagram that failed to decode (dropped)."""
        self.stream(stream).malformed += 1

    def on_stale(self, stream: str) -> None:
        """One decoded datagram dropped as stale (old sequence number or expired)."""
        self.stream(stream).dropped_stale += 1

    def snapshot(self, now: float | None = None) -> dict[str, Any]:
        """JSON-able cumulative counters; ``now`` (run seconds) is recorded as ``time_s``."""
        return {
            "node": self.node,
            "time_s": now,
            "streams": {name: s.to_json() for name, s in sorted(self.streams.items())},
        }


def merge_snapshots(snapshots: Sequence[Mapping[str, Any]]) -> dict[str, StreamStats]:
    """Sum the streams of many nodes' snapshots (one snapshot per node, the latest).

    Raises ValueError on a malformed snapshot.
    """
    merged: dict[str, StreamStats] = {}
    for snapshot in snapshots:
        streams = snapshot.get("streams")
        if not isinstance(streams, Mapping):
            raise ValueError("malformed snapshot: no 'streams' table")
        for name, data in streams.items():
            if not isinstance(data, Mapping):
                raise ValueError(f"malformed snapshot: stream {name!r} is not a table")
            merged.setdefault(str(name), StreamStats()).merge(StreamStats.from_json(data))
    return merged


def _ms(seconds: float | None) -> float | None:
    return None if seconds is None else seconds * 1e3


def network_section(
    snapshots: Sequence[Mapping[str, Any]],
    n_vehicles: int,
    duration_s: float,
    expected_receivers: Mapping[str, float],
) -> dict[str, dict[str, Any]]:
    """The ``network`` section of a daemon run result: one entry per stream.

    Give the latest snapshot of each node. Per stream:

    - ``msgs``, ``bytes``: datagrams and payload bytes sent, summed over nodes;
    - ``msgs_rx``, ``bytes_rx``, ``malformed``, ``dropped_stale``: summed receive counters;
    - ``kbps_per_vehicle``: ``bytes * 8 / 1000 / duration_s / n_vehicles``, the offered
      load per vehicle (RSU streams too are divided by the number of vehicles);
    - ``latency_ms_p50``, ``latency_ms_p99``, ``latency_ms_mean``: one-way latency over
      all received datagrams (None when nothing was received);
    - ``delivery_ratio``: ``msgs_rx / (msgs * expected_receivers[stream])``.

    ``expected_receivers[stream]`` is how many of the nodes in ``snapshots`` should
    receive each datagram of that stream: for future paths broadcast by N cars with
    M RSUs listening, ``N - 1 + M`` (every other car and every RSU); for a stream
    addressed to one node (autonomous path, mode command), 1. Count only nodes whose
    snapshots are given (a monitor that does not count ``fp`` is not a receiver).
    The ratio is None when a stream is missing from ``expected_receivers`` or nothing
    was sent; it is not clamped, so duplicates would show as a value above 1.
    """
    if n_vehicles <= 0:
        raise ValueError(f"n_vehicles must be positive, got {n_vehicles}")
    if not (math.isfinite(duration_s) and duration_s > 0.0):
        raise ValueError(f"duration_s must be positive, got {duration_s}")
    section: dict[str, dict[str, Any]] = {}
    for name, stats in sorted(merge_snapshots(snapshots).items()):
        receivers = expected_receivers.get(name)
        expected = stats.msgs_tx * receivers if receivers is not None else 0
        section[name] = {
            "msgs": stats.msgs_tx,
            "bytes": stats.bytes_tx,
            "msgs_rx": stats.msgs_rx,
            "bytes_rx": stats.bytes_rx,
            "malformed": stats.malformed,
            "dropped_stale": stats.dropped_stale,
            "kbps_per_vehicle": stats.bytes_tx * 8 / 1000 / duration_s / n_vehicles,
            "latency_ms_p50": _ms(stats.latency.percentile(0.5)),
            "latency_ms_p99": _ms(stats.latency.percentile(0.99)),
            "latency_ms_mean": _ms(stats.latency.mean_s),
            "delivery_ratio": stats.msgs_rx / expected if expected > 0 else None,
        }
    return section
