"""RsuCore: messages in, messages out; modes, soft state, expiry, and a full crossing."""

from __future__ import annotations

import itertools
import math
from dataclasses import dataclass, field

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from protocol.messages import (
    AutonomousPath,
    Command,
    CoordinatedPath,
    FuturePath,
    Header,
    Mode,
    ModeCommand,
    RsuBeacon,
)
from services.model.types import Policy
from services.rsu.config import RsuConfig
from services.rsu.core import Outgoing, RsuCore

ZONE = np.array([[-3.5, -3.5], [3.5, -3.5], [3.5, 3.5], [-3.5, 3.5]])
VMAX = 50 / 3.6
EAST, NORTH = 0.0, math.pi / 2


def config(**kw: object) -> RsuConfig:
    return RsuConfig("rsu-1", "x0", (0.0, 0.0), ZONE, **kw)  # type: ignore[arg-type]


def line(start: tuple[float, float], heading: float, v: float, t0: float) -> np.ndarray:
    t = t0 + np.linspace(0.0, 10.0, 120)
    s = v * (t - t0)
    return np.column_stack([start[0] + s * math.cos(heading), start[1] + s * math.sin(heading), t])


def fp(
    vehicle: str,
    start: tuple[float, float],
    heading: float,
    v: float,
    now: float,
    mode: Mode = Mode.AUTO,
    seq: int = 1,
) -> FuturePath:
    pts = line(start, heading, v, now)
    return FuturePath(
        Header(vehicle, seq, round(now * 1e6)), start[0], start[1], v, heading, 4.5, 1.8, mode, pts
    )


def ap(
    vehicle: str, start: tuple[float, float], heading: float, v: float, now: float, mode: Mode
) -> AutonomousPath:
    pts = line(start, heading, v, now)
    return AutonomousPath(
        Header(vehicle, 1, round(now * 1e6)), start[0], start[1], v, heading, 4.5, 1.8, mode, pts
    )


def kinds(out: list[Outgoing]) -> list[tuple[str | None, str, Mode | None]]:
    result = []
    for o in out:
        m = o.message
        mode = m.mode if isinstance(m, ModeCommand | CoordinatedPath) else None
        result.append((o.vehicle, type(m).__name__, mode))
    return result


# A eastbound on y = -1.75, B northbound on x = +1.75: they cross at (1.75, -1.75).
def a_at(seconds_to_cross: float, v: float = VMAX) -> tuple[float, float]:
    return (1.75 - seconds_to_cross * v, -1.75)


def b_at(seconds_to_cross: float, v: float = VMAX) -> tuple[float, float]:
    return (1.75, -1.75 - seconds_to_cross * v)


# -- basics -------------------------------------------------------------------------------


def test_beacon_headers_and_deadlines() -> None:
    core = RsuCore(config(coverage_m=120.0), listen_s=0.0)
    assert core.next_deadline() == 0.0  # the first beacon is due at once
    out = core.tick(0.0)
    assert len(out) == 1 and out[0].vehicle is None
    beacon = out[0].message
    assert isinstance(beacon, RsuBeacon)
    assert (beacon.intersection, beacon.x, beacon.y, beacon.radius) == ("x0", 0.0, 0.0, 120.0)
    assert beacon.header.sender == "rsu-1" and beacon.header.time_us == 0
    assert core.next_deadline() == pytest.approx(1.0)
    ticks = [core.tick(round(0.1 * k, 1)) for k in range(1, 31)]
    beacons = [o.message for batch in ticks for o in batch if isinstance(o.message, RsuBeacon)]
    assert [b.header.time_us for b in beacons] == [1_000_000, 2_000_000, 3_000_000]
    seqs = [beacon.header.seq] + [b.header.seq for b in beacons]
    assert seqs == sorted(seqs) and len(set(seqs)) == len(seqs)


@given(
    st.lists(
        st.tuples(st.sampled_from(["A", "B", None]), st.floats(0.0, 0.08)), min_size=1, max_size=40
    )
)
@settings(max_examples=60, deadline=None)
def test_headers_increase_in_sequence_and_time_whatever_the_tick_lateness(
    steps: list[tuple[str | None, float]],
) -> None:
    """A daemon ticks the core at the step's scheduled time, which a late tick has passed,
    and hands it paths at their reception time: every header the core sends still has a
    higher sequence and a time no older than the one before, and never later than the
    latest time the core was given (receivers' replay windows refuse a higher sequence
    with an older time; seen in daemon runs as refused beacons)."""
    core = RsuCore(config(), listen_s=0.0)
    headers: list[Header] = []
    latest = 0.0
    for k, (car, late) in enumerate(steps):
        scheduled = 0.1 * k
        received = scheduled + late  # a path handled while the tick waits
        if car is not None:
            start = a_at(6.0 - 0.1 * k) if car == "A" else b_at(6.2 - 0.1 * k)
            heading = EAST if car == "A" else NORTH
            latest = max(latest, received)
            out = core.on_message(received, fp(car, start, heading, VMAX, received, seq=k + 1))
            headers += [o.message.header for o in out]
        latest = max(latest, scheduled)
        headers += [o.message.header for o in core.tick(scheduled)]  # late: after the path
        assert all(h.time_us <= round(latest * 1e6) for h in headers)
    assert headers, "the first tick sends a beacon"
    for before, after in itertools.pairwise(headers):
        assert after.seq > before.seq and after.time_us >= before.time_us, (before, after)


