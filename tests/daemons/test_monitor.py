"""The monitor: waiting for actors, starting, recording ground truth, ending, network section."""

from __future__ import annotations

import asyncio
import hashlib
import json
import logging
from pathlib import Path
from typing import Any

import pytest

from protocol import keys as keyexpr
from services.daemons.monitor import (
    MonitorConfig,
    MonitorService,
    expected_receivers,
    format_network,
    network_summary,
    new_run_id,
    rebuild_result,
)
from services.edge.lifecycle import EXIT_FAILED, serve
from services.edge.plumbing import (
    StartRun,
    StatsReport,
    StopRun,
    TruthReport,
    alive_key,
    control_key,
    decode_control,
    encode_stats,
    encode_truth,
    truth_key,
)
from services.edge.settings import ConfigError
from services.edge.transport import RELIABLE_QOS, MemoryBus, MemoryTransport, Subscription
from services.model.results import NetworkSection, TruthCounts
from services.model.scenario import load_scenario
from services.model.types import RunMode
from services.sim.truth import MonitorCore
from tests.daemons.test_daemons import PAPER, config, truth, wait_for


def snapshot(node: str, fp_tx: int = 0, fp_rx: int = 0, nbytes: int = 100) -> dict[str, Any]:
    stream = {
        "msgs_tx": fp_tx,
        "bytes_tx": fp_tx * nbytes,
        "msgs_rx": fp_rx,
        "bytes_rx": fp_rx * nbytes,
        "malformed": 0,
        "dropped_stale": 0,
        "latency": {
            "count": fp_rx,
            "sum_s": 0.002 * fp_rx,
            "min_s": 0.002 if fp_rx else None,
            "max_s": 0.002 if fp_rx else 0.0,
            "negative": 0,
            "buckets": {"166": fp_rx} if fp_rx else {},
        },
    }
    return {"node": node, "time_s": 0.0, "streams": {"fp": stream}}


class FakeActors:
    """Plays every actor of a run on the bus: tokens, acknowledgements, truth, stats."""

    def __init__(self, bus: MemoryBus, nodes: tuple[str, ...]) -> None:
        self.transport = MemoryTransport(bus)
        self.nodes = nodes
        self.tokens: dict[str, Subscription] = {}
        self.starts: list[StartRun] = []
        self.stops: list[StopRun] = []

    def open(self) -> None:
        self.transport.open()
        self.transport.subscribe(control_key(), self._on_control)
        for node in self.nodes:
            self.tokens[node] = self.transport.declare_liveliness(alive_key(node))

    def _on_control(self, key: str, payload: bytes) -> None:
        message = decode_control(payload)
        if isinstance(message, StopRun):
            self.stops.append(message)
            return
        self.starts.append(message)
        for node in self.nodes:
            self.stats(node, message.run_id, final=False)

    def stats(
        self, node: str, run_id: str, final: bool, late_ticks: int | None = None, **counts: int
    ) -> None:
        snap = snapshot(node, **counts)
        if late_ticks is not None:
            snap["late_ticks"] = late_ticks
        report = StatsReport(node, run_id, final, snap)
        self.transport.publish(keyexpr.stats(node), encode_stats(report), RELIABLE_QOS)

    def truth(self, run_id: str, vid: str, step: int, x: float, speed: float = 5.0) -> None:
        state = truth(vid, t=step * 0.05, x=x, speed=speed)
        if vid == "B":  # northbound
            state = type(state)(vid, step * 0.05, 1.75, x, 1.5707963, speed, 0.0, 0.0, 4.5, 1.8)
        report = TruthReport(run_id, step, state, "AUTO", "cruise")
        self.transport.publish(truth_key(vid), encode_truth(report), RELIABLE_QOS)


def monitor(bus: MemoryBus, **fields: object) -> MonitorService:
    defaults: dict[str, object] = {
        "scenario": str(PAPER),
        "start_delay_s": 0.05,
        "stats_wait_s": 1.0,
        "time.speed": 5.0,
    }
    cfg = config(MonitorConfig, **{**defaults, **fields})
    return MonitorService(cfg, load_scenario(PAPER), MemoryTransport(bus))


