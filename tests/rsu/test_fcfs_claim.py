"""Issue 12, ``slot`` first come, first served: a car standing at the stop line is not
starved by a stream on the crossing road (``RsuCore._claim``), and waits for its slot
where it stands (``VelocityManager._stop_and_go``).

Found in the demand experiment (600 veh/h per approach, straight): a car standing at
the stop line needs a gap of about 4.5 s in the crossing stream (its zone occupancy
from rest plus a headway on each side); the stream's cars, about 3.5 s apart, were each
promoted ``C_FAST`` on arrival, since a car told to stop claims nothing in the table.
"""

from __future__ import annotations

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from protocol.messages import AutonomousPath, CoordinatedPath, Mode, ModeCommand
from services.model.types import Policy
from services.rsu import core as rsu_core
from services.rsu import paths
from services.rsu.core import RsuCore
from services.rsu.reservation import ReservationTable
from services.rsu.velocity import VelocityManager
from tests.rsu.test_issue12_causes import (
    EAST,
    NORTH,
    VMAX,
    config,
    message,
    no_conflict_within,
)

STREAM = tuple(3.0 + 3.0 * i for i in range(7))
"""Zone entries of the crossing stream after now [s]: a gap of 3 s is too short for A."""

STOP_X = -3.5 - 2.0 - 2.25
"""Centre of an eastbound 4.5 m car whose front stands ``stop_gap_m`` (2 m) before the zone."""


def from_rest(x0: float, t0: float, accel: float = 1.5) -> np.ndarray:
    """An eastbound path on y = -1.75 from rest at ``x0``, accelerating to V_max."""
    t = np.linspace(0.0, 10.0, 120)
    t_v = VMAX / accel
    s = np.where(t < t_v, 0.5 * accel * t**2, 0.5 * accel * t_v**2 + VMAX * (t - t_v))
    return np.column_stack([x0 + s, np.full(t.shape, -1.75), t0 + t])


def northbound(enters_zone_at: float, now: float) -> np.ndarray:
    """A car at V_max on x = +1.75 whose centre reaches the zone (y = -3.5) at the given
    time, its path 20 s long (so that a stream of them fills the slot search's horizon)."""
    t = np.linspace(0.0, 20.0, 240)
    y = -3.5 - VMAX * (enters_zone_at - now) + VMAX * t
    return np.column_stack([np.full(t.shape, 1.75), y, now + t])


def test_a_car_standing_a_little_past_its_stop_point_still_gets_a_slot() -> None:
    """A stands 40 cm past the point ``stop_gap_m`` before the zone; B crosses in 4 s. A's
    slot waits where it stands (``slot_stop``) instead of falling back to a stop with no
    entry at all (the search found no stop point behind the car)."""
    cfg = config(Policy.SLOT)
    table = ReservationTable(cfg.d_margin_m, cfg.headway_s, cfg.expiry_s)
    table.update("B", northbound(4.0, 0.0), 0.0)
    a = from_rest(STOP_X + 0.4, 0.0)
    plan = VelocityManager(cfg).plan(
        "A", message(AutonomousPath, "A", a, 0.0, EAST, Mode.C_SLOW), Mode.C_SLOW, 0.0, table
    )
    assert plan.kind == "slot_stop"
    assert np.isfinite(plan.entry_time) and plan.entry_time > 4.0
    margins = (cfg.release_margin_m, cfg.release_margin_s)
    assert table.naive_conflicts("A", plan.points, 0.0, cfg.t_free_s, (), *margins) == []


def _stream(core: RsuCore, now: float, arrived: float, entries: tuple[float, ...]) -> None:
    """Northbound C_FAST cars N0, N1, ... at V_max reaching the zone at ``entries``."""
    for i, when in enumerate(entries):
        pts = northbound(when, now)
        vid = f"N{i}"
        core._cars[vid] = rsu_core._Car(
            vid,
            mode=Mode.C_FAST,
            x=float(pts[0, 0]),
            y=float(pts[0, 1]),
            heading=NORTH,
            speed=VMAX,
            arrived=arrived,
        )
        core._cars[vid].autonomous = message(AutonomousPath, vid, pts, VMAX, NORTH, Mode.C_FAST)
        core.table.update(vid, pts, now, (4.5, 1.8))


def _standing_a(core: RsuCore, now: float, x: float = STOP_X) -> list[rsu_core.Outgoing]:
    """A (C_SLOW, first in coverage at t = 0) stands at ``x`` and asks again."""
    core._cars["A"] = rsu_core._Car(
        "A", mode=Mode.C_SLOW, x=x, y=-1.75, heading=EAST, speed=0.0, arrived=0.0
    )
    ap = message(AutonomousPath, "A", from_rest(x, now), 0.0, EAST, Mode.C_SLOW)
    return core.on_message(now, ap, "rsu-1")