def test_free_approaching_car_gets_c_fast() -> None:
    core = RsuCore(config(), listen_s=0.0)
    out = core.on_message(0.0, fp("A", a_at(6.0), EAST, VMAX, 0.0))
    assert kinds(out) == [("A", "ModeCommand", Mode.C_FAST), ("A", "CoordinatedPath", Mode.C_FAST)]
    cmd, cp = out[0].message, out[1].message
    assert isinstance(cmd, ModeCommand) and cmd.command == Command.INITIATE
    assert isinstance(cp, CoordinatedPath) and cp.vehicle == "A"
    assert cp.header.sender == "rsu-1" and cp.header.seq > cmd.header.seq
    assert core.mode_of("A") == Mode.C_FAST
    assert core.pending("A") == (Command.INITIATE, Mode.C_FAST)
    assert core.counters["initiations"] == 1 and core.counters["coordinated_paths"] == 1


def test_car_heading_for_the_zone_beyond_t_free_is_approaching() -> None:
    """Its path ends short of the zone (enters at 10.3 s) but closer to it: approaching."""
    core = RsuCore(config(), listen_s=0.0)
    out = core.on_message(0.0, fp("A", a_at(10.7), EAST, VMAX, 0.0))
    assert kinds(out)[0] == ("A", "ModeCommand", Mode.C_FAST)
    assert core.mode_of("A") == Mode.C_FAST and "A" in core.table


def test_car_fallen_back_to_auto_is_taken_back() -> None:
    """Soft state: a C_FAST car whose future path says AUTO (timed out) is initiated again."""
    core = RsuCore(config(), listen_s=0.0)
    core.on_message(0.0, fp("A", a_at(6.0), EAST, VMAX, 0.0))
    core.on_message(0.1, fp("A", a_at(5.9), EAST, VMAX, 0.1, mode=Mode.C_FAST))  # acknowledged
    assert core.pending("A") is None
    out = core.on_message(0.6, fp("A", a_at(5.4), EAST, VMAX, 0.6, mode=Mode.AUTO))
    assert kinds(out) == [("A", "ModeCommand", Mode.C_FAST), ("A", "CoordinatedPath", Mode.C_FAST)]
    assert core.counters["reinitiations"] == 1


def test_conflicting_sender_slows_when_neither_is_committed() -> None:
    """Both AUTO: the path already in the table keeps its way; the sender slows."""
    core = RsuCore(config(), listen_s=0.0)
    # A crawls inside the zone (not approaching: no C_FAST), through the crossing at 2.75 s
    assert core.on_message(0.0, fp("A", (-1.0, -1.75), EAST, 1.0, 0.0)) == []
    assert core.mode_of("A") == Mode.AUTO
    # B comes up at V_max, at the crossing at 4.5 s: within T_collision of A's path
    out = core.on_message(0.0, fp("B", b_at(4.5), NORTH, VMAX, 0.0))
    assert kinds(out) == [("B", "ModeCommand", Mode.C_SLOW), ("B", "CoordinatedPath", Mode.C_SLOW)]
    assert core.mode_of("B") == Mode.C_SLOW and core.mode_of("A") == Mode.AUTO
    cp = out[1].message
    assert isinstance(cp, CoordinatedPath) and np.all(cp.speeds == 0.0)
    # the table entry of a C_SLOW car is the coordinated path it was sent
    entry = core.table.get("B")
    assert entry is not None and np.array_equal(entry.points, cp.points)
    # B's stop (48 m from V_max) is short of the crossing: A's next path is free of it
    assert core.on_message(0.1, fp("A", (-0.9, -1.75), EAST, 1.0, 0.1, seq=2)) == []
    assert core.mode_of("A") == Mode.AUTO
    # B's own future paths are discarded while it slows (even one that shows C_SLOW)
    core.on_message(0.1, fp("B", b_at(4.4), NORTH, VMAX, 0.1, Mode.C_SLOW, seq=2))
    entry = core.table.get("B")
    assert entry is not None and np.array_equal(entry.points, cp.points)
    assert entry.updated == 0.1


def test_auto_car_conflicting_with_a_c_fast_car_slows() -> None:
    core = RsuCore(config(), listen_s=0.0)
    core.on_message(0.0, fp("A", a_at(4.0), EAST, VMAX, 0.0))
    assert core.mode_of("A") == Mode.C_FAST
    out = core.on_message(0.0, fp("B", b_at(4.5), NORTH, VMAX, 0.0))
    assert kinds(out)[0] == ("B", "ModeCommand", Mode.C_SLOW)
    assert core.mode_of("A") == Mode.C_FAST and core.mode_of("B") == Mode.C_SLOW


def test_c_fast_autonomous_path_puts_the_conflicting_auto_car_in_c_slow() -> None:
    core = RsuCore(config(), listen_s=0.0)
    # A at the crossing at 8.0 s: C_FAST. B 0.5 s later: conflict, but not within 5 s yet.
    assert kinds(core.on_message(0.0, fp("A", a_at(8.0), EAST, VMAX, 0.0)))[0][2] == Mode.C_FAST
    core.on_message(3.0, fp("A", a_at(5.0), EAST, VMAX, 3.0, Mode.C_FAST, seq=2))  # alive, ack
    assert core.pending("A") is None
    assert core.on_message(3.0, fp("B", b_at(5.5), NORTH, VMAX, 3.0)) == []
    assert core.mode_of("B") == Mode.AUTO
    assert core.counters["event_no_conflict"] == 1
    # A's autonomous path at 3.4 s: the conflict is now within T_collision, and A has priority
    out = core.on_message(3.4, ap("A", a_at(4.6), EAST, VMAX, 3.4, Mode.C_FAST), rsu_key="rsu-1")
    assert kinds(out) == [
        ("A", "CoordinatedPath", Mode.C_FAST),
        ("B", "ModeCommand", Mode.C_SLOW),
        ("B", "CoordinatedPath", Mode.C_SLOW),
    ]
    cp = out[0].message
    assert isinstance(cp, CoordinatedPath)
    assert np.all(cp.speeds[cp.points[:, 0] < 3.5 + 4.5] == pytest.approx(VMAX))
    assert core.mode_of("A") == Mode.C_FAST and core.mode_of("B") == Mode.C_SLOW
    assert core.counters["given_way"] == 1


