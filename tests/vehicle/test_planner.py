"""The autonomous planner's rules on crafted situations in the paper's intersection.

Car A drives east on y = -1.75 (route ``east``, centre of the intersection at
s = 200 m); car B drives north on x = +1.75 (route ``north``, same s).
"""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import assume, example, given, settings
from hypothesis import strategies as st

from protocol.messages import FuturePath, Header, Mode
from services.model.kinematics import TruthState
from services.model.scenario import Scenario, ScenarioFile, limits_from_params, load_scenario
from services.vehicle.planner import DS, AutonomousPlanner, Coordination, Plan, Reason
from tests.vehicle.conftest import PAPER

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


@pytest.mark.parametrize(
    ("gap_m", "speed", "passes"),
    [
        (0.15, 0.0, True),  # standing, 0.15 m beside the swept body: creep past it
        (0.02, 0.0, False),  # standing, closer than PASS_MARGIN_M: stop
        (0.15, 1.0, False),  # moving (crosswise) inside SIDE_MARGIN_M: stop
    ],
)
def test_a_standing_car_just_beside_the_path_is_passed_at_the_creep_speed(
    paper: Scenario, gap_m: float, speed: float, passes: bool
) -> None:
    # issue 12: a car standing with its nose 0.1 m beside a crossing lane held the car in
    # that lane by the 0.3 m side margin, and that car held it: neither ever moved
    p = planner(paper, "A")
    ego = state(paper, "A", 100.0, 0.0)
    near_edge = p.width / 2.0 + gap_m  # lateral offset of the other body's near side
    x, y = paper.route("east").point_at(110.0)
    other = TruthState("X", 0.0, x, y + near_edge + 2.25, math.pi / 2, speed, 0.0, 0.0, 4.5, 1.8)
    plan = p.plan(0.0, ego, [other], {})
    assert plan.reason is Reason.EMERGENCY
    past = plan.profile.s > 115.0
    stop = plan.profile.stop_s()
    if passes:
        assert stop is None or stop > 115.0
        beside = (plan.profile.s > 106.0) & (plan.profile.s < 112.0)
        assert float(plan.profile.v[beside].max()) <= p.params.creep_mps + 1e-9
        assert float(plan.profile.v[past].max()) > 0.0
    else:
        assert stop is not None and stop < 110.0
        assert float(plan.profile.v[past].max()) == 0.0


# --------------------------------------------------------------------------- rule 5
# The paper's intersection with the east-west road (lanes eb, wb) as a priority road:
# A (eastbound) is on it, B (northbound) comes from the minor road.


def _priority(paper: Scenario) -> Scenario:
    doc = paper.spec.model_dump()
    doc["intersections"][0]["priority_lanes"] = ["eb", "wb"]
    return Scenario(ScenarioFile.model_validate(doc), paper.source)


def test_the_priority_road_goes_first_where_the_car_on_the_right_would(paper: Scenario) -> None:
    sc = _priority(paper)
    # the symmetric tie of test_yield_tie_goes_to_the_car_on_the_right: B comes from A's
    # right and went first; on a priority road A does, and both agree
    a = state(sc, "A", CENTER_S - 14.0, 3.0)
    b = state(sc, "B", CENTER_S - 14.0, 3.0)
    assert planner(sc, "A").plan(0.0, a, [b], {}).yielding_to == ()
    assert planner(sc, "B").plan(0.0, b, [a], {}).yielding_to == ("A",)
    # the earlier arrival at the stop line no longer counts against the priority road
    line = planner(sc, "B").crossings[0].s_stop
    b = state(sc, "B", line - 0.5, 1.0)
    a = state(sc, "A", line - 12.0, 7.0)
    assert planner(sc, "B").plan(0.0, b, [a], {}).yielding_to == ("A",)
    assert planner(sc, "A").plan(0.0, a, [b], {}).yielding_to == ()


