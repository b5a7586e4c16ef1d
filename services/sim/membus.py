"""The in-memory V2X channel of the in-process harness: loss, latency, jitter, seeded.

Every message crosses it as bytes (the real codec on both sides), so the
in-process runs exercise the same encode/decode path as the daemons. Loss is
drawn independently per receiver (as on a radio channel, where each receiver
misses a broadcast on its own). Deterministic for a given seed and sequence of
sends.
"""

from __future__ import annotations

import heapq
from dataclasses import dataclass, field

import numpy as np


@dataclass(frozen=True, slots=True)
class ChannelModel:
    """Per-receiver delivery model of the simulated air interface."""

    loss: float = 0.0  # probability a receiver misses a datagram, 0..1
    latency_s: float = 0.002  # one-way base latency [s]
    jitter_s: float = 0.001  # uniform extra delay in [0, jitter] [s]

    def __post_init__(self) -> None:
        if not 0.0 <= self.loss <= 1.0:
            raise ValueError(f"loss must be within [0, 1], got {self.loss}")
        if self.latency_s < 0.0 or self.jitter_s < 0.0:
            raise ValueError("latency and jitter must be >= 0")


@dataclass(order=True, slots=True)
class Delivery:
    at: float
    order: int
    receiver: str = field(compare=False)
    key: str = field(compare=False)
    payload: bytes = field(compare=False)


@dataclass(slots=True)
class MemoryChannel:
    """A delivery queue ordered by arrival time on the virtual clock."""

    model: ChannelModel
    seed: int
    _rng: np.random.Generator = field(init=False)
    # (at, order, delivery): tuples compare in C, the dataclass's generated ``__lt__`` in
    # Python (a quarter of a 100-car fp-only run); ``order`` is unique, so the same order
    _queue: list[tuple[float, int, Delivery]] = field(init=False, default_factory=list)
    _order: int = field(init=False, default=0)
    sent: int = field(init=False, default=0)
    lost: int = field(init=False, default=0)
    bytes_sent: int = field(init=False, default=0)

    def __post_init__(self) -> None:
        self._rng = np.random.default_rng(self.seed)

    def send(self, now: float, key: str, payload: bytes, receivers: list[str]) -> None:
        """Offer one datagram to each receiver."""
        self.sent += 1
        self.bytes_sent += len(payload)
        m = self.model
        for receiver in receivers:
            if m.loss > 0.0 and self._rng.random() < m.loss:
                self.lost += 1
                continue
            delay = m.latency_s + (self._rng.random() * m.jitter_s if m.jitter_s > 0 else 0.0)
            self._order += 1
            at = now + delay
            delivery = Delivery(at, self._order, receiver, key, payload)
            heapq.heappush(self._queue, (at, self._order, delivery))

    def due(self, now: float) -> list[Delivery]:
        """Pop every delivery whose arrival time is ≤ ``now``, in arrival order."""
        out: list[Delivery] = []
        queue = self._queue
        while queue and queue[0][0] <= now:
            out.append(heapq.heappop(queue)[2])
        return out
