"""The RSU daemon: runs it takes part in, answers at once, terminations on the way out."""

from __future__ import annotations

import asyncio
import logging
import time
from collections.abc import Callable

import numpy as np
import pytest

from protocol import (
    Command,
    CoordinatedPath,
    FuturePath,
    Header,
    Mode,
    ModeCommand,
    RsuBeacon,
    decode,
    encode,
)
from protocol import keys as keyexpr
from services.daemons.rsu import TERMINATION_ROUNDS, RsuDaemon, RsuDaemonConfig
from services.edge.lifecycle import EXIT_FAILED, serve
from services.edge.plumbing import StartRun, StopRun, alive_key, control_key, encode_control
from services.edge.transport import RELIABLE_QOS, V2X_QOS, MemoryBus, MemoryTransport
from services.model.scenario import load_scenario
from services.model.types import Policy, RunMode
from services.rsu.core import RsuCore
from tests.daemons.test_daemons import PAPER, config, start_message, wait_for

VMAX = 50 / 3.6


def approaching_fp(now: float, seconds_to_cross: float = 6.0, mode: Mode = Mode.AUTO) -> FuturePath:
    """Car A eastbound on y = -1.75, reaching x = 1.75 in ``seconds_to_cross`` at V_max."""
    x0 = 1.75 - seconds_to_cross * VMAX
    t = now + np.linspace(0.0, 10.0, 120)
    pts = np.column_stack([x0 + VMAX * (t - now), np.full(120, -1.75), t])
    return FuturePath(Header("A", 1, round(now * 1e6)), x0, -1.75, VMAX, 0.0, 4.5, 1.8, mode, pts)


class Harness:
    """An RSU daemon on a memory bus; the peer plays monitor and cars."""

    def __init__(self, **fields: object) -> None:
        self.bus = MemoryBus()
        cfg = config(RsuDaemonConfig, node_id="rsu1", scenario=str(PAPER), **fields)
        self.daemon = RsuDaemon(cfg, load_scenario(PAPER), MemoryTransport(self.bus))
        self.peer = MemoryTransport(self.bus)
        self.stop = asyncio.Event()
        self.received: list[tuple[str, object]] = []
        self.task: asyncio.Task[int] | None = None

    async def __aenter__(self) -> Harness:
        self.peer.open()
        self.peer.declare_liveliness(alive_key("monitor"))
        self.peer.subscribe("crosspath/v2x/rsu/rsu1/**", self._on)
        self.task = asyncio.ensure_future(serve(self.daemon, install_signals=False, stop=self.stop))
        await wait_for(lambda: self.daemon.shell._token is not None)
        return self

    def _on(self, key: str, payload: bytes) -> None:
        if "/ap/" not in key:
            self.received.append((key, decode(payload)))

    async def __aexit__(self, *exc: object) -> None:
        self.stop.set()
        assert self.task is not None
        assert await asyncio.wait_for(self.task, 10.0) == 0
        self.peer.close()

    def control(self, message: StartRun | StopRun) -> None:
        self.peer.publish(control_key(), encode_control(message), RELIABLE_QOS)

    def commands(self, command: Command | None = None) -> list[ModeCommand]:
        return [
            m
            for k, m in self.received
            if isinstance(m, ModeCommand) and (command is None or m.command is command)
        ]

    def now(self) -> float:
        clock = self.daemon.shell.clock
        assert clock is not None
        return clock.now()

    async def send_until(self, done: Callable[[], bool], vehicle: str = "A") -> int:
        """Play car ``vehicle`` broadcasting its approaching future path every 0.1 s of
        run time until ``done()`` (a new RSU listens for one reservation expiry before it
        commands anyone); the number of paths sent."""
        sent = 0
        deadline = time.monotonic() + 5.0
        while not done():
            if time.monotonic() > deadline:
                raise AssertionError("condition not reached in time")
            if self.daemon.shell.clock is None:  # the run just ended: ``done`` will say
                await asyncio.sleep(0.01)
                continue
            fp = approaching_fp(self.now())
            self.peer.publish(keyexpr.future_path(vehicle), encode(fp), V2X_QOS)
            sent += 1
            await asyncio.sleep(0.1 / 5.0)  # the tests run at speed 5
        return sent


async def test_rsu_stays_idle_outside_rsu_mode() -> None:
    async with Harness() as h:
        h.control(start_message("fp", RunMode.FP_ONLY))
        h.control(start_message("elsewhere", RunMode.RSU, rsus=("rsu9",)))
        await asyncio.sleep(0.1)
        assert h.daemon.active is None and h.received == []


