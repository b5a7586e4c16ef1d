"""Velocity manager (paper and slot policies) and the path helpers it stands on."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from protocol.messages import AutonomousPath, FloatArray, Header, Mode, VehicleLimits
from services.model.types import Policy
from services.rsu import paths, velocity
from services.rsu.config import RsuConfig
from services.rsu.reservation import ReservationTable
from services.rsu.velocity import VelocityManager

ZONE = np.array([[-3.5, -3.5], [3.5, -3.5], [3.5, 3.5], [-3.5, 3.5]])
VMAX = 50 / 3.6


def config(policy: Policy = Policy.PAPER) -> RsuConfig:
    return RsuConfig("rsu-1", "x0", (0.0, 0.0), ZONE, policy=policy)


def straight(
    start: tuple[float, float],
    heading: float,
    v: float,
    t0: float,
    n: int = 120,
    horizon: float = 10,
) -> np.ndarray:
    t = t0 + np.linspace(0.0, horizon, n)
    s = v * (t - t0)
    return np.column_stack([start[0] + s * math.cos(heading), start[1] + s * math.sin(heading), t])


def ap(vehicle: str, points: np.ndarray, v: float, heading: float) -> AutonomousPath:
    header = Header(vehicle, 1, round(float(points[0, 2]) * 1e6))
    x, y = float(points[0, 0]), float(points[0, 1])
    return AutonomousPath(header, x, y, v, heading, 4.5, 1.8, Mode.C_SLOW, points)


def table_with(vehicle: str, points: np.ndarray, now: float = 0.0) -> ReservationTable:
    table = ReservationTable(2.8, 1.0, 0.5)
    table.update(vehicle, points, now)
    return table


# The crafted crossing: A eastbound on y = -1.75, B northbound on x = +1.75; their paths
# cross at (1.75, -1.75). A passes it at 4 s.
CROSS = (1.75, -1.75)


def car_a(v: float = VMAX, at: float = 4.0) -> np.ndarray:
    return straight((CROSS[0] - at * v, CROSS[1]), 0.0, v, 0.0)


def car_b(v: float, at: float) -> AutonomousPath:
    return ap("B", straight((CROSS[0], CROSS[1] - at * v), math.pi / 2, v, 0.0), v, math.pi / 2)


# -- paths ------------------------------------------------------------------------------------


def test_retime_inverts_segment_speeds() -> None:
    rng = np.random.default_rng(1)
    xy = np.cumsum(rng.uniform(0.2, 2.0, size=(30, 2)), axis=0)
    t = np.cumsum(rng.uniform(0.05, 0.3, size=30)) + 7.0
    pts = np.column_stack([xy, t])
    speeds = paths.segment_speeds(pts, 3.0)
    assert speeds[0] == 3.0
    back = paths.retime(pts, speeds, float(t[0]))
    np.testing.assert_allclose(back, pts, rtol=1e-12, atol=1e-9)


def test_retime_eq1_and_unreachable_points() -> None:
    pts = np.array([[0.0, 0.0, 0.0], [3.0, 4.0, 9.0], [3.0, 4.0, 9.0], [6.0, 8.0, 9.0]])
    out = paths.retime(pts, np.array([1.0, 5.0, 0.0, 0.0]), 2.0)
    assert out[:3, 2].tolist() == [2.0, 3.0, 3.0]  # 5 m at 5 m/s; a zero-length segment
    assert out[3, 2] == math.inf  # 5 m at 0 m/s: never
    np.testing.assert_array_equal(out[:, :2], pts[:, :2])
    assert paths.arc_length(pts).tolist() == [0.0, 5.0, 5.0, 10.0]


def test_zone_helpers() -> None:
    zone = paths.convex_polygon(ZONE[::-1])  # clockwise works too
    inside = paths.inside_convex(np.array([[0, 0], [3.5, 3.5], [3.6, 0], [-10, 0]]), zone)
    assert inside.tolist() == [True, True, False, False]
    east = straight((-20.0, -1.75), 0.0, 10.0, 0.0, n=41, horizon=4.0)  # 1 m apart
    span = paths.zone_span(east, zone)
    assert span is not None
    assert east[span[0], 0] == pytest.approx(-3.0) and east[span[1], 0] == pytest.approx(4.0)
    assert paths.zone_entry_time(east, zone) == pytest.approx(1.7)
    assert paths.zone_span(east + np.array([0.0, 10.0, 0.0]), zone) is None
    assert paths.zone_entry_time(east + np.array([0.0, 10.0, 0.0]), zone) == math.inf
    assert paths.polygon_centroid(zone + 5.0) == pytest.approx((5.0, 5.0))


_coord = st.floats(-50.0, 50.0, allow_nan=False)


@settings(max_examples=60, deadline=None)
@given(
    line=st.lists(st.tuples(_coord, _coord), min_size=1, max_size=12),
    points=st.lists(st.tuples(_coord, _coord), min_size=1, max_size=8),
)
def test_project_many_is_project_of_each_point_and_the_closest(
    line: list[tuple[float, float]], points: list[tuple[float, float]]
) -> None:
    """Batching projections (issue 14) changes no number: each row alone gives the same
    bits, and the answer is the closest point of the polyline (no vertex is closer)."""
    xy = np.array(line, dtype=np.float64)
    q = np.array(points, dtype=np.float64)
    s, dist, index = paths.project_many(xy, q)
    for k, (x, y) in enumerate(points):
        assert paths.project(xy, x, y) == (s[k], dist[k], index[k])
        nearest_vertex = float(np.min(np.hypot(xy[:, 0] - x, xy[:, 1] - y)))
        assert 0.0 <= dist[k] <= nearest_vertex + 1e-9
        assert 0.0 <= s[k] <= float(np.sum(np.hypot(*np.diff(xy, axis=0).T))) + 1e-9


@pytest.mark.parametrize(
    "bad",
    [
        [[0, 0], [1, 0]],
        [[0, 0], [2, 0], [1, 1], [2, 2], [0, 2]],  # not convex
        [[0, 0], [1, 1], [2, 2]],  # no area
        [[0, 0], [1, 0], [math.inf, 1]],
    ],
)
def test_bad_zone_raises(bad: list[list[float]]) -> None:
    with pytest.raises(ValueError):
        paths.convex_polygon(bad)


def test_leaving_and_approaching() -> None:
    zone = paths.convex_polygon(ZONE)
    c = (0.0, 0.0)
    assert not paths.is_leaving(-10.0, -1.75, 0.0, zone, c)  # before the zone, eastbound
    assert not paths.is_leaving(2.0, -1.75, 0.0, zone, c)  # inside
    assert paths.is_leaving(5.0, -1.75, 0.0, zone, c)  # past it, moving away
    assert not paths.is_leaving(5.0, -1.75, math.pi, zone, c)  # westbound: approaching
    east = straight((-100.0, -1.75), 0.0, VMAX, 0.0)
    assert paths.is_approaching(-100.0, -1.75, east, zone, c, 150.0, 0.0, 10.0)
    # entering beyond the horizon, but ending short of the zone (a cautious plan)
    cautious = straight((-60.0, -1.75), 0.0, 5.0, 0.0)  # ends at x = -10: 10 m from the centre
    assert paths.is_approaching(-60.0, -1.75, cautious, zone, c, 150.0, 0.0, 6.0)
    # entering beyond the horizon and ending far from the zone: not (yet) approaching
    assert not paths.is_approaching(-100.0, -1.75, east, zone, c, 150.0, 0.0, 6.0)
    far = straight((-400.0, -1.75), 0.0, VMAX, 0.0)  # ends 261 m short, though closer
    assert not paths.is_approaching(-400.0, -1.75, far, zone, c, 500.0, 0.0, 10.0)
    edge = paths.APPROACH_END_M + math.hypot(3.5, 3.5)  # beyond the zone's circumradius
    for margin, expected in ((0.5, True), (-0.5, False)):
        ends_at = straight((-60.0, 0.0), 0.0, (60.0 - edge + margin) / 10.0, 0.0)
        assert paths.is_approaching(-60.0, 0.0, ends_at, zone, c, 150.0, 0.0, 6.0) is expected
    away = straight((10.0, -1.75), 0.0, VMAX, 0.0)
    assert not paths.is_approaching(10.0, -1.75, away, zone, c, 150.0, 0.0, 10.0)
    assert not paths.is_approaching(-100.0, -1.75, east, zone, c, 90.0, 0.0, 10.0)  # coverage
    assert not paths.is_approaching(
        0.0, -1.75, east + np.array([100.0, 0.0, 0.0]), zone, c, 150.0, 0.0, 10.0
    )


# -- paper policy ----------------------------------------------------------------------------


def test_paper_slow_is_an_honest_comfortable_stop_with_zero_speeds() -> None:
    cfg = config()
    vm = VelocityManager(cfg)
    path = car_b(10.0, 6.0).points
    plan = vm.plan("B", ap("B", path, 10.0, math.pi / 2), Mode.C_SLOW, 0.0, ReservationTable())
    assert plan.kind == "stop"
    assert np.all(plan.speeds == 0.0) and plan.speeds.shape[0] == plan.points.shape[0]
    stop_s = 10.0**2 / (2 * cfg.decel_comfort_mps2)  # 25 m
    y = plan.points[:, 1]
    assert y.max() == pytest.approx(path[0, 1] + stop_s)
    moving = plan.points[plan.points[:, 1] < y.max() - 1e-9]
    # positions are the autonomous path's (a prefix of it), then the stop point
    np.testing.assert_allclose(moving[:, :2], path[: moving.shape[0], :2])
    # times: the braking curve s(t) = v t - b t^2 / 2, stop at t = v / b = 5 s
    s = moving[:, 1] - path[0, 1]
    expected_t = (10.0 - np.sqrt(10.0**2 - 2 * cfg.decel_comfort_mps2 * s)) / 2.0
    np.testing.assert_allclose(moving[:, 2], expected_t, atol=1e-9)
    t_stop = plan.points[moving.shape[0], 2]
    assert t_stop == pytest.approx(5.0)
    # then it holds until the horizon, points at most hold_step apart
    held = plan.points[moving.shape[0] :]
    assert np.all(held[:, 1] == y.max())
    assert held[-1, 2] == pytest.approx(cfg.t_free_s)
    assert np.diff(held[:, 2]).max() <= cfg.hold_step_s + 1e-9
    assert np.all(np.diff(plan.points[:, 2]) >= 0.0)


def test_paper_slow_of_a_car_at_rest_holds_where_it_is() -> None:
    vm = VelocityManager(config())
    path = straight((1.75, -30.0), math.pi / 2, 0.0, 3.0)  # all points at one place
    plan = vm.plan("B", ap("B", path, 0.0, math.pi / 2), Mode.C_SLOW, 3.0, ReservationTable())
    assert np.all(plan.points[:, :2] == [1.75, -30.0])
    assert plan.points[0, 2] == 3.0 and plan.points[-1, 2] == pytest.approx(13.0)
    assert np.all(plan.speeds == 0.0)


def test_paper_fast_is_vmax_through_the_zone_then_own_speeds() -> None:
    cfg = config()
    vm = VelocityManager(cfg)
    # B at 5 m/s, 40 m before the crossing point; its own plan: 8 m/s
    path = straight((1.75, -41.75), math.pi / 2, 8.0, 0.0)
    plan = vm.plan("B", ap("B", path, 5.0, math.pi / 2), Mode.C_FAST, 0.0, ReservationTable())
    assert plan.kind == "fast"
    np.testing.assert_allclose(plan.points[:, :2], path[:, :2])  # same positions
    y = plan.points[:, 1]
    exit_y = y[np.flatnonzero(y > 3.5)[0]]
    through = y <= exit_y + 4.5
    assert np.all(plan.speeds[through] == pytest.approx(VMAX))
    assert np.all(plan.speeds[~through][1:] == pytest.approx(8.0))
    # honest times: accelerating at 1.5 m/s^2 from 5 m/s, not jumping to V_max
    s = y - y[0]
    t_acc = (-5.0 + np.sqrt(25.0 + 2 * 1.5 * s)) / 1.5
    early = s < 30.0  # before it must brake for the 8 m/s after the zone (at 34 m)
    np.testing.assert_allclose(plan.points[early, 2], t_acc[early], rtol=1e-6, atol=1e-6)
    assert plan.entry_time == pytest.approx(plan.points[np.flatnonzero(y >= -3.5)[0], 2])


def test_paper_fast_keeps_the_stop_at_the_end_of_an_autonomous_path() -> None:
    vm = VelocityManager(config())
    path = straight((1.75, -20.0), math.pi / 2, 5.0, 0.0, n=60, horizon=6.0)
    hold = np.column_stack([np.repeat(path[-1:, :2], 5, 0), path[-1, 2] + 1 + np.arange(5)])
    held = np.vstack([path, hold])
    plan = vm.plan("B", ap("B", held, 5.0, math.pi / 2), Mode.C_FAST, 0.0, ReservationTable())
    assert plan.speeds[-1] == 0.0
    assert np.all(plan.points[-1, :2] == path[-1, :2])
    assert plan.points[-1, 2] >= 10.0 - 1e-9  # held until the horizon
    assert np.all(np.isfinite(plan.points))


def test_plan_for_auto_is_refused() -> None:
    vm = VelocityManager(config())
    with pytest.raises(ValueError):
        vm.plan("B", car_b(VMAX, 4.5), Mode.AUTO, 0.0, ReservationTable())


# -- the crafted crossing, both policies -------------------------------------------------------


@pytest.mark.parametrize(("v_b", "gap"), [(VMAX, 0.5), (5.0, 1.5)])
def test_crossing_paper_stops_and_slot_delays_just_enough(v_b: float, gap: float) -> None:
    """B reaches the crossing ``gap`` s after A: a conflict at either speed."""
    table = table_with("A", car_a())
    b = car_b(v_b, 4.0 + gap)
    assert table.naive_conflicts("B", b.points, 0.0, 10.0), "the crafted case must conflict"

    paper = VelocityManager(config(Policy.PAPER)).plan("B", b, Mode.C_SLOW, 0.0, table)
    assert np.all(paper.speeds == 0.0)

    vm = VelocityManager(config(Policy.SLOT))
    slot = vm.plan("B", b, Mode.C_SLOW, 0.0, table)
    assert slot.kind == "slot"
    assert table.naive_conflicts("B", slot.points, 0.0, 10.0) == []
    # B does not stop: every target speed and every segment speed stays positive
    assert slot.speeds.min() > 1.0
    seg = paths.segment_speeds(slot.points, v_b)[1:]
    assert seg.min() > 1.0
    np.testing.assert_allclose(slot.points[:, :2], b.points[:, :2])  # same positions
    # later than it would have entered alone, by about what the headway needs, not more
    own_entry = paths.zone_entry_time(b.points, ZONE)
    assert slot.entry_time > own_entry
    assert slot.entry_time - own_entry < 2.0
    # and the earliest such slot with clearance (issue 12, cause 6): one search step
    # earlier comes within the release margins of a conflict
    cfg = config()
    margins = (cfg.release_margin_m, cfg.release_margin_s)
    assert table.naive_conflicts("B", slot.points, 0.0, 10.0, (), *margins) == []
    earlier = _meet(vm, b, slot.entry_time - cfg.slot_step_s)
    assert earlier is not None
    assert table.naive_conflicts("B", earlier.points, 0.0, 10.0, (), *margins) != []


def _meet(vm: VelocityManager, path: AutonomousPath, target: float) -> velocity.SpeedPlan | None:
    """The slot search's inner step: the fastest profile entering the zone at ``target``."""
    tr = velocity._track(path, vm.limits_of(path), 0.0, 10.0)
    cap, entry = vm._fast_caps(tr)
    assert entry is not None
    env = velocity._envelope(tr.d, cap, 2.0)
    return vm._meet(tr, entry, env, cap, target)