@pytest.mark.parametrize(
    ("sender", "a_cross", "b_cross"),
    [
        ("B", 8.0, 8.5),  # B's new path makes it the later arriver: the sender yields
        ("A", 9.5, 10.0),  # A's new path conflicts, B is still the later one: the other yields
    ],
)
def test_two_c_fast_cars_the_later_arriver_yields(
    sender: str, a_cross: float, b_cross: float
) -> None:
    core = RsuCore(config(), listen_s=0.0)
    # Both C_FAST first, 2 s apart (clear): A at the crossing at 8 s, B at 10 s
    core.on_message(0.0, fp("A", a_at(8.0), EAST, VMAX, 0.0))
    core.on_message(0.0, fp("B", b_at(10.0), NORTH, VMAX, 0.0))
    assert core.modes() == {"A": Mode.C_FAST, "B": Mode.C_FAST}
    now = 5.0
    core.on_message(now, fp("A", a_at(8.0 - now), EAST, VMAX, now, Mode.C_FAST, seq=2))
    core.on_message(now, fp("B", b_at(10.0 - now), NORTH, VMAX, now, Mode.C_FAST, seq=2))
    if sender == "A":
        path = ap("A", a_at(a_cross - now), EAST, VMAX, now, Mode.C_FAST)
    else:
        path = ap("B", b_at(b_cross - now), NORTH, VMAX, now, Mode.C_FAST)
    out = core.on_message(now, path)
    assert core.mode_of("B") == Mode.C_SLOW and core.mode_of("A") == Mode.C_FAST
    assert ("B", "ModeCommand", Mode.C_SLOW) in kinds(out)
    assert ("B", "CoordinatedPath", Mode.C_SLOW) in kinds(out)
    if sender == "A":
        assert kinds(out)[0] == ("A", "CoordinatedPath", Mode.C_FAST)


def grid_path(
    vehicle: str, start: tuple[float, float], heading: float, t0: float, mode: Mode, kind: type
) -> FuturePath | AutonomousPath:
    """V_max path with pass times on a 0.1 s grid, rounded to 1 ms as on the wire."""
    t = np.round(t0 + 0.1 * np.arange(120), 3)
    s = VMAX * (t - t0)
    pts = np.column_stack([start[0] + s * math.cos(heading), start[1] + s * math.sin(heading), t])
    header = Header(vehicle, 3, round(t0 * 1e6))
    result: FuturePath | AutonomousPath = kind(
        header, start[0], start[1], VMAX, heading, 4.5, 1.8, mode, pts
    )
    return result


def test_two_c_fast_cars_with_the_same_zone_entry_the_larger_id_yields() -> None:
    core = RsuCore(config(), listen_s=0.0)
    core.on_message(0.0, grid_path("A", a_at(8.0), EAST, 0.0, Mode.AUTO, FuturePath))
    core.on_message(0.0, fp("B", b_at(10.0), NORTH, VMAX, 0.0))
    assert core.modes() == {"A": Mode.C_FAST, "B": Mode.C_FAST}
    entry_a = core.table.get("A")
    assert entry_a is not None
    zone_entry = entry_a.points[np.flatnonzero(entry_a.points[:, 0] >= -3.5)[0], 2]
    now = 4.5
    core.on_message(now, fp("A", a_at(8.0 - now), EAST, VMAX, now, Mode.C_FAST, seq=2))
    # B's first point inside the zone (y >= -3.5) passes at exactly A's zone entry time
    b_start = (1.75, -3.5 + 0.01 - VMAX * (zone_entry - now))
    out = core.on_message(now, grid_path("B", b_start, NORTH, now, Mode.C_FAST, AutonomousPath))
    assert core.mode_of("B") == Mode.C_SLOW and core.mode_of("A") == Mode.C_FAST
    assert kinds(out)[0] == ("B", "ModeCommand", Mode.C_SLOW)


# -- leaving ------------------------------------------------------------------------------


def test_coordinated_car_leaving_is_terminated_auto_car_leaving_gets_nothing() -> None:
    core = RsuCore(config(), listen_s=0.0)
    core.on_message(0.0, fp("A", a_at(4.0), EAST, VMAX, 0.0))
    core.on_message(0.1, fp("A", a_at(3.9), EAST, VMAX, 0.1, Mode.C_FAST, seq=2))
    assert core.mode_of("A") == Mode.C_FAST and core.pending("A") is None
    # still inside the zone: nothing
    assert core.on_message(4.3, fp("A", (3.0, -1.75), EAST, VMAX, 4.3, Mode.C_FAST, seq=3)) == []
    assert core.mode_of("A") == Mode.C_FAST
    out = core.on_message(4.4, fp("A", (4.4, -1.75), EAST, VMAX, 4.4, Mode.C_FAST, seq=4))
    assert kinds(out) == [("A", "ModeCommand", Mode.AUTO)]
    cmd = out[0].message
    assert isinstance(cmd, ModeCommand) and cmd.command == Command.TERMINATE
    assert core.mode_of("A") == Mode.AUTO and core.pending("A") == (Command.TERMINATE, Mode.AUTO)
    # an AUTO car past the zone is never put into a coordinated mode, even in conflict
    core.on_message(4.5, fp("A", (5.8, -1.75), EAST, VMAX, 4.5, Mode.AUTO, seq=5))
    assert core.pending("A") is None
    core.on_message(4.5, fp("C", (20.0, -1.75), math.pi, 2.0, 4.5))  # oncoming on A's lane
    out = core.on_message(4.6, fp("A", (7.2, -1.75), EAST, VMAX, 4.6, Mode.AUTO, seq=6))
    assert out == [] and core.mode_of("A") == Mode.AUTO
    assert core.counters["event_leaving"] >= 2


