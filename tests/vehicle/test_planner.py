"""The autonomous planner's rules on crafted situations in the paper's intersection.

Car A drives east on y = -1.75 (route ``east``, centre of the intersection at
s = 200 m); car B drives north on x = +1.75 (route ``north``, same s).
"""

from __future__ import annotations

import math

import numpy as np

from protocol.messages import FuturePath, Header, Mode
from services.model.kinematics import TruthState
from services.model.scenario import Scenario
from services.vehicle.planner import AutonomousPlanner, Reason

CENTER_S = 200.0


def planner(sc: Scenario, vid: str) -> AutonomousPlanner:
    spec = sc.vehicle(vid)
    p = sc.params
    return AutonomousPlanner(
        vehicle_id=vid,
        scenario=sc,
        route_id=spec.route,
        goal_s=sc.goal_m(vid),
        length=spec.length_m,
        width=spec.width_m,
        limits=sc.limits(vid),
        headway_s=p.headway_s,
        sensor_range_m=p.sensor_range_m,
    )


def state(sc: Scenario, vid: str, s: float, v: float, t: float = 0.0) -> TruthState:
    spec = sc.vehicle(vid)
    route = sc.route(spec.route)
    x, y = route.point_at(s)
    return TruthState(vid, t, x, y, route.heading_at(s), v, 0.0, s, spec.length_m, spec.width_m)


def test_cruise_far_from_everything(paper: Scenario) -> None:
    plan = planner(paper, "A").plan(0.0, state(paper, "A", 20.0, 13.0), [], {})
    assert plan.reason is Reason.CRUISE
    assert math.isclose(float(plan.profile.v.max()), paper.params.v_max_mps, rel_tol=1e-6)


def test_goal_stop(paper: Scenario) -> None:
    p = planner(paper, "A")
    goal = paper.goal_m("A")
    plan = p.plan(0.0, state(paper, "A", goal - 30.0, 10.0), [], {})
    assert plan.reason is Reason.GOAL
    assert plan.profile.speed_at(goal) == 0.0
    assert plan.profile.stop_s() is not None


def test_blind_corner_caution_slows_before_the_stop_line(paper: Scenario) -> None:
    p = planner(paper, "A")
    crossing = p.crossings[0]
    ego = state(paper, "A", crossing.s_stop - 50.0, 13.0)
    plan = p.plan(0.0, ego, [], {})
    assert plan.reason is Reason.CAUTION
    # from every point it could still stop at the stop line braking comfortably (2 m/s²)
    before = plan.profile.s <= crossing.s_stop - 0.3
    room = crossing.s_stop - 0.3 - plan.profile.s[before]
    assert np.all(plan.profile.v[before] ** 2 <= 2 * 2.0 * room + 1.5**2 + 1e-6)
    # past the line it may only creep
    past = (plan.profile.s > crossing.s_stop) & (plan.profile.s < crossing.s_in)
    assert np.all(plan.profile.v[past] <= 1.5 + 1e-9)


def test_caution_lifted_when_the_cross_road_is_visible(paper: Scenario) -> None:
    p = planner(paper, "A")
    crossing = p.crossings[0]
    # at the zone's edge, creeping: the whole crossing lane is in sight
    ego = state(paper, "A", crossing.s_in - 2.25 - 1.0, 1.0)
    plan = p.plan(0.0, ego, [], {})
    assert plan.reason is not Reason.CAUTION


def test_caution_lifted_in_c_fast(paper: Scenario) -> None:
    from services.vehicle.planner import Coordination

    p = planner(paper, "A")
    ego = state(paper, "A", 150.0, 13.0)
    plan = p.plan(0.0, ego, [], {}, Coordination(lift_caution=True))
    assert plan.reason is Reason.CRUISE


def test_car_appearing_from_behind_the_corner_makes_the_later_car_yield(paper: Scenario) -> None:
    # B is 14 m from the centre at 5 m/s; A, 15 m from the centre at 4 m/s, appears round the corner
    pb = planner(paper, "B")
    b = state(paper, "B", CENTER_S - 16.0, 4.0)
    a = state(paper, "A", CENTER_S - 12.0, 4.0)
    plan = pb.plan(0.0, b, [a], {})
    assert plan.reason is Reason.YIELD
    assert plan.yielding_to == ("A",)
    stop = plan.profile.stop_s()
    assert stop is not None and stop <= pb.crossings[0].s_stop
    # A sees the same facts and goes first
    pa = planner(paper, "A")
    plan_a = pa.plan(0.0, a, [b], {})
    assert plan_a.yielding_to == ()