def test_slot_stops_before_the_zone_when_the_wait_is_long() -> None:
    """A crawls through the crossing (1 m/s, there from 3 s to 9 s): B must stop and wait."""
    cfg = config(Policy.SLOT)
    slow_a = straight((CROSS[0] - 6.0, CROSS[1]), 0.0, 1.0, 0.0)
    table = table_with("A", slow_a)
    b = car_b(5.0, 3.0)  # 15 m before the crossing at 5 m/s
    plan = VelocityManager(cfg).plan("B", b, Mode.C_SLOW, 0.0, table)
    assert plan.kind == "slot_stop"
    assert table.naive_conflicts("B", plan.points, 0.0, 10.0) == []
    stopped = plan.points[plan.speeds == 0.0]
    assert stopped.shape[0] >= 2
    # stopped short of the zone by at least half a car and the gap
    assert stopped[:, 1].max() <= -3.5 - (4.5 / 2 + cfg.stop_gap_m) + 1e-9
    assert np.all(np.diff(plan.points[:, 2]) >= -1e-12)
    assert plan.entry_time > paths.zone_entry_time(b.points, ZONE)


def test_slot_falls_back_to_the_paper_stop_when_it_cannot_stop_in_time() -> None:
    """B is 12 m before the zone at V_max: it can neither stop nor find a gap."""
    table = ReservationTable()
    # a wall of cars crossing every 0.5 s for the whole horizon
    for i in range(24):
        table.update(f"A{i}", straight((CROSS[0] - 20.0 - 7 * i, CROSS[1]), 0.0, VMAX, 0.0), 0.0)
    b = car_b(VMAX, 1.0)
    plan = VelocityManager(config(Policy.SLOT)).plan("B", b, Mode.C_SLOW, 0.0, table)
    assert plan.kind == "slot_fallback"
    assert np.all(plan.speeds == 0.0)


