"""Run metrics from crafted trajectories, checked against hand calculations."""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Callable
from pathlib import Path

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from services.model.kinematics import TruthState
from services.model.scenario import Scenario, load_scenario, parse_scenario
from services.sim.metrics import MetricsRecorder, RunMetrics

ROOT = Path(__file__).resolve().parents[2]
PAPER = ROOT / "scenarios" / "paper-blind-intersection.toml"
CORRIDOR = Path(__file__).resolve().parents[1] / "data" / "corridor.toml"
SMALL_FLOWS = Path(__file__).resolve().parents[1] / "data" / "four-way-flows-small.toml"
DT = 0.05

Profile = Callable[[float], tuple[float, float]]  # t -> (s, v)


@pytest.fixture(scope="module")
def paper() -> Scenario:
    return load_scenario(PAPER)


def truth(sc: Scenario, vid: str, t: float, s: float, v: float) -> TruthState:
    spec = sc.vehicle(vid)
    route = sc.route(spec.route)
    x, y = route.point_at(s)
    return TruthState(vid, t, x, y, route.heading_at(s), v, 0.0, s, spec.length_m, spec.width_m)


def simulate(sc: Scenario, profiles: dict[str, Profile], t_end: float) -> RunMetrics:
    rec = MetricsRecorder(sc)
    for k in range(round(t_end / DT) + 1):
        t = k * DT
        states = []
        for vid, prof in profiles.items():
            s, v = prof(t)
            states.append(truth(sc, vid, t, s, v))
        rec.record(t, states)
    return rec.result()


def constant(v: float, t0: float = 0.0, s0: float = 0.0) -> Profile:
    return lambda t: (s0 + v * max(0.0, t - t0), v if t >= t0 else 0.0)


def test_pet_of_two_crafted_crossings(paper: Scenario) -> None:
    # A at 10 m/s from t = 0: footprint enters the zone when its front bumper reaches
    # x = -3.5 (s = 196.5 - 2.25) at 19.425 s and leaves when its rear passes x = 3.5
    # (s = 203.5 + 2.25) at 20.575 s. B does the same 3 s later: PET = 22.425 - 20.575.
    res = simulate(paper, {"A": constant(10.0), "B": constant(10.0, t0=3.0)}, 40.0)
    assert res.min_pet_s == pytest.approx(1.85, abs=1e-6)
    assert res.min_pet_pair == ("A", "B")
    assert res.min_pet_intersection == "X1"
    assert res.collisions == 0
    a, b = res.vehicles["A"], res.vehicles["B"]
    assert a.entered_zone_s == pytest.approx(19.425, abs=1e-6)
    assert a.left_zone_s == pytest.approx(20.575, abs=1e-6)
    assert b.entered_zone_s == pytest.approx(22.425, abs=1e-6)
    assert a.first_through and not b.first_through
    # Closest approach: A's rear-left corner (x = 3.5 at 20.575 s ...) vs B arriving.
    assert 0.0 < res.min_gap_m < 20.0
    assert res.min_gap_pair == ("A", "B")


def test_pet_is_symmetric_and_zero_when_sharing_the_zone(paper: Scenario) -> None:
    res = simulate(paper, {"A": constant(10.0, t0=2.0), "B": constant(10.0)}, 40.0)
    assert res.min_pet_s == pytest.approx(0.85, abs=1e-6)
    assert res.vehicles["B"].first_through
    res = simulate(paper, {"A": constant(10.0), "B": constant(10.0, t0=1.0)}, 40.0)
    assert res.min_pet_s == 0.0  # B enters at 20.425 s while A is still in the box


def test_a_collision(paper: Scenario) -> None:
    # Both arrive together: their footprints overlap in the box for a while = one collision.
    res = simulate(paper, {"A": constant(10.0), "B": constant(10.0, t0=0.1)}, 40.0)
    assert res.collisions == 1
    (ev,) = res.collision_events
    assert (ev.a, ev.b) == ("A", "B")
    assert 19.4 < ev.t < 20.6
    assert res.min_gap_m == 0.0
    assert res.min_pet_s == 0.0
    assert res.as_dict()["collisions"] == 1


def test_two_separate_collision_episodes() -> None:
    sc = load_scenario(CORRIDOR)

    # lead stands at s = 100; the follower rams it, backs off (teleport), rams again.
    def follower(t: float) -> tuple[float, float]:
        if t < 5.0:
            return 90.0 + 2.0 * t, 2.0  # reaches 95.25 (contact) at 2.625 s
        return 80.0 + 3.0 * (t - 5.0), 3.0

    rec = MetricsRecorder(sc)
    for k in range(0, 300):
        t = k * DT
        s, v = follower(t)
        rec.record(t, [truth(sc, "lead", t, 100.0, 0.0), truth(sc, "follower", t, s, v)])
    res = rec.result()
    assert res.collisions == 2
    assert [round(e.t, 2) for e in res.collision_events] == [2.65, 10.1]
    assert res.min_gap_m == 0.0