def test_c_slow_car_on_autonomous_paths_stays_then_is_released() -> None:
    core = RsuCore(config(), listen_s=0.0)
    core.on_message(0.0, fp("A", (-1.0, -1.75), EAST, 1.0, 0.0))  # crawling in the zone
    core.on_message(0.0, fp("B", b_at(4.5), NORTH, VMAX, 0.0))
    assert core.mode_of("B") == Mode.C_SLOW
    core.on_message(0.1, fp("B", b_at(4.4), NORTH, VMAX, 0.1, Mode.C_SLOW, seq=2))
    # its autonomous path still conflicts: it stays C_SLOW and gets a coordinated path
    core.on_message(0.1, fp("A", (-0.9, -1.75), EAST, 1.0, 0.1, seq=2))
    out = core.on_message(0.1, ap("B", b_at(4.4), NORTH, VMAX, 0.1, Mode.C_SLOW), "rsu-1")
    assert kinds(out) == [("B", "CoordinatedPath", Mode.C_SLOW)]
    # A's plan changes: it will be well clear by then -> B's path is free and approaching
    core.on_message(0.2, fp("A", (-0.8, -1.75), EAST, VMAX, 0.2, seq=3))
    out = core.on_message(0.2, ap("B", b_at(4.3), NORTH, VMAX, 0.2, Mode.C_SLOW), "rsu-1")
    assert kinds(out) == [("B", "ModeCommand", Mode.C_FAST), ("B", "CoordinatedPath", Mode.C_FAST)]
    assert core.mode_of("B") == Mode.C_FAST


def test_c_slow_car_released_to_auto_when_not_approaching() -> None:
    cfg = config()
    core = RsuCore(cfg, listen_s=0.0)
    # B will conflict with A at the crossing; B's path reaches the zone beyond T_free? No:
    # B is stopped close to the zone (so its own path never enters it: not approaching).
    core.on_message(0.0, fp("A", (-1.0, -1.75), EAST, 1.0, 0.0))
    core.on_message(0.0, fp("B", b_at(4.5), NORTH, VMAX, 0.0))
    assert core.mode_of("B") == Mode.C_SLOW
    core.on_message(0.1, fp("A", (-20.0, -1.75), math.pi, 5.0, 0.1, seq=2))  # A turned away
    standing = ap("B", (1.75, -12.0), NORTH, 0.0, 0.1, Mode.C_SLOW)
    out = core.on_message(0.1, standing, "rsu-1")
    assert kinds(out) == [("B", "ModeCommand", Mode.AUTO)]
    assert core.mode_of("B") == Mode.AUTO
    entry = core.table.get("B")
    assert entry is not None and np.array_equal(entry.points, standing.points)


# -- soft state, expiry -------------------------------------------------------------------


def test_commands_repeat_until_the_future_path_shows_the_mode() -> None:
    core = RsuCore(config(command_repeat_s=0.1), listen_s=0.0)
    core.on_message(0.0, fp("A", a_at(6.0), EAST, VMAX, 0.0))
    core.tick(0.0)  # beacon
    assert core.next_deadline() == pytest.approx(0.1)

    def repeats(now: float) -> list[tuple[str | None, str, Mode | None]]:
        return [k for k in kinds(core.tick(now)) if k[1] == "ModeCommand"]

    assert repeats(0.05) == []
    assert repeats(0.1) == [("A", "ModeCommand", Mode.C_FAST)]
    assert repeats(0.15) == []
    assert repeats(0.2) == [("A", "ModeCommand", Mode.C_FAST)]
    # a future path that does not show C_FAST yet: still pending, and not used for decisions
    assert core.on_message(0.25, fp("A", a_at(5.75), EAST, VMAX, 0.25, Mode.AUTO, seq=2)) == []
    assert core.counters["fp_unacknowledged"] == 1
    assert repeats(0.3) == [("A", "ModeCommand", Mode.C_FAST)]
    core.on_message(0.35, fp("A", a_at(5.65), EAST, VMAX, 0.35, Mode.C_FAST, seq=3))
    assert core.pending("A") is None and core.counters["acks"] == 1
    assert repeats(0.4) == [] and repeats(0.5) == []
    assert core.counters["repeats"] == 3


def test_silent_car_is_forgotten_and_no_longer_commanded() -> None:
    core = RsuCore(config(), listen_s=0.0)
    core.on_message(0.0, fp("A", a_at(6.0), EAST, VMAX, 0.0))
    assert core.mode_of("A") == Mode.C_FAST
    assert core.next_deadline() == 0.0  # beacon not sent yet
    core.tick(0.0)
    assert core.next_deadline() == pytest.approx(0.1)
    for k in range(1, 5):
        assert any(o.vehicle == "A" for o in core.tick(k / 10))
    out = core.tick(0.5)
    assert [o for o in out if o.vehicle == "A"] == []
    assert core.counters["expired"] == 1
    assert core.mode_of("A") == Mode.AUTO and core.pending("A") is None
    assert "A" not in core.table and core.modes() == {}
    assert core.next_deadline() == pytest.approx(1.0)  # only the beacon is left
    assert [o for o in core.tick(0.6) if o.vehicle == "A"] == []
    # coming back: a fresh start in AUTO
    core.on_message(0.7, fp("A", a_at(5.0), EAST, VMAX, 0.7, Mode.C_FAST, seq=9))
    assert core.mode_of("A") == Mode.C_FAST
    assert core.pending("A") == (Command.INITIATE, Mode.C_FAST)