async def test_monitor_fails_clearly_when_actors_are_missing() -> None:
    bus = MemoryBus()
    actors = FakeActors(bus, ("A",))
    actors.open()
    mon = monitor(bus, wait_actors_s=0.3)
    assert await serve(mon, install_signals=False) == 0
    assert mon.exit_code == 1 and mon.result is None
    assert mon.failure is not None
    assert "actors not present after 0.3 s: B, rsu1" in mon.failure
    assert [line.split(":")[0] for line in mon.presence()] == ["B", "rsu1"]
    assert all("no liveliness token" in line for line in mon.presence())
    assert actors.starts == []


async def test_monitor_runs_records_and_builds_the_result(tmp_path: Path) -> None:
    bus = MemoryBus()
    actors = FakeActors(bus, ("A", "B", "rsu1"))
    actors.open()
    out = tmp_path / "result.json"
    mon = monitor(bus, max_sim_s=0.5, json_out=str(out), run_id="run-42", seed=0)
    task = asyncio.ensure_future(serve(mon, install_signals=False))
    await wait_for(lambda: bool(actors.starts))
    start = actors.starts[0]
    assert start.run_id == "run-42" and start.mode is RunMode.RSU and start.seed == 0
    assert dict(start.start_times) == load_scenario(PAPER).draw_start_times(0)
    assert start.vehicles == ("A", "B") and start.rsus == ("rsu1",) and start.speed == 5.0
    for step in range(15):
        actors.truth("run-42", "A", step, -200.0 + step * 0.25)
        if step >= 4:  # B arrives at 0.167 s: in the world from step 4 (issue 12)
            actors.truth("run-42", "B", step, -200.0 + step * 0.25)
        actors.truth("old-run", "A", step, 0.0)  # another run's truth is ignored
    await wait_for(lambda: bool(actors.stops))
    assert actors.stops[0].run_id == "run-42" and actors.stops[0].sim_s == pytest.approx(0.5)
    actors.stats("A", "run-42", True, fp_tx=5, fp_rx=5)
    actors.stats("B", "run-42", True, fp_tx=5, fp_rx=5)
    actors.stats("rsu1", "run-42", True, fp_rx=10)
    actors.stats("monitor", "run-42", True, fp_tx=999)  # not an actor: ignored
    assert await asyncio.wait_for(task, 10.0) == 0
    assert mon.exit_code == 0 and mon.failure is None
    result = mon.result
    assert result is not None
    assert json.loads(out.read_text()) == result.to_dict()
    assert result.harness == "daemons" and result.run_id == "run-42"
    assert result.sim_s == pytest.approx(0.5)
    assert result.end_reason is not None and result.end_reason.startswith("max_sim_s")
    assert result.truth == TruthCounts(steps=11, gaps=0, late=0)
    assert set(result.vehicles) == {"A", "B"} and result.collisions == 0
    assert result.network is not None
    fp = result.network.stream("fp")
    assert fp is not None
    assert (fp.msgs, fp.bytes, fp.msgs_rx) == (10, 1000, 20)
    # 10 sent x (1 RSU + the other car while both are in the world: steps 4..10 of 0..10)
    assert fp.delivery_ratio == pytest.approx(20 / (10 * (1 + 14 / 18)))
    assert fp.kbps_per_vehicle == pytest.approx(1000 * 8 / 1000 / 0.5 / 2)
    assert fp.latency_ms_p50 == pytest.approx(2.0, rel=0.05)
    assert result.network.total_kbps_per_vehicle == pytest.approx(fp.kbps_per_vehicle)
    assert sorted(result.final_stats or []) == ["A", "B", "rsu1"]
    prov = result.provenance
    assert prov is not None and prov.channel.kind == "zenoh" and prov.policy == "paper"
    assert prov.scenario_sha256 == hashlib.sha256(PAPER.read_bytes()).hexdigest()
    assert set(prov.policy_params) == {"rsu1"}
    # issue 16: a clean run says so; the step log rebuilds the same result
    assert result.degraded is False and result.truth_gaps == {"A": 0, "B": 0}
    assert result.late_ticks == {"A": 0, "B": 0, "rsu1": 0}
    log = tmp_path / "result.steps.jsonl"
    assert log.is_file()
    rebuilt = rebuild_result(tmp_path)
    assert rebuilt.error is None and rebuilt.rebuilt_from == str(log)
    same = ("collisions", "min_gap_m", "min_pet_s", "sim_s", "truth", "network", "vehicles")
    assert {k: getattr(rebuilt, k) for k in same} == {k: getattr(result, k) for k in same}