@pytest.mark.parametrize("start_b", [0.1, 2.0])
def test_batched_pair_checks_equal_step_by_step_checks(paper: Scenario, start_b: float) -> None:
    """Exact distances are computed in batches; ``result()`` flushes. Reading the result
    after every step (one pair check per step) must give the same collisions and gap."""
    profiles = {"A": constant(10.0), "B": constant(10.0, t0=start_b)}
    batched, stepwise = MetricsRecorder(paper), MetricsRecorder(paper)
    for k in range(round(30.0 / DT) + 1):
        t = k * DT
        states = [truth(paper, vid, t, *prof(t)) for vid, prof in profiles.items()]
        batched.record(t, states)
        stepwise.record(t, states)
        stepwise.result()
    a, b = batched.result(), stepwise.result()
    assert a.collision_events == b.collision_events
    assert (a.min_gap_m, a.min_gap_t_s, a.min_gap_pair) == (
        b.min_gap_m,
        b.min_gap_t_s,
        b.min_gap_pair,
    )
    assert a.collisions == (1 if start_b < 1.0 else 0)
    assert 0.0 <= a.min_gap_m < 20.0 and a.min_gap_t_s is not None


def test_passing_time_by_hand(paper: Scenario) -> None:
    # Constant 10 m/s: from s = 10 to s = 200 + 100 takes 29 s.
    res = simulate(paper, {"A": constant(10.0)}, 40.0)
    assert res.vehicles["A"].passing_time_s == pytest.approx(29.0, abs=1e-9)
    assert res.vehicles["A"].passing_start_s == pytest.approx(1.0)
    # Uniform acceleration 1.5 m/s² from rest: s = 0.75 t².
    res = simulate(paper, {"A": lambda t: (0.75 * t * t, 1.5 * t)}, 25.0)
    expected = 20.0 - math.sqrt(10.0 / 0.75)
    assert res.vehicles["A"].passing_time_s == pytest.approx(expected, abs=2e-3)
    # Never reaching the end gate: no passing time.
    res = simulate(paper, {"A": constant(10.0)}, 20.0)
    assert res.vehicles["A"].passing_time_s is None


def test_one_car_has_no_gap_or_pet(paper: Scenario) -> None:
    res = simulate(paper, {"A": constant(10.0)}, 5.0)
    assert res.min_gap_m == math.inf
    assert res.min_pet_s == math.inf
    d = res.as_dict()
    assert d["min_gap_m"] is None and d["min_pet_s"] is None
    assert set(d["vehicles"]["A"]) >= {"passing_time_s", "first_through", "stops", "max_speed_mps"}


def stop_and_go(t: float) -> tuple[float, float]:
    """Drive to s = 100 at 10 m/s, wait 5 s, drive on to the goal 350 and stop there."""
    if t < 10.0:
        return 10.0 * t, 10.0
    if t < 15.0:
        return 100.0, 0.0
    s = 100.0 + 10.0 * (t - 15.0)
    return (s, 10.0) if s < 349.5 else (349.5, 0.0)


def test_stops_finished_and_max_speed(paper: Scenario) -> None:
    res = simulate(paper, {"A": stop_and_go}, 60.0)
    a = res.vehicles["A"]
    assert a.stops == 1  # the wait; the final stop at the goal does not count
    assert a.finished
    assert a.finished_s == pytest.approx(15.0 + 24.95, abs=DT)
    assert a.max_speed_mps == 10.0
    assert a.passing_time_s == pytest.approx(29.0 + 5.0, abs=1e-9)


def test_stop_short_of_the_goal_is_not_finished(paper: Scenario) -> None:
    res = simulate(paper, {"A": lambda t: (min(10.0 * t, 300.0), 0.0 if t >= 30 else 10.0)}, 40.0)
    assert not res.vehicles["A"].finished
    assert res.vehicles["A"].stops == 1


