"""Issue 12: the six causes of conflicting coordinated paths, each with the RSU core alone.

Crafted paths at a 4-way box (centre at the origin, 7 m square): A eastbound on
y = -1.75, B northbound on x = +1.75 (they cross at (1.75, -1.75)), followers in
A's lane behind it.
"""

from __future__ import annotations

import math
from typing import TypeVar

import numpy as np
import pytest
from hypothesis import assume, example, given, settings
from hypothesis import strategies as st

from protocol.messages import (
    AutonomousPath,
    CoordinatedPath,
    FuturePath,
    Header,
    Mode,
    ModeCommand,
    VehiclePath,
)
from services.model.geometry import Polyline, convex_overlap, footprint
from services.model.types import Policy
from services.rsu import core as rsu_core
from services.rsu import paths, velocity
from services.rsu.config import RsuConfig
from services.rsu.core import Outgoing, RsuCore
from services.rsu.modes import RsuEvent
from services.rsu.reservation import ReservationTable, follow_distance
from services.rsu.velocity import VelocityManager
from services.vehicle.future_path import future_path_points
from services.vehicle.profile import SpeedProfile, forward_pass, grid, pass_times, stop_cap

ZONE = np.array([[-3.5, -3.5], [3.5, -3.5], [3.5, 3.5], [-3.5, 3.5]])
VMAX = 50 / 3.6
EAST, NORTH, WEST = 0.0, math.pi / 2, math.pi
CROSS = (1.75, -1.75)


def config(policy: Policy = Policy.PAPER, **kw: object) -> RsuConfig:
    return RsuConfig("rsu-1", "x0", (0.0, 0.0), ZONE, policy=policy, **kw)  # type: ignore[arg-type]


def straight(start: tuple[float, float], heading: float, v: float, t0: float) -> np.ndarray:
    t = t0 + np.linspace(0.0, 10.0, 120)
    s = v * (t - t0)
    return np.column_stack([start[0] + s * math.cos(heading), start[1] + s * math.sin(heading), t])


def held(x: float, y: float, t0: float) -> np.ndarray:
    """A car standing at (x, y) for the horizon (two points, as a future path has)."""
    return np.array([[x, y, t0], [x, y, t0 + 10.0]])


P = TypeVar("P", bound=VehiclePath)


def message(
    cls: type[P],
    vehicle: str,
    pts: np.ndarray,
    v: float,
    heading: float,
    mode: Mode = Mode.AUTO,
    seq: int = 1,
) -> P:
    t0 = float(pts[0, 2])
    x, y = float(pts[0, 0]), float(pts[0, 1])
    return cls(Header(vehicle, seq, round(t0 * 1e6)), x, y, v, heading, 4.5, 1.8, mode, pts)


def sent(out: list[Outgoing], vehicle: str) -> list[tuple[str, Mode]]:
    return [
        (type(o.message).__name__, o.message.mode)
        for o in out
        if o.vehicle == vehicle and isinstance(o.message, ModeCommand | CoordinatedPath)
    ]


def no_conflict_within(core: RsuCore, now: float, horizon: float) -> list[tuple[str, str]]:
    """Pairs of table entries in conflict within ``horizon`` of ``now`` (the invariant)."""
    bad = []
    for vehicle in core.table:
        entry = core.table.get(vehicle)
        assert entry is not None
        shape = (entry.length, entry.width)
        for c in core.table.naive_conflicts(vehicle, entry.points, now, horizon, shape=shape):
            bad.append((vehicle, c.vehicle))
    return bad


# -- cause 1: a stop at the end of the car's own path -------------------------------------


def test_cause1_future_path_of_a_stopping_car_ends_with_a_held_stop() -> None:
    """The builder used to leave its last point a few cm past the previous one: the RSU
    then read a crawl, not a stop, and planned C_FAST at V_max off the end of the path."""
    route = Polyline([(-100.0, -1.75), (100.0, -1.75)])
    s = grid(0.0, 60.0, 0.5)
    v = forward_pass(np.minimum(VMAX, stop_cap(s, 37.3, 2.0)), 8.0, 0.5, 1.5)
    profile = SpeedProfile(s, v, pass_times(s, v, 0.0))
    pts = future_path_points(profile, route, 0.0, 10.0, 120)
    assert np.hypot(*(pts[-1, :2] - pts[-2, :2])) == 0.0  # zero-length last segment
    assert pts[-1, 2] == 10.0 and pts[-1, 0] <= -100.0 + 37.5 + 1e-6  # the grid's stop
    # the RSU's C_FAST plan on it stops there too (target 0 at the end, held)
    path = message(AutonomousPath, "A", pts, 8.0, EAST, Mode.C_FAST)
    plan = VelocityManager(config()).plan("A", path, Mode.C_FAST, 0.0, ReservationTable())
    assert plan.speeds[-1] == 0.0
    assert plan.points[-1, 2] >= 10.0 - 1e-9
    assert float(plan.points[:, 0].max()) <= float(pts[-1, 0]) + 1e-6


def test_cause1_rsu_sees_a_stop_a_few_cm_past_the_last_point() -> None:
    """Robust on the RSU's side too: an old-style path (last point 4 cm on, 6 s later)."""
    pts = straight((-40.0, -1.75), EAST, 6.0, 0.0)[:50]
    last = pts[-1].copy()
    last[0] += 0.04
    last[2] = 10.0
    pts = np.vstack([pts, last])
    path = message(AutonomousPath, "A", pts, 6.0, EAST, Mode.C_FAST)
    plan = VelocityManager(config()).plan("A", path, Mode.C_FAST, 0.0, ReservationTable())
    assert plan.speeds[-1] == 0.0
    assert float(plan.points[:, 0].max()) <= float(last[0]) + 1e-6
    assert plan.points[-1, 2] >= 10.0 - 1e-9  # held to the horizon


# -- cause 2: the C_FAST path itself is checked ----------------------------------------------


def test_cause2_promotion_is_judged_on_the_plan_not_on_the_cars_own_path() -> None:
    """B's own path (3 m/s) crosses A's 5 s after A: free. Its V_max plan would cross
    within a headway of A: B must not get C_FAST on it."""
    core = RsuCore(config(), listen_s=0.3)
    a = straight((CROSS[0] - 5.0 * VMAX, CROSS[1]), EAST, VMAX, 0.0)
    assert core.on_message(0.0, message(FuturePath, "A", a, VMAX, EAST)) == []  # listened
    b = straight((CROSS[0], CROSS[1] - 30.0), NORTH, 3.0, 0.4)
    assert core.table.naive_conflicts("B", b, 0.4, 10.0) == []  # its own path is clear
    fast = VelocityManager(config()).plan(
        "B", message(AutonomousPath, "B", b, 3.0, NORTH), Mode.C_FAST, 0.4, core.table
    )
    assert core.table.naive_conflicts("B", fast.points, 0.4, 10.0) != []  # the plan is not
    out = core.on_message(0.4, message(FuturePath, "B", b, 3.0, NORTH))
    assert core.mode_of("B") != Mode.C_FAST
    assert ("ModeCommand", Mode.C_FAST) not in sent(out, "B")
    assert no_conflict_within(core, 0.4, config().t_collision_s) == []


def test_cause2_every_c_fast_path_sent_is_clear_of_the_table() -> None:
    core = RsuCore(config(), listen_s=0.0)
    out = core.on_message(
        0.0, message(FuturePath, "A", straight((-60.0, -1.75), EAST, VMAX, 0.0), VMAX, EAST)
    )
    cps = [o.message for o in out if isinstance(o.message, CoordinatedPath)]
    assert cps and cps[0].mode == Mode.C_FAST
    b = straight((1.75, -40.0), NORTH, 8.0, 0.1)
    out = core.on_message(0.1, message(FuturePath, "B", b, 8.0, NORTH))
    for o in out:
        m = o.message
        if isinstance(m, CoordinatedPath) and m.mode == Mode.C_FAST:
            assert core.table.naive_conflicts(m.vehicle, m.points, 0.1, 10.0) == []
    assert no_conflict_within(core, 0.1, config().t_collision_s) == []