def test_future_paths_keep_a_coordinated_car_alive() -> None:
    core = RsuCore(config(), listen_s=0.0)
    core.on_message(0.0, fp("A", a_at(6.0), EAST, VMAX, 0.0))
    for k in range(1, 10):
        now = k / 10
        core.on_message(now, fp("A", a_at(6.0 - now), EAST, VMAX, now, Mode.C_FAST, seq=k + 1))
        core.tick(now)
    assert core.mode_of("A") == Mode.C_FAST and core.counters["expired"] == 0


def test_cp_rule_keeps_the_last_coordinated_path_while_it_holds() -> None:
    """Under the coordinated path's change rule (``cp_change_m``), a C_FAST car that drives
    as planned gets no new coordinated path until ``cp_refresh_s`` has passed; its table
    entry stays the path it was sent (the one it drives), refreshed; a changed plan or a
    new initiation is sent at once. Periodic (the default) answers every one."""
    for rule, expect in ((None, 10), (0.5, 2)):
        core = RsuCore(config(cp_change_m=rule, cp_refresh_s=0.5), listen_s=0.0)
        out = core.on_message(0.0, fp("A", a_at(6.0), EAST, VMAX, 0.0))
        first = out[1].message
        assert isinstance(first, CoordinatedPath)
        core.on_message(0.05, fp("A", a_at(5.95), EAST, VMAX, 0.05, Mode.C_FAST, seq=2))
        sent = []
        for k in range(1, 11):
            now = k / 10
            path = ap("A", a_at(6.0 - now), EAST, VMAX, now, Mode.C_FAST)
            o = core.on_message(now, path, "rsu-1")
            sent += [now for m in o if isinstance(m.message, CoordinatedPath)]
            entry = core.table.get("A")
            assert entry is not None and core.table.is_live("A", now)
            if rule is not None and now < 0.5:
                assert entry.points is not None and np.array_equal(entry.points, first.points)
        assert len(sent) == expect, sent
        if rule is not None:
            assert sent == pytest.approx([0.5, 1.0])  # the refreshes only
            assert core.counters["cp_unchanged"] == 10 - expect
    # a plan that changed by more than the deviation is sent at once
    core = RsuCore(config(cp_change_m=0.5), listen_s=0.0)
    core.on_message(0.0, fp("A", a_at(6.0), EAST, VMAX, 0.0))
    core.on_message(0.05, fp("A", a_at(5.95), EAST, VMAX, 0.05, Mode.C_FAST, seq=2))
    slower = core.on_message(0.1, ap("A", a_at(5.9), EAST, VMAX / 2, 0.1, Mode.C_FAST), "rsu-1")
    assert kinds(slower) == [("A", "CoordinatedPath", Mode.C_FAST)]


# -- what is ignored ----------------------------------------------------------------------


def test_ignored_inputs_are_counted_and_never_raise() -> None:
    core = RsuCore(config(), listen_s=0.0)
    core.on_message(0.0, fp("A", a_at(6.0), EAST, VMAX, 0.0))
    snapshot = core.table.get("A")
    cases: list[tuple[object, str | None, str]] = [
        (ap("A", a_at(5.9), EAST, VMAX, 0.1, Mode.C_FAST), "rsu-2", "foreign_rsu"),
        (ap("Z", a_at(5.9), EAST, VMAX, 0.1, Mode.C_FAST), "rsu-1", "unknown_vehicle"),
        (fp("F", (0.0, -200.0), NORTH, VMAX, 0.1), None, "out_of_coverage"),
        (RsuBeacon(Header("rsu-9", 1, 0), "x9", 0.0, 0.0, 100.0), None, "ignored_kind"),
        (
            ModeCommand(Header("rsu-9", 1, 0), "A", Command.TERMINATE, Mode.AUTO),
            None,
            "ignored_kind",
        ),
        (fp("A", a_at(6.1), EAST, VMAX, -0.1, Mode.C_FAST, seq=0), None, "stale"),
        (fp("N", (math.nan, 0.0), EAST, VMAX, 0.1), None, "invalid_not_finite"),
        (fp("S", (0.0, -10.0), NORTH, -3.0, 0.1), None, "invalid_negative"),
    ]
    for message, key, counter in cases:
        before = core.counters[counter]
        assert core.on_message(0.1, message, key) == [], counter  # type: ignore[arg-type]
        assert core.counters[counter] == before + 1, counter
    bad_points = FuturePath(
        Header("P", 1, 100_000),
        0.0,
        -20.0,
        5.0,
        NORTH,
        4.5,
        1.8,
        Mode.AUTO,
        np.array([[0.0, -20.0, 0.1], [0.0, math.inf, 0.2]]),
    )
    assert core.on_message(0.1, bad_points) == []
    assert core.table.get("A") is snapshot
    assert set(core.modes()) == {"A"}
    # an AUTO car's autonomous path: not coordinated, ignored
    core.on_message(0.1, fp("Q", (-1.0, 30.0), NORTH, 1.0, 0.1))  # driving away
    assert core.mode_of("Q") == Mode.AUTO
    assert core.on_message(0.1, ap("Q", (-1.0, 30.0), NORTH, 1.0, 0.1, Mode.AUTO)) == []
    assert core.counters["ap_not_coordinated"] == 1
    assert core.counters["invalid"] == 3 and core.counters["invalid_points_out_of_bounds"] == 1