def test_a_committed_car_from_the_minor_road_still_goes_first(paper: Scenario) -> None:
    sc = _priority(paper)
    pb = planner(sc, "B")
    zone_in = pb.crossings[0].s_in - pb.length / 2.0
    b = state(sc, "B", zone_in - 2.0, 10.0)  # 2 m from the zone at 10 m/s: cannot stop
    a = state(sc, "A", CENTER_S - 20.0, 8.0)
    assert planner(sc, "A").plan(0.0, a, [b], {}).yielding_to == ("B",)
    assert pb.plan(0.0, b, [a], {}).yielding_to == ()


def test_a_coordinated_car_gives_way_to_an_unconnected_car_on_the_priority_road(
    paper: Scenario,
) -> None:
    sc = _priority(paper)
    pb = planner(sc, "B")
    b = state(sc, "B", CENTER_S - 25.0, 8.0)
    a = state(sc, "A", CENTER_S - 24.0, 8.0)
    fast = Coordination(lift_caution=True, skip_yield=True)
    # known only from the sensors: no RSU orders it, B stops for it even in C_FAST
    plan = pb.plan(0.0, b, [a], {}, fast)
    assert plan.yielding_to == ("A",) and plan.reason is Reason.YIELD
    # A car that shares its future path is the RSU's to order: no yield
    assert pb.plan(0.0, b, [a], {"A": _fp_of(sc, a)}, fast).yielding_to == ()
    # without a priority road, the coordinated car leaves sensed cars to its RSU
    assert planner(paper, "B").plan(0.0, b, [a], {}, fast).yielding_to == ()
    # and the car on the priority road never waits for the minor road's
    assert planner(sc, "A").plan(0.0, a, [b], {}, fast).yielding_to == ()


def _paper() -> Scenario:
    return load_scenario(PAPER)


def _fp_of(sc: Scenario, t: TruthState) -> FuturePath:
    route = sc.route(sc.vehicle(t.id).route)
    s = t.s + t.speed * np.arange(0.0, 10.0, 0.1)
    xy = route.points_at(s)
    pts = np.column_stack([xy, 0.0 + np.arange(0.0, 10.0, 0.1)])
    return FuturePath(Header(t.id, 1, 0), t.x, t.y, t.speed, t.heading, 4.5, 1.8, Mode.AUTO, pts)


@settings(max_examples=200, deadline=None)
@given(
    sa=st.floats(CENTER_S - 60.0, CENTER_S - 5.0),
    sb=st.floats(CENTER_S - 60.0, CENTER_S - 5.0),
    va=st.floats(0.0, 13.9),
    vb=st.floats(0.0, 13.9),
)
def test_rule5_the_two_cars_agree(sa: float, sb: float, va: float, vb: float) -> None:
    """Any two cars at a priority road, known to each other from the sensors only: never
    both wait for each other, and the car on the priority road waits only for a car that
    can no longer stop."""
    sc = _priority(_paper())
    pa, pb = planner(sc, "A"), planner(sc, "B")
    a, b = state(sc, "A", sa, va), state(sc, "B", sb, vb)
    a_waits = pa.plan(0.0, a, [b], {}).yielding_to == ("B",)
    b_waits = pb.plan(0.0, b, [a], {}).yielding_to == ("A",)
    assert not (a_waits and b_waits)
    if a_waits:
        crossing = pb.crossings[0]
        assert pb._own_arrival(0.0, b, crossing).committed


# ------------------------------------------------------------- oncoming, sensed only
# The 4-way of four-way-flows: wn turns left from the west across the westbound lane,
# ew drives straight on it, es turns left from the east across the eastbound lane.
FLOWS = load_scenario(PAPER.parent / "four-way-flows.toml")


def _route_planner(vid: str, route: str) -> AutonomousPlanner:
    p = FLOWS.params
    return AutonomousPlanner(
        vehicle_id=vid,
        scenario=FLOWS,
        route_id=route,
        goal_s=FLOWS.route(route).length,
        length=4.5,
        width=1.8,
        limits=limits_from_params(p, None),
        headway_s=p.headway_s,
        sensor_range_m=p.sensor_range_m,
    )


