"""The run clock against a fake wall clock."""

from __future__ import annotations

import pytest

from services.edge.clock import RunClock


class FakeTime:
    """A wall clock the test moves; its sleep advances it."""

    def __init__(self, t: float) -> None:
        self.t = t
        self.sleeps: list[float] = []

    def __call__(self) -> float:
        return self.t

    async def sleep(self, seconds: float) -> None:
        self.sleeps.append(seconds)
        early = len(self.sleeps) == 1  # the first sleep wakes early: sleep_until must re-check
        self.t += seconds * 0.5 if early else seconds


def test_now_scales_from_the_epoch() -> None:
    wall = FakeTime(1000.0)
    clock = RunClock(epoch_unix=990.0, speed=2.0, time_fn=wall)
    assert clock.now() == 20.0
    assert clock.now_us() == 20_000_000
    wall.t = 1000.25
    assert clock.now() == 20.5
    wall.t = 989.0
    assert clock.now() == -2.0  # before the epoch
    assert clock.wall_delay(1.0) == 0.5
    assert clock.to_wall(20.0) == 1000.0


def test_now_us_floors() -> None:
    clock = RunClock(epoch_unix=0.0, time_fn=lambda: 1.0000015)
    assert clock.now_us() == 1_000_001


def test_starting_now() -> None:
    wall = FakeTime(500.0)
    assert RunClock.starting_now(None, time_fn=wall).now() == 0.0
    assert RunClock.starting_now(400.0, time_fn=wall).now() == 100.0


async def test_sleep_until_reaches_the_run_time() -> None:
    wall = FakeTime(100.0)
    clock = RunClock(epoch_unix=100.0, speed=4.0, time_fn=wall, sleep_fn=wall.sleep)
    await clock.sleep_until(2.0)  # 0.5 wall seconds
    assert clock.now() >= 2.0
    assert wall.sleeps[0] == 0.5
    assert wall.sleeps[1] == 0.25  # re-checked after the early wake-up
    count = len(wall.sleeps)
    await clock.sleep_until(1.0)  # already past
    assert len(wall.sleeps) == count


@pytest.mark.parametrize("speed", [0.0, -1.0, float("nan"), float("inf")])
def test_bad_speed(speed: float) -> None:
    with pytest.raises(ValueError, match="speed"):
        RunClock(epoch_unix=0.0, speed=speed)