def test_slot_for_a_car_already_in_the_zone_is_the_paper_stop() -> None:
    path = straight((1.75, -1.0), math.pi / 2, 5.0, 0.0)
    plan = VelocityManager(config(Policy.SLOT)).plan(
        "B", ap("B", path, 5.0, math.pi / 2), Mode.C_SLOW, 0.0, ReservationTable()
    )
    assert plan.kind == "slot_fallback" and np.all(plan.speeds == 0.0)


def test_slot_without_conflict_is_the_fastest_path() -> None:
    b = car_b(VMAX, 5.0)
    plan = VelocityManager(config(Policy.SLOT)).plan("B", b, Mode.C_SLOW, 0.0, ReservationTable())
    assert plan.kind == "slot"
    np.testing.assert_allclose(plan.points[:, 2], b.points[:, 2], atol=1e-6)


# -- each car's own limits, and curves ----------------------------------------------------------

TRUCK = VehicleLimits(8.0, 1.0, 1.5, 1.2)


def with_limits(path: AutonomousPath, limits: VehicleLimits | None) -> AutonomousPath:
    return dataclasses.replace(path, limits=limits)


def test_a_declared_top_speed_replaces_the_scenario_one() -> None:
    path = straight((1.75, -41.75), math.pi / 2, 8.0, 0.0)
    truck = with_limits(ap("B", path, 5.0, math.pi / 2), TRUCK)
    for policy, mode in ((Policy.PAPER, Mode.C_FAST), (Policy.SLOT, Mode.C_SLOW)):
        plan = VelocityManager(config(policy)).plan("B", truck, mode, 0.0, ReservationTable())
        assert plan.speeds.max() <= TRUCK.v_max + 1e-9
        seg = paths.segment_speeds(plan.points, 5.0)[1:]
        assert seg[np.isfinite(seg)].max() <= TRUCK.v_max + 1e-9
        # honest times: from 5 m/s at the truck's 1.0 m/s² (not the scenario's 1.5)
        y = plan.points[:, 1]
        s = y - y[0]
        early = s < (TRUCK.v_max**2 - 25.0) / (2 * TRUCK.accel)  # still accelerating
        t_acc = (-5.0 + np.sqrt(25.0 + 2 * TRUCK.accel * s)) / TRUCK.accel
        np.testing.assert_allclose(plan.points[early, 2], t_acc[early], rtol=1e-6, atol=1e-6)
        # and the zone entry it predicts follows: 3.5 m/s² more would have it 1 s+ early
        entry = paths.zone_entry_time(plan.points, ZONE)
        assert plan.entry_time == pytest.approx(entry)
        d_acc = (TRUCK.v_max**2 - 25.0) / (2 * TRUCK.accel)
        d_entry = -3.5 - y[0]
        expected = (TRUCK.v_max - 5.0) / TRUCK.accel + (d_entry - d_acc) / TRUCK.v_max
        assert entry == pytest.approx(expected, abs=0.05)


