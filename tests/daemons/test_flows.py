"""Flows with the daemons (issue 12): the expanded scenario, insertion and removal in the
car daemon, the monitor's presence-aware truth core, several cars per process."""

from __future__ import annotations

import argparse
import asyncio
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import TypeVar

import pytest

from services.daemons.host import CarHost, host_configs, parse_ids
from services.daemons.monitor import MonitorConfig, MonitorService
from services.daemons.rsu import RsuDaemon, RsuDaemonConfig
from services.daemons.vehicle import VehicleDaemon, VehicleDaemonConfig, load_daemon
from services.daemons.world import TruthBoard, entry_predecessors
from services.edge.lifecycle import serve
from services.edge.plumbing import PlumbingError, TruthReport, decode_truth, encode_truth
from services.edge.settings import CommonDaemonConfig, ConfigError, load_config
from services.edge.transport import MemoryBus, MemoryTransport
from services.model.kinematics import TruthState
from services.model.scenario import Scenario, ScenarioError, load_scenario
from services.model.types import RunMode
from services.sim.truth import TruthSteps, arrival_step
from services.supervise.expand import expand_scenario, plain_scenario, scenario_toml
from services.supervise.hosts import default_cars_per_process, group_cars, host_name
from services.supervise.launcher import actor_commands, loopback_endpoints, node_order

REPO = Path(__file__).resolve().parents[2]
SMALL = REPO / "tests" / "data" / "four-way-flows-small.toml"
FLOWS = REPO / "scenarios" / "four-way-flows.toml"
FORTY = REPO / "scenarios" / "four-way-flows-40.toml"
PAPER = REPO / "scenarios" / "paper-blind-intersection.toml"

C = TypeVar("C", bound=CommonDaemonConfig)


def config(model: type[C], **fields: object) -> C:
    return load_config(model, None, fields, env={})


# --------------------------------------------------------------------------- expansion


def test_the_expanded_file_is_the_seeds_cars_with_fixed_start_times(tmp_path: Path) -> None:
    sc = load_scenario(FLOWS)
    with pytest.raises(ScenarioError, match="crosspath up"):
        sc.require_no_flows("a daemon")
    out = expand_scenario(sc, 3, tmp_path / "scenario.toml")
    plain = load_scenario(out)
    plain.require_no_flows("a daemon")  # no flows left
    drawn = sc.for_seed(3)
    assert [v.id for v in plain.vehicles] == [v.id for v in drawn.vehicles]
    assert plain.draw_start_times(0) == plain.draw_start_times(99) == drawn.draw_start_times(3)
    assert plain.spec == plain_scenario(sc, 3).spec and plain.name == sc.name
    # a [[vehicles]] range is fixed to the seed's draw too
    paper = plain_scenario(load_scenario(PAPER), 5)
    assert paper.draw_start_times(0) == load_scenario(PAPER).draw_start_times(5)


def test_the_forty_car_scenario_has_forty_cars_for_every_seed() -> None:
    sc = load_scenario(FORTY)
    assert {len(sc.for_seed(seed).vehicles) for seed in (0, 1, 7)} == {40}


# --------------------------------------------------------------------------- hosts


def test_cars_are_grouped_into_hosts_that_keep_one_node_per_car(tmp_path: Path) -> None:
    path = expand_scenario(load_scenario(SMALL), 0, tmp_path / "scenario.toml")
    sc = load_scenario(path)
    cars = [v.id for v in sc.vehicles]
    assert default_cars_per_process(2) == 1 and default_cars_per_process(40, cpus=2) == 10
    assert default_cars_per_process(len(cars), cpus=2) == 3
    nodes = node_order(sc, RunMode.RSU)
    endpoints = loopback_endpoints(nodes)
    # the launcher builds one command per car, then groups them
    commands = actor_commands(path, RunMode.RSU, "paper", 0, 1.0, endpoints)
    assert len(commands) == 2 + len(cars)
    grouped = group_cars(commands, cars, 5)
    assert list(grouped) == ["monitor", "rsu1", host_name(0), host_name(1), host_name(2)]
    argv = grouped[host_name(1)]
    ids = argv[argv.index("--ids") + 1].split(",")
    assert ids == cars[5:10]
    listens = [argv[i + 1] for i, a in enumerate(argv) if a == "--listen"]
    assert listens == [loc for car in ids for loc in endpoints[car].locators]
    assert "zenoh.connect_in_turn=true" in argv  # the host's cars open their links in turn
    # the host gives each car its own endpoints; car k also connects to cars 0..k-1
    args = argparse.Namespace(
        scenario=path, node_id=None, listen=listens, connect=["tcp/127.0.0.1:1"]
    )
    base = config(VehicleDaemonConfig, node_id=ids[0], scenario=str(path))
    base = base.model_copy(
        update={
            "zenoh": base.zenoh.model_copy(
                update={"listen": args.listen, "connect": [], "connect_in_turn": True}
            )
        }
    )
    per_car = host_configs(base, ids)
    assert [c.node_id for c in per_car] == ids
    assert per_car[2].zenoh.listen == endpoints[ids[2]].locators
    assert per_car[2].zenoh.connect == endpoints[ids[0]].locators + endpoints[ids[1]].locators
    assert all(c.zenoh.connect_in_turn for c in per_car)
    with pytest.raises(ConfigError):
        host_configs(base, ids[:3])  # 10 endpoints do not split among 3 cars
    with pytest.raises(ValueError):
        parse_ids("A,A")
    assert group_cars(commands, cars, 1) == commands