def _on(planner_: AutonomousPlanner, s: float, v: float) -> TruthState:
    route = planner_.route
    x, y = route.point_at(s)
    return TruthState(planner_.vehicle_id, 0.0, x, y, route.heading_at(s), v, 0.0, s, 4.5, 1.8)


def test_a_left_turn_gives_way_to_an_oncoming_car_it_knows_only_from_its_sensors() -> None:
    turner, straight = _route_planner("a-turner", "wn"), _route_planner("b-straight", "ew")
    t = _on(turner, turner.crossings[0].s_stop, 0.0)  # waiting at its line, arrived first
    o = _on(straight, straight.crossings[0].s_in - 25.0, 8.0)
    # the oncoming car's route does not cross the turner's lane: it never gives way
    assert straight.plan(0.0, o, [t], {}).yielding_to == ()
    # so the turner does, though it reached its line first and has the lower id
    assert turner.plan(0.0, t, [o], {}).yielding_to == ("b-straight",)


def test_two_oncoming_left_turns_standing_at_their_lines_do_not_wait_for_each_other() -> None:
    west, east = _route_planner("a-west", "wn"), _route_planner("b-east", "es")
    w = _on(west, west.crossings[0].s_stop, 0.0)
    e = _on(east, east.crossings[0].s_stop, 0.0)
    waits = [
        west.plan(0.0, w, [e], {}).yielding_to == ("b-east",),
        east.plan(0.0, e, [w], {}).yielding_to == ("a-west",),
    ]
    assert waits.count(True) == 1


def _aged_fp(sc: Scenario, t: TruthState, age: float) -> FuturePath:
    """``t``'s future path as sent ``age`` [s] before ``t.t``: from where the car was then
    (on at its speed), dated then."""
    route = sc.route(sc.vehicle(t.id).route)
    then = t.t - age
    s0 = t.s - t.speed * age
    steps = np.arange(0.0, 10.0, 0.1)
    xy = route.points_at(s0 + t.speed * steps)
    pts = np.column_stack([xy, then + steps])
    x, y = route.point_at(s0)
    header = Header(t.id, 1, round(then * 1e6))
    return FuturePath(header, x, y, t.speed, t.heading, 4.5, 1.8, Mode.AUTO, pts)


@settings(max_examples=200, deadline=None)
@given(
    st.floats(0.0, 1.5),
    st.floats(-0.45, 0.45),
    st.floats(0.0, 0.9),
    st.floats(0.0, 0.9),
    st.floats(0.0, 0.1),
    st.floats(0.0, 0.1),
)
@example(0.5, 0.35, 0.0, 0.0, 0.0, 0.1)  # the demand experiment's pair, in the paper's geometry
@example(0.0, 0.25, 0.0, 0.0, 0.0625, 0.0)  # found by this test: a car at its line, 1/16 s old
def test_slow_cars_at_their_lines_agree_whatever_their_paths_age(
    da: float, gap: float, va: float, vb: float, age_a: float, age_b: float
) -> None:
    """Two cars standing or creeping (below the arrival floor) before their stop lines,
    ``gap`` [m] apart in distance to their lines (around the 0.3 s tie at the 1 m/s
    floor), each known to the other only by a future path up to a planning period old:
    they never both wait for each other. (A path's arrival runs down at 1 s/s only for a
    car at or above the floor; two cars standing at their lines judged each other a
    period apart and each gave way to the other for ever: the demand experiment,
    fp-only, 400 veh/h, seed 1.)"""
    db = da + gap
    assume(db >= 0.0)
    sc = _paper()
    pa, pb = planner(sc, "A"), planner(sc, "B")
    now = 10.0
    a = state(sc, "A", pa.crossings[0].s_stop - da, va, now)
    b = state(sc, "B", pb.crossings[0].s_stop - db, vb, now)
    a_waits = "B" in pa.plan(now, a, [], {"B": _aged_fp(sc, b, age_b)}).yielding_to
    b_waits = "A" in pb.plan(now, b, [], {"A": _aged_fp(sc, a, age_a)}).yielding_to
    assert not (a_waits and b_waits)