def test_a_declared_braking_replaces_the_scenario_one() -> None:
    path = car_b(10.0, 6.0)
    plan = VelocityManager(config()).plan(
        "B", with_limits(path, TRUCK), Mode.C_SLOW, 0.0, ReservationTable()
    )
    stop_s = 10.0**2 / (2 * TRUCK.decel)  # 33.3 m, not the scenario's 25 m
    assert plan.points[:, 1].max() == pytest.approx(path.points[0, 1] + stop_s)
    assert plan.points[-1, 2] >= 10.0 - 1e-9


def test_undeclared_limits_are_the_configuration() -> None:
    cfg = config()
    vm = VelocityManager(cfg)
    assert vm.limits_of(car_b(10.0, 6.0)) == VehicleLimits(
        cfg.v_max_mps, cfg.accel_mps2, cfg.decel_comfort_mps2, cfg.lat_accel_mps2
    )
    assert vm.limits_of(with_limits(car_b(10.0, 6.0), TRUCK)) is TRUCK


RADIUS = 6.0


def turning_path(v: float = 10.0, step: float = 0.84) -> FloatArray:
    """North on x = 1.75 up to y = -6, a right turn of radius 6 m, then east on y = 0;
    timed at a constant ``v`` (its own planner ignores the curve: the RSU must not)."""
    approach = 54.0
    arc = RADIUS * math.pi / 2
    s = np.arange(120) * step
    x = np.empty_like(s)
    y = np.empty_like(s)
    on_in = s <= approach
    x[on_in], y[on_in] = 1.75, -6.0 - approach + s[on_in]
    on_arc = (s > approach) & (s <= approach + arc)
    th = (s[on_arc] - approach) / RADIUS
    x[on_arc] = 1.75 + RADIUS - RADIUS * np.cos(th)
    y[on_arc] = -6.0 + RADIUS * np.sin(th)
    out = s > approach + arc
    x[out], y[out] = 1.75 + RADIUS + (s[out] - approach - arc), 0.0
    return np.column_stack([x, y, s / v])  # exact: the test's curvature is the true one


