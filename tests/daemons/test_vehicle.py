"""The vehicle daemon: following run control, its loop, hostile input (in memory and over Zenoh)."""

from __future__ import annotations

import asyncio
import logging
import math
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from protocol import FuturePath, decode, encode
from protocol import keys as keyexpr
from services.daemons.vehicle import (
    MAX_EXTRAPOLATION_S,
    VehicleDaemon,
    VehicleDaemonConfig,
    advance,
)
from services.edge.lifecycle import EXIT_FAILED, serve
from services.edge.plumbing import (
    StatsReport,
    StopRun,
    TruthReport,
    alive_key,
    all_truths,
    control_key,
    decode_stats,
    decode_truth,
    encode_control,
    encode_truth,
    truth_key,
)
from services.edge.settings import ZenohSettings
from services.edge.transport import (
    RELIABLE_QOS,
    V2X_QOS,
    MemoryBus,
    MemoryTransport,
    ZenohTransport,
)
from services.model.scenario import load_scenario
from services.model.types import RunMode
from services.supervise.launcher import free_ports
from services.vehicle.agent import VehicleAgent
from tests.daemons.test_daemons import (
    PAPER,
    config,
    future_path,
    start_message,
    truth,
    wait_for,
)

REPO = Path(__file__).resolve().parents[2]


class Harness:
    """A vehicle daemon on a memory bus, and a peer that plays monitor and other car."""

    def __init__(self, node: str = "A") -> None:
        self.bus = MemoryBus()
        self.scenario = load_scenario(PAPER)
        cfg = config(VehicleDaemonConfig, node_id=node, scenario=str(PAPER), stats_period_s=0.1)
        self.daemon = VehicleDaemon(cfg, self.scenario, MemoryTransport(self.bus))
        self.peer = MemoryTransport(self.bus)
        self.stop = asyncio.Event()
        self.truths: list[TruthReport] = []
        self.fps: list[FuturePath] = []
        self.stats: list[StatsReport] = []
        self.task: asyncio.Task[int] | None = None

    async def __aenter__(self) -> Harness:
        self.peer.open()
        self.peer.declare_liveliness(alive_key("monitor"))
        self.peer.subscribe(all_truths(), lambda k, p: self.truths.append(decode_truth(p)))
        self.peer.subscribe(keyexpr.all_stats(), lambda k, p: self.stats.append(decode_stats(p)))

        def on_fp(key: str, payload: bytes) -> None:
            message = decode(payload)
            assert isinstance(message, FuturePath)
            self.fps.append(message)

        self.peer.subscribe(keyexpr.all_future_paths(), on_fp)
        self.task = asyncio.ensure_future(serve(self.daemon, install_signals=False, stop=self.stop))
        await wait_for(lambda: self.daemon.shell._token is not None)
        return self

    async def __aexit__(self, *exc: object) -> None:
        self.stop.set()
        assert self.task is not None
        assert await asyncio.wait_for(self.task, 10.0) == 0
        self.peer.close()

    def control(self, message: object) -> None:
        from services.edge.plumbing import StartRun

        assert isinstance(message, StartRun | StopRun)
        self.peer.publish(control_key(), encode_control(message), RELIABLE_QOS)