# -- cause 3: yielding between C_FAST and C_SLOW --------------------------------------------


def test_cause3_a_c_fast_car_yields_to_a_c_slow_cars_path() -> None:
    """A C_SLOW entry is all that car can give: a C_FAST car whose plan meets it yields."""
    core = RsuCore(config(), listen_s=0.0)
    cfg = config()
    # B: commanded C_SLOW, its entry a path it cannot leave (a slot through the crossing)
    b_path = straight((CROSS[0], CROSS[1] - 40.0), NORTH, 8.0, 0.0)
    core.on_message(
        0.0, message(FuturePath, "A", straight((-90.0, -1.75), EAST, VMAX, 0.0), VMAX, EAST)
    )
    assert core.mode_of("A") == Mode.C_FAST
    car_b = rsu_core._Car(
        "B", mode=Mode.C_SLOW, x=CROSS[0], y=CROSS[1] - 40.0, heading=NORTH, speed=8.0
    )
    core._cars["B"] = car_b
    core.table.update("B", b_path, 0.0)
    # A's next autonomous path: its C_FAST plan now reaches the crossing as B does
    a_when = float(paths.zone_entry_time(b_path, ZONE))
    a = straight((CROSS[0] - (a_when - 0.2) * VMAX, CROSS[1]), EAST, VMAX, 0.2)
    core.on_message(0.2, message(AutonomousPath, "A", a, VMAX, EAST, Mode.C_FAST), "rsu-1")
    assert core.mode_of("A") == Mode.C_SLOW
    assert core.mode_of("B") == Mode.C_SLOW
    assert no_conflict_within(core, 0.2, cfg.t_collision_s) == []


# -- cause 4: no flip-flop ---------------------------------------------------------------------


def test_cause4_a_follower_does_not_flip_its_mode_every_step() -> None:
    """A stands at the stop line; B follows in A's lane, its own path running through. Over
    4 s of autonomous paths every 0.1 s B's mode changes a bounded number of times, and
    never twice within the dwell after its first changes."""
    core = RsuCore(config(), listen_s=0.0)
    a_x = -3.5 - 5.0 - 2.25
    changes: list[tuple[float, Mode]] = []
    b_x, b_v = a_x - 35.0, 6.0
    for k in range(40):
        now = round(0.1 * k, 1)
        core.on_message(
            now,
            message(FuturePath, "A", held(a_x, -1.75, now), 0.0, EAST, core.mode_of("A"), k + 1),
        )
        b = straight((b_x, -1.75), EAST, b_v, now)
        before = core.mode_of("B")
        if before == Mode.AUTO:
            core.on_message(now, message(FuturePath, "B", b, b_v, EAST, Mode.AUTO, k + 1))
        else:
            core.on_message(now, message(FuturePath, "B", b, b_v, EAST, before, k + 1))
            core.on_message(now, message(AutonomousPath, "B", b, b_v, EAST, before, k + 1), "rsu-1")
        if core.mode_of("B") != before:
            changes.append((now, core.mode_of("B")))
        entry = core.table.get("B")
        if entry is not None and core.mode_of("B") != Mode.AUTO:
            # B follows its coordinated path exactly
            s_now = np.interp(now + 0.1, entry.points[:, 2], paths.arc_length(entry.points))
            b_x = float(entry.points[0, 0]) + float(s_now)
            b_v = max(
                0.0,
                float(
                    np.interp(
                        now + 0.1, entry.points[:, 2], paths.segment_speeds(entry.points, b_v)
                    )
                ),
            )
        else:
            b_x += 0.1 * b_v
        assert b_x <= a_x - follow_distance(4.5, 4.5, 1.0) + 1e-6, "B drove into A"
    assert changes, "B is coordinated at all"
    assert len(changes) <= rsu_core.MAX_MODE_CHANGES, changes
    late = changes[rsu_core.FREE_MODE_CHANGES :]
    gaps = [
        t2 - t1
        for (t1, _), (t2, _) in zip(changes[rsu_core.FREE_MODE_CHANGES - 1 :], late, strict=False)
    ]
    assert all(g >= rsu_core.MODE_DWELL_S - 1e-9 for g in gaps), changes


@pytest.mark.parametrize("dwell", [True, False])
def test_cause4_an_auto_car_held_by_the_dwell_drives_its_own_clear_path(dwell: bool) -> None:
    """B (AUTO, 3 m/s, its own path entering the zone beyond T_collision and clear over
    T_free; its V_max plan is not, cause 2) has used its free mode changes. Within the
    dwell after its last one it keeps driving its own path, AUTO, reserved as it is: it
    used to be slowed into C_SLOW for the dwell alone, released when it stopped, judged
    free again, and so round every 3-4 s (a queued follower, four-way-flows, seed 0).
    Without the dwell, the paper's rule: it waits its turn in C_SLOW."""
    cfg = config()
    core = RsuCore(cfg, listen_s=0.3)
    a = straight((CROSS[0] - 5.0 * VMAX, CROSS[1]), EAST, VMAX, 0.0)
    core.on_message(0.0, message(FuturePath, "A", a, VMAX, EAST))
    b = straight((CROSS[0], CROSS[1] - 30.0), NORTH, 3.0, 0.4)
    assert paths.zone_entry_time(b, ZONE) > 0.4 + cfg.t_collision_s
    assert core.table.naive_conflicts("B", b, 0.4, cfg.t_free_s) == []
    changed_at = 0.2 if dwell else -math.inf
    core._cars["B"] = rsu_core._Car("B", changes=rsu_core.FREE_MODE_CHANGES, changed_at=changed_at)
    out = core.on_message(0.4, message(FuturePath, "B", b, 3.0, NORTH))
    if dwell:
        assert core.mode_of("B") == Mode.AUTO and sent(out, "B") == []
        entry = core.table.get("B")
        assert entry is not None and np.array_equal(entry.points, b)
    else:
        assert core.mode_of("B") == Mode.C_SLOW
        assert ("ModeCommand", Mode.C_SLOW) in sent(out, "B")
    assert no_conflict_within(core, 0.4, cfg.t_collision_s) == []


# -- cause 5: the paper's stop stops behind the car ahead -------------------------------------


def test_cause5_paper_stop_stops_behind_the_car_ahead_braking_as_hard_as_needed() -> None:
    a_x = -10.75
    table = ReservationTable(2.8, 1.0, 0.5)
    table.update("A", held(a_x, -1.75, 0.0), 0.0)
    b = straight((a_x - 30.0, -1.75), EAST, VMAX, 0.0)  # its own path runs through A
    plan = VelocityManager(config()).plan(
        "B", message(AutonomousPath, "B", b, VMAX, EAST, Mode.C_SLOW), Mode.C_SLOW, 0.0, table
    )
    stop_x = float(plan.points[:, 0].max())
    assert stop_x <= a_x - follow_distance(4.5, 4.5, table.follow_gap_m)
    assert stop_x >= a_x - 30.0 + 5.0  # it does not stop short either: it brakes to there
    assert table.naive_conflicts("B", plan.points, 0.0, 10.0) == []
    assert np.all(plan.speeds == 0.0)


def test_cause5_a_stop_within_its_own_paths_stop() -> None:
    """The autonomous path stops 15 m on (its planner sees a car ahead): so does the plan."""
    pts = straight((-60.0, -1.75), EAST, VMAX, 0.0)
    pts = pts[pts[:, 0] <= -45.0]
    pts = np.vstack([pts, [[pts[-1, 0], -1.75, 10.0]]])
    plan = VelocityManager(config()).plan(
        "B",
        message(AutonomousPath, "B", pts, VMAX, EAST, Mode.C_SLOW),
        Mode.C_SLOW,
        0.0,
        ReservationTable(),
    )
    assert float(plan.points[:, 0].max()) <= float(pts[-1, 0]) + 1e-6


# -- cause 6: slot entry with clearance -------------------------------------------------------