async def test_monitor_counts_a_missing_truth_step_and_fails_on_a_lost_actor() -> None:
    bus = MemoryBus()
    actors = FakeActors(bus, ("A", "B", "rsu1"))
    actors.open()
    mon = monitor(bus, run_id="run-7", stats_wait_s=0.2)
    task = asyncio.ensure_future(serve(mon, install_signals=False))
    await wait_for(lambda: bool(actors.starts))
    for step in range(30):
        actors.truth("run-7", "A", step, -200.0 + step * 0.25)
        if step != 10:  # B's step 10 never comes (B is in the world from step 4, issue 12)
            actors.truth("run-7", "B", step, -200.0 + step * 0.25)
    await wait_for(lambda: mon.next_step >= 30, timeout=5.0)
    assert mon.truth_gaps == 1
    actors.tokens["B"].close()  # B crashes
    assert await asyncio.wait_for(task, 10.0) == 0
    assert mon.exit_code == 1
    assert mon.failure is not None and mon.failure.startswith("B lost")
    assert actors.stops and actors.stops[-1].reason.startswith("B lost")
    result = mon.result
    assert result is not None and result.error == mon.failure
    assert result.truth_gaps is not None and result.truth_gaps["B"] >= 1
    assert result.truth_gaps["A"] == 0 and result.degraded is True


async def test_late_ticks_of_an_actor_mark_the_run_degraded() -> None:
    bus = MemoryBus()
    actors = FakeActors(bus, ("A", "B", "rsu1"))
    actors.open()
    mon = monitor(bus, run_id="run-8", max_sim_s=0.2, stats_wait_s=2.0)
    task = asyncio.ensure_future(serve(mon, install_signals=False))
    await wait_for(lambda: bool(actors.starts))
    for step in range(5):
        for vid in ("A", "B"):
            actors.truth("run-8", vid, step, -200.0 + step * 0.25)
    await wait_for(lambda: bool(actors.stops))
    actors.stats("A", "run-8", True, late_ticks=0)
    actors.stats("B", "run-8", True, late_ticks=7)
    actors.stats("rsu1", "run-8", True, late_ticks=0)
    assert await asyncio.wait_for(task, 10.0) == 0
    result = mon.result
    assert result is not None and result.error is None
    assert result.truth_gaps == {"A": 0, "B": 0}  # every step's truth came
    assert result.late_ticks == {"A": 0, "B": 7, "rsu1": 0} and result.degraded is True


async def test_monitor_fails_when_an_actor_never_acknowledges() -> None:
    bus = MemoryBus()
    actors = FakeActors(bus, ("A", "B", "rsu1"))
    actors.open()
    actors.nodes = ("A", "B")  # rsu1 is present but deaf
    mon = monitor(bus, ack_timeout_s=0.6, stats_wait_s=0.1)
    assert await serve(mon, install_signals=False) == 0
    assert mon.exit_code == 1
    assert mon.failure is not None and "from rsu1" in mon.failure
    assert len(actors.starts) >= 2  # the start was repeated meanwhile


async def test_stop_signal_aborts_the_run_with_a_partial_result() -> None:
    bus = MemoryBus()
    actors = FakeActors(bus, ("A", "B"))
    actors.open()
    stop = asyncio.Event()
    mon = monitor(bus, mode="fp-only", stats_wait_s=0.1)
    task = asyncio.ensure_future(serve(mon, install_signals=False, stop=stop))
    await wait_for(lambda: bool(actors.starts))
    assert actors.starts[0].rsus == ()
    stop.set()
    assert await asyncio.wait_for(task, 10.0) == 0
    assert mon.exit_code == 1 and mon.result is not None
    assert mon.result.policy is None and "signal" in (mon.result.error or "")
    assert actors.stops


