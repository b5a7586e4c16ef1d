"""The monitor's pure core: truth steps from crafted reports, and the run's decisions."""

from __future__ import annotations

import logging
from dataclasses import dataclass
from pathlib import Path

import pytest

from services.model.kinematics import TruthState
from services.model.scenario import Scenario, load_scenario
from services.sim.truth import (
    FUTURE_TOLERANCE_S,
    START_REPEAT_S,
    TRUTH_WAIT_S,
    Actions,
    MonitorCore,
    MonitorRules,
    Phase,
    TruthSteps,
)

PAPER = Path(__file__).resolve().parents[2] / "scenarios" / "paper-blind-intersection.toml"
DT = 0.05  # the paper scenario's physics step [s]
EPOCH = 1_700_000_000.0


@pytest.fixture(scope="module")
def paper() -> Scenario:
    return load_scenario(PAPER)


@dataclass(frozen=True)
class Report:
    """A truth report as the core sees one (``services.edge.plumbing.TruthReport``)."""

    vehicle: str
    step: int
    state: TruthState
    mode: str = "AUTO"
    reason: str = "cruise"


def report(sc: Scenario, vid: str, step: int, s: float = 10.0, v: float = 5.0) -> Report:
    spec = sc.vehicle(vid)
    route = sc.route(spec.route)
    x, y = route.point_at(s)
    state = TruthState(
        vid, step * DT, x, y, route.heading_at(s), v, 0.0, s, spec.length_m, spec.width_m
    )
    return Report(vid, step, state)


def steps(sc: Scenario, **kw: object) -> TruthSteps:
    options: dict[str, object] = {"speed": 1.0, "max_sim_s": 120.0, "trace": True}
    options.update(kw)
    return TruthSteps(sc, ("A", "B"), **options)  # type: ignore[arg-type]


# --------------------------------------------------------------------------- TruthSteps


def test_a_complete_step_is_recorded_at_once_in_order(paper: Scenario) -> None:
    ts = steps(paper)
    assert ts.next_deadline() is None  # nothing to wait for before any report
    ts.on_report(0.0, report(paper, "A", 0))
    assert ts.next_step == 0 and ts.last_t is None
    assert ts.next_deadline() == pytest.approx(TRUTH_WAIT_S)
    ts.on_report(0.0, report(paper, "B", 0))
    assert ts.next_step == 1 and ts.last_t == 0.0
    assert [row[:2] for row in ts.trace_rows] == [(0.0, "A"), (0.0, "B")]
    assert ts.gaps == 0 and ts.late == 0


def test_out_of_order_steps_wait_for_the_earlier_one(paper: Scenario) -> None:
    ts = steps(paper)
    for vid in ("A", "B"):
        ts.on_report(0.1, report(paper, vid, 2))
    ts.on_report(0.1, report(paper, "B", 1))
    assert ts.next_step == 0  # step 0 is missing: nothing is recorded
    ts.on_report(0.1, report(paper, "A", 0))
    ts.on_report(0.1, report(paper, "B", 0))
    assert ts.next_step == 1  # step 1 still misses A
    ts.on_report(0.1, report(paper, "A", 1))
    assert ts.next_step == 3
    assert [row[0] for row in ts.trace_rows] == [0.0, 0.0, 0.05, 0.05, 0.1, 0.1]


def test_a_duplicate_replaces_the_first_and_is_counted(paper: Scenario) -> None:
    ts = steps(paper)
    ts.on_report(0.0, report(paper, "A", 0, s=10.0))
    ts.on_report(0.0, report(paper, "A", 0, s=11.0))
    assert ts.counters["duplicate"] == 1 and ts.next_step == 0
    ts.on_report(0.0, report(paper, "B", 0))
    rows = {row[1]: row for row in ts.trace_rows}
    assert rows["A"][4] == pytest.approx(11.0)  # s of the second report


@dataclass(frozen=True)
class LeftReport(Report):
    presence: str = "left"


def test_a_repeated_left_report_is_ignored(paper: Scenario) -> None:
    """A car repeats its "left" report (services.daemons.vehicle ``LEFT_REPEATS``): the
    first is its truth, the repeats change nothing and are not logged."""
    ts = steps(paper)
    first = report(paper, "A", 0)
    left = LeftReport(first.vehicle, first.step, first.state)
    assert ts.on_report(0.0, left) is True
    assert ts.on_report(0.0, left) is False and ts.on_report(0.01, left) is False
    assert ts.counters["duplicate"] == 0
    # a report of that car after its leave is out of the world
    assert ts.on_report(0.05, report(paper, "A", 1)) is False
    assert ts.counters["out_of_world"] == 1