def hostile(problem: str) -> FuturePath:
    """A future path of car H just south of the zone, spoilt as ``problem`` says."""
    x, y, speed, points = 1.75, -20.0, 5.0, line((1.75, -20.0), NORTH, 5.0, 0.1)
    sender = "H"
    if problem == "not_finite":
        speed = math.inf
    elif problem == "negative":
        speed = -1.0
    elif problem == "no_sender":
        sender = ""
    elif problem == "out_of_bounds":
        y = -1e12
    elif problem == "points_out_of_bounds":
        points = points.copy()
        points[5, 0] = 1e12
    path = FuturePath(Header(sender, 1, 100_000), x, y, speed, NORTH, 4.5, 1.8, Mode.AUTO, points)
    if problem == "points_shape":  # the message itself always reshapes to (N, 3)
        object.__setattr__(path, "points", points[:, :2])
    return path


@pytest.mark.parametrize(
    "problem",
    [
        "not_finite",
        "negative",
        "no_sender",
        "out_of_bounds",
        "points_shape",
        "points_out_of_bounds",
    ],
)
def test_a_hostile_path_is_counted_and_dropped(problem: str) -> None:
    core = RsuCore(config(), listen_s=0.0)
    core.on_message(0.0, fp("A", a_at(6.0), EAST, VMAX, 0.0))
    before = dict(core.counters)
    assert core.on_message(0.1, hostile(problem)) == []
    assert core.counters[f"invalid_{problem}"] == 1 and core.counters["invalid"] == 1
    assert set(core.table) == {"A"} and set(core.modes()) == {"A"}
    changed = {k for k in core.counters if core.counters[k] != before.get(k, 0)}
    assert changed == {"fp_rx", "invalid", f"invalid_{problem}"}
    # the same car's valid path afterwards is taken
    core.on_message(0.1, fp("H", (1.75, -20.0), NORTH, 5.0, 0.1))
    assert "H" in core.table


@pytest.mark.parametrize("error", [ValueError("bug"), ZeroDivisionError("bug")])
def test_a_bug_in_the_decision_code_is_not_swallowed(
    monkeypatch: pytest.MonkeyPatch, error: Exception
) -> None:
    core = RsuCore(config(), listen_s=0.0)

    def broken(*args: object) -> list[Outgoing]:
        raise error

    monkeypatch.setattr(core, "_decide", broken)
    with pytest.raises(type(error), match="bug"):
        core.on_message(0.0, fp("A", a_at(6.0), EAST, VMAX, 0.0))
    monkeypatch.setattr(core.table, "expire", broken)
    with pytest.raises(type(error), match="bug"):
        core.tick(0.1)


def test_coordinated_paths_are_thinned_to_max_points() -> None:
    core = RsuCore(config(max_points=30), listen_s=0.0)
    core.on_message(0.0, fp("A", (-1.0, -1.75), EAST, 1.0, 0.0))
    out = core.on_message(0.0, fp("B", b_at(4.5), NORTH, VMAX, 0.0))
    cp = out[1].message
    assert isinstance(cp, CoordinatedPath) and cp.points.shape[0] == 30
    assert np.all(np.diff(cp.points[:, 2]) >= 0) and cp.points[-1, 2] == pytest.approx(10.0)
    entry = core.table.get("B")
    assert entry is not None and np.array_equal(entry.points, cp.points)
    assert core.counters["thinned_paths"] == 1
    with pytest.raises(ValueError):
        config(max_points=1)


def test_forget() -> None:
    core = RsuCore(config(), listen_s=0.0)
    core.on_message(0.0, fp("A", a_at(6.0), EAST, VMAX, 0.0))
    assert core.forget("A") and not core.forget("A")
    assert "A" not in core.table and core.pending("A") is None


def test_bad_config_raises() -> None:
    with pytest.raises(ValueError):
        config(coverage_m=-1.0)
    with pytest.raises(ValueError):
        config(t_collision_s=12.0)
    with pytest.raises(ValueError):
        RsuConfig("rsu-1", "x0", (0.0, 0.0), np.array([[0, 0], [1, 0], [0.5, 0.0]]))
    with pytest.raises(ValueError):
        config(policy="fastest")
    assert config(policy="slot").policy == Policy.SLOT


# -- a full crossing, closed loop -----------------------------------------------------------