def menger_curvature(points: FloatArray) -> FloatArray:
    """Curvature [1/m] at each inner point from it and its two neighbours (0 at the ends)."""
    p = points[:, :2]
    a = np.hypot(*(p[1:-1] - p[:-2]).T)
    b = np.hypot(*(p[2:] - p[1:-1]).T)
    c = np.hypot(*(p[2:] - p[:-2]).T)
    u, w = p[1:-1] - p[:-2], p[2:] - p[:-2]
    area2 = np.abs(u[:, 0] * w[:, 1] - u[:, 1] * w[:, 0])
    k = np.zeros(p.shape[0])
    with np.errstate(divide="ignore", invalid="ignore"):
        k[1:-1] = np.where(a * b * c > 0, 2.0 * area2 / (a * b * c), 0.0)
    return k


@pytest.mark.parametrize(
    ("policy", "mode", "limits"),
    [
        (Policy.PAPER, Mode.C_FAST, None),
        (Policy.PAPER, Mode.C_FAST, TRUCK),
        (Policy.SLOT, Mode.C_SLOW, None),
        (Policy.SLOT, Mode.C_SLOW, TRUCK),
    ],
)
def test_speeds_in_a_curve_stay_under_the_lateral_limit(
    policy: Policy, mode: Mode, limits: VehicleLimits | None
) -> None:
    pts = turning_path()
    path = with_limits(ap("B", pts, 10.0, math.pi / 2), limits)
    vm = VelocityManager(config(policy))
    a_lat = vm.limits_of(path).lat_accel
    plan = vm.plan("B", path, mode, 0.0, ReservationTable())
    assert plan.kind in ("fast", "slot")
    np.testing.assert_allclose(plan.points[:, :2], pts[:, :2])  # the same positions
    # the path's own curvature, from its points: speed <= sqrt(a_lat * r) everywhere
    kappa = menger_curvature(plan.points)
    assert kappa.max() == pytest.approx(1.0 / RADIUS, rel=0.05)  # the test sees the turn
    cap = np.sqrt(a_lat / np.maximum(kappa, 1e-12))
    assert np.all(plan.speeds <= cap + 1e-9)
    # on the arc itself, against the true radius (target speeds and the timed profile)
    x, y = plan.points[:, 0], plan.points[:, 1]
    on_arc = (y > -6.0) & (x < 1.75 + RADIUS)
    assert on_arc.sum() >= 5
    limit = math.sqrt(a_lat * RADIUS)
    assert np.all(plan.speeds[on_arc] <= limit + 1e-9)
    seg = paths.segment_speeds(plan.points, 10.0)
    both = on_arc[1:] & on_arc[:-1]
    assert np.all(seg[1:][both] <= limit + 1e-9)
    # and it is the curve that slows it, not a stop: well above a crawl there
    assert plan.speeds[on_arc].min() >= 0.8 * limit
    assert plan.speeds.max() <= vm.limits_of(path).v_max + 1e-9