def test_cause6_slot_entry_keeps_the_release_margins_and_survives_the_next_replan() -> None:
    cfg = config(Policy.SLOT)
    table = ReservationTable(2.8, 1.0, 0.5)
    table.update("A", straight((CROSS[0] - 4.0 * VMAX, CROSS[1]), EAST, VMAX, 0.0), 0.0)
    b = straight((CROSS[0], CROSS[1] - 4.3 * VMAX), NORTH, VMAX, 0.0)
    vm = VelocityManager(cfg)
    plan = vm.plan(
        "B", message(AutonomousPath, "B", b, VMAX, NORTH, Mode.C_SLOW), Mode.C_SLOW, 0.0, table
    )
    assert plan.kind.startswith("slot") and plan.kind != "slot_fallback"
    margins = (cfg.release_margin_m, cfg.release_margin_s)
    assert table.naive_conflicts("B", plan.points, 0.0, 10.0, (), *margins) == []
    # 0.1 s on, B exactly where its plan said, A too: the re-plan is still clear
    t = 0.1
    bx, by = (float(np.interp(t, plan.points[:, 2], plan.points[:, i])) for i in (0, 1))
    v = float(paths.segment_speeds(plan.points, VMAX)[1])
    again = straight((bx, by), NORTH, v, t)
    table.update("A", straight((CROSS[0] - 3.9 * VMAX, CROSS[1]), EAST, VMAX, t), t)
    replan = vm.plan(
        "B", message(AutonomousPath, "B", again, v, NORTH, Mode.C_SLOW), Mode.C_SLOW, t, table
    )
    assert table.naive_conflicts("B", replan.points, t, cfg.t_collision_s) == []


# -- cause 7: a body in the zone -------------------------------------------------------------
# Found in four-way-flows (slot, seed 0): two turning cars crawled into the box, each
# judged by its centre; at a crawl the point rule's 2.8 m between centres misses bodies
# that touch (a 4.5 m x 1.8 m car reaches 3.15 m ahead of its centre at a corner).


def test_cause7_a_car_with_its_front_in_the_zone_is_committed() -> None:
    """Its centre outside, its front 0.75 m in, at rest, told to stop: it is committed (it
    blocks the crossing until it drives on), whatever its table entry says."""
    core = RsuCore(config(), listen_s=0.0)
    car = rsu_core._Car("A", mode=Mode.C_SLOW, x=-4.5, y=-1.75, heading=EAST, speed=0.0)
    core._cars["A"] = car
    core.table.update("A", held(-4.5, -1.75, 0.0), 0.0)
    assert not core._zone.contains_point(car.x, car.y)
    assert core._committed(car)
    car.x = -6.0  # front 0.75 m short of the zone: not committed at rest
    assert not core._committed(car)


def test_cause7_a_body_with_only_its_nose_in_the_zone_takes_the_zone() -> None:
    """B stands northbound with its nose 1 m over the zone's edge and its centre 3.25 m
    outside (an overrun stop leaves it so: demand experiment, slot, 600 veh/h, seed 4).
    A's path east through the crossing passes 3 m from B's centre, beyond the point
    rule's 2.8 m, and its centre never enters the zone on its path: only the nose says
    B is in the zone. Left alone, A would drive into it."""
    cfg = config()
    core = RsuCore(cfg, listen_s=0.0)
    b_y = -3.5 + 1.0 - 2.25
    car_b = rsu_core._Car("B", mode=Mode.C_SLOW, x=CROSS[0], y=b_y, heading=NORTH, speed=0.0)
    core._cars["B"] = car_b
    core.table.update("B", held(CROSS[0], b_y, 0.0), 0.0)
    assert core._committed(car_b) and core._occupancy(held(CROSS[0], b_y, 0.0), car_b)
    a = straight((-20.0, CROSS[1]), EAST, 6.0, 0.0)  # not committed: it can still stop
    assert core.table.naive_conflicts("A", a, 0.0, cfg.t_free_s) == []  # the point rule
    car_a = rsu_core._Car("A", x=-20.0, y=CROSS[1], heading=EAST, speed=6.0)
    assert not core._committed(car_a, a) and core._zone_taken(car_a, a, 0.0)
    # one lane over (westbound, y = +1.75) it passes: 4.25 m clear of B's nose
    w = straight((20.0, -CROSS[1]), WEST, 6.0, 0.0)
    car_w = rsu_core._Car("W", x=20.0, y=-CROSS[1], heading=WEST, speed=6.0)
    assert not core._zone_taken(car_w, w, 0.0)


def test_cause7_no_slot_through_a_body_standing_in_the_zone() -> None:
    """A stands in the box 2.95 m from B's lane (beyond the point rule's 2.8 m, but its
    front reaches across B's lane). B's slot must wait until A's hold is over."""
    cfg = config(Policy.SLOT)
    core = RsuCore(cfg, listen_s=0.0)
    core._cars["A"] = rsu_core._Car("A", mode=Mode.C_SLOW, x=-1.2, y=-1.75, heading=EAST)
    core.table.update("A", held(-1.2, -1.75, 0.0), 0.0)
    b = straight((CROSS[0], CROSS[1] - 40.0), NORTH, 8.0, 0.0)
    assert core.table.naive_conflicts("B", b, 0.0, cfg.t_free_s) == []  # the point rule
    out = core.on_message(0.0, message(FuturePath, "B", b, 8.0, NORTH))
    assert core.mode_of("B") == Mode.C_SLOW
    cps = [o.message for o in out if isinstance(o.message, CoordinatedPath)]
    assert len(cps) == 1
    entry = paths.zone_entry_time(cps[0].points, ZONE)
    assert entry >= 10.0 + cfg.headway_s  # after A's hold, or never (a stop)


def test_cause7_a_car_in_the_zone_is_not_released_into_a_body_across_its_lane() -> None:
    """B (C_SLOW) crawls in the box; A (AUTO, not told to stop) stands in the box 3.55 m
    from B's lane, heading away from it, its rear 0.4 m from B's side. The point rule sees
    no conflict, even with the release margins; the bodies' sweeps meet: B stays C_SLOW
    until A has gone. (A facing B would be standing for B: cause 8.)"""
    cfg = config()
    core = RsuCore(cfg, listen_s=0.0)
    core.on_message(0.0, message(FuturePath, "A", held(-1.8, 1.75, 0.0), 0.0, WEST))
    assert core.mode_of("A") == Mode.AUTO
    b = straight((1.75, -3.0), NORTH, 0.5, 0.0)
    assert core.table.naive_conflicts("B", b, 0.0, cfg.t_free_s, (), 0.6, 0.2) == []
    core._cars["B"] = rsu_core._Car("B", mode=Mode.C_SLOW, x=1.75, y=-3.0, heading=NORTH)
    core.on_message(0.0, message(AutonomousPath, "B", b, 0.5, NORTH, Mode.C_SLOW), "rsu-1")
    assert core.mode_of("B") == Mode.C_SLOW
    assert core.counters["zone_taken"] == 1
    # A drives off west, out of the box: B is released once A's body is past
    a2 = straight((-12.0, 1.75), WEST, 3.0, 4.0)
    core.on_message(4.0, message(FuturePath, "A", a2, 3.0, WEST, seq=2))
    b2 = straight((1.75, -2.9), NORTH, 0.5, 4.0)
    core.on_message(4.0, message(AutonomousPath, "B", b2, 0.5, NORTH, Mode.C_SLOW, 2), "rsu-1")
    assert core.mode_of("B") == Mode.AUTO


def test_cause7_opposing_traffic_is_not_held_by_a_body_in_the_zone() -> None:
    """The same, A on the opposing lane (3.5 m away, bodies 1.7 m apart): B is released."""
    cfg = config()
    core = RsuCore(cfg, listen_s=0.0)
    south = -NORTH
    core.on_message(
        0.0, message(FuturePath, "A", straight((-1.75, 3.0), south, 3.0, 0.0), 3.0, south)
    )
    b = straight((1.75, -3.0), NORTH, 0.5, 0.0)
    core._cars["B"] = rsu_core._Car("B", mode=Mode.C_SLOW, x=1.75, y=-3.0, heading=NORTH)
    core.on_message(0.0, message(AutonomousPath, "B", b, 0.5, NORTH, Mode.C_SLOW), "rsu-1")
    assert core.mode_of("B") == Mode.AUTO
    assert core.counters["zone_taken"] == 0