@dataclass
class SimCar:
    """Just enough of a car to answer the RSU: straight line, speed control, V2X."""

    vehicle: str
    origin: tuple[float, float]
    heading: float
    v: float
    s: float = 0.0
    mode: Mode = Mode.AUTO
    cp: CoordinatedPath | None = None
    cp_at: float = -1.0
    seq: int = 0
    trace: list[tuple[float, float, float, float]] = field(default_factory=list)

    def pos(self, s: float | None = None) -> np.ndarray:
        d = self.s if s is None else s
        direction = np.array([math.cos(self.heading), math.sin(self.heading)])
        return np.array(self.origin) + d * direction

    def autonomous(self, now: float) -> np.ndarray:
        t = np.linspace(0.0, 10.0, 120)
        t_acc = max(0.0, (VMAX - self.v) / 1.5)
        ta = np.minimum(t, t_acc)
        dist = self.v * ta + 0.75 * ta * ta + VMAX * (t - ta)
        xy = self.pos()[None, :] + dist[:, None] * np.array(
            [math.cos(self.heading), math.sin(self.heading)]
        )
        return np.column_stack([xy, now + t])

    def send(self, kind: type, now: float, points: np.ndarray) -> FuturePath | AutonomousPath:
        self.seq += 1
        x, y = self.pos()
        header = Header(self.vehicle, self.seq, round(now * 1e6))
        msg: FuturePath | AutonomousPath = kind(
            header, float(x), float(y), self.v, self.heading, 4.5, 1.8, self.mode, points
        )
        return msg

    def receive(self, now: float, message: object) -> None:
        if isinstance(message, ModeCommand):
            self.mode = message.mode if message.command == Command.INITIATE else Mode.AUTO
        elif isinstance(message, CoordinatedPath) and self.mode != Mode.AUTO:
            self.cp, self.cp_at = message, now

    def target(self, now: float) -> float:
        cp = self.cp
        if self.mode == Mode.AUTO or cp is None or now - self.cp_at > 0.3:
            return VMAX
        x, y = self.pos()
        i = int(np.argmin(np.hypot(cp.points[:, 0] - x, cp.points[:, 1] - y)))
        j = int(np.searchsorted(cp.points[:, 2], cp.points[i, 2] + 0.5))  # look 0.5 s ahead
        return float(cp.speeds[min(j, cp.speeds.shape[0] - 1)])

    def step(self, now: float, dt: float) -> None:
        accel = max(-2.0, min(1.5, (self.target(now) - self.v) / dt))
        self.v = max(0.0, self.v + accel * dt)
        self.s += self.v * dt
        x, y = self.pos()
        self.trace.append((now + dt, float(x), float(y), self.v))


Change = tuple[float, str, Mode, float, float]  # when, car, new mode, x, y


def crossing(
    policy: Policy, loss: float = 0.0, seed: int = 7
) -> tuple[RsuCore, dict[str, SimCar], list[Change]]:
    """A (east) and B (north) at V_max, B 0.5 s behind A at the crossing point."""
    rng = np.random.default_rng(seed)
    core = RsuCore(config(policy=policy), listen_s=0.0)
    a = SimCar("A", (1.75 - 7.0 * VMAX, -1.75), EAST, VMAX)
    b = SimCar("B", (1.75, -1.75 - 7.5 * VMAX), NORTH, VMAX)
    cars = {"A": a, "B": b}
    changes: list[Change] = []
    last = {"A": Mode.AUTO, "B": Mode.AUTO}
    for k in range(250):
        now = round(k * 0.1, 6)
        out: list[Outgoing] = []
        for car in (a, b):
            auto = car.autonomous(now)
            # while coordinated, the broadcast future path is the coordinated one
            shown = car.cp.points if car.mode != Mode.AUTO and car.cp is not None else auto
            if rng.random() >= loss:
                out += core.on_message(now, car.send(FuturePath, now, shown))
            if car.mode != Mode.AUTO and rng.random() >= loss:
                out += core.on_message(now, car.send(AutonomousPath, now, auto), "rsu-1")
        out += core.tick(now)
        for o in out:
            if o.vehicle in cars and rng.random() >= loss:
                cars[o.vehicle].receive(now, o.message)
        for car in (a, b):
            mode = core.mode_of(car.vehicle)
            if mode != last[car.vehicle]:
                x, y = car.pos()
                changes.append((now, car.vehicle, mode, float(x), float(y)))
                last[car.vehicle] = mode
            car.step(now, 0.1)
    return core, cars, changes


def zone_times(car: SimCar) -> tuple[float, float]:
    inside = [t for t, x, y, _ in car.trace if abs(x) <= 3.5 + 2.25 and abs(y) <= 3.5 + 2.25]
    return min(inside), max(inside)


@pytest.mark.parametrize("policy", [Policy.PAPER, Policy.SLOT])
def test_full_crossing_sequence(policy: Policy) -> None:
    core, cars, changes = crossing(policy)
    a, b = cars["A"], cars["B"]
    seq = [(v, m) for _, v, m, _, _ in changes]
    # A is free and approaching first: C_FAST; B, conflicting with it, is slowed
    assert seq[0] == ("A", Mode.C_FAST)
    assert seq[1] == ("B", Mode.C_SLOW)
    t_slow = changes[1][0]
    assert core.mode_of("A") == Mode.AUTO and core.mode_of("B") == Mode.AUTO
    # B is released (to C_FAST) once clear of A, and both end terminated after leaving
    released = next(c for c in changes if c[1] == "B" and c[0] > t_slow)
    assert released[2] in (Mode.C_FAST, Mode.AUTO)
    a_term = next(c for c in changes if c[1] == "A" and c[2] == Mode.AUTO)
    b_term = [c for c in changes if c[1] == "B" and c[2] == Mode.AUTO][-1]
    assert a_term[3] > 3.5  # A terminated past the zone (x)
    assert b_term[4] > 3.5  # B terminated past the zone (y)
    assert a_term[0] < b_term[0]
    assert len(changes) <= 6  # no flapping
    assert core.counters["terminations"] == 2 and core.counters["invalid"] == 0
    # safety: A went first and B kept its distance
    a_in, a_out = zone_times(a)
    b_in, _ = zone_times(b)
    assert a_in < b_in and a_out < b_in + 1.0
    gaps = [
        math.dist((xa, ya), (xb, yb))
        for (_, xa, ya, _), (_, xb, yb, _) in zip(a.trace, b.trace, strict=True)
    ]
    assert min(gaps) > 5.0
    if policy == Policy.SLOT:
        # slot: B released only as A leaves, and never stopped nor nearly so
        assert released[0] >= a_term[0] - 0.2
        assert min(v for *_, v in b.trace) > 8.0