async def test_rsu_beacons_initiates_and_terminates_when_the_run_stops() -> None:
    async with Harness() as h:
        h.control(start_message("run-1", RunMode.RSU, speed=5.0))
        await wait_for(lambda: any(isinstance(m, RsuBeacon) for _, m in h.received))
        key, beacon = next((k, m) for k, m in h.received if isinstance(m, RsuBeacon))
        assert key == keyexpr.rsu_beacon("rsu1") and isinstance(beacon, RsuBeacon)
        assert beacon.intersection == "X1" and beacon.radius == 150.0
        await h.send_until(lambda: bool(h.commands(Command.INITIATE)))
        initiation = h.commands(Command.INITIATE)[0]
        assert initiation.vehicle == "A" and initiation.mode is Mode.C_FAST
        await wait_for(lambda: any(isinstance(m, CoordinatedPath) for _, m in h.received))
        assert all(k.endswith("/cmd/A") for k, m in h.received if not isinstance(m, RsuBeacon))
        assert h.daemon.coordinated() == ["A"]
        h.control(StopRun("run-1", "test over"))
        await wait_for(lambda: h.daemon.runs_done == 1)
        terminations = h.commands(Command.TERMINATE)
        # A never showed AUTO, so every round reached it
        assert len(terminations) == TERMINATION_ROUNDS
        assert all(t.vehicle == "A" and t.mode is Mode.AUTO for t in terminations)
        assert h.daemon.terminations_sent == TERMINATION_ROUNDS
        # in the core's own header sequence: after everything sent before (a counter of
        # its own restarted at 1 and the cars' replay windows could refuse them)
        sent = (RsuBeacon, ModeCommand, CoordinatedPath)
        before = [
            m.header.seq for _, m in h.received if isinstance(m, sent) and m not in terminations
        ]
        assert min(t.header.seq for t in terminations) > max(before)
        assert [t.header.seq for t in terminations] == sorted({t.header.seq for t in terminations})
        stats = h.daemon.shell.stats  # reset after the run; the final report had them
        assert stats.streams == {}


async def test_signal_stop_terminates_coordinated_cars_until_they_show_auto() -> None:
    async with Harness() as h:
        h.control(start_message("run-2", RunMode.RSU, speed=5.0))
        await wait_for(lambda: h.daemon.active is not None)
        await h.send_until(lambda: bool(h.commands(Command.INITIATE)))

        def on_termination(key: str, payload: bytes) -> None:
            message = decode(payload)
            if isinstance(message, ModeCommand) and message.command is Command.TERMINATE:
                # the car obeys: its next future path shows AUTO (from where it was: the
                # RSU refuses a path that jumps, issue 13)
                fp = approaching_fp(h.now(), mode=Mode.AUTO)
                h.peer.publish(keyexpr.future_path("A"), encode(fp), V2X_QOS)

        h.peer.subscribe(keyexpr.rsu_command("rsu1", "A"), on_termination)
        h.stop.set()
        assert h.task is not None
        assert await asyncio.wait_for(h.task, 10.0) == 0
        assert len(h.commands(Command.TERMINATE)) == 1  # acknowledged: no repeats


async def test_rsu_counts_garbage_on_its_keys_and_keeps_working() -> None:
    async with Harness(policy="slot") as h:
        h.control(start_message("run-3", RunMode.RSU, speed=5.0, policy=Policy.PAPER))
        await wait_for(lambda: h.daemon.active is not None)
        assert h.daemon.policy_override is Policy.SLOT
        for payload in (b"", b"\x00" * 2000, b"\x01garbage"):
            h.peer.publish(keyexpr.autonomous_path("rsu1", "A"), payload, V2X_QOS)
            h.peer.publish(keyexpr.future_path("B"), payload, V2X_QOS)
        wrong = approaching_fp(h.now())  # A's path on B's key
        h.peer.publish(keyexpr.future_path("B"), encode(wrong), V2X_QOS)
        await wait_for(lambda: h.daemon.shell.stats.stream("fp").malformed == 4)
        assert h.daemon.shell.stats.stream("ap").malformed == 3
        sent = await h.send_until(lambda: bool(h.commands(Command.INITIATE)))
        await wait_for(lambda: h.daemon.shell.stats.stream("fp").msgs_rx == sent)
        assert h.daemon.shell.stats.stream("fp").malformed == 4  # the valid ones were not
        h.control(StopRun("run-3"))
        await wait_for(lambda: h.daemon.runs_done == 1)


async def test_a_bug_in_the_rsu_core_stops_the_daemon_with_its_traceback(
    monkeypatch: pytest.MonkeyPatch, caplog: pytest.LogCaptureFixture
) -> None:
    def broken(self: RsuCore, *args: object) -> None:
        raise ValueError("injected bug")  # what the core used to swallow as a WARNING

    monkeypatch.setattr(RsuCore, "_decide", broken)
    h = Harness()
    await h.__aenter__()
    try:
        h.control(start_message("run-5", RunMode.RSU, speed=5.0))
        await wait_for(lambda: h.daemon.active is not None)
        with caplog.at_level(logging.INFO, logger="crosspath"):
            assert h.task is not None
            task = h.task
            await h.send_until(task.done)
            assert await asyncio.wait_for(task, 10.0) == EXIT_FAILED
    finally:
        h.stop.set()
        h.peer.close()
    assert h.daemon.shell.internal_errors == 1 and h.daemon.runs_done == 1
    traced = [r for r in caplog.records if r.exc_info]
    assert len(traced) == 1 and traced[0].levelno == logging.ERROR
    assert isinstance(traced[0].exc_info[1], ValueError)  # type: ignore[index]
    assert "handling a datagram on crosspath/v2x/fp/A failed" in traced[0].getMessage()
    exits = [r.getMessage() for r in caplog.records if "internal error: " in r.getMessage()]
    assert len(exits) == 1 and "injected bug" in exits[0]  # the one-line exit, no traceback