def test_a_daemon_refuses_a_file_with_flows_and_names_crosspath_up() -> None:
    args = argparse.Namespace(scenario=FLOWS, node_id="we-0")
    with pytest.raises(ConfigError, match="crosspath up"):
        load_daemon(args)


# --------------------------------------------------------------------------- truth core


def state(vid: str, t: float, s: float, speed: float = 5.0) -> TruthState:
    return TruthState(vid, t, -60.0 + s, -1.75, 0.0, speed, 0.0, s, 4.5, 1.8)


def test_truth_steps_expect_a_car_only_between_arrival_and_removal() -> None:
    sc = plain_scenario(load_scenario(SMALL), 0)
    cars = [v.id for v in sc.vehicles]
    starts = sc.draw_start_times(0)
    a, b = "we-0", "we-1"  # b arrives at 3 s
    assert starts[a] == 0.0 and starts[b] == pytest.approx(3.0)
    assert entry_predecessors(sc, b, starts) == [a] and entry_predecessors(sc, a, starts) == []
    others = [c for c in cars if c not in (a, b)]
    ts = TruthSteps(sc, cars, speed=1.0, max_sim_s=60.0, start_times={a: 0.0, b: 3.0})
    ts.start_times = {**{c: 1000.0 for c in others}, a: 0.0, b: 3.0}
    ts = TruthSteps(sc, cars, speed=1.0, max_sim_s=60.0, start_times=ts.start_times)
    dt = 0.05
    kb = arrival_step(3.0, dt)
    assert kb == 60 and ts.expected(0) == [a] and set(ts.expected(kb)) == {a, b}
    # b before its arrival is not in the world: dropped
    assert not ts.on_report(0.0, TruthReport("r", 0, state(b, 0.0, 0.0)))
    for k in range(kb + 10):
        ts.on_report(k * dt, TruthReport("r", k, state(a, k * dt, k * 0.25)))
        if k >= kb:  # b waits 5 steps at its entry, then is inserted
            presence = "waiting" if k < kb + 5 else "in"
            ts.on_report(k * dt, TruthReport("r", k, state(b, k * dt, 0.0, 0.0), presence=presence))
    assert ts.next_step == kb + 10 and ts.gaps == 0
    assert [len(rows) for k, rows in ts.steps() if k in (kb, kb + 4, kb + 5)] == [1, 1, 2]
    # a leaves at its goal: after that step it is not expected any more
    k = kb + 10
    ts.on_report(k * dt, TruthReport("r", k, state(a, k * dt, 100.0, 0.0), presence="left"))
    ts.on_report(k * dt, TruthReport("r", k, state(b, k * dt, 1.0)))
    ts.on_report((k + 1) * dt, TruthReport("r", k + 1, state(b, (k + 1) * dt, 1.2)))
    assert ts.next_step == k + 2 and ts.expected(k + 1) == [b]
    assert not ts.on_report(k * dt, TruthReport("r", k + 2, state(a, k * dt, 100.0)))  # gone
    m = ts.metrics()
    assert m.vehicles[b].insertion_delay_s == pytest.approx(5 * dt)
    assert m.vehicles[a].insertion_delay_s == 0.0
    assert m.vehicles[others[0]].insertion_delay_s is None  # never arrived
    recv = ts.expected_receivers(1)
    assert 1.0 < recv["fp"] < 2.0 and recv["ap"] == 1.0 and 1.0 < recv["beacon"] < 2.0


def test_nobody_in_the_world_closes_steps_on_time_and_all_left_ends_the_run() -> None:
    sc = plain_scenario(load_scenario(SMALL), 0)
    ts = TruthSteps(sc, ["we-0"], speed=1.0, max_sim_s=60.0, start_times={"we-0": 1.0})
    assert ts.next_deadline() == 0.0
    ts.advance(0.5)  # steps 0..10 are due, nobody is in the world: closed on time only
    assert ts.next_step == 11 and ts.next_deadline() == pytest.approx(0.55)
    ts.advance(1.0)
    assert ts.next_step == 20  # step 20 waits for we-0
    ts.on_report(1.0, TruthReport("r", 20, state("we-0", 1.0, 120.0, 0.0), presence="left"))
    assert ts.done_reason == "every car has left at its goal"


def test_truth_reports_carry_presence_and_refuse_a_bad_one() -> None:
    r = TruthReport("r", 3, state("A", 0.15, 1.0), presence="waiting")
    assert decode_truth(encode_truth(r)) == r
    with pytest.raises(PlumbingError):
        TruthReport("r", 3, state("A", 0.15, 1.0), presence="gone")