async def started(**fields: object) -> tuple[FakeActors, MonitorService, asyncio.Task[int]]:
    """A monitor serving on a fresh bus with every actor present, once it sent its start."""
    bus = MemoryBus()
    actors = FakeActors(bus, ("A", "B", "rsu1"))
    actors.open()
    mon = monitor(bus, **fields)
    task = asyncio.ensure_future(serve(mon, install_signals=False))
    await wait_for(lambda: bool(actors.starts))
    return actors, mon, task


async def test_a_bug_in_the_monitor_ends_the_run_and_exits_1(
    monkeypatch: pytest.MonkeyPatch, caplog: pytest.LogCaptureFixture
) -> None:
    def broken(self: MonitorCore, *args: object) -> None:
        raise KeyError("injected bug")

    monkeypatch.setattr(MonitorCore, "on_truth", broken)
    actors, mon, task = await started(run_id="run-8", stats_wait_s=0.1)
    with caplog.at_level(logging.ERROR, logger="crosspath"):
        actors.truth("run-8", "A", 0, -200.0)
        assert await asyncio.wait_for(task, 10.0) == EXIT_FAILED
    traced = [r for r in caplog.records if r.exc_info]
    assert len(traced) == 1 and isinstance(traced[0].exc_info[1], KeyError)  # type: ignore[index]
    assert mon.failure == "monitor hit an internal error before the run was over"
    assert actors.stops and actors.stops[-1].run_id == "run-8"  # the actors were told


async def test_a_hostile_truth_report_is_counted_not_raised() -> None:
    actors, mon, task = await started(run_id="run-6", max_sim_s=0.2, stats_wait_s=0.1)
    actors.transport.publish(truth_key("A"), b"\x81garbage", RELIABLE_QOS)
    actors.truth("run-6", "A", 10**9, -200.0)  # a step from the far future
    await wait_for(lambda: mon.core.truth.counters["future"] == 1)
    for step in range(6):
        actors.truth("run-6", "A", step, -200.0 + step * 0.25)
        actors.truth("run-6", "B", step, -200.0 + step * 0.25)
    assert await asyncio.wait_for(task, 10.0) == 0
    assert mon.exit_code == 0 and mon.shell.plumbing_malformed == 1
    assert mon.next_step == 5 and mon.truth_gaps == 0  # the far step forced nothing


def test_network_summary_and_table() -> None:
    assert expected_receivers(2, 1) == {"fp": 2, "ap": 1, "cmd": 1, "beacon": 2}
    assert expected_receivers(5, 0)["fp"] == 4
    assert network_summary([], 2, 1, 10.0) == {"total_kbps_per_vehicle": 0.0}
    section = network_summary([snapshot("A", 10, 0), snapshot("B", 0, 10)], 2, 0, 1.0)
    assert section["fp"]["delivery_ratio"] == pytest.approx(1.0)
    assert section["total_kbps_per_vehicle"] == pytest.approx(4.0)
    table = format_network(NetworkSection.model_validate(section))
    assert table.splitlines()[0].split()[:3] == ["stream", "msgs", "bytes"]
    assert "fp" in table and "total 4.0 kbps per vehicle" in table


def test_monitor_config() -> None:
    cfg = config(MonitorConfig, scenario=str(PAPER))
    assert cfg.node_id == "monitor" and cfg.mode is RunMode.RSU and cfg.run_id is None
    with pytest.raises(ConfigError) as info:
        config(MonitorConfig, scenario=str(PAPER), seed=-1)
    assert info.value.field == "seed"
    with pytest.raises(ConfigError) as info:
        config(MonitorConfig, scenario=str(PAPER), run_id="bad id")
    assert info.value.field == "run_id"
    run_id = new_run_id()
    assert keyexpr.is_valid_id(run_id) and run_id.startswith("r")