def test_yield_tie_goes_to_the_car_on_the_right(paper: Scenario) -> None:
    # exactly symmetric: same distance, same speed; B (northbound) comes from A's right
    a = state(paper, "A", CENTER_S - 14.0, 3.0)
    b = state(paper, "B", CENTER_S - 14.0, 3.0)
    plan_a = planner(paper, "A").plan(0.0, a, [b], {})
    plan_b = planner(paper, "B").plan(0.0, b, [a], {})
    assert plan_a.yielding_to == ("B",)
    assert plan_b.yielding_to == ()


def test_the_car_at_its_stop_line_goes_before_a_faster_one(paper: Scenario) -> None:
    # B creeps at its stop line; A is 12 m further out but fast: earliest zone entry would
    # favour A, arrival at the stop line favours B (issue 17)
    line = planner(paper, "B").crossings[0].s_stop
    b = state(paper, "B", line - 0.5, 1.0)
    a = state(paper, "A", line - 12.0, 7.0)
    assert planner(paper, "A").plan(0.0, a, [b], {}).yielding_to == ("B",)
    assert planner(paper, "B").plan(0.0, b, [a], {}).yielding_to == ()


def test_opposing_car_is_never_yielded_to(paper: Scenario) -> None:
    # a westbound car on y = +1.75 never shares a point with A on y = -1.75
    p = planner(paper, "A")
    a = state(paper, "A", CENTER_S - 14.0, 3.0)
    w = TruthState("W", 0.0, 12.0, 1.75, math.pi, 3.0, 0.0, 0.0, 4.5, 1.8)
    assert p.plan(0.0, a, [w], {}).yielding_to == ()
    pts = np.array([[12.0 - d, 1.75, d / 3.0] for d in np.arange(0.0, 30.0, 1.0)])
    fp = FuturePath(Header("W", 1, 0), 12.0, 1.75, 3.0, math.pi, 4.5, 1.8, Mode.AUTO, pts)
    assert p.plan(0.0, a, [], {"W": fp}).yielding_to == ()


def test_no_yield_when_the_other_car_is_well_past(paper: Scenario) -> None:
    a = state(paper, "A", CENTER_S + 20.0, 10.0)
    b = state(paper, "B", CENTER_S - 14.0, 3.0)
    plan_b = planner(paper, "B").plan(0.0, b, [a], {})
    assert plan_b.yielding_to == ()


def test_future_path_makes_the_car_yield_before_it_can_see(paper: Scenario) -> None:
    # A's future path says it crosses the zone in 2..3 s; B, 10 m further out, would be in
    # it within the headway after A: A arrives first and B yields
    pts = np.array([[x, -1.75, 0.0 + (x + 30.0) / 10.0] for x in np.arange(-30.0, 60.0, 1.0)])
    fp = FuturePath(Header("A", 1, 0), -30.0, -1.75, 10.0, 0.0, 4.5, 1.8, Mode.AUTO, pts)
    b = state(paper, "B", CENTER_S - 40.0, 10.0)
    plan = planner(paper, "B").plan(0.0, b, [], {"A": fp})
    assert plan.yielding_to == ("A",)
    assert plan.reason in (Reason.YIELD, Reason.CAUTION)


def test_emergency_stop_for_a_car_on_the_path(paper: Scenario) -> None:
    p = planner(paper, "A")
    ego = state(paper, "A", 100.0, 12.0)
    blocker = state(paper, "A", 125.0, 0.0)
    blocker = TruthState("X", 0.0, blocker.x, blocker.y, 0.0, 0.0, 0.0, 125.0, 4.5, 1.8)
    plan = p.plan(0.0, ego, [blocker], {})
    assert plan.reason is Reason.EMERGENCY
    stop = plan.profile.stop_s()
    assert stop is not None and stop < 125.0 - 4.5