async def test_car_follows_a_run_publishing_truth_and_future_paths() -> None:
    async with Harness("A") as h:
        start = start_message("run-1", RunMode.FP_ONLY, speed=10.0)
        h.control(start)
        h.control(start)  # a duplicate is ignored
        await wait_for(lambda: len(h.truths) >= 30)
        assert h.daemon.active is not None and h.daemon.active.run_id == "run-1"
        steps = [t.step for t in h.truths]
        assert steps == list(range(len(steps)))  # one report per physics step, in order
        dt = 1.0 / h.scenario.params.physics_hz
        assert all(math.isclose(t.state.t, t.step * dt) for t in h.truths)
        assert {t.vehicle for t in h.truths} == {"A"} and h.truths[-1].mode == "AUTO"
        assert h.truths[-1].state.speed > 0.0  # A starts at 0 and accelerates
        assert h.fps and all(f.header.sender == "A" for f in h.fps)
        # 10 Hz future paths: one per second physics step
        assert abs(len(h.fps) - (len(steps) + 1) // 2) <= 2
        h.control(StopRun("run-1", "test over", 3.0))
        await wait_for(lambda: h.daemon.active is None and h.daemon.runs_done == 1)
        await wait_for(lambda: any(s.final and s.run_id == "run-1" for s in h.stats))
        final = next(s for s in h.stats if s.final)
        assert final.snapshot["streams"]["fp"]["msgs_tx"] == len(h.fps)
        n = len(h.fps)
        await asyncio.sleep(0.2)
        assert len(h.fps) == n  # stopped sending
        h.control(start)  # a late repeat of the old start is ignored
        await asyncio.sleep(0.1)
        assert h.daemon.active is None


async def test_car_ignores_foreign_runs_sends_nothing_standalone_and_serves_the_next_run() -> None:
    async with Harness("B") as h:
        h.control(
            start_message(
                "other", RunMode.RSU, vehicles=("X", "Y"), start_times={"X": 0.0, "Y": 0.0}
            )
        )
        h.control(start_message("wrong-map", RunMode.RSU, scenario="another-scenario"))
        await asyncio.sleep(0.1)
        assert h.daemon.active is None and h.truths == []
        h.control(
            start_message("solo", RunMode.STANDALONE, speed=10.0, start_times={"A": 0, "B": 0})
        )
        await wait_for(lambda: len(h.truths) >= 20)
        assert h.fps == [] and h.truths[-1].state.speed > 0.0
        h.control(StopRun("solo"))
        await wait_for(lambda: h.daemon.runs_done == 1)
        # the same daemon serves the next run
        h.truths.clear()
        h.control(start_message("next", RunMode.FP_ONLY, speed=10.0))
        await wait_for(lambda: len(h.truths) >= 5 and len(h.fps) >= 2)
        # B arrives at 0.5 s: no truth before its insertion (issue 12)
        assert {t.run_id for t in h.truths} == {"next"} and h.truths[0].step == 10
        h.control(StopRun("next"))
        await wait_for(lambda: h.daemon.runs_done == 2)


async def test_car_senses_the_other_car_from_its_ground_truth() -> None:
    async with Harness("A") as h:
        h.control(start_message("run-s", RunMode.FP_ONLY, speed=5.0))
        await wait_for(lambda: len(h.truths) >= 2)
        other = truth("B", t=h.truths[-1].state.t, x=-190.0, speed=1.0)
        report = TruthReport("run-s", 10**6, other, "AUTO", "cruise")
        h.peer.publish(truth_key("B"), encode_truth(report), RELIABLE_QOS)
        h.peer.publish(truth_key("C"), encode_truth(report), RELIABLE_QOS)  # B's truth on C's key
        h.peer.publish(truth_key("B"), b"junk", RELIABLE_QOS)
        await wait_for(lambda: "B" in h.daemon.others)
        assert set(h.daemon.others) == {"B"}
        await wait_for(lambda: h.daemon.shell.plumbing_malformed >= 1)
        h.control(StopRun("run-s"))


async def test_monitor_loss_ends_the_run() -> None:
    async with Harness("A") as h:
        h.control(start_message("run-m", RunMode.FP_ONLY, speed=10.0))
        await wait_for(lambda: h.daemon.active is not None)
        h.peer.close()  # the monitor's liveliness token goes
        await wait_for(lambda: h.daemon.active is None and h.daemon.runs_done == 1)
        h.peer = MemoryTransport(h.bus)


async def test_stop_signal_mid_run_publishes_final_stats() -> None:
    async with Harness("A") as h:
        h.control(start_message("run-t", RunMode.FP_ONLY, speed=10.0))
        await wait_for(lambda: len(h.fps) >= 3)
        h.stop.set()
        assert h.task is not None
        assert await asyncio.wait_for(h.task, 10.0) == 0
        assert any(s.final and s.run_id == "run-t" for s in h.stats)
        n = len(h.fps)
        await asyncio.sleep(0.1)
        assert len(h.fps) == n


def test_advance_moves_truth_along_its_heading() -> None:
    t0 = truth("B", t=1.0, x=-50.0, speed=10.0)
    moved = advance(t0, 1.1)
    assert moved.x == pytest.approx(-49.0) and moved.y == t0.y and moved.t == 1.1
    assert moved.s == pytest.approx(t0.s + 1.0)
    assert advance(t0, 0.9) is t0  # never backwards
    assert advance(t0, 1.0 + MAX_EXTRAPOLATION_S + 0.01) is t0  # too old: as last seen


async def test_a_bug_in_the_agent_stops_the_daemon_with_its_traceback(
    monkeypatch: pytest.MonkeyPatch, caplog: pytest.LogCaptureFixture
) -> None:
    def broken(self: VehicleAgent, *args: object) -> None:
        raise ZeroDivisionError("injected bug")

    monkeypatch.setattr(VehicleAgent, "on_message", broken)
    h = Harness("A")
    await h.__aenter__()
    try:
        h.control(start_message("run-9", RunMode.FP_ONLY, speed=5.0))
        await wait_for(lambda: h.daemon.agent is not None)
        clock = h.daemon.shell.clock
        assert clock is not None
        with caplog.at_level(logging.ERROR, logger="crosspath"):
            h.peer.publish(keyexpr.future_path("B"), encode(future_path("B", clock.now())), V2X_QOS)
            assert h.task is not None
            assert await asyncio.wait_for(h.task, 10.0) == EXIT_FAILED
    finally:
        h.stop.set()
        h.peer.close()
    traced = [r for r in caplog.records if r.exc_info]
    assert len(traced) == 1 and isinstance(traced[0].exc_info[1], ZeroDivisionError)  # type: ignore[index]
    # the run was ended and its final stats published, counting the bug
    final = [s for s in h.stats if s.final and s.run_id == "run-9"]
    assert final and final[-1].snapshot["internal_errors"] == 1


# --------------------------------------------------------------------------- over Zenoh


@pytest.mark.daemons
async def test_real_vehicle_daemon_survives_garbage_and_counts_it() -> None:
    ((udp, tcp),) = free_ports(1)
    listen = [f"udp/127.0.0.1:{udp}", f"tcp/127.0.0.1:{tcp}"]
    proc = subprocess.Popen(
        [sys.executable, "-m", "services.cli.main", "vehicle", "--scenario", str(PAPER),
         "--id", "A", "--listen", listen[0], "--listen", listen[1],
         "--set", "stats_period_s=0.2"],
        cwd=REPO, env={**os.environ, "PYTHONPATH": str(REPO)},
        stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
    )  # fmt: skip
    raw = ZenohTransport(ZenohSettings(listen=[], connect=listen))
    try:
        await raw.open_async()
        alive: set[str] = set()
        raw.watch_liveliness("crosspath/sim/alive/*", lambda k, a: alive.add(k) if a else None)
        reports: list[StatsReport] = []
        raw.subscribe(keyexpr.stats("A"), lambda k, p: reports.append(decode_stats(p)))
        await wait_for(lambda: alive_key("A") in alive, timeout=30.0)

        def malformed(stream: str) -> int:
            if not reports:
                return 0
            data = reports[-1].snapshot["streams"].get(stream, {})
            return int(data.get("malformed", 0))

        garbage = bytes(range(256))[::-1] * 2
        oversized = b"\x01" * 2000
        valid = encode(future_path("X", 0.0))
        padded = valid + b"\x00" * (2000 - len(valid))  # a valid message, but 2000 B
        deadline = time.monotonic() + 20.0
        k = 0
        while malformed("fp") < 5 or malformed("cmd") < 3 or malformed("beacon") < 2:
            assert time.monotonic() < deadline, reports[-1:] or "no stats"
            k += 1  # every round's V2X bytes differ: exact copies are dropped as duplicates
            tag = k.to_bytes(4, "little")
            raw.publish(keyexpr.future_path("X"), garbage + tag, V2X_QOS)
            raw.publish(keyexpr.future_path("X"), padded[:-4] + tag, V2X_QOS)
            raw.publish(keyexpr.rsu_command("rsu1", "A"), oversized[:-4] + tag, V2X_QOS)
            raw.publish(keyexpr.rsu_beacon("rsu1"), b"\xff" + tag, V2X_QOS)
            raw.publish(control_key(), garbage, RELIABLE_QOS)
            raw.publish(truth_key("B"), oversized, RELIABLE_QOS)
            await asyncio.sleep(0.1)
        # it keeps running and reporting
        assert proc.poll() is None
        seen = len(reports)
        await wait_for(lambda: len(reports) >= seen + 2, timeout=10.0)
        last = reports[-1].snapshot
        assert last["plumbing_malformed"] >= 1
        assert last["streams"]["fp"]["msgs_rx"] == 0  # nothing was taken as valid
        proc.send_signal(signal.SIGTERM)
        _out, err = await asyncio.to_thread(proc.communicate, timeout=20)
        assert proc.returncode == 0, err
        assert "Traceback" not in err
    finally:
        raw.close()
        if proc.poll() is None:
            proc.kill()
            proc.wait()