def test_a_missing_car_is_never_filled_in_it_is_a_gap(paper: Scenario) -> None:
    ts = steps(paper, speed=2.0)
    for k in range(4):
        ts.on_report(k * DT, report(paper, "A", k, s=10.0 + k))
        if k != 3:  # B's step 3 never comes
            ts.on_report(k * DT, report(paper, "B", k, s=20.0 + k))
    assert ts.next_step == 3
    # overdue TRUTH_WAIT_S wall seconds after its time: run time 3 dt + 1 s x speed 2
    deadline = 3 * DT + TRUTH_WAIT_S * 2.0
    assert ts.next_deadline() == pytest.approx(deadline)
    ts.advance(deadline - 0.01)
    assert ts.next_step == 3
    ts.advance(deadline)
    assert ts.next_step == 4 and ts.gaps == 1 and ts.counters["gaps"] == 1
    assert ts.truth_gaps() == {"A": 0, "B": 1} and ts.degraded
    # step 3 has A only: nothing of B's step 2 is carried over to it
    rows_3 = [row for row in ts.trace_rows if row[0] == pytest.approx(3 * DT)]
    assert [row[1] for row in rows_3] == ["A"]
    assert [k for k, rows in ts.steps() if len(rows) == 1] == [3]


def test_a_late_report_is_kept_as_its_steps_truth(paper: Scenario) -> None:
    ts = steps(paper, speed=2.0)
    for k in range(4):
        ts.on_report(k * DT, report(paper, "A", k, s=10.0 + k))
        if k != 3:
            ts.on_report(k * DT, report(paper, "B", k, s=20.0 + k))
    ts.advance(3 * DT + TRUTH_WAIT_S * 2.0)
    assert ts.degraded
    # B's report for step 3 comes after its step was closed: late, and still its truth
    ts.on_report(3.0, report(paper, "B", 3, s=23.0))
    assert ts.late == 1 and ts.next_step == 4
    assert ts.truth_gaps() == {"A": 0, "B": 0} and not ts.degraded and ts.gaps == 0
    rows = {row[1]: row for row in ts.trace_rows if row[0] == pytest.approx(3 * DT)}
    assert rows["B"][4] == pytest.approx(23.0)


def test_a_car_a_second_ahead_closes_the_gap_step_without_waiting(paper: Scenario) -> None:
    ts = steps(paper)
    ahead = round(1.0 / DT)
    for k in range(ahead + 1):
        ts.on_report(k * DT, report(paper, "A", k))
        if k != 0:  # B misses step 0
            ts.on_report(k * DT, report(paper, "B", k))
    # at the last report A and B are one second past step 0: step 0 is closed without B
    assert ts.next_step == ahead + 1 and ts.gaps == 1
    assert ts.truth_gaps() == {"A": 0, "B": 1}


def _centre_s(sc: Scenario, vid: str) -> float:
    return sc.vehicle_crossings(vid)[0].center_s


def test_an_overlap_at_a_late_cars_step_is_a_collision_once_its_report_comes(
    paper: Scenario,
) -> None:
    """Issue 16, step 508: A stands in the conflict zone; B crosses it in one step, and
    its report of that very step is late. Filled in from B's step before (30 m back) the
    run looked clean; now it is a gap (degraded, never clean) until the report arrives,
    and then the overlap of that step is a collision."""
    ts = steps(paper)
    a_s, b_s = _centre_s(paper, "A"), _centre_s(paper, "B")
    hit = 10
    ahead = round(1.0 / DT)
    for k in range(hit + ahead + 1):
        ts.on_report(k * DT, report(paper, "A", k, s=a_s, v=0.0))
        if k != hit:
            ts.on_report(k * DT, report(paper, "B", k, s=b_s + 30.0 * (k - hit)))
    assert ts.next_step == hit + ahead + 1  # A a second ahead: step `hit` closed without B
    before = ts.metrics()
    assert before.collisions == 0 and ts.truth_gaps()["B"] == 1 and ts.degraded
    assert before.min_gap_m > 20.0  # every step measured is far apart: only the gap is not
    ts.on_report((hit + ahead) * DT, report(paper, "B", hit, s=b_s))  # late, at last
    after = ts.metrics()
    assert ts.late == 1 and not ts.degraded
    assert after.collisions == 1 and after.min_gap_m == 0.0
    assert after.collision_events[0].t == pytest.approx(hit * DT)


def test_after_close_only_late_reports_of_closed_steps_are_kept(paper: Scenario) -> None:
    ts = steps(paper)
    for k in range(3):
        ts.on_report(k * DT, report(paper, "A", k))
    ts.on_report(0.0, report(paper, "B", 0))
    assert ts.next_step == 1
    ts.close()
    assert ts.next_deadline() is None
    assert not ts.on_report(0.2, report(paper, "B", 1))  # never closed: after the end
    ts.advance(100.0)
    assert ts.next_step == 1 and [k for k, _rows in ts.steps()] == [0]
    assert ts.truth_gaps() == {"A": 0, "B": 0}