def test_following_cars_have_no_pet_but_a_gap() -> None:
    sc = load_scenario(CORRIDOR)
    # lead (4.5 m) 20 m ahead of the follower (5 m) at the same speed: gap 20 - 4.75.
    res = simulate(sc, {"lead": constant(10.0, s0=20.0), "follower": constant(10.0)}, 40.0)
    assert res.min_gap_m == pytest.approx(20.0 - 2.25 - 2.5)
    assert res.min_pet_s == math.inf
    assert res.vehicles["lead"].first_through
    assert not res.vehicles["follower"].first_through
    assert len(res.vehicles["lead"].zone_visits) == 2  # X1 then X2
    assert [z.intersection for z in res.vehicles["lead"].zone_visits] == ["X1", "X2"]
    # Passing ends 100 m after the last intersection's centre (s = 400).
    assert res.vehicles["lead"].passing_end_s == pytest.approx((400.0 - 20.0) / 10.0)


def test_modes_and_reasons_are_timed(paper: Scenario) -> None:
    rec = MetricsRecorder(paper)
    for k in range(21):
        t = k * 0.1
        mode = "AUTO" if t < 0.95 else "C_SLOW"
        rec.record(t, [truth(paper, "A", t, t, 1.0)], {"A": mode}, {"A": "caution"})
    a = rec.result().vehicles["A"]
    assert a.mode_time_s["AUTO"] == pytest.approx(1.0)
    assert a.mode_time_s["C_SLOW"] == pytest.approx(1.0)
    assert a.reason_time_s == {"caution": pytest.approx(2.0)}
    assert [m for _, m in a.mode_changes] == ["AUTO", "C_SLOW"]


def test_cars_may_be_absent(paper: Scenario) -> None:
    rec = MetricsRecorder(paper)
    rec.record(0.0, [truth(paper, "A", 0.0, 0.0, 0.0)])
    rec.record(0.05, [truth(paper, "A", 0.05, 0.0, 0.0), truth(paper, "B", 0.05, 0.0, 0.0)])
    res = rec.result()
    assert res.min_gap_m > 100.0
    assert res.sim_s == 0.05


def test_record_rejects_bad_input(paper: Scenario) -> None:
    rec = MetricsRecorder(paper)
    a = truth(paper, "A", 1.0, 0.0, 0.0)
    rec.record(1.0, [a])
    with pytest.raises(ValueError, match="increase"):
        rec.record(1.0, [a])
    with pytest.raises(ValueError, match="twice"):
        rec.record(2.0, [a, a])
    with pytest.raises(ValueError, match="unknown"):
        rec.record(2.0, [dataclasses.replace(a, id="Z")])


def test_many_cars_run_in_reasonable_size() -> None:
    lines = [
        '[scenario]\nname = "many"\n',
        '[[routes]]\nid = "r"\npoints = [[0.0, 0.0], [2000.0, 0.0]]\n',
    ]
    for i in range(12):
        lines.append(f'[[vehicles]]\nid = "v{i}"\nroute = "r"\nstart_offset_m = {i * 30.0}\n')
    sc = parse_scenario("\n".join(lines))
    profiles: dict[str, Profile] = {f"v{i}": constant(10.0, s0=i * 30.0) for i in range(12)}
    res = simulate(sc, profiles, 120.0)
    assert res.collisions == 0
    assert res.min_gap_m == pytest.approx(30.0 - 4.5)
    assert len(res.vehicles) == 12


@pytest.mark.parametrize(
    ("b_at_step_2", "collisions"),
    [("missing", 1), ("apart", 2), ("overlapping", 1)],
)
def test_a_car_missing_at_a_step_neither_ends_nor_starts_an_overlap(
    paper: Scenario, b_at_step_2: str, collisions: int
) -> None:
    """Issue 16: a step without B's truth measures nothing for the pair A-B: an overlap
    across it stays one collision, and B is never compared at an older position."""
    a_c = paper.vehicle_crossings("A")[0].center_s
    b_c = paper.vehicle_crossings("B")[0].center_s
    rec = MetricsRecorder(paper)
    for k in range(5):
        a = truth(paper, "A", k * DT, a_c, 0.0)
        if k == 2 and b_at_step_2 == "missing":
            rec.record(k * DT, [a])
            continue
        apart = k in (0, 4) or (k == 2 and b_at_step_2 == "apart")
        b = truth(paper, "B", k * DT, b_c - (40.0 if apart else 0.0), 0.0)
        rec.record(k * DT, [a, b])
    res = rec.result()
    assert res.collisions == collisions
    assert res.collision_events[0].t == pytest.approx(DT)
    assert res.min_gap_m == 0.0


# -- conflict-area PET ---------------------------------------------------------------------