def test_a_standing_car_claims_its_slot_from_later_arrivals() -> None:
    """Cars on the crossing road 3 s apart, each in coverage after A and able to stop:
    A takes the first slot; those whose paths meet A's yield (C_SLOW) in the same step,
    and no two paths in the table conflict afterwards."""
    core = RsuCore(config(Policy.SLOT), listen_s=0.0)
    now = 1.0
    _stream(core, now, arrived=0.5, entries=tuple(now + e for e in STREAM))
    out = _standing_a(core, now)
    assert core.counters["slot_claims"] >= 1
    a = core.table.get("A")
    assert a is not None and paths.zone_entry_time(a.points, core._zone) < now + 6.0
    # N0 enters before A's slot; N1 (and whoever its new path meets) gives way
    assert core.mode_of("N0") == Mode.C_FAST
    yielded = [v for v in core.modes() if v != "A" and core.mode_of(v) == Mode.C_SLOW]
    assert "N1" in yielded
    assert core.counters["claim_yields"] == len(yielded)
    for vid in yielded:
        told = [o.message for o in out if o.vehicle == vid]
        assert any(isinstance(m, ModeCommand) and m.mode == Mode.C_SLOW for m in told)
        assert any(isinstance(m, CoordinatedPath) for m in told)
    assert no_conflict_within(core, now, core.config.t_collision_s) == []


def test_no_claim_over_cars_that_came_first() -> None:
    """The same stream, in coverage before A: first come, first served, A waits."""
    core = RsuCore(config(Policy.SLOT), listen_s=0.0)
    now = 1.0
    _stream(core, now, arrived=-1.0, entries=tuple(now + e for e in STREAM))
    _standing_a(core, now)
    assert core.counters["slot_claims"] == 0
    assert all(core.mode_of(v) == Mode.C_FAST for v in core.modes() if v != "A")
    assert no_conflict_within(core, now, core.config.t_collision_s) == []


def test_no_claim_over_a_car_that_can_no_longer_stop() -> None:
    """N0 is 1.2 s from the zone at V_max (committed): A's claim goes behind it."""
    core = RsuCore(config(Policy.SLOT), listen_s=0.0)
    now = 1.0
    _stream(core, now, arrived=0.5, entries=tuple(now + e - 1.8 for e in STREAM))
    _standing_a(core, now)
    assert core.mode_of("N0") == Mode.C_FAST
    a = core.table.get("A")
    n0 = core.table.get("N0")
    assert a is not None and n0 is not None
    zone = core._zone
    assert paths.zone_entry_time(a.points, zone) > paths.zone_entry_time(n0.points, zone)
    assert no_conflict_within(core, now, core.config.t_collision_s) == []


@settings(max_examples=60, deadline=None)
@given(
    first=st.floats(0.8, 6.0),
    spacing=st.floats(1.6, 4.0),
    after_a=st.lists(st.booleans(), min_size=1, max_size=8),
    behind=st.floats(0.0, 6.0),
)
def test_a_claim_only_moves_later_cars_that_can_stop_and_leaves_no_conflict(
    first: float, spacing: float, after_a: list[bool], behind: float
) -> None:
    """Any crossing stream, each car in coverage before or after A, near the zone or
    far, A standing up to 6 m behind its stop point: after A's step no two paths in the
    table conflict within ``T_collision``, and a car whose mode changed came after A and
    could still stop comfortably before the zone, or follows in its lane one that changed
    (a follower yields to the car ahead)."""
    core = RsuCore(config(Policy.SLOT), listen_s=0.0)
    now = 1.0
    _stream(core, now, 0.5, tuple(now + first + spacing * i for i in range(len(after_a))))
    for i, later in enumerate(after_a):
        core._cars[f"N{i}"].arrived = 0.5 if later else -1.0
    before = {v: (core.mode_of(v), core._committed(core._cars[v])) for v in core.modes()}
    _standing_a(core, now, STOP_X - behind)
    assert no_conflict_within(core, now, core.config.t_collision_s) == []
    changed = [i for i in range(len(after_a)) if core.mode_of(f"N{i}") != before[f"N{i}"][0]]
    for i in changed:  # the stream is one lane: N0 leads
        committed = before[f"N{i}"][1]
        assert (after_a[i] and not committed) or any(j < i for j in changed), (i, changed)