def test_a_shared_board_forgets_cars_that_left_and_other_runs() -> None:
    board = TruthBoard()
    board.reset("r1")
    board.take(TruthReport("r1", 1, state("A", 0.05, 1.0), presence="waiting"))
    assert "A" not in board.entered
    board.take(TruthReport("r1", 2, state("A", 0.1, 1.0)))
    board.take(TruthReport("r0", 9, state("B", 0.1, 1.0)))
    assert set(board.latest) == {"A"} and board.entered == {"A"}
    board.take(TruthReport("r1", 3, state("A", 0.15, 1.0), presence="left"))
    board.take(TruthReport("r1", 2, state("A", 0.1, 1.0)))  # late: ignored once gone
    assert board.latest == {} and board.entered == {"A"}
    board.reset("r1")  # the same run: kept
    assert board.entered == {"A"}
    board.reset("r2")
    assert board.entered == set()


# --------------------------------------------------------------------------- a run


@dataclass
class Run:
    monitor: MonitorService
    cars: list[VehicleDaemon]


async def run_flows(
    scenario: Scenario,
    path: Path,
    hosts: Sequence[Sequence[str]],
    speed: float,
    max_sim_s: float = 300.0,
) -> Run:
    """The monitor, the RSU and the cars (in hosts of several) in this loop over one bus."""
    bus = MemoryBus()
    stop = asyncio.Event()
    services: list[CarHost | RsuDaemon] = []
    cars: list[VehicleDaemon] = []
    for ids in hosts:
        group = [
            VehicleDaemon(
                config(VehicleDaemonConfig, node_id=v, scenario=str(path), stats_period_s=0.5),
                scenario,
                MemoryTransport(bus),
            )
            for v in ids
        ]
        cars += group
        services.append(CarHost(group))
    for r in scenario.rsus:
        rcfg = config(RsuDaemonConfig, node_id=r.id, scenario=str(path))
        services.append(RsuDaemon(rcfg, scenario, MemoryTransport(bus)))
    mcfg = config(
        MonitorConfig,
        scenario=str(path),
        mode="rsu",
        start_delay_s=0.3,
        stats_wait_s=2.0,
        max_sim_s=max_sim_s,  # the run ends when every car has left; this bounds a stall
        **{"time.speed": speed},
    )
    monitor = MonitorService(mcfg, scenario, MemoryTransport(bus))
    tasks = [asyncio.ensure_future(serve(s, install_signals=False, stop=stop)) for s in services]
    try:
        code = await serve(monitor, install_signals=False)
    finally:
        stop.set()
        codes = await asyncio.gather(*tasks)
    assert code == 0 and codes == [0] * len(services)
    return Run(monitor, cars)


async def test_flow_cars_are_inserted_and_removed_by_daemons_in_shared_hosts(
    tmp_path: Path,
) -> None:
    plain = plain_scenario(load_scenario(SMALL), 0)
    keep = ["we-0", "we-1", "we-2", "ew-0", "sn-0", "ns-0"]  # 3 through one entry: a queue
    cars_spec = [v for v in plain.spec.vehicles if v.id in keep]
    sc = Scenario(plain.spec.model_copy(update={"vehicles": cars_spec}), str(tmp_path / "s.toml"))
    path = tmp_path / "s.toml"
    path.write_text(scenario_toml(sc))
    sc = load_scenario(path)
    cars = [v.id for v in sc.vehicles]
    assert cars == keep
    run = await run_flows(sc, path, [cars[:3], cars[3:]], speed=4.0)
    result = run.monitor.result
    assert result is not None and result.error is None and result.harness == "daemons"
    assert result.end_reason == "every car has left at its goal"
    summary = result.summary
    assert summary is not None
    assert summary.vehicles_inserted == 6 and summary.vehicles_finished == 6
    assert summary.all_finished and summary.mean_delay_s is not None
    assert all(
        v.insertion_delay_s is not None and v.delay_s is not None for v in result.vehicles.values()
    )
    # we-1 arrives (3 s) while we-0 is still near the entry: it waits, as in the harness
    wait = result.vehicles["we-1"].insertion_delay_s
    assert wait is not None and wait > 0.5
    assert result.network is not None and result.network.stream("fp") is not None
    actors = result.actors or {}
    for car in run.cars:  # each car reported its insertion and removal in its own stats
        entry = actors[car.node]
        assert entry["inserted_s"] is not None and entry["left_s"] is not None
        assert entry["left_s"] > entry["inserted_s"] >= result.start_times[car.node] - 1e-9
        assert car.shell.stats.snapshot(None)["node"] == car.node
    # one world subscription per host: only each host's first car owns it
    assert [c.world_owner for c in run.cars] == [k in (0, 3) for k in range(6)]
    assert run.cars[0].world is run.cars[2].world is not run.cars[3].world