@settings(max_examples=100, deadline=None)
@given(v0=st.floats(1.0, 13.8), spare=st.floats(0.2, 40.0))
def test_a_coordinated_path_that_ends_at_rest_is_a_stop_the_car_keeps(
    paper: Scenario, v0: float, spare: float
) -> None:
    """A ``C_SLOW`` coordinated path (speed 0 at every point) ends where the RSU reserved
    the car's stop, short of the zone or behind the car ahead; it may need harder than
    comfortable braking. The car stops there (or short of it), whatever it needs up to
    its emergency deceleration: the comfortable rule alone overshot by 2.6 m into the
    crossing (demand experiment, paper, 400 veh/h, seed 0)."""
    lim = paper.limits("A")
    s0 = 60.0
    room = v0 * v0 / (2.0 * lim.decel_emergency) + spare
    end = s0 + room
    target_s = np.array([s0, 0.5 * (s0 + end), end, end])
    c = Coordination(target_s=target_s, target_v=np.zeros(4), skip_yield=True)
    plan = planner(paper, "A").plan(0.0, state(paper, "A", s0, v0), [], {}, c)
    stop = plan.profile.stop_s()
    assert stop is not None and stop <= end + DS  # the profile's grid
    comfortable = v0 * v0 / (2.0 * lim.decel_comfort)
    if comfortable <= room:  # no harder than comfortable when that reaches it
        assert stop >= s0 + comfortable - DS


# --------------------------------------------------------------------------- following
# The autonomous path follows a car ahead by its future path (issue 12, the opposing-left-
# turner lock): a follower's path no longer rests where it could stop behind its leader,
# it runs on behind it through the intersection, as it will drive.


def _leader_fp(
    planner_: AutonomousPlanner, vid: str, s0: float, v0: float, accel: float, rest_s: float = 1e9
) -> tuple[TruthState, FuturePath]:
    """A car ``vid`` on ``planner_``'s route at ``s0`` [m], ``v0`` [m/s], and its future path
    over 10 s: accelerating (or braking) at ``accel`` [m/s²] within [0, 13.89] m/s, stopping
    at ``rest_s`` at the latest, sampled every 0.1 s."""
    route = planner_.route
    s, v, rows = s0, v0, []
    for k in range(101):
        x, y = route.point_at(min(s, route.length))
        rows.append((x, y, 0.1 * k))
        v = min(max(v + accel * 0.1, 0.0), 13.89)
        s = min(s + v * 0.1, rest_s)
    x, y = route.point_at(s0)
    truth = TruthState(vid, 0.0, x, y, route.heading_at(s0), v0, 0.0, s0, 4.5, 1.8)
    heading = route.heading_at(s0)
    fp = FuturePath(Header(vid, 1, 0), x, y, v0, heading, 4.5, 1.8, Mode.AUTO, np.array(rows))
    return truth, fp


_AP = Coordination(lift_caution=True, skip_yield=True)


def _ap(planner_: AutonomousPlanner, ego: TruthState, leader: TruthState, fp: FuturePath) -> Plan:
    follow = Coordination(lift_caution=True, skip_yield=True, follow={leader.id: fp})
    return planner_.plan(0.0, ego, [leader], {}, follow)