# Found in four-way-flows (paper, seed 3, every send rule ``change``): W (westbound, front in
# the box) was demoted to C_SLOW; S (northbound, C_FAST, committed) stood short of W's body,
# its own planner holding it there. W waited for S in the crossing order, S for W's body:
# 15 of 32 cars never got through.


def _box_lock(w_x: float) -> RsuCore:
    """S stands committed in the box (centre 0.3 m in, front 2.55 m) with its path at rest;
    W, C_SLOW, stands at ``w_x`` on the westbound lane and sends a path west through the
    box at 3 m/s (5 m from S's centre where it crosses S's lane: no point conflict)."""
    core = RsuCore(config(), listen_s=0.0)
    core._cars["S"] = rsu_core._Car("S", mode=Mode.C_FAST, x=1.75, y=-3.2, heading=NORTH)
    core.table.update("S", held(1.75, -3.2, 0.0), 0.0)
    w = straight((w_x, 1.75), WEST, 3.0, 0.0)
    core._cars["W"] = rsu_core._Car("W", mode=Mode.C_SLOW, x=w_x, y=1.75, heading=WEST)
    core.on_message(0.0, message(AutonomousPath, "W", w, 3.0, WEST, Mode.C_SLOW), "rsu-1")
    return core


def test_cause8_a_car_held_by_this_cars_body_is_not_waited_for() -> None:
    """W's body (front 1.15 m into the box) stands 1.8 m ahead of S's front, across S's
    lane: S waits for W, so W goes first (``RsuCore._held_by``)."""
    core = _box_lock(4.6)
    assert core._held_by(core._cars["S"], core.table.get("S").points, core._cars["W"])  # type: ignore[union-attr]
    assert core.mode_of("W") == Mode.C_FAST
    assert core.counters["order_kept"] == 0


def test_cause8_a_car_held_by_another_body_keeps_its_order() -> None:
    """The same S, W 12 m further east, not in S's way: S stands in the box for something
    else, and W waits its turn behind S's body."""
    core = _box_lock(16.6)
    assert not core._held_by(core._cars["S"], core.table.get("S").points, core._cars["W"])  # type: ignore[union-attr]
    assert core.mode_of("W") == Mode.C_SLOW
    assert core.counters["order_kept"] >= 1


# Found in the demand experiment (600 veh/h, paper, seed 0): W (westbound, AUTO) overran
# its stop and stood with its nose 0.7 m in the box, 0.1 m beside B's lane; B (northbound,
# C_SLOW) stood in the box in front of W. W's planner waited for B's body; B was never
# released, its path passing W's centre 3.3 m off (inside 2.8 m plus the release margin),
# and its sweep within 2 x 0.25 m of W's nose. 9 of 44 cars never got through.


@pytest.mark.parametrize(("w_heading", "released"), [(WEST, True), (EAST, False)])
def test_cause8_a_car_is_released_past_a_body_standing_for_it(
    w_heading: float, released: bool
) -> None:
    """W stands with its nose 0.7 m in the box, facing B's body (WEST: it waits for B);
    B's path north passes W's centre 3.3 m off: inside the release margins, clear of it
    without them. B is released (its own planner creeps past W's nose 0.1 m off).
    W standing there facing away (EAST) waits for nobody: B keeps the margins and waits."""
    cfg = config()
    core = RsuCore(cfg, listen_s=0.0)
    t = np.linspace(0.0, 10.0, 101)  # standing, one point every 0.1 s
    w = np.column_stack([np.full_like(t, 5.05), np.full_like(t, 1.75), t])
    core.on_message(0.0, message(FuturePath, "W", w, 0.0, w_heading))
    assert core.mode_of("W") == Mode.AUTO
    core._cars["B"] = rsu_core._Car("B", mode=Mode.C_SLOW, x=1.75, y=-0.55, heading=NORTH)
    core.table.update("B", held(1.75, -0.55, 0.0), 0.0)
    assert core._stands_for(core._cars["W"], w, core._cars["B"]) == released
    b = straight((1.75, -0.255), NORTH, 1.5, 0.25)
    # inside the release margins of W's centre, clear of it without them
    assert core.table.conflicts("B", b, 0.25, cfg.t_free_s, (), *core._margins)
    assert not core.table.conflicts("B", b, 0.25, cfg.t_free_s)
    core.on_message(0.25, message(AutonomousPath, "B", b, 0.0, NORTH, Mode.C_SLOW), "rsu-1")
    assert core.mode_of("B") == (Mode.AUTO if released else Mode.C_SLOW)


# -- cause 9: two committed cars ---------------------------------------------------------------
# Found in the demand experiment (paper, 400 veh/h, straight, seed 0, with the final-stop
# controller): of two C_FAST cars that could no longer stop comfortably before the zone,
# the later arriver was told to stop; 3 cm past the hard stop's reach, its stop fell back to
# a comfortable one in the middle of the crossing, the other car was then told to stop for
# it, and they collided.


def _front_out_of_zone(plan_points: np.ndarray, heading: float) -> bool:
    """The body of a car at rest at the plan's last point keeps its front out of the zone."""
    x, y = float(plan_points[-1, 0]), float(plan_points[-1, 1])
    front = (x + 2.25 * math.cos(heading), y + 2.25 * math.sin(heading))
    return not paths.ConvexZone.of(ZONE).contains_point(*front)


@settings(max_examples=150, deadline=None)
@given(v=st.floats(1.0, VMAX), slack=st.floats(-0.5, 1.0))
def test_cause9_a_stop_that_can_stay_out_of_the_zone_does(v: float, slack: float) -> None:
    """B northbound at ``v``, its front its hard braking distance (at ``HARD_STOP_FACTOR``
    x comfortable) plus its travel in ``REACTION_S`` plus ``slack`` [m] from the zone.
    Its paper stop keeps the front out of the zone whenever hard braking after the
    reaction time can, the whole stop gap (or the reaction travel, if longer) short
    when that fits; otherwise it brakes at ``FIRM_STOP_FACTOR`` all the same, out of the
    zone or into it as little as it can (a comfortable stop would run through the
    crossing it yields to); comfortable, as the paper's, once its front is in the zone."""
    cfg = config()
    hard = v * v / (2.0 * velocity.HARD_STOP_FACTOR * cfg.decel_comfort_mps2)
    lag = v * velocity.REACTION_S
    front_gap = hard + lag + slack
    y0 = -3.5 - front_gap - 2.25
    b = straight((CROSS[0], y0), NORTH, v, 0.0)
    plan = VelocityManager(cfg).plan(
        "B",
        message(AutonomousPath, "B", b, v, NORTH, Mode.C_SLOW),
        Mode.C_SLOW,
        0.0,
        ReservationTable(),
    )
    stop_y = float(plan.points[-1, 1])
    if slack >= 1e-6:
        assert plan.short and _front_out_of_zone(plan.points, NORTH)
        short_by = max(cfg.stop_gap_m, lag)
        if front_gap - short_by >= hard + 1e-6:
            assert stop_y + 2.25 <= -3.5 - short_by + 1e-6
        assert stop_y + 2.25 <= -3.5 - lag + 1e-6  # it stops in time, reaction and all
    elif slack <= -1e-6:
        if front_gap > 1e-6:  # braking at the firm factor, as short as it can (a
            # comfortable stop, if that is shorter still: at a crawl)
            firm = v * v / (2.0 * velocity.FIRM_STOP_FACTOR * cfg.decel_comfort_mps2)
            comfortable = v * v / (2.0 * cfg.decel_comfort_mps2)
            stop = min(firm, comfortable)
            assert math.isclose(stop_y - y0, stop, abs_tol=0.05)
            if abs(stop + lag - front_gap) > 0.1:  # short when that braking keeps it out
                assert plan.short == (stop + lag < front_gap)
            late = min(stop + lag, comfortable)  # where it will stand, its reaction on
            if not plan.short and late > stop + 0.05:  # reserved there
                assert plan.reserved is not None
                assert math.isclose(float(plan.reserved[-1, 1]) - y0, late, abs_tol=0.05)
        else:  # its front is in the zone already: the paper's comfortable stop
            assert not plan.short
            comfortable = v * v / (2.0 * cfg.decel_comfort_mps2)
            assert math.isclose(stop_y - y0, comfortable, abs_tol=0.05)


