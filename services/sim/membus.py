"""The in-memory V2X channel of the in-process harness: loss, latency, jitter, seeded.

Every message crosses it as bytes (the real codec on both sides), so the
in-process runs exercise the same encode/decode path as the daemons. Loss is
drawn independently per receiver (as on a radio channel, where each receiver
misses a broadcast on its own). Deterministic for a given seed and sequence of
sends.
"""

from __future__ import annotations

from bisect import bisect_right
from dataclasses import dataclass, field
from itertools import repeat
from operator import itemgetter

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


Delivery = tuple[float, int, str, str, bytes]
"""One datagram due at one receiver: (arrival time [s], send order, receiver, key,
payload). A plain tuple: the queue sorts them in C, on (time, order) as ``order`` is
unique."""


@dataclass(slots=True)
class MemoryChannel:
    """A delivery queue ordered by arrival time on the virtual clock.

    One send offers the datagram to every receiver in one batch: without loss the
    receivers' jitters are one vectorised draw (the same numbers as one draw per
    receiver) and the deliveries are plain tuples appended in C; :meth:`due` sorts the
    queue by (arrival time, send order), which is the order a heap would pop
    (issue 14: the per-receiver heap push was a tenth of a 200-car run).
    """

    model: ChannelModel
    seed: int
    _rng: np.random.Generator = field(init=False)
    # (at, order, receiver, key, payload); ``order`` is unique, so tuples compare on
    # (at, order) only. Kept sorted lazily: ``_sorted`` says whether it already is.
    _queue: list[Delivery] = field(init=False, default_factory=list)
    _sorted: bool = field(init=False, default=True)
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
        n = len(receivers)
        if n == 0:
            return
        m = self.model
        queue = self._queue
        if m.loss > 0.0:
            # Loss and jitter draws interleave per receiver: one at a time.
            rng = self._rng
            for receiver in receivers:
                if rng.random() < m.loss:
                    self.lost += 1
                    continue
                delay = m.latency_s + (rng.random() * m.jitter_s if m.jitter_s > 0 else 0.0)
                self._order += 1
                queue.append((now + delay, self._order, receiver, key, payload))
        else:
            if m.jitter_s > 0:
                # now + (latency + u * jitter): the same float operations as per receiver
                ats: list[float] = (now + (m.latency_s + self._rng.random(n) * m.jitter_s)).tolist()
            else:
                ats = [now + m.latency_s] * n
            first = self._order + 1
            self._order += n
            queue.extend(zip(ats, range(first, first + n), receivers, repeat(key), repeat(payload)))
        self._sorted = False

    def due(self, now: float) -> list[Delivery]:
        """Pop every delivery whose arrival time is ≤ ``now``, in arrival order."""
        queue = self._queue
        if not queue:
            return []
        if not self._sorted:
            queue.sort()
            self._sorted = True
        if queue[-1][0] <= now:
            out = queue[:]
            queue.clear()
        else:
            k = bisect_right(queue, now, key=itemgetter(0))
            out = queue[:k]
            del queue[:k]
        return out
