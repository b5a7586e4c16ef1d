"""The run clock of the daemons: wall time mapped onto the run's time base.

Every message carries its generation time in seconds on the run's time base
(``protocol.messages``): run time 0 is the wall-clock instant ``epoch_unix``
that all daemons of a run share, and run time advances ``speed`` times as fast
as wall time (``speed`` 2.0 runs the scenario twice as fast as reality).

Clock-skew assumption: daemons on different hosts read their own wall clock,
so the hosts must be synchronised (NTP gives about a millisecond on a LAN, PTP
microseconds). Skew shows up directly as error in measured one-way latency (it
can even make it negative, which ``services.edge.stats`` counts) and, times
``speed``, as error in the pass times the cars and RSU compare. On one host all
daemons share the same clock and there is no skew.

The in-process simulation does not use this module: it drives the pure cores
with a virtual clock of its own.
"""

from __future__ import annotations

import asyncio
import math
import time
from collections.abc import Awaitable, Callable


class RunClock:
    """Run time in seconds from a shared wall-clock epoch and a speed factor."""

    __slots__ = ("_sleep", "_time_fn", "epoch_unix", "speed")

    def __init__(
        self,
        epoch_unix: float,
        speed: float = 1.0,
        time_fn: Callable[[], float] = time.time,
        sleep_fn: Callable[[float], Awaitable[None]] = asyncio.sleep,
    ) -> None:
        if not math.isfinite(epoch_unix):
            raise ValueError(f"epoch_unix must be finite, got {epoch_unix}")
        if not (math.isfinite(speed) and speed > 0.0):
            raise ValueError(f"speed must be a positive number, got {speed}")
        self.epoch_unix = float(epoch_unix)
        self.speed = float(speed)
        self._time_fn = time_fn
        self._sleep = sleep_fn

    @classmethod
    def starting_now(
        cls,
        epoch_unix: float | None = None,
        speed: float = 1.0,
        time_fn: Callable[[], float] = time.time,
    ) -> RunClock:
        """A clock at ``epoch_unix``, or with run time 0 at this instant when it is None."""
        return cls(time_fn() if epoch_unix is None else epoch_unix, speed, time_fn)

    def now(self) -> float:
        """Run time in seconds: ``(wall - epoch_unix) * speed`` (negative before the epoch)."""
        return (self._time_fn() - self.epoch_unix) * self.speed

    def now_us(self) -> int:
        """Run time in whole microseconds (floor), as the message header carries it."""
        return math.floor(self.now() * 1e6)

    def wall_delay(self, run_dt: float) -> float:
        """Wall seconds that ``run_dt`` run seconds take."""
        return run_dt / self.speed

    def to_wall(self, run_t: float) -> float:
        """The Unix time at which run time ``run_t`` happens."""
        return self.epoch_unix + run_t / self.speed

    async def sleep_until(self, run_t: float) -> None:
        """Return once run time has reached ``run_t`` (at once if it has).

        Re-reads the clock after every sleep, so an early wake-up or a wall-clock
        step is corrected instead of drifting.
        """
        while True:
            delay = self.wall_delay(run_t - self.now())
            if delay <= 0.0:
                return
            await self._sleep(delay)