def test_curve_caps_ignore_the_wire_quantisation_on_straight_roads() -> None:
    for heading in (0.0, 0.3, math.pi / 4, 2.0):
        for step in (0.1, 0.5, 1.15):
            s = np.arange(200, dtype=np.float64) * step
            line = np.column_stack([s * math.cos(heading), s * math.sin(heading)])
            xy = np.asarray(np.round(line, 2), dtype=np.float64)  # as on the wire
            caps = paths.curve_caps(xy, paths.arc_length(np.column_stack([xy, s])), 2.0, VMAX)
            assert np.all(caps == VMAX), (heading, step)


@pytest.mark.parametrize("quantised", [False, True])
@pytest.mark.parametrize("radius", [3.0, 6.0, 20.0])
@pytest.mark.parametrize("step", [0.1, 0.5, 1.15])
def test_curve_caps_of_a_circle_are_its_radius_or_slower(
    radius: float, step: float, quantised: bool
) -> None:
    th = np.arange(0.0, math.pi, step / radius)
    xy = np.column_stack([radius * np.cos(th), radius * np.sin(th)])
    if quantised:
        xy = np.round(xy, 2)  # as on the wire: the radius the points describe wobbles
    s = paths.arc_length(np.column_stack([xy, th]))
    caps = paths.curve_caps(xy, s, 2.0, VMAX)
    true = math.sqrt(2.0 * radius)
    assert np.all(caps <= true * (1.03 if quantised else 1 + 1e-9))
    assert np.all(caps >= 0.9 * true)