def _committed_pair(a_gap: float, a_v: float, b_gap: float, b_v: float) -> RsuCore:
    """A eastbound and B northbound, both C_FAST at V_max through the crossing, fronts
    ``a_gap`` / ``b_gap`` [m] from the zone at ``a_v`` / ``b_v``."""
    core = RsuCore(config(), listen_s=0.0)
    for vid, gap, v, heading in (("A", a_gap, a_v, EAST), ("B", b_gap, b_v, NORTH)):
        d = 3.5 + gap + 2.25
        x, y = (-d, CROSS[1]) if heading == EAST else (CROSS[0], -d)
        car = rsu_core._Car(vid, mode=Mode.C_FAST, x=x, y=y, heading=heading, speed=v)
        car.autonomous = message(AutonomousPath, vid, straight((x, y), heading, v, 0.0), v, heading)
        core._cars[vid] = car
        core.table.update(vid, straight((x, y), heading, v, 0.0), 0.0)
    return core


@settings(max_examples=200, deadline=None)
@given(
    a_gap=st.floats(0.5, 30.0),
    a_v=st.floats(3.0, VMAX),
    b_gap=st.floats(0.5, 30.0),
    b_v=st.floats(3.0, VMAX),
)
def test_cause9_of_two_committed_cars_one_that_can_stay_out_yields(
    a_gap: float, a_v: float, b_gap: float, b_v: float
) -> None:
    """Whatever their speeds and distances: of two committed crossing cars, exactly one
    yields, and when either can still keep its body out of the zone braking hard, the
    one that yields can."""
    core = _committed_pair(a_gap, a_v, b_gap, b_v)
    a, b = core._cars["A"], core._cars["B"]
    assume(core._committed(a) and core._committed(b))
    a_yields = core._yields(0.0, a, core.table.get("A").points, b)  # type: ignore[union-attr]
    b_yields = core._yields(0.0, b, core.table.get("B").points, a)  # type: ignore[union-attr]
    assert a_yields != b_yields
    if core._stops_short(a) or core._stops_short(b):
        assert core._stops_short(a if a_yields else b)


@pytest.mark.parametrize(
    ("b_lead_s", "kind", "a_yields"),
    [
        (0.5, "slot", True),  # B's slot takes the zone first: A, the later arriver, yields
        (-0.5, "slot", False),  # A is first: B's slot is the later arriver
        (-0.5, "stop", True),  # a stop is all B can give: whoever meets it yields
    ],
)
def test_cause9_a_slot_is_the_later_arriver_as_a_c_fast_path_is(
    b_lead_s: float, kind: str, a_yields: bool
) -> None:
    """A (C_FAST, 13.9 m/s, 10 m from the zone: it cannot keep out of it) meets B (C_SLOW
    on a path through the crossing). A slot enters the zone as a C_FAST path does, so of
    the two the later arriver yields (demand experiment, slot, 600 veh/h, seed 4: a car
    that could no longer stop gave way to a slot that reached the zone after it)."""
    core = _committed_pair(10.0, VMAX, 20.0, VMAX)
    a, b = core._cars["A"], core._cars["B"]
    a_path = core.table.get("A").points  # type: ignore[union-attr]
    a_entry = paths.zone_entry_time(a_path, ZONE)
    b_entry = a_entry - b_lead_s
    d = 3.5 + b_entry * VMAX  # B's centre enters the zone at b_entry
    b.y = -d
    core.table.update("B", straight((CROSS[0], -d), NORTH, VMAX, 0.0), 0.0)
    b.mode, b.kind, b.held_short = Mode.C_SLOW, kind, False
    assert not core._stops_short(a)
    assert math.isclose(
        paths.zone_entry_time(core.table.get("B").points, ZONE),  # type: ignore[union-attr]
        b_entry,
        abs_tol=0.1,
    )
    assert core._yields(0.0, a, a_path, b) == a_yields


def test_cause9_a_committed_car_keeps_its_way_past_one_stopped_short() -> None:
    """A (13.9 m/s, front 22 m from the zone: it cannot stop before it) arrives after B
    (6 m/s, front 7 m from it: only a hard stop after the reaction time, 4.5 + 2.4 m,
    keeps it out). B is told to stop, out of the zone, and A's next autonomous path keeps
    C_FAST."""
    core = _committed_pair(22.0, VMAX, 7.0, 6.0)
    a, b = core._cars["A"], core._cars["B"]
    assert core._committed(a) and core._committed(b)
    assert not core._stops_short(a) and core._stops_short(b)
    a_path = core.table.get("A").points  # type: ignore[union-attr]
    assert paths.zone_entry_time(a_path, ZONE) > paths.zone_entry_time(
        core.table.get("B").points,  # type: ignore[union-attr]
        ZONE,
    )  # the later arriver, which the paper's rule alone would stop
    out = core._give_way_to(0.0, a, None)
    assert ("ModeCommand", Mode.C_SLOW) in sent(out, "B")
    b_stop = core.table.get("B").points  # type: ignore[union-attr]
    assert b.held_short and _front_out_of_zone(b_stop, NORTH)
    a.x += 0.1 * VMAX
    nxt = straight((a.x, a.y), EAST, VMAX, 0.1)
    core.on_message(0.1, message(AutonomousPath, "A", nxt, VMAX, EAST, Mode.C_FAST, 2), "rsu-1")
    assert core.mode_of("A") == Mode.C_FAST
    assert no_conflict_within(core, 0.1, config().t_collision_s) == []


# -- cause 10: a plan that jumps earlier ---------------------------------------------------


@pytest.mark.parametrize("off_path_m", [0.0, 5.0])
def test_cause10_a_c_fast_car_whose_plan_jumped_earlier_keeps_its_path(
    off_path_m: float,
) -> None:
    """A (C_FAST) was sent a path retimed behind a car ahead: it enters the zone at 7 s.
    That car has gone; B (C_FAST) was promoted into the gap A's path left. A's next
    autonomous path runs free: its new plan would reach the zone 0.3 s after B, so A,
    the later arriver, would yield (demand experiment, slot, 600 veh/h, seed 1: there
    both were committed by then, and the box locked). A keeps the path it drives,
    resent, and B its way. A car that is not where its last path puts it (5 m off)
    does not drive it and keeps nothing: it yields."""
    cfg = config()
    core = RsuCore(cfg, listen_s=0.0)
    x0, v_old = -3.5 - 29.2, 29.2 / 7.0
    old = straight((x0, CROSS[1]), EAST, v_old, 0.0)
    old_cp = CoordinatedPath(Header("rsu-1", 1, 0), "A", Mode.C_FAST, old, np.full(120, v_old))
    car_a = rsu_core._Car("A", mode=Mode.C_FAST, x=x0, y=CROSS[1], heading=EAST, speed=v_old)
    car_a.last_cp = old_cp
    core._cars["A"] = car_a
    core.table.update("A", old_cp.points, 0.0)
    assert core.table.get("A").points is old_cp.points  # type: ignore[union-attr]
    here = x0 + off_path_m
    free = message(
        AutonomousPath, "A", straight((here, CROSS[1]), EAST, VMAX, 0.0), v_old, EAST, Mode.C_FAST
    )
    new = VelocityManager(cfg).plan("A", free, Mode.C_FAST, 0.0, core.table)
    new_entry = paths.zone_entry_time(new.points, ZONE)
    assert new_entry < paths.zone_entry_time(old, ZONE) - cfg.headway_s
    d = 3.5 + (new_entry - 0.3) * VMAX  # B's centre enters the zone 0.3 s before A's plan
    car_b = rsu_core._Car("B", mode=Mode.C_FAST, x=CROSS[0], y=-d, heading=NORTH, speed=VMAX)
    car_b.autonomous = message(
        AutonomousPath, "B", straight((CROSS[0], -d), NORTH, VMAX, 0.0), VMAX, NORTH
    )
    core._cars["B"] = car_b
    core.table.update("B", straight((CROSS[0], -d), NORTH, VMAX, 0.0), 0.0)
    assert core.table.naive_conflicts("A", old, 0.0, cfg.t_free_s) == []  # A's path was clear
    car_a.x = here
    free = message(
        AutonomousPath, "A", straight((here, CROSS[1]), EAST, VMAX, 0.0), v_old, EAST, Mode.C_FAST
    )
    out = core.on_message(0.0, free, "rsu-1")
    assert core.mode_of("B") == Mode.C_FAST
    if off_path_m == 0.0:
        assert core.mode_of("A") == Mode.C_FAST
        (cp,) = [o.message for o in out if o.vehicle == "A"]
        assert isinstance(cp, CoordinatedPath) and np.array_equal(cp.points, old)
        assert core.counters["reservation_kept"] == 1
    else:
        assert core.mode_of("A") == Mode.C_SLOW
        assert core.counters["reservation_kept"] == 0
    assert no_conflict_within(core, 0.0, cfg.t_collision_s) == []