def test_a_left_turner_s_autonomous_path_follows_its_leader_through_the_box() -> None:
    turner = _route_planner("b-turner", "sw")
    lead = _route_planner("a-lead", "sn")
    zone = turner.crossings[0]
    ego = _on(turner, zone.s_in - 20.0, 5.0)
    leader, fp = _leader_fp(lead, "a-lead", ego.s + 8.0, 5.0, 1.5)
    # braking for the leader as if it might stop hard now, the path rests short of the turn
    plain = turner.plan(0.0, ego, [leader], {}, _AP).profile.stop_s()
    assert plain is not None and plain < zone.s_out
    # by its future path (straight on, away from the turn), it runs on through the box
    followed = _ap(turner, ego, leader, fp).profile
    stop = followed.stop_s()
    assert stop is None or stop > zone.s_out + 10.0
    assert math.isfinite(float(np.interp(zone.s_out, followed.s, followed.t)))


def test_a_follower_stops_a_follow_distance_behind_where_its_leaders_path_rests() -> None:
    car, lead = _route_planner("b", "sn"), _route_planner("a", "sn")
    zone = car.crossings[0]
    rest = zone.s_in + 2.0  # the leader will stand in the box, e.g. for a crossing car
    ego = _on(car, zone.s_in - 20.0, 5.0)
    leader, fp = _leader_fp(lead, "a", ego.s + 8.0, 5.0, 0.0, rest_s=rest)
    stop = _ap(car, ego, leader, fp).profile.stop_s()
    d = 4.5 + car.params.emergency_gap_m
    assert stop is not None and rest - d - 1.0 <= stop <= rest - d


def test_a_sensed_car_without_a_future_path_is_braked_for_as_before() -> None:
    car, lead = _route_planner("b", "sn"), _route_planner("a", "sn")
    zone = car.crossings[0]
    ego = _on(car, zone.s_in - 20.0, 5.0)
    leader, fp = _leader_fp(lead, "a", ego.s + 8.0, 5.0, 1.5)
    other = FuturePath(fp.header, fp.x, fp.y, fp.speed, fp.heading, 4.5, 1.8, Mode.AUTO, fp.points)
    plain = car.plan(0.0, ego, [leader], {}, _AP).profile
    unknown = Coordination(lift_caution=True, skip_yield=True, follow={"someone-else": other})
    assert np.array_equal(car.plan(0.0, ego, [leader], {}, unknown).profile.v, plain.v)


@settings(max_examples=150, deadline=None)
@given(
    st.floats(0.0, 12.0),  # leader's speed [m/s]
    st.floats(-3.0, 1.5),  # its acceleration [m/s²]
    st.floats(0.0, 15.0),  # extra room beyond the follow distance [m]
    st.floats(0.0, 1.0),  # follower's speed as a share of the leader's
    st.floats(-40.0, 10.0),  # where the leader is, from the zone [m]
)
def test_the_followed_path_never_reaches_a_place_before_the_leader_is_a_follow_distance_on(
    v_lead: float, accel: float, room: float, share: float, at: float
) -> None:
    # t_f(s) >= t_l(s + d): the follower is never within a follow distance behind where
    # the leader's path puts it (so the RSU's follow rule never finds the two in conflict)
    car, lead = _route_planner("b", "sn"), _route_planner("a", "sn")
    d = 4.5 + car.params.emergency_gap_m
    s_lead = car.crossings[0].s_in + at
    ego = _on(car, s_lead - d - room, v_lead * share)
    leader, fp = _leader_fp(lead, "a", s_lead, v_lead, accel)
    profile = _ap(car, ego, leader, fp).profile
    s_l, _ = car.route.project_many(fp.points[:, :2])
    t_l = fp.points[:, 2]
    moving = np.concatenate([[True], np.diff(s_l) > 1e-9])
    s_l, t_l = s_l[moving], t_l[moving]
    ahead = profile.s + d
    inside = (ahead >= s_l[0]) & (ahead <= s_l[-1]) & np.isfinite(profile.t)
    assume(bool(np.any(inside)))
    t_leader = np.interp(ahead[inside], s_l, t_l)
    assert bool(np.all(profile.t[inside] >= t_leader - 0.1))