def test_peer_mistakes_are_counted_and_dropped(paper: Scenario) -> None:
    ts = steps(paper, speed=10.0)
    a0 = report(paper, "A", 0)
    ts.on_report(0.0, Report("Z", 0, a0.state))  # not a car of the run
    far = round((FUTURE_TOLERANCE_S * 10.0 + 1.0) / DT)
    ts.on_report(0.0, report(paper, "A", far))  # a step from the far future
    assert ts.counters["unknown_vehicle"] == 1 and ts.counters["future"] == 1
    assert ts.next_deadline() is None and ts.next_step == 0
    ts.on_report(0.0, report(paper, "A", 0))
    ts.on_report(0.0, report(paper, "B", 0))
    assert ts.next_step == 1  # the far step did not force anything through


def test_the_run_is_done_at_max_sim_s_or_when_every_car_stands_at_its_goal(
    paper: Scenario,
) -> None:
    ts = steps(paper, max_sim_s=0.1)
    for k in range(5):
        for vid in ("A", "B"):
            ts.on_report(k * DT, report(paper, vid, k))
    assert ts.done_reason == "max_sim_s (0.1 s) reached" and ts.next_step == 3
    assert ts.next_deadline() is None and ts.late == 0

    ts = steps(paper)
    for vid in ("A", "B"):
        ts.on_report(0.0, report(paper, vid, 0, s=paper.goal_m(vid), v=0.0))
    assert ts.done_reason == "every car stands at its goal"


def test_truth_steps_refuse_bad_settings(paper: Scenario) -> None:
    for kw in ({"speed": 0.0}, {"max_sim_s": float("nan")}, {"wait_s": -1.0}):
        with pytest.raises(ValueError):
            steps(paper, **kw)
    with pytest.raises(ValueError, match="distinct"):
        TruthSteps(paper, ("A", "A"), speed=1.0, max_sim_s=1.0)


# --------------------------------------------------------------------------- MonitorCore


def rules(**kw: object) -> MonitorRules:
    fields: dict[str, object] = {
        "run_id": "run-1",
        "vehicles": ("A", "B"),
        "rsus": ("rsu1",),
        "max_sim_s": 0.2,
        "epoch_unix": EPOCH,
        "wait_actors_s": 10.0,
        "ack_timeout_s": 2.0,
        "stats_wait_s": 3.0,
    }
    fields.update(kw)
    return MonitorRules(**fields)  # type: ignore[arg-type]


def started(sc: Scenario, **kw: object) -> MonitorCore:
    core = MonitorCore(sc, rules(**kw))
    for node in ("A", "B", "rsu1", "monitor"):
        core.on_alive(EPOCH - 5.0, node, True)
    assert core.poll(EPOCH - 1.0) == Actions(start=True)
    assert core.phase is Phase.RUNNING and core.epoch == EPOCH
    return core


def test_the_run_starts_once_every_actor_is_alive(paper: Scenario) -> None:
    core = MonitorCore(paper, rules(epoch_unix=None, start_delay_s=0.5))
    assert core.next_deadline() is None
    core.on_alive(100.0, "A", True)
    assert core.poll(100.0) == Actions()
    assert core.next_deadline() == 110.0  # waiting for the others
    core.on_alive(101.0, "B", True)
    core.on_alive(101.0, "rsu1", True)
    assert core.poll(101.0) == Actions(start=True)
    assert core.epoch == 101.5 and core.started and core.run_time(102.5) == pytest.approx(1.0)


def test_missing_actors_fail_the_run_naming_them(paper: Scenario) -> None:
    core = MonitorCore(paper, rules(wait_actors_s=0.3))
    core.on_alive(0.0, "A", True)
    assert core.poll(0.0) == Actions()
    assert core.poll(0.3) == Actions(over=True)
    assert core.failure is not None and "actors not present after 0.3 s: B, rsu1" in core.failure
    assert not core.started and core.phase is Phase.OVER


def test_the_start_repeats_until_every_actor_acknowledged(paper: Scenario) -> None:
    core = started(paper)
    t = EPOCH - 1.0
    assert core.next_deadline() == pytest.approx(t + START_REPEAT_S)
    assert core.poll(t + 0.1) == Actions()
    assert core.poll(t + START_REPEAT_S) == Actions(start=True)
    for node in ("A", "B", "rsu1"):
        core.on_stats(node, final=False)
    assert core.poll(t + 2 * START_REPEAT_S) == Actions()
    assert core.next_deadline() is None  # no car reported truth yet


def test_an_actor_that_never_acknowledges_fails_the_run(paper: Scenario) -> None:
    core = started(paper)
    core.on_stats("A", final=False)
    core.on_stats("B", final=False)
    assert core.next_deadline() == pytest.approx(EPOCH - 1.0 + START_REPEAT_S)
    actions = core.poll(EPOCH + 2.0)
    assert actions.stop is not None and "no acknowledgement of run run-1 from rsu1" in actions.stop
    assert core.phase is Phase.ENDING and core.end_wall == EPOCH + 2.0