@pytest.mark.parametrize("v", [11.0, 12.3, VMAX])
def test_cause9_a_stop_is_reserved_where_the_car_will_stand_after_its_reaction(v: float) -> None:
    """A (C_FAST at ``v``, front 12 m from the zone: it cannot keep out even braking at
    the firm factor) is told to stop. Its reserved stop (what every other car is planned
    around) runs on ``REACTION_S`` at ``v`` before the firm braking, and the re-plans of
    the next 0.3 s, the car still at ``v`` (it has not reacted yet), keep that stop point:
    the table shows where it will stand (demand experiment, slot, 400 veh/h, seed 3: a
    stop reserved 0.7 m short of the zone ended in it, where a crossing car planned
    through the empty zone hit it)."""
    cfg = config()
    core = RsuCore(cfg, listen_s=0.0)
    x0 = -3.5 - 12.0 - 2.25
    path = straight((x0, CROSS[1]), EAST, v, 0.0)
    car = rsu_core._Car("A", mode=Mode.C_FAST, x=x0, y=CROSS[1], heading=EAST, speed=v)
    car.autonomous = message(AutonomousPath, "A", path, v, EAST, Mode.C_FAST)
    core._cars["A"] = car
    core.table.update("A", path, 0.0)
    core._apply(0.0, car, RsuEvent.CONFLICT, car.autonomous, None)
    assert core.mode_of("A") == Mode.C_SLOW and not car.held_short
    firm = v * v / (2.0 * velocity.FIRM_STOP_FACTOR * cfg.decel_comfort_mps2)
    comfortable = v * v / (2.0 * cfg.decel_comfort_mps2)
    expected = x0 + min(firm + v * velocity.REACTION_S, comfortable)
    stops = [float(core.table.get("A").points[-1, 0])]  # type: ignore[union-attr]
    assert math.isclose(stops[0], expected, abs_tol=0.05)
    car.changes = rsu_core.MAX_MODE_CHANGES  # the dwell keeps it C_SLOW (nothing else does)
    for k in (1, 2, 3):
        now = 0.1 * k
        car.x = x0 + v * now  # not braking yet
        pts = straight((car.x, CROSS[1]), EAST, v, now)
        core.on_message(
            now, message(AutonomousPath, "A", pts, v, EAST, Mode.C_SLOW, k + 1), "rsu-1"
        )
        stops.append(float(core.table.get("A").points[-1, 0]))  # type: ignore[union-attr]
    assert max(stops) - min(stops) <= 0.05, stops


def left_turn(y0: float, v: float, t0: float) -> np.ndarray:
    """North on x = 1.75 from y = ``y0`` to the zone's edge, a left turn of radius 5.25 m
    about the zone's corner (-3.5, -3.5), then west on y = 1.75; at a constant ``v``."""
    radius = 5.25
    approach = -3.5 - y0
    arc = radius * math.pi / 2
    s = np.linspace(0.0, v * 10.0, 120)
    x, y = np.empty_like(s), np.empty_like(s)
    on_in = s <= approach
    x[on_in], y[on_in] = 1.75, y0 + s[on_in]
    on_arc = (s > approach) & (s <= approach + arc)
    th = (s[on_arc] - approach) / radius
    x[on_arc], y[on_arc] = -3.5 + radius * np.cos(th), -3.5 + radius * np.sin(th)
    out = s > approach + arc
    x[out], y[out] = -3.5 - (s[out] - approach - arc), 1.75
    return np.column_stack([x, y, t0 + s / v])


def _turn_pair(s_gap: float, s_v: float, l_y: float, l_v: float) -> RsuCore:
    """S southbound straight on, its front ``s_gap`` [m] from the zone at ``s_v``, and L a
    left turner from the south (:func:`left_turn`) at y = ``l_y`` at ``l_v``; both
    ``C_FAST`` on their own paths."""
    core = RsuCore(config(), listen_s=0.0)
    s_path = straight((-1.75, 3.5 + s_gap + 2.25), -NORTH, s_v, 0.0)
    l_path = left_turn(l_y, l_v, 0.0)
    for vid, pts, v, heading in (("S", s_path, s_v, -NORTH), ("L", l_path, l_v, NORTH)):
        x, y = float(pts[0, 0]), float(pts[0, 1])
        car = rsu_core._Car(vid, mode=Mode.C_FAST, x=x, y=y, heading=heading, speed=v)
        car.autonomous = message(AutonomousPath, vid, pts, v, heading, Mode.C_FAST)
        core._cars[vid] = car
        core.table.update(vid, pts, 0.0)
    return core


def test_cause9_of_two_that_cannot_stay_out_the_one_whose_stop_clears_yields() -> None:
    """L, a left turner from the south, has its nose in the zone at 2.2 m/s; S, southbound
    straight on, is 3.75 m from it at 4.65 m/s. Both are C_FAST and neither can keep out
    of the zone any more, even braking hard. S arrives later, so the paper's rule stops
    S, and S's stop leaves its nose in the zone, where L's turn sweeps (demand
    experiment, turning mix, paper, 600 veh/h, seed 1: they touched). L's stop stands
    clear of S's lane, so L yields and S drives on."""
    core = _turn_pair(3.75, 4.65, -4.2, 2.2)
    s, lt = core._cars["S"], core._cars["L"]
    s_path = core.table.get("S").points  # type: ignore[union-attr]
    l_path = core.table.get("L").points  # type: ignore[union-attr]
    assert core._committed(s) and core._committed(lt)
    assert not core._stops_short(s) and not core._stops_short(lt)
    assert paths.zone_entry_time(s_path, ZONE) > paths.zone_entry_time(l_path, ZONE)
    assert not core._stop_clears(0.0, s, lt, l_path)  # S's stop ends in L's sweep
    assert core._stop_clears(0.0, lt, s, s_path)
    assert core._yields(0.0, lt, l_path, s) and not core._yields(0.0, s, s_path, lt)
    out = core._give_way_to(0.0, s, None)
    assert ("ModeCommand", Mode.C_SLOW) in sent(out, "L")
    assert core._stop_clears(0.0, lt, s, s_path)  # the stop it was sent, now its entry
    assert core.mode_of("S") == Mode.C_FAST


