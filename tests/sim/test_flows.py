"""Demand in the in-process harness (issue 12): insertion, removal, delays, the summary."""

from __future__ import annotations

import math

import numpy as np
import pytest

from services.model.geometry import Polyline, fillet_polyline
from services.model.kinematics import Limits, TruthState
from services.model.scenario import Scenario, parse_scenario
from services.model.types import RunMode
from services.sim.car import INSERT_GAP_M, entry_clear
from services.sim.harness import SimOptions, Simulation
from services.sim.metrics import RunMetrics, VehicleMetrics, free_flow_time_s
from services.sim.results import run_summary

ONE_ROAD = """
[scenario]
name = "one-road"

[params]
max_sim_s = {max_sim_s}

[[lanes]]
id = "eb"
points = [[-60.0, -1.75], [60.0, -1.75]]

[[lanes]]
id = "wb"
points = [[60.0, 1.75], [-60.0, 1.75]]

[[routes]]
id = "r"
points = [[-60.0, -1.75], [60.0, -1.75]]
"""


def _one_road(vehicles: str, max_sim_s: float = 200.0) -> Scenario:
    return parse_scenario(ONE_ROAD.format(max_sim_s=max_sim_s) + vehicles)


def _cars(n: int, start: float = 0.0) -> str:
    return "".join(
        f'\n[[vehicles]]\nid = "c{k:02d}"\nroute = "r"\nstart_time_s = {start}\n' for k in range(n)
    )


def test_twelve_cars_without_offsets_enter_one_after_another_without_collision() -> None:
    sc = _one_road(_cars(12))
    seen: dict[str, float] = {}

    def watch(now: float, truths: dict[str, TruthState]) -> None:
        for vid in truths:
            seen.setdefault(vid, now)

    sim = Simulation(sc, SimOptions(mode=RunMode.STANDALONE))
    sim.on_step = watch
    r = sim.run()
    m = sim.metrics.result()
    assert r.collisions == 0
    assert r.all_finished and r.summary is not None and r.summary.all_finished
    assert r.summary.vehicles_inserted == 12 and r.summary.vehicles_finished == 12
    inserted = [m.vehicles[f"c{k:02d}"].inserted_s for k in range(12)]
    assert all(t is not None for t in inserted)
    times = [float(t) for t in inserted if t is not None]
    assert times[0] == 0.0
    assert bool(np.all(np.diff(times) > 0.0))  # one after another
    delays = [r.vehicles[f"c{k:02d}"].insertion_delay_s for k in range(12)]
    assert delays[0] == 0.0
    assert all(d is not None and d > 0.0 for d in delays[1:])
    assert seen == {f"c{k:02d}": t for k, t in enumerate(times)}  # absent until inserted
    for k in range(12):
        delay = r.vehicles[f"c{k:02d}"].delay_s
        ins = r.vehicles[f"c{k:02d}"].insertion_delay_s
        assert delay is not None and ins is not None and delay >= ins - 1e-3


def test_a_finished_car_leaves_and_no_longer_blocks_its_route() -> None:
    sc = _one_road(_cars(1) + '\n[[vehicles]]\nid = "late"\nroute = "r"\nstart_time_s = 40.0\n')
    present: list[set[str]] = []
    sim = Simulation(sc, SimOptions(mode=RunMode.STANDALONE))
    sim.on_step = lambda now, truths: present.append(set(truths))
    r = sim.run()
    m = sim.metrics.result()
    first, late = m.vehicles["c00"], m.vehicles["late"]
    assert first.finished_s is not None and first.finished_s < 40.0
    assert r.all_finished and late.finished
    assert late.inserted_s == pytest.approx(40.0) and late.insertion_delay_s == pytest.approx(0.0)
    assert {"c00", "late"} not in present  # never both in the world
    assert "c00" in sim.left and "late" in sim.left
    assert r.sim_s < 40.0 + 2.0 * first.finished_s  # ended when the last car left


def test_a_waiting_car_does_not_enter_on_top_of_a_standing_car() -> None:
    sc = _one_road(
        '\n[[vehicles]]\nid = "a"\nroute = "r"\ngoal_m = 3.0\n'
        '\n[[vehicles]]\nid = "b"\nroute = "r"\nstart_time_s = 0.0\n',
        max_sim_s=5.0,
    )
    sim = Simulation(sc, SimOptions(mode=RunMode.STANDALONE))
    r = sim.run()
    assert r.collisions == 0
    # "a" drives 3 m and stops there: "b" enters only once "a" has left
    m = sim.metrics.result()
    a_done, b_in = m.vehicles["a"].finished_s, m.vehicles["b"].inserted_s
    assert a_done is not None and b_in is not None and b_in > a_done


def _truth(vid: str, x: float, y: float, heading: float = 0.0, speed: float = 0.0) -> TruthState:
    return TruthState(vid, 0.0, x, y, heading, speed, 0.0, 0.0, 4.5, 1.8)