def test_a_run_to_max_sim_s_then_the_final_stats(paper: Scenario) -> None:
    core = started(paper)
    for node in ("A", "B", "rsu1"):
        core.on_stats(node, final=False)
    for k in range(6):
        now = EPOCH + k * DT
        for vid in ("A", "B"):
            core.on_truth(now, report(paper, vid, k))
        actions = core.poll(now)
        if core.done_reason is not None:
            break
        assert actions == Actions()
    assert actions == Actions(stop="max_sim_s (0.2 s) reached")
    assert core.truth.next_step == 5 and core.truth.last_t == pytest.approx(0.2)
    assert not core.on_truth(now, report(paper, "A", 5))  # after the end: not taken
    assert core.truth.late == 0 and core.truth.next_step == 5
    # a late (here duplicate) report of a closed step is still that step's truth
    assert core.on_truth(now, report(paper, "A", 1, s=10.5))
    assert core.truth.late == 1 and core.truth.counters["duplicate"] == 1
    assert core.next_deadline() == pytest.approx(now + 3.0)
    core.on_stats("A", final=True)
    core.on_stats("B", final=True)
    assert core.poll(now + 0.1) == Actions()
    core.on_stats("rsu1", final=True)
    assert core.poll(now + 0.2) == Actions(over=True)
    assert core.failure is None and core.phase is Phase.OVER


def test_the_stats_wait_ends_with_a_warning(
    paper: Scenario, caplog: pytest.LogCaptureFixture
) -> None:
    core = started(paper, max_sim_s=0.05)
    for node in ("A", "B", "rsu1"):
        core.on_stats(node, final=False)
    for vid in ("A", "B"):
        core.on_truth(EPOCH + DT, report(paper, vid, 0))
        core.on_truth(EPOCH + DT, report(paper, vid, 1))
    assert core.poll(EPOCH + DT).stop is not None
    core.on_stats("A", final=True)
    with caplog.at_level(logging.WARNING, logger="crosspath.monitor"):
        assert core.poll(EPOCH + DT + 2.9) == Actions()
        assert core.poll(EPOCH + DT + 3.0) == Actions(over=True)
    assert "no final stats from B, rsu1" in caplog.text


def test_a_lost_actor_fails_the_run_and_is_not_waited_for(paper: Scenario) -> None:
    core = started(paper)
    for node in ("A", "B", "rsu1"):
        core.on_stats(node, final=False)
    core.on_alive(EPOCH + 1.0, "B", False)
    assert core.failure is not None and core.failure.startswith("B lost")
    assert core.poll(EPOCH + 1.0).stop == core.failure
    core.on_stats("A", final=True)
    core.on_stats("rsu1", final=True)
    assert core.poll(EPOCH + 1.1) == Actions(over=True)  # B sends no final report


def test_expected_crashes_are_listed_and_the_start_repeats_all_run(paper: Scenario) -> None:
    core = started(paper, may_crash=frozenset({"rsu1"}))
    for node in ("A", "B", "rsu1"):
        core.on_stats(node, final=False)
    core.on_alive(EPOCH + 1.0, "rsu1", False)
    core.on_alive(EPOCH + 1.5, "rsu1", True)
    assert core.failure is None
    assert core.crashes == [
        {"node": "rsu1", "event": "lost", "t_s": 1.0},
        {"node": "rsu1", "event": "back", "t_s": 1.5},
    ]
    assert core.poll(EPOCH + 1.5) == Actions(start=True)  # for the restarted RSU
    assert core.poll(EPOCH + 1.6) == Actions()
    assert core.poll(EPOCH + 1.5 + START_REPEAT_S) == Actions(start=True)


def test_abort_before_and_during_the_run(paper: Scenario) -> None:
    core = MonitorCore(paper, rules())
    core.abort()
    assert core.poll(0.0) == Actions(over=True)
    assert core.failure == "monitor stopped by a signal before the run started"

    core = started(paper)
    core.abort("hit an internal error")
    actions = core.poll(EPOCH)
    assert actions.stop == "monitor hit an internal error before the run was over"
    assert core.failure == actions.stop


def test_monitor_rules_are_checked(paper: Scenario) -> None:
    with pytest.raises(ValueError, match="share an id"):
        MonitorCore(paper, rules(rsus=("A",)))
    with pytest.raises(ValueError, match="not actors"):
        MonitorCore(paper, rules(may_crash=frozenset({"Z"})))
    with pytest.raises(ValueError, match="ack_timeout_s"):
        MonitorCore(paper, rules(ack_timeout_s=0.0))