@settings(max_examples=200, deadline=None)
@given(
    base=st.tuples(st.floats(-9.9e6, 9.9e6), st.floats(-9.9e6, 9.9e6)),
    others=st.lists(
        st.tuples(
            st.floats(-3.0, 3.0),  # along this car's path from the box's middle [m]
            st.floats(-2.0, 2.0),  # beyond the lane reach, sideways [m]
            st.sampled_from([-1.0, 1.0]),  # left or right of the path
            st.floats(0.5, 3.0),  # width [m]
            st.booleans(),  # the first point near, else the last
        ),
        min_size=1,
        max_size=8,
    ),
    both=st.booleans(),
)
def test_lane_prefilter_keeps_every_car_near_the_path(
    base: tuple[float, float],
    others: list[tuple[float, float, float, float, bool]],
    both: bool,
) -> None:
    """The lane searches' vectorised prefilter (float32 ends, issue 14) drops no car whose
    path's first (and, for ``stop_limit``, last) point is within its lane reach of the
    box around this car's path, even far from the origin where float32 rounds by up to a
    metre, and keeps none that the exact test puts beyond it by more than that rounding.
    Ends are placed near the reach's edge, where the rounding decides."""
    bx, by = base
    own = straight((bx - 3.0, by), 0.0, 1.0, 0.0, n=8, horizon=6.0)  # along y = by
    path = ap("Q", own, 1.0, 0.0)
    vm = VelocityManager(config())
    tr = velocity._track(path, vm.limits_of(path), 0.0, 10.0)
    table = ReservationTable(2.8, 1.0, 0.5)
    y_lo, y_hi = float(tr.xy[:, 1].min()), float(tr.xy[:, 1].max())
    placed = []
    for i, (along, beyond, side, width, first_near) in enumerate(others):
        lane = 0.5 * (1.8 + width) + 0.5
        edge = y_hi + lane + beyond if side > 0 else y_lo - lane - beyond
        near, away = (bx + along, edge), (bx + along, edge + side * (1.0 + abs(beyond)))
        ends = (near, near) if first_near else (away, near)
        pts = np.array([[*ends[0], 0.0], [*ends[1], 1.0]])
        table.update(f"o{i}", pts, 0.0, (4.5, width))
        placed.append((pts, lane))
    got = {e.vehicle for e, _ in velocity._near_lane("Q", tr, 0.0, table, (), both_ends=both)}
    x_lo, x_hi = float(tr.xy[:, 0].min()), float(tr.xy[:, 0].max())

    def gap(x: float, y: float) -> float:
        return math.hypot(max(x_lo - x, x - x_hi, 0.0), max(y_lo - y, y - y_hi, 0.0))

    rounding = 4.0 * 2.0**-24 * (abs(bx) + abs(by) + 16.0) + 1e-6
    for i, (pts, lane) in enumerate(placed):
        tested = pts if both else pts[:1]
        worst = max(gap(float(x), float(y)) for x, y, _ in tested)
        if worst <= lane:
            assert f"o{i}" in got
        elif worst > lane + rounding:
            assert f"o{i}" not in got