def test_slot_gets_b_through_sooner_than_paper() -> None:
    _, paper, _ = crossing(Policy.PAPER)
    _, slot, _ = crossing(Policy.SLOT)
    # Since issue 12 the paper policy promotes B on its checked C_FAST plan as soon as
    # that plan clears A, so B gets through right behind A with either policy here: slot
    # enters sooner and leaves no later (one trace step, 0.1 s, apart).
    assert zone_times(slot["B"])[0] < zone_times(paper["B"])[0]
    assert zone_times(slot["B"])[1] <= zone_times(paper["B"])[1]
    assert zone_times(slot["B"])[0] - zone_times(paper["A"])[1] < 1.5  # right behind A


@pytest.mark.parametrize("policy", [Policy.PAPER, Policy.SLOT])
def test_full_crossing_survives_message_loss(policy: Policy) -> None:
    core, cars, changes = crossing(policy, loss=0.2, seed=3)
    assert core.counters["repeats"] > 0
    assert core.mode_of("A") == Mode.AUTO and core.mode_of("B") == Mode.AUTO
    # with A's first future path lost, B may be the one that gets C_FAST: then A yields
    first, second = changes[0][1], ("B" if changes[0][1] == "A" else "A")
    assert changes[0][2] == Mode.C_FAST
    assert (second, Mode.C_SLOW) in [(v, m) for _, v, m, _, _ in changes]
    assert zone_times(cars[first])[0] < zone_times(cars[second])[0]
    assert core.counters["terminations"] >= 2 and core.counters["invalid"] == 0


# -- a (re)started RSU: listening first, committed cars keep their order ---------------------


def test_a_started_core_listens_one_expiry_before_commanding() -> None:
    core = RsuCore(config())  # listen_s defaults to one reservation expiry (0.5 s)
    assert core.listen_s == 0.5
    assert [type(o.message).__name__ for o in core.tick(0.0)] == ["RsuBeacon"]
    # A free, approaching car: heard and reserved, but not commanded while listening
    assert core.on_message(0.2, fp("A", a_at(6.0), EAST, VMAX, 0.2)) == []
    assert "A" in core.table and core.mode_of("A") == Mode.AUTO
    assert core.counters["fp_listened"] == 1 and core.listening(0.4)
    out = core.on_message(0.5, fp("A", a_at(5.7), EAST, VMAX, 0.5, seq=2))
    assert kinds(out) == [("A", "ModeCommand", Mode.C_FAST), ("A", "CoordinatedPath", Mode.C_FAST)]


def test_listening_lasts_while_a_car_still_claims_a_coordinated_mode() -> None:
    core = RsuCore(config(), listen_s=0.5)
    # B still shows the C_FAST an earlier incarnation of this RSU gave it
    core.on_message(0.0, fp("B", b_at(6.0), NORTH, VMAX, 0.0, Mode.C_FAST))
    assert core.on_message(0.6, fp("B", b_at(5.4), NORTH, VMAX, 0.6, Mode.C_FAST, seq=2)) == []
    assert core.listening(0.7)
    # it fell back to AUTO (no coordinated path for 0.3 s): now the RSU takes it
    out = core.on_message(0.8, fp("B", b_at(5.2), NORTH, VMAX, 0.8, seq=3))
    assert ("B", "ModeCommand", Mode.C_FAST) in kinds(out)
    # at most one expiry longer, whatever cars claim
    other = RsuCore(config(), listen_s=0.5)
    other.on_message(0.0, fp("B", b_at(6.0), NORTH, VMAX, 0.0, Mode.C_FAST))
    assert other.listening(0.9) and not other.listening(1.0)
    with pytest.raises(ValueError, match="listen_s"):
        RsuCore(config(), listen_s=-1.0)


def test_no_car_is_promoted_ahead_of_a_committed_car_s_zone_occupancy() -> None:
    """B drives up to the zone in AUTO, too close to stop (committed). A, slow and still able
    to stop, is clear of B's path by the point-pair check, but the C_FAST plan it would get
    puts its body in the zone within the headway of B's body: A is not given C_FAST, it
    slows, and nobody re-orders B."""
    core = RsuCore(config(), listen_s=0.2)
    # B: front 5 m from the zone edge at 8 m/s (braking takes 16 m): committed
    assert core.on_message(0.0, fp("B", (1.75, -3.5 - 5.0 - 2.25), NORTH, 8.0, 0.0)) == []
    # A: front 6 m from the zone at 2 m/s (braking 1 m): its own path reaches the crossing
    # 3.8 s after B's, but V_max from here would enter the zone as B's rear leaves it
    out = core.on_message(0.3, fp("A", (-3.5 - 6.0 - 2.25, -1.75), EAST, 2.0, 0.3))
    assert kinds(out)[0] == ("A", "ModeCommand", Mode.C_SLOW)
    assert core.mode_of("A") == Mode.C_SLOW and core.mode_of("B") == Mode.AUTO
    assert core.counters["order_kept"] == 1
    assert not any(o.vehicle == "B" for o in out)


def test_a_car_far_enough_from_a_committed_car_still_gets_c_fast() -> None:
    core = RsuCore(config(), listen_s=0.2)
    core.on_message(0.0, fp("A", (-10.75, -1.75), EAST, 5.0, 0.0))
    out = core.on_message(0.3, fp("B", b_at(6.0), NORTH, VMAX, 0.3))  # 2.5 s after A's rear
    assert kinds(out)[0] == ("B", "ModeCommand", Mode.C_FAST)
    assert core.counters["order_kept"] == 0