@settings(max_examples=150, deadline=None)
@given(
    s_gap=st.floats(0.0, 25.0),
    s_v=st.floats(1.0, VMAX),
    l_y=st.floats(-25.0, -3.6),
    l_v=st.floats(0.5, 10.0),
)
def test_cause9_the_car_that_yields_stands_clear_when_either_can(
    s_gap: float, s_v: float, l_y: float, l_v: float
) -> None:
    """Whatever their speeds and distances, of a left turner and a straight car crossing its
    turn, both committed: exactly one yields; one that can still keep out of the zone
    braking hard when either can; else one whose stop stands clear of the other's way
    when either's does."""
    core = _turn_pair(s_gap, s_v, l_y, l_v)
    s, lt = core._cars["S"], core._cars["L"]
    s_path = core.table.get("S").points  # type: ignore[union-attr]
    l_path = core.table.get("L").points  # type: ignore[union-attr]
    assume(core._committed(s) and core._committed(lt))
    s_yields = core._yields(0.0, s, s_path, lt)
    assert s_yields != core._yields(0.0, lt, l_path, s)
    yielder, keeper, keeper_path = (s, lt, l_path) if s_yields else (lt, s, s_path)
    if core._stops_short(s) or core._stops_short(lt):
        assert core._stops_short(yielder)
        return
    s_clear = core._stop_clears(0.0, s, lt, l_path)
    l_clear = core._stop_clears(0.0, lt, s, s_path)
    if s_clear or l_clear:
        assert core._stop_clears(0.0, yielder, keeper, keeper_path)


def _rests_at(y_rest: float, v: float, t0: float) -> np.ndarray:
    """Northbound on x = 1.75 at ``v``, braking at a constant rate to rest at ``y_rest``,
    then held: a path its own planner stopped (behind a body it senses)."""
    a = 1.9
    run = v * v / (2.0 * a)
    t_stop = v / a
    t = np.linspace(0.0, t_stop, 60)
    y = y_rest - run + v * t - 0.5 * a * t * t
    hold = np.linspace(t_stop, 10.0, 60)[1:]
    ys = np.concatenate([y, np.full(hold.shape, y_rest)])
    return np.column_stack([np.full(ys.shape, 1.75), ys, t0 + np.concatenate([t, hold])])


@pytest.mark.parametrize("standing", [True, False])
def test_cause10_a_car_is_not_let_rest_in_a_box_another_car_stands_in(standing: bool) -> None:
    """W, a left turner from the north, stands mid-turn in the zone (or crosses it at
    3 m/s). N, ``C_FAST`` from the south, sends a path its own planner ends at rest with
    its nose 2.3 m into the zone (W's body is in its turn). Standing, W would wait for N's
    nose and N for W's body, for good (demand experiment, turning mix, paper, 600 veh/h,
    seed 0): N, which can still stop short, is told to stop out of the zone. Behind a car
    that crosses, N's stop is only for a moment and it keeps its way."""
    core = RsuCore(config(), listen_s=0.0)
    w_v = 0.0 if standing else 3.0
    w_pts = held(-1.72, 1.33, 0.0) if standing else straight((-1.72, 1.33), -NORTH, w_v, 0.0)
    w = rsu_core._Car("W", mode=Mode.C_SLOW, x=-1.72, y=1.33, heading=-NORTH, speed=w_v)
    w.autonomous = message(AutonomousPath, "W", w_pts, w_v, -NORTH, Mode.C_SLOW)
    w.kind = "stop"
    core._cars["W"] = w
    core.table.update("W", w_pts, 0.0)
    n_pts = _rests_at(-3.43, 8.0, 0.0)
    y0 = float(n_pts[0, 1])
    n = rsu_core._Car("N", mode=Mode.C_FAST, x=1.75, y=y0, heading=NORTH, speed=8.0)
    core._cars["N"] = n
    core.table.update("N", n_pts, 0.0)
    core.on_message(0.0, message(AutonomousPath, "N", n_pts, 8.0, NORTH, Mode.C_FAST, 2), "rsu-1")
    if standing:
        assert core.mode_of("N") == Mode.C_SLOW
        assert _front_out_of_zone(core.table.get("N").points, NORTH)  # type: ignore[union-attr]
        assert core.counters["box_blocked"] >= 1
    else:
        assert core.mode_of("N") == Mode.C_FAST
        assert core.counters["box_blocked"] == 0


@settings(max_examples=100, deadline=None)
@given(
    w_x=st.floats(-3.0, 3.0),
    w_y=st.floats(-3.0, 3.0),
    w_heading=st.sampled_from([EAST, NORTH, WEST, -NORTH, 0.75 * math.pi, -0.25 * math.pi]),
    n_v=st.floats(1.0, VMAX),
    n_rest=st.floats(-5.7, -1.0),
)
@example(w_x=-0.5, w_y=-1.0, w_heading=NORTH, n_v=8.0, n_rest=-1.0)  # a C_FAST stop, 7 Dec
def test_cause10_no_car_that_can_stay_out_rests_in_a_box_one_stands_in(
    w_x: float, w_y: float, w_heading: float, n_v: float, n_rest: float
) -> None:
    """Wherever a car W stands in the zone and however fast N comes, ``C_FAST``, on a path
    its own planner ends at rest with its body in the zone: if N can still keep out of
    the zone braking hard, it is told to stop (``C_SLOW``, or a ``C_FAST`` plan that ends
    at rest: the velocity manager stops it behind W's body), and its stop keeps its front
    out of the zone (unless W waits for N's body, ``_held_by``). The second form was
    found 7 December (W at (-0.5, -1) facing north, N at 8 m/s: a plan resting 3.7 m
    short of the zone)."""
    core = RsuCore(config(), listen_s=0.0)
    w = rsu_core._Car("W", mode=Mode.C_SLOW, x=w_x, y=w_y, heading=w_heading, speed=0.0)
    w_pts = held(w_x, w_y, 0.0)
    w.autonomous = message(AutonomousPath, "W", w_pts, 0.0, w_heading, Mode.C_SLOW)
    w.kind = "stop"
    core._cars["W"] = w
    core.table.update("W", w_pts, 0.0)
    n_pts = _rests_at(n_rest, n_v, 0.0)
    n = rsu_core._Car("N", mode=Mode.C_FAST, x=1.75, y=float(n_pts[0, 1]), heading=NORTH, speed=n_v)
    core._cars["N"] = n
    core.table.update("N", n_pts, 0.0)
    assume(not core._held_by(w, w_pts, n))
    assume(n_rest + 2.25 > -3.5 + paths.BODY_TOUCH_M + 1e-3)  # its body truly in the zone
    # N's own planner stops it short of W's body, with room to pass
    w_body = footprint(w_x, w_y, w_heading, 4.5 + 0.5, 1.8 + 0.5)
    assume(not convex_overlap(w_body, footprint(1.75, n_rest, NORTH, 4.5, 1.8)))
    gap = -3.5 - (float(n_pts[0, 1]) + 2.25)  # its front from the zone
    hard = velocity.HARD_STOP_FACTOR * config().decel_comfort_mps2
    short = gap > 0.0 and n_v * n_v <= 2.0 * hard * (gap - n_v * velocity.REACTION_S) - 1e-6
    core.on_message(0.0, message(AutonomousPath, "N", n_pts, n_v, NORTH, Mode.C_FAST, 2), "rsu-1")
    if short:
        entry = core.table.get("N")
        assert entry is not None and _front_out_of_zone(entry.points, NORTH)
        assert core.mode_of("N") == Mode.C_SLOW or paths.ends_at_rest(entry.points)