@settings(max_examples=200, deadline=None)
@given(
    steps=st.lists(
        st.tuples(
            st.sampled_from([0.0, 1e-9, 0.5, 2.0]),  # step length [m] (repeats, tiny ones)
            st.floats(-math.pi, math.pi),
        ),
        min_size=1,
        max_size=12,
    ),
    index=st.lists(st.integers(-3, 15), min_size=1, max_size=6),
)
def test_headings_at_is_heading_of_for_every_index(
    steps: list[tuple[float, float]], index: list[int]
) -> None:
    """The batched heading lookup of ``stop_limit`` answers as ``heading_of`` does, for
    every index (ties between two moving segments go to the earlier, no moving segment
    gives NaN for None), on polylines with repeated and near-repeated points."""
    xy = np.zeros((len(steps) + 1, 2))
    for k, (length, angle) in enumerate(steps):
        xy[k + 1] = xy[k] + length * np.array([math.cos(angle), math.sin(angle)])
    got = paths.headings_at(xy, np.array(index, dtype=np.int64))
    for i, h in zip(index, got.tolist(), strict=True):
        want = paths.heading_of(xy, i)
        if want is None:
            assert math.isnan(h)
        else:
            assert h == want


@settings(max_examples=300, deadline=None)
@given(
    steps=st.lists(
        st.tuples(st.sampled_from([0.0, 1e-9, 0.3, 2.0, 9.0]), st.floats(-math.pi, math.pi)),
        min_size=0,
        max_size=10,
    ),
    near=st.tuples(st.integers(0, 9), st.floats(0.0, 1.0), st.floats(-12.0, 12.0)),
    reach=st.floats(0.0, 10.0),
)
def test_farther_than_never_drops_a_point_project_finds_within_reach(
    steps: list[tuple[float, float]], near: tuple[int, float, float], reach: float
) -> None:
    """The cheap test before ``_ahead_in_lane``'s projection says "farther" only when
    ``project`` finds the point farther than ``reach`` from the polyline too. Points are
    placed beside a segment (which one, how far along, how far sideways), where the
    vertex bound is tightest."""
    xy = np.zeros((len(steps) + 1, 2))
    for k, (length, angle) in enumerate(steps):
        xy[k + 1] = xy[k] + length * np.array([math.cos(angle), math.sin(angle)])
    if xy.shape[0] < 2:
        xy = np.vstack([xy, xy])
    k, along, side = near
    a, b = xy[min(k, xy.shape[0] - 2)], xy[min(k, xy.shape[0] - 2) + 1]
    step = b - a
    norm = float(np.hypot(*step))
    perp = np.array([-step[1], step[0]]) / norm if norm > 0 else np.array([0.0, 1.0])
    point = a + along * step + side * perp
    _, dist, _ = paths.project(xy, float(point[0]), float(point[1]))
    if paths.farther_than(xy, float(point[0]), float(point[1]), reach):
        assert dist > reach