def test_conflict_area_pet_of_two_crafted_crossings(paper: Scenario) -> None:
    """A's centre line comes within d_margin (2.8 m) of B's from x = -1.0 m (sampled every
    0.25 m) to the box's far edge, B's from the box's near edge to y = 1.0 m: A is on its
    area from 19.675 s (front at s = 199.0 - 2.25) to 20.575 s (rear past 203.5 + 2.25),
    B from t0 + 19.425 s to t0 + 20.325 s."""
    res = simulate(paper, {"A": constant(10.0), "B": constant(10.0, t0=3.0)}, 40.0)
    assert res.min_conflict_pet_s == pytest.approx(22.425 - 20.575, abs=1e-6)  # = zone PET
    assert res.min_conflict_pet_pair == ("A", "B")
    # A 1.2 s behind B: 0.05 s between B leaving the box and A entering it, 0.55 s at
    # the area (B's rear is past A's path before A's front reaches B's)
    res = simulate(paper, {"A": constant(10.0, t0=1.2), "B": constant(10.0)}, 40.0)
    assert res.min_pet_s == pytest.approx(0.05, abs=1e-6)
    assert res.min_conflict_pet_s == pytest.approx(20.875 - 20.325, abs=1e-6)
    assert res.as_dict()["min_conflict_pet_s"] == pytest.approx(0.55, abs=1e-6)


@settings(max_examples=40, deadline=None)
@given(st.floats(-3.0, 3.0), st.floats(4.0, 14.0), st.floats(4.0, 14.0))
def test_conflict_area_pet_of_random_crossings(
    paper: Scenario, offset: float, va: float, vb: float
) -> None:
    """Any two speeds and start offsets: the analytic PET at the area of the paper's
    crossing (areas as in the crafted test; linear interpolation between steps is exact
    at constant speed), and never below the zone PET (the area lies inside the zone)."""
    ta0, tb0 = max(0.0, -offset), max(0.0, offset)
    res = simulate(paper, {"A": constant(va, t0=ta0), "B": constant(vb, t0=tb0)}, 80.0)
    a_in, a_out = ta0 + (199.0 - 2.25) / va, ta0 + (203.5 + 2.25) / va
    b_in, b_out = tb0 + (196.5 - 2.25) / vb, tb0 + (201.0 + 2.25) / vb
    assert res.min_conflict_pet_s == pytest.approx(max(0.0, b_in - a_out, a_in - b_out), abs=1e-6)
    assert res.min_conflict_pet_s >= res.min_pet_s - 1e-9


def test_a_merge_has_zone_pet_0_but_a_conflict_area_pet() -> None:
    """A left turner from the south (route "sw") into the westbound lane enters the box
    0.1 s before the straight westbound car ahead ("ew") leaves it by the west edge, 7.4 m
    away: zone PET 0. Where their paths meet (for the turner from about 0.7 m into the
    turn's arc, 2.45 m past the box's edge, reached at 5 m/s about 0.5 s after entering;
    for the lead up to where the turner heads within 35 degrees of its way), the lane was
    clear: conflict-area PET about 0.5 s."""
    text = SMALL_FLOWS.read_text()
    text = text[: text.index("[[flows]]")] + text[text.index("[[rsus]]") :]
    text += (
        '\n[[vehicles]]\nid = "lead"\nroute = "ew"\n\n[[vehicles]]\nid = "turner"\nroute = "sw"\n'
    )
    sc = parse_scenario(text)
    rec = MetricsRecorder(sc)
    lead_route, turn_route = sc.route("ew"), sc.route("sw")
    zone = sc.zone_polygon("X1")
    lead_span, turn_span = (
        lead_route.interval_in_polygon(zone),
        turn_route.interval_in_polygon(zone),
    )
    assert lead_span is not None and turn_span is not None
    lead_out = (lead_span[1] + 2.25) / 10.0  # lead's rear leaves the box
    turn_t0 = lead_out - 0.1 - (turn_span[0] - 2.25) / 5.0  # its front enters 0.1 s before
    profiles = {"lead": constant(10.0), "turner": constant(5.0, t0=turn_t0)}
    for k in range(round(11.0 / DT) + 1):  # the lead reaches its route's end at 12 s
        t = k * DT
        rec.record(t, [truth(sc, vid, t, *prof(t)) for vid, prof in profiles.items()])
    res = rec.result()
    assert res.collisions == 0
    assert res.min_pet_s == 0.0
    assert 0.45 < res.min_conflict_pet_s < 0.6, res.min_conflict_pet_s
    # the lead's stretch ends where the two paths have become one lane (heading within
    # 35 degrees), about 1 m short of the box's west edge: beyond it they follow
    lead_area = rec._conflict_area("ew", "sw", "X1")
    assert lead_area is not None and lead_span[0] <= lead_area[0] < lead_area[1]
    assert lead_span[1] - 2.0 < lead_area[1] < lead_span[1] - 0.5, (lead_area, lead_span)