@pytest.mark.parametrize("held_by_rsu", [True, False])
def test_cause10_a_car_is_released_past_a_body_this_rsu_holds(held_by_rsu: bool) -> None:
    """B, C_SLOW, waits south of the zone; W stands in the zone beside B's way, centres
    2.6 m apart (inside the point rule's 2.8 m), bodies 0.8 m apart (demand experiment,
    turning mix, slot, 600 veh/h, seed 0: two opposing left turners, one held at the
    zone's edge; the other's turn passed its body 0.15-0.25 m clear, and the point rule
    held both, for good). W held by this RSU's stop moves only when the RSU releases it,
    which it judges against B's new path: B goes, and W stays held. W standing on its
    own (``AUTO``) may move at any time: B waits."""
    cfg = config(Policy.SLOT)
    core = RsuCore(cfg, listen_s=0.0)
    wx = 1.75 - 2.6
    w_pts = held(wx, 0.0, 0.0)
    if held_by_rsu:
        w = rsu_core._Car("W", mode=Mode.C_SLOW, x=wx, y=0.0, heading=-NORTH, kind="stop")
        w.autonomous = message(AutonomousPath, "W", w_pts, 0.0, -NORTH, Mode.C_SLOW)
        core._cars["W"] = w
        core.table.update("W", w_pts, 0.0)
    else:
        core.on_message(0.0, message(FuturePath, "W", w_pts, 0.0, -NORTH))
    b_pts = straight((1.75, -6.0), NORTH, 3.0, 0.0)
    assert core.table.naive_conflicts("B", b_pts, 0.0, cfg.t_free_s) != []  # the point rule
    b = rsu_core._Car("B", mode=Mode.C_SLOW, x=1.75, y=-6.0, heading=NORTH, kind="stop")
    core._cars["B"] = b
    core.table.update("B", held(1.75, -6.0, 0.0), 0.0)
    core.on_message(0.0, message(AutonomousPath, "B", b_pts, 0.0, NORTH, Mode.C_SLOW), "rsu-1")
    assert (core.mode_of("B") != Mode.C_SLOW) == held_by_rsu
    if held_by_rsu:  # W, whose way now meets B's new path, stays held
        w_own = straight((wx, 0.0), -NORTH, 2.0, 0.1)
        core.on_message(
            0.1, message(AutonomousPath, "W", w_own, 0.0, -NORTH, Mode.C_SLOW, 2), "rsu-1"
        )
        assert core.mode_of("W") == Mode.C_SLOW


@settings(max_examples=100, deadline=None)
@given(
    wx=st.floats(-4.0, 4.0),
    wy=st.floats(-4.0, 4.0),
    w_heading=st.floats(-math.pi, math.pi),
    b_v=st.floats(0.5, VMAX),
)
@example(wx=-1.0, wy=-4.0, w_heading=0.0, b_v=0.5)  # found 7 Dec: 0.06 m, beyond the point rule
def test_cause10_no_release_past_a_held_body_touches_it(
    wx: float, wy: float, w_heading: float, b_v: float
) -> None:
    """Wherever this RSU holds W standing, B (C_SLOW, south of the zone) is released or
    promoted only onto a path whose body keeps clear of W's (``STUCK_PASS_M``)."""
    cfg = config(Policy.SLOT)
    core = RsuCore(cfg, listen_s=0.0)
    w_pts = held(wx, wy, 0.0)
    w = rsu_core._Car("W", mode=Mode.C_SLOW, x=wx, y=wy, heading=w_heading, kind="stop")
    w.autonomous = message(AutonomousPath, "W", w_pts, 0.0, w_heading, Mode.C_SLOW)
    core._cars["W"] = w
    core.table.update("W", w_pts, 0.0)
    b_pts = straight((1.75, -12.0), NORTH, b_v, 0.0)
    b = rsu_core._Car("B", mode=Mode.C_SLOW, x=1.75, y=-12.0, heading=NORTH, kind="stop")
    core._cars["B"] = b
    core.table.update("B", held(1.75, -12.0, 0.0), 0.0)
    core.on_message(0.0, message(AutonomousPath, "B", b_pts, 0.0, NORTH, Mode.C_SLOW), "rsu-1")
    if core.mode_of("B") == Mode.C_SLOW:
        return
    entry = core.table.get("B")
    pts = b_pts if entry is None else entry.points
    grow = rsu_core.STUCK_PASS_M - 1e-6
    w_body = footprint(wx, wy, w_heading, 4.5 + grow, 1.8 + grow)
    for x, y in pts[:, :2]:
        assert not convex_overlap(
            w_body, footprint(float(x), float(y), NORTH, 4.5 + grow, 1.8 + grow)
        )


def _standing_pair(
    t_theta: float, t_v: float, e_nose_in: float, e_mode: Mode
) -> tuple[RsuCore, rsu_core._Car, rsu_core._Car]:
    """T, a left turner from the south (:func:`left_turn`), ``t_theta`` [rad] into its
    turn, in the zone, at ``t_v`` [m/s] (0: standing) on its own path; E eastbound from
    the west, standing with its nose ``e_nose_in`` [m] into the zone and its centre out,
    in ``e_mode``."""
    core = RsuCore(config(Policy.SLOT), listen_s=0.0)
    radius = 5.25
    tx, ty = -3.5 + radius * math.cos(t_theta), -3.5 + radius * math.sin(t_theta)
    heading = t_theta + math.pi / 2
    arc = left_turn(-3.5 - 1e-6, max(t_v, 0.5), 0.0)
    start = int(np.argmin(np.hypot(arc[:, 0] - tx, arc[:, 1] - ty)))
    t_pts = held(tx, ty, 0.0) if t_v == 0.0 else arc[start:] - [0.0, 0.0, arc[start, 2]]
    t = rsu_core._Car("T", mode=Mode.AUTO, x=tx, y=ty, heading=heading, speed=t_v)
    t.autonomous = message(AutonomousPath, "T", t_pts, t_v, heading, Mode.AUTO)
    ex = -3.5 + e_nose_in - 2.25
    e_pts = held(ex, -1.75, 0.0)
    e = rsu_core._Car("E", mode=e_mode, x=ex, y=-1.75, heading=EAST, speed=0.0)
    e.autonomous = message(AutonomousPath, "E", e_pts, 0.0, EAST, e_mode)
    if e_mode == Mode.C_SLOW:
        e.kind = "stop"
    for car, pts in ((t, t_pts), (e, e_pts)):
        core._cars[car.vehicle] = car
        core.table.update(car.vehicle, pts, 0.0)
    return core, t, e


@pytest.mark.parametrize("t_v", [0.0, 0.3])
def test_cause11_a_car_standing_in_the_zone_does_not_stop_short(t_v: float) -> None:
    """A car whose front is in the zone cannot keep its body out of it, standing or
    moving off: it does not "stop short" (standing, it did, and so yielded to any car
    that could not: demand experiment, turning, slot, 800 veh/h, seed 8)."""
    core, t, e = _standing_pair(0.6, t_v, 0.5, Mode.AUTO)
    assert core._committed(t) and core._committed(e)
    assert not core._stops_short(t) and not core._stops_short(e)


@settings(max_examples=120, deadline=None)
@given(
    t_theta=st.floats(0.25, 1.3),
    t_v=st.sampled_from([0.0, 0.05, 0.3, 1.0]),
    e_nose_in=st.floats(0.01, 2.2),
    e_mode=st.sampled_from([Mode.AUTO, Mode.C_SLOW, Mode.C_FAST]),
)
def test_cause11_a_car_in_the_zone_never_yields_to_one_at_its_edge(
    t_theta: float, t_v: float, e_nose_in: float, e_mode: Mode
) -> None:
    """Wherever T stands or moves off in its turn and however far E's nose is in: when
    neither can keep out of the zone and neither's stop settles it (both clear the
    other's way, or neither does), E, whose centre is outside, yields, and T does not.
    Before, a C_SLOW E, waiting for T's body, kept the way, and T was re-stopped each
    time it moved off (that run, with a front-gap rule since dropped: 15 of 48 cars never
    through)."""
    core, t, e = _standing_pair(t_theta, t_v, e_nose_in, e_mode)
    t_path = core.table.get("T").points  # type: ignore[union-attr]
    e_path = core.table.get("E").points  # type: ignore[union-attr]
    assume(not core._ahead_in_lane(e, t, t_path) and not core._ahead_in_lane(t, e, e_path))
    assume(not core._stops_short(e))  # a C_SLOW E held short would rightly keep its way
    assert core._committed(t) and core._committed(e) and not core._stops_short(t)
    t_clear = core._stop_clears(0.0, t, e, e_path)
    assume(t_clear == core._stop_clears(0.0, e, t, t_path))
    assert core._yields(0.0, e, e_path, t)
    assert not core._yields(0.0, t, t_path, e)