def test_entry_clear_gaps() -> None:
    entry = _truth("new", 0.0, 0.0)
    need = 4.5 + INSERT_GAP_M  # centre to centre at rest
    assert entry_clear(entry, [], 1.0, 2.0)
    assert not entry_clear(entry, [_truth("a", need - 0.1, 0.0)], 1.0, 2.0)
    assert entry_clear(entry, [_truth("a", need + 0.1, 0.0)], 1.0, 2.0)
    # a car ahead moving at 5 m/s needs its headway too
    assert not entry_clear(entry, [_truth("a", need + 4.0, 0.0, speed=5.0)], 1.0, 2.0)
    assert entry_clear(entry, [_truth("a", need + 5.1, 0.0, speed=5.0)], 1.0, 2.0)
    # a car behind coming on at 5 m/s: headway plus its stopping distance (6.25 m)
    assert not entry_clear(entry, [_truth("a", -(need + 11.0), 0.0, speed=5.0)], 1.0, 2.0)
    assert entry_clear(entry, [_truth("a", -(need + 11.5), 0.0, speed=5.0)], 1.0, 2.0)
    # the opposing lane next to the entry does not block; a car across the entry does
    assert entry_clear(entry, [_truth("a", 1.0, 3.5, heading=math.pi)], 1.0, 2.0)
    assert not entry_clear(entry, [_truth("a", 0.0, 0.5, heading=math.pi / 2)], 1.0, 2.0)


def test_free_flow_time_of_a_straight_road() -> None:
    lim = Limits(v_max=10.0, accel=1.0, decel_comfort=2.0, decel_emergency=5.0, actuator_lag_s=0.3)
    line = Polyline([(0.0, 0.0), (200.0, 0.0)])
    # 10 s / 50 m to v_max, 5 s / 25 m to stop, 125 m cruising at 10 m/s
    assert free_flow_time_s(line, 0.0, 200.0, lim) == pytest.approx(27.5, abs=0.05)
    # too short to reach v_max: a triangle, v_peak^2 = 2 * 20 / (1/1 + 1/2)
    v = math.sqrt(2.0 * 20.0 / 1.5)
    assert free_flow_time_s(line, 0.0, 20.0, lim) == pytest.approx(v / 1.0 + v / 2.0, abs=0.05)
    # a sharp corner caps the speed: slower than the straight road of the same length
    bend = Polyline(fillet_polyline([(0.0, 0.0), (100.0, 0.0), (100.0, 100.0)], 5.0))
    straight = Polyline([(0.0, 0.0), (bend.length, 0.0)])
    assert (
        free_flow_time_s(bend, 0.0, bend.length, lim)
        > free_flow_time_s(straight, 0.0, straight.length, lim) + 0.5
    )


def _vm(**kw: object) -> VehicleMetrics:
    base: dict[str, object] = {
        "passing_time_s": None,
        "first_through": False,
        "stops": 0,
        "max_speed_mps": 0.0,
        "finished": False,
        "finished_s": None,
        "entered_zone_s": None,
        "left_zone_s": None,
        "passing_start_s": None,
        "passing_end_s": None,
        "zone_visits": (),
        "mode_time_s": {},
        "reason_time_s": {},
        "mode_changes": (),
    }
    base.update(kw)
    return VehicleMetrics(**base)  # type: ignore[arg-type]


def test_summary_on_a_crafted_run() -> None:
    delays = [1.0, 2.0, 3.0, 10.0]
    cars = {
        f"v{k}": _vm(finished=True, stops=k, inserted_s=0.0, arrival_s=0.0, delay_s=d)
        for k, d in enumerate(delays)
    }
    cars["waiting"] = _vm()  # never inserted
    cars["stuck"] = _vm(stops=2, inserted_s=5.0, arrival_s=1.0)  # inserted, never finished
    metrics = RunMetrics(
        collisions=0, min_gap_m=1.0, min_pet_s=math.inf, sim_s=120.0, vehicles=cars
    )
    s = run_summary(metrics, 120.0)
    assert s.vehicles_inserted == 5
    assert s.vehicles_finished == 4
    assert s.all_finished is False
    assert s.mean_delay_s == pytest.approx(4.0)
    assert s.p95_delay_s == pytest.approx(float(np.percentile(delays, 95)))
    assert s.throughput_vph == pytest.approx(4 * 3600.0 / 120.0)
    assert s.stops_per_vehicle == pytest.approx((0 + 1 + 2 + 3 + 2) / 5)
    empty = run_summary(RunMetrics(0, math.inf, math.inf, 0.0, {}), 0.0)
    assert empty.vehicles_inserted == 0 and empty.all_finished is False
    assert empty.mean_delay_s is None and empty.throughput_vph is None


def test_flow_scenario_runs_and_the_result_has_its_keys() -> None:
    sc = _one_road(
        '\n[[flows]]\nid = "f"\nroute = "r"\nvehicles_per_hour = 1800.0\nend_s = 20.0\n'
        'arrivals = "uniform"\n'
    )
    sim = Simulation(sc, SimOptions(mode=RunMode.STANDALONE, seed=0))
    r = sim.run()
    assert set(r.vehicles) == {f"f-{n}" for n in range(10)}
    assert r.collisions == 0 and r.all_finished
    data = r.to_dict()
    assert {"delay_s", "insertion_delay_s"} <= set(data["vehicles"]["f-0"])
    assert data["summary"]["vehicles_finished"] == 10
    assert set(data["start_times"]) == set(r.vehicles)
