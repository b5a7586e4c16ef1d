"""The daemons' shared shell: plumbing codecs, the V2X edge, config errors, whole runs in memory.

The whole-run tests drive every daemon (cars, RSU, monitor) in one event loop
over the in-memory bus, on a fast run clock, and compare with the in-process
harness; the tests that start real daemons over Zenoh are marked ``daemons``.
"""

from __future__ import annotations

import argparse
import asyncio
import io
import logging
import math
import os
import selectors
import signal
import socket
import subprocess
import sys
import time
from collections.abc import Callable, Mapping
from pathlib import Path
from typing import Any, TypeVar

import msgpack
import numpy as np
import pytest

from protocol import FuturePath, Header, Mode, encode
from protocol import keys as keyexpr
from protocol.keys import Stream
from services.daemons.monitor import MonitorConfig, MonitorService
from services.daemons.rsu import RsuDaemon, RsuDaemonConfig
from services.daemons.vehicle import VehicleDaemon, VehicleDaemonConfig
from services.edge.clock import RunClock
from services.edge.lifecycle import EXIT_CONFIG, EXIT_FAILED, ServiceExit, serve
from services.edge.plumbing import (
    MAX_PLUMBING_BYTES,
    PlumbingError,
    StartRun,
    StatsReport,
    StopRun,
    TruthReport,
    alive_key,
    all_alive,
    control_key,
    decode_control,
    decode_stats,
    decode_truth,
    encode_control,
    encode_stats,
    encode_truth,
    node_of_alive_key,
    truth_key,
)
from services.edge.settings import CommonDaemonConfig, load_config
from services.edge.shell import (
    MAX_AGE_S,
    MAX_FUTURE_S,
    MAX_SCOPED_KEYS,
    UNREACHABLE_WARN_S,
    DaemonShell,
    RateLimitedLog,
    ScopedSubscription,
    sleep_until,
    wait_event,
)
from services.edge.transport import RELIABLE_QOS, MemoryBus, MemoryTransport
from services.model.kinematics import TruthState
from services.model.scenario import Scenario, load_scenario
from services.model.types import Policy, RunMode
from services.sim.harness import SimOptions, simulate
from services.supervise.launcher import free_ports

REPO = Path(__file__).resolve().parents[2]
PAPER = REPO / "scenarios" / "paper-blind-intersection.toml"

C = TypeVar("C", bound=CommonDaemonConfig)


# --------------------------------------------------------------------------- helpers


def config(model: type[C], **fields: object) -> C:
    """A daemon config from dotted fields, without environment."""
    return load_config(model, None, fields, env={})


def start_message(
    run_id: str = "run-1",
    mode: RunMode = RunMode.RSU,
    epoch_unix: float | None = None,
    speed: float = 1.0,
    **kw: Any,
) -> StartRun:
    fields: dict[str, Any] = {
        "scenario": "paper-blind-intersection",
        "policy": Policy.PAPER,
        "seed": 0,
        "start_times": {"A": 0.0, "B": 0.5},
        "max_sim_s": 120.0,
        "monitor": "monitor",
        "vehicles": ("A", "B"),
        "rsus": ("rsu1",),
    }
    fields.update(kw)
    return StartRun(
        run_id=run_id,
        mode=mode,
        epoch_unix=time.time() if epoch_unix is None else epoch_unix,
        speed=speed,
        **fields,
    )


async def wait_for(predicate: Callable[[], bool], timeout: float = 5.0) -> None:
    deadline = time.monotonic() + timeout
    while not predicate():
        if time.monotonic() > deadline:
            raise AssertionError("condition not reached in time")
        await asyncio.sleep(0.01)


def truth(vid: str = "A", t: float = 0.0, x: float = -200.0, speed: float = 0.0) -> TruthState:
    return TruthState(vid, t, x, -1.75, 0.0, speed, 0.0, 0.0, 4.5, 1.8)


def future_path(sender: str, t: float, seq: int = 1) -> FuturePath:
    pts = np.column_stack(
        [np.linspace(-100.0, -80.0, 20), np.full(20, -1.75), t + np.linspace(0.0, 2.0, 20)]
    )
    return FuturePath(
        Header(sender, seq, round(t * 1e6)), -100.0, -1.75, 10.0, 0.0, 4.5, 1.8, Mode.AUTO, pts
    )


# --------------------------------------------------------------------------- control codecs


def test_start_and_stop_round_trip() -> None:
    start = start_message(epoch_unix=1_700_000_000.5, speed=2.0, seed=7)
    back = decode_control(encode_control(start))
    assert isinstance(back, StartRun)
    assert back == start
    assert back.mode is RunMode.RSU and back.policy is Policy.PAPER
    assert dict(back.start_times) == {"A": 0.0, "B": 0.5}
    stop = StopRun("run-1", "every car stands at its goal", 47.0)
    assert decode_control(encode_control(stop)) == stop


def test_truth_and_stats_round_trip() -> None:
    report = TruthReport("run-1", 42, truth("B", 2.1, -150.0, 7.5), "C_FAST", "cruise")
    back = decode_truth(encode_truth(report))
    assert back == report and back.vehicle == "B"
    stats = StatsReport("A", "run-1", True, {"node": "A", "time_s": 1.0, "streams": {}})
    assert decode_stats(encode_stats(stats)) == stats
    assert len(encode_truth(report)) < 200


def _packed(body: Mapping[str, Any]) -> bytes:
    data: bytes = msgpack.packb(dict(body), use_bin_type=True)
    return data


def _start_body(**changes: Any) -> dict[str, Any]:
    body = start_message().to_wire()
    body["v"] = 1
    body.update(changes)
    return {k: v for k, v in body.items() if v is not ...}


@pytest.mark.parametrize(
    ("payload", "needle"),
    [
        (b"", "not msgpack"),
        (b"\xc1garbage", "not msgpack"),
        (_packed({"v": 1, "type": "launch"}), "unknown message type 'launch'"),
        (msgpack.packb([1, 2, 3]), "expected a map"),
        (_packed({"v": 9, "type": "stop", "run_id": "r"}), "unsupported format version 9"),
        (_packed({"v": 1, "type": "stop"}), "missing field 'run_id'"),
        (_packed({"v": 1, "type": "stop", "run_id": "a/b"}), "run_id"),
        (_packed(_start_body(mode="turbo")), "unknown run mode 'turbo'"),
        (_packed(_start_body(policy="fifo")), "unknown policy 'fifo'"),
        (_packed(_start_body(speed=0.0)), "speed: must be > 0.0"),
        (_packed(_start_body(speed=math.nan)), "speed: need a finite number"),
        (_packed(_start_body(seed=-1)), "seed: need an int >= 0"),
        (_packed(_start_body(seed=True)), "seed"),
        (_packed(_start_body(start_times={"A": 0.0})), "no start time for B"),
        (_packed(_start_body(start_times={"A": 0.0, "B": -1.0})), "start_times.B"),
        (_packed(_start_body(vehicles=[])), "at least one vehicle"),
        (_packed(_start_body(vehicles=["A", "A"])), "duplicate id"),
        (_packed(_start_body(epoch_unix=...)), "missing field 'epoch_unix'"),
        (_packed(_start_body(monitor="mon itor")), "monitor"),
        (b"\x00" * (MAX_PLUMBING_BYTES + 1), "exceeds"),
    ],
)
def test_bad_control_messages_are_refused_clearly(payload: bytes, needle: str) -> None:
    with pytest.raises(PlumbingError) as info:
        decode_control(payload)
    assert needle in str(info.value)


def test_bad_truth_and_stats_are_refused() -> None:
    good = msgpack.unpackb(encode_truth(TruthReport("r", 1, truth())), raw=False)
    for change, needle in (
        ({"state": [0.0] * 8}, "list of 9 numbers"),
        ({"state": [math.inf] + [0.0] * 8}, "state.t"),
        ({"step": -1}, "step"),
        ({"vehicle": "x" * 40}, "vehicle"),
        ({"type": "stats"}, "unexpected message type"),
        ({"mode": 5}, "mode"),
    ):
        with pytest.raises(PlumbingError, match=needle.replace(".", r"\.")):
            decode_truth(_packed({**good, **change}))
    with pytest.raises(PlumbingError, match="snapshot"):
        decode_stats(_packed({"v": 1, "type": "stats", "node": "A", "snapshot": {"x": 1}}))
    with pytest.raises(PlumbingError, match="final"):
        decode_stats(
            _packed({"v": 1, "type": "stats", "node": "A", "final": 1, "snapshot": {"streams": {}}})
        )


def test_plumbing_keys() -> None:
    assert control_key() == "crosspath/sim/control"
    assert truth_key("A", prefix="lab1/crosspath") == "lab1/crosspath/sim/truth/A"
    assert alive_key("rsu1") == "crosspath/sim/alive/rsu1"
    assert all_alive() == "crosspath/sim/alive/*"
    assert node_of_alive_key("crosspath/sim/alive/B") == "B"
    with pytest.raises(keyexpr.BadKey):
        node_of_alive_key("crosspath/sim/truth/B")


# --------------------------------------------------------------------------- the V2X edge


class Recorder:
    def __init__(self) -> None:
        self.got: list[tuple[str, str, float]] = []

    def __call__(self, parsed: keyexpr.ParsedKey, message: Any, now: float) -> None:
        self.got.append((str(parsed.stream), message.header.sender, now))


async def test_shell_counts_garbage_oversized_spoofed_and_stale() -> None:
    bus = MemoryBus()
    shell = DaemonShell(
        config(VehicleDaemonConfig, node_id="B", scenario=str(PAPER)), "test", MemoryTransport(bus)
    )
    await shell.open()
    rec = Recorder()
    shell.subscribe_v2x(keyexpr.all_future_paths(), Stream.FP, rec, ignore_vehicle="B")
    peer = MemoryTransport(bus)
    peer.open()
    qos = shell.transport  # any QoS: the memory bus ignores it
    del qos
    from services.edge.transport import V2X_QOS

    async def send(key: str, payload: bytes) -> None:
        peer.publish(key, payload, V2X_QOS)
        await asyncio.sleep(0)  # one at a time: a lane's queued datagram is replaced by a newer

    # outside a run: malformed ones are counted, valid ones dropped uncounted
    await send(keyexpr.future_path("A"), b"\x01\x02garbage")
    await send(keyexpr.future_path("A"), encode(future_path("A", 0.0)))
    await asyncio.sleep(0.05)
    fp = shell.stats.stream("fp")
    assert (fp.malformed, fp.msgs_rx) == (1, 0) and rec.got == []

    clock = shell.begin_run("run-1", time.time() - 10.0, 1.0)  # run time is about 10 s
    now = clock.now()
    good = encode(future_path("A", now - 0.005))
    await send(keyexpr.future_path("A"), good)
    await send(keyexpr.future_path("A"), good + b"\x00" * (2000 - len(good)))  # oversized
    await send(keyexpr.future_path("C"), good)  # sender A on C's key: spoofed
    await send(keyexpr.future_path("A"), encode(future_path("A", now - MAX_AGE_S - 1.0)))  # old
    await send(
        keyexpr.future_path("A"), encode(future_path("A", now + MAX_FUTURE_S + 1.0))
    )  # future
    await send(keyexpr.future_path("B"), good)  # our own key: skipped, not counted
    await send(keyexpr.future_path("A"), b"")
    await asyncio.sleep(0.05)
    fp = shell.stats.stream("fp")
    assert fp.malformed == 3  # oversized, spoofed, empty
    assert fp.dropped_stale == 2
    assert fp.msgs_rx == 1 and fp.bytes_rx == len(good)
    assert rec.got and rec.got[0][:2] == ("fp", "A") and rec.got[0][2] == pytest.approx(now, abs=1)
    assert 0.004 < fp.latency.max_s < 1.0
    snapshot = shell.stats_report(final=False).snapshot
    assert snapshot["streams"]["fp"]["malformed"] == 3
    await shell.close()
    peer.close()


async def test_scoped_v2x_subscriptions_declare_only_the_runs_senders() -> None:
    """In a run a scoped subscription is declared on its senders' keys only: a datagram on
    any other key never reaches the daemon (not even its refusal counter); between runs,
    and for a run with more senders than MAX_SCOPED_KEYS, the wildcard."""
    bus = MemoryBus()
    shell = DaemonShell(
        config(VehicleDaemonConfig, node_id="B", scenario=str(PAPER)), "test", MemoryTransport(bus)
    )
    await shell.open()
    rec = Recorder()
    scoped = shell.subscribe_v2x(
        keyexpr.all_future_paths(),
        Stream.FP,
        rec,
        ignore_vehicle="B",
        scope=lambda start: [keyexpr.future_path(v) for v in start.vehicles if v != "B"],
    )
    assert isinstance(scoped, ScopedSubscription)
    assert scoped.keys == [keyexpr.all_future_paths()]
    peer = MemoryTransport(bus)
    peer.open()
    from services.edge.transport import V2X_QOS

    start = start_message(vehicles=("A", "B", "C"), start_times={"A": 0.0, "B": 0.0, "C": 0.0})
    shell.actors = frozenset((*start.vehicles, *start.rsus, start.monitor))
    shell.scope_v2x(start)
    assert scoped.keys == sorted([keyexpr.future_path("A"), keyexpr.future_path("C")])
    clock = shell.begin_run(start.run_id, time.time() - 10.0, 1.0)
    for i in range(200):  # a flood from ids that are not in the run
        peer.publish(
            keyexpr.future_path(f"f{i:03d}"), encode(future_path(f"f{i:03d}", 1.0)), V2X_QOS
        )
    peer.publish(keyexpr.future_path("A"), encode(future_path("A", clock.now())), V2X_QOS)
    await wait_for(lambda: bool(rec.got))
    await asyncio.sleep(0.05)
    counts = shell.receive["fp"].stats.counts
    assert counts["refused"] == 0 and counts["offered"] == 1
    assert [sender for _s, sender, _t in rec.got] == ["A"]

    # more senders than the bound: the wildcard, and the network-thread refusal
    many = tuple(f"v{i}" for i in range(MAX_SCOPED_KEYS + 2))
    shell.scope_v2x(start_message(vehicles=many, start_times=dict.fromkeys(many, 0.0)))
    assert scoped.keys == [keyexpr.all_future_paths()]
    for i in range(50):
        peer.publish(
            keyexpr.future_path(f"f{i:03d}"), encode(future_path(f"f{i:03d}", 1.0)), V2X_QOS
        )
    await wait_for(lambda: shell.receive["fp"].stats.counts["refused"] == 50)

    shell.scope_v2x(None)  # between runs
    assert scoped.keys == [keyexpr.all_future_paths()]
    scoped.close()
    assert scoped.keys == []
    shell.scope_v2x(start)  # a closed subscription stays closed
    assert scoped.keys == []
    other = shell.subscribe_v2x(
        keyexpr.all_beacons(),
        Stream.BEACON,
        rec,
        scope=lambda start: ["crosspath/v2x/rsu/r/beacon"],
    )
    # declared in a run (as a car's radio at its insertion): the run's keys at once
    assert isinstance(other, ScopedSubscription) and other.keys == ["crosspath/v2x/rsu/r/beacon"]
    await shell.close()  # undeclares everything; a later run declares nothing
    shell.scope_v2x(start)
    assert other.keys == []
    peer.close()


async def test_a_failing_handler_is_a_bug_logged_counted_and_raised_later(
    caplog: pytest.LogCaptureFixture,
) -> None:
    bus = MemoryBus()
    shell = DaemonShell(
        config(VehicleDaemonConfig, node_id="B", scenario=str(PAPER)), "test", MemoryTransport(bus)
    )
    await shell.open()
    calls: list[int] = []

    def boom(parsed: keyexpr.ParsedKey, message: Any, now: float) -> None:
        calls.append(1)
        raise RuntimeError("core bug")

    def bad_plumbing(key: str, payload: bytes) -> None:
        if payload == b"peer":
            raise PlumbingError("a peer's mistake")
        raise KeyError("our bug")

    shell.subscribe_v2x(keyexpr.all_future_paths(), Stream.FP, boom)
    shell.subscribe_plumbing("crosspath/sim/truth/*", bad_plumbing)
    shell.begin_run("run-1", time.time(), 1.0)
    peer = MemoryTransport(bus)
    peer.open()
    with caplog.at_level(logging.DEBUG, logger="crosspath"):
        peer.publish(truth_key("A"), b"peer", RELIABLE_QOS)
        await asyncio.sleep(0.05)
        assert shell.plumbing_malformed == 1 and shell.fault is None  # counted, not a bug
        shell.publish_v2x(keyexpr.future_path("B"), future_path("B", 0.0))
        await asyncio.sleep(0)  # else the newer one replaces it in the inbox (latest wins)
        shell.publish_v2x(keyexpr.future_path("B"), future_path("B", 0.0, seq=2))
        peer.publish(truth_key("A"), b"ours", RELIABLE_QOS)
        await asyncio.sleep(0.05)
    assert len(calls) == 2 and shell.internal_errors == 3
    assert shell.faulted.is_set() and shell.fault is not None and "core bug" in shell.fault
    traced = [r for r in caplog.records if r.exc_info]
    assert len(traced) == 1 and isinstance(traced[0].exc_info[1], RuntimeError)
    assert shell.stats_report(final=False).snapshot["internal_errors"] == 3
    with pytest.raises(ServiceExit, match="core bug") as info:
        shell.raise_fault()
    assert info.value.exit_code == EXIT_FAILED
    assert shell.stats.stream("fp").msgs_tx == 2
    await shell.close()
    peer.close()


async def test_publish_counts_encoded_bytes_and_final_report() -> None:
    bus = MemoryBus()
    shell = DaemonShell(
        config(VehicleDaemonConfig, node_id="A", scenario=str(PAPER)), "test", MemoryTransport(bus)
    )
    await shell.open()
    reports: list[StatsReport] = []
    listener = MemoryTransport(bus)
    listener.open()
    listener.subscribe(keyexpr.all_stats(), lambda k, p: reports.append(decode_stats(p)))
    shell.begin_run("run-9", time.time(), 1.0)
    message = future_path("A", 0.0)
    assert shell.publish_v2x(keyexpr.future_path("A"), message)
    await shell.end_run(drain_s=0.0)
    await asyncio.sleep(0.05)
    assert [r.run_id for r in reports] == ["run-9", "run-9"]  # acknowledgement, final
    assert reports[-1].final and not reports[0].final
    assert reports[-1].snapshot["streams"]["fp"]["bytes_tx"] == len(encode(message))
    assert shell.run_id is None and shell.clock is None
    await shell.close()
    listener.close()


async def test_wait_event_times_out_or_wakes_and_leaves_no_task_behind() -> None:
    event = asyncio.Event()
    before = asyncio.all_tasks()
    t0 = time.monotonic()
    assert await wait_event(event, 0.02) is False
    assert 0.015 < time.monotonic() - t0 < 1.0
    asyncio.get_running_loop().call_later(0.02, event.set)
    assert await wait_event(event, 100.0) is True
    assert time.monotonic() - t0 < 1.0
    await asyncio.sleep(0)  # the cancelled waiters finish
    assert asyncio.all_tasks() == before
    assert await wait_event(event, 0.0) is True and await wait_event(asyncio.Event(), 0.0) is False


async def test_sleep_until_returns_false_when_halted() -> None:
    halt = asyncio.Event()
    clock = RunClock(time.time(), 1.0)
    asyncio.get_running_loop().call_later(0.05, halt.set)
    t0 = time.monotonic()
    assert await sleep_until(clock, 100.0, halt) is False
    assert time.monotonic() - t0 < 1.0
    assert await sleep_until(clock, -1.0, asyncio.Event()) is True


def test_rate_limited_log_suppresses_and_reports() -> None:
    clock = [0.0]
    stream = io.StringIO()
    import logging

    logger = logging.getLogger("crosspath.test.ratelog")
    handler = logging.StreamHandler(stream)
    logger.addHandler(handler)
    logger.setLevel(logging.DEBUG)
    try:
        rl = RateLimitedLog(logger, 1.0, time_fn=lambda: clock[0])
        for _ in range(5):
            rl.log(logging.WARNING, "k", "bad %s", "thing")
        clock[0] = 1.5
        rl.log(logging.WARNING, "k", "bad %s", "thing")
    finally:
        logger.removeHandler(handler)
    lines = stream.getvalue().splitlines()
    assert lines == ["bad thing", "bad thing (4 similar suppressed)"]


# --------------------------------------------------------------------------- config


def _args(command: str, *argv: str) -> argparse.Namespace:
    from services.cli.main import build_parser

    return build_parser().parse_args([command, *argv])


@pytest.mark.parametrize(
    ("command", "toml", "field"),
    [
        ("vehicle", 'node_id = "A"\nscenario = "{paper}"\nbogus = 1\n', "bogus"),
        ("vehicle", 'node_id = "A"\nscenario = "{paper}"\nstats_period_s = -1\n', "stats_period_s"),
        ("vehicle", 'node_id = "Z"\nscenario = "{paper}"\n', "node_id"),
        ("vehicle", 'node_id = "A"\nscenario = "/nonexistent.toml"\n', "scenario"),
        ("rsu", 'node_id = "rsu1"\nscenario = "{paper}"\npolicy = "fifo"\n', "policy"),
        ("rsu", 'node_id = "A"\nscenario = "{paper}"\n', "node_id"),
        ("monitor", 'scenario = "{paper}"\nmode = "warp"\n', "mode"),
        ("monitor", 'scenario = "{paper}"\nrun_id = "a/b"\n', "run_id"),
        ("monitor", 'scenario = "{paper}"\n[zenoh]\nmax_links = 0\n', "zenoh.max_links"),
    ],
)
def test_config_errors_exit_2_naming_the_field(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], command: str, toml: str, field: str
) -> None:
    path = tmp_path / "daemon.toml"
    path.write_text(toml.replace("{paper}", str(PAPER)))
    args = _args(command, "--config", str(path))
    assert args._run(args) == 2
    err = capsys.readouterr().err
    assert f"crosspath {command}: config error: {field}:" in err, err


def test_command_flags_override_the_file(tmp_path: Path) -> None:
    from services.daemons.vehicle import load_daemon

    path = tmp_path / "car.toml"
    path.write_text(f'node_id = "A"\nscenario = "{PAPER}"\n')
    cfg, scenario = load_daemon(
        _args("vehicle", "--config", str(path), "--id", "B", "--listen", "udp/127.0.0.1:7000")
    )
    assert cfg.node_id == "B" and scenario.name == "paper-blind-intersection"
    assert cfg.zenoh.listen == ["udp/127.0.0.1:7000"]


@pytest.mark.parametrize(
    ("name", "model"),
    [
        ("vehicle-A.toml", VehicleDaemonConfig),
        ("vehicle-B.toml", VehicleDaemonConfig),
        ("rsu-rsu1.toml", RsuDaemonConfig),
        ("monitor.toml", MonitorConfig),
    ],
)
def test_example_configs_load(
    name: str, model: type[VehicleDaemonConfig | RsuDaemonConfig | MonitorConfig]
) -> None:
    cfg = load_config(model, REPO / "deploy" / "examples" / name, {}, env={})
    scenario = load_scenario(cfg.scenario)  # a packaged scenario, by name
    ids = {v.id for v in scenario.vehicles} | {r.id for r in scenario.rsus} | {"monitor"}
    assert cfg.node_id in ids
    assert cfg.zenoh.multicast_scouting is False and cfg.zenoh.max_links == 2


@pytest.mark.daemons
def test_config_error_of_a_real_daemon_process(tmp_path: Path) -> None:
    path = tmp_path / "car.toml"
    path.write_text(f'node_id = "A"\nscenario = "{PAPER}"\nspeed_limit = 3\n')
    proc = subprocess.run(
        [sys.executable, "-m", "services.cli.main", "vehicle", "--config", str(path)],
        cwd=REPO,
        env={**os.environ, "PYTHONPATH": str(REPO)},
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert proc.returncode == 2
    assert "crosspath vehicle: config error: speed_limit: Extra inputs are not permitted" in (
        proc.stderr
    )


# --------------------------------------------------------------------------- endpoints


def _rsu_process(tmp_path: Path, zenoh: str) -> subprocess.Popen[str]:
    """``crosspath rsu`` as a process, its ``[zenoh]`` table ``zenoh``."""
    path = tmp_path / "rsu.toml"
    path.write_text(f'node_id = "rsu1"\nscenario = "{PAPER}"\n[zenoh]\n{zenoh}\n')
    return subprocess.Popen(
        [sys.executable, "-m", "services.cli.main", "rsu", "--config", str(path)],
        cwd=REPO,
        env={**os.environ, "PYTHONPATH": str(REPO)},
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )


@pytest.mark.daemons
@pytest.mark.parametrize(
    ("endpoint", "reason"),
    [
        ("in use", "Address already in use"),
        ("tcp/999.1.1.1:7447", "failed to lookup address information"),
        ("foo/1.2.3.4:1", "Unicast not supported for foo protocol"),
    ],
)
def test_an_endpoint_that_cannot_be_opened_is_one_line_and_exit_78(
    tmp_path: Path, endpoint: str, reason: str
) -> None:
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as busy:
        busy.bind(("127.0.0.1", 0))
        busy.listen()
        if endpoint == "in use":
            endpoint = f"tcp/127.0.0.1:{busy.getsockname()[1]}"
        proc = _rsu_process(tmp_path, f'listen = ["{endpoint}"]')
        _out, err = proc.communicate(timeout=60)
    assert proc.returncode == EXIT_CONFIG == 78, err
    # the one error line, besides the loud warning of a daemon started without credentials
    lines = [line for line in err.splitlines() if line.strip() and "INSECURE" not in line]
    assert len(lines) == 1, err
    assert "ERROR" in lines[0] and f"cannot listen on {endpoint}: {reason}" in lines[0]


@pytest.mark.daemons
def test_a_peer_with_no_reachable_endpoint_says_so_and_keeps_trying(tmp_path: Path) -> None:
    ((udp, tcp),) = free_ports(1)
    nowhere = [f"udp/127.0.0.1:{udp}", f"tcp/127.0.0.1:{tcp}"]
    proc = _rsu_process(tmp_path, f"connect = {nowhere!r}".replace("'", '"'))
    try:
        assert proc.stderr is not None
        selector = selectors.DefaultSelector()
        selector.register(proc.stderr, selectors.EVENT_READ)
        deadline = time.monotonic() + UNREACHABLE_WARN_S + 20.0
        seen: list[str] = []

        def reach(line: str) -> bool:  # not the start-up warning of a daemon without keys
            return "WARNING" in line and "INSECURE" not in line

        while not any(reach(line) for line in seen):
            assert time.monotonic() < deadline, seen
            if selector.select(timeout=0.5):
                line = proc.stderr.readline()
                assert line, f"stderr closed: {seen}"
                seen.append(line.strip())
        (warning,) = [line for line in seen if reach(line)]
        assert "no peer reachable after 5 s" in warning and "still trying" in warning
        assert all(endpoint in warning for endpoint in nowhere)
        assert proc.poll() is None  # it keeps running (and Zenoh keeps trying)
        proc.send_signal(signal.SIGTERM)
        _out, err = proc.communicate(timeout=20)
        assert proc.returncode == 0, err
        assert not any(reach(line) for line in err.splitlines())  # one warning only
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()


# --------------------------------------------------------------------------- whole runs in memory


async def run_in_memory(
    scenario: Scenario, mode: RunMode, speed: float, seed: int = 0
) -> MonitorService:
    """Every daemon of the scenario in this loop over one memory bus; the finished monitor."""
    bus = MemoryBus()
    stop = asyncio.Event()
    actors: list[VehicleDaemon | RsuDaemon] = []
    for v in scenario.vehicles:
        cfg = config(VehicleDaemonConfig, node_id=v.id, scenario=str(PAPER), stats_period_s=0.5)
        actors.append(VehicleDaemon(cfg, scenario, MemoryTransport(bus)))
    for r in scenario.rsus:
        rcfg = config(RsuDaemonConfig, node_id=r.id, scenario=str(PAPER))
        actors.append(RsuDaemon(rcfg, scenario, MemoryTransport(bus)))
    mcfg = config(
        MonitorConfig,
        scenario=str(PAPER),
        mode=str(mode),
        seed=seed,
        start_delay_s=0.2,
        stats_wait_s=2.0,
        **{"time.speed": speed},
    )
    monitor = MonitorService(mcfg, scenario, MemoryTransport(bus))
    tasks = [asyncio.ensure_future(serve(a, install_signals=False, stop=stop)) for a in actors]
    try:
        code = await serve(monitor, install_signals=False)
    finally:
        stop.set()
        codes = await asyncio.gather(*tasks)
    assert code == 0 and codes == [0] * len(actors)
    assert all(
        a.runs_done == (1 if isinstance(a, VehicleDaemon) or mode is RunMode.RSU else 0)
        for a in actors
    )
    return monitor


@pytest.mark.parametrize("mode", [RunMode.RSU, RunMode.FP_ONLY])
async def test_daemons_over_memory_match_the_in_process_harness(mode: RunMode) -> None:
    scenario = load_scenario(PAPER)
    # speed 4, not 10: all the daemons share one event loop here, and a lane of the
    # receive inbox keeps only its latest datagram (ReceivePolicy depth 1), so a loop
    # that falls behind coalesces future paths (at speed 10 on a 2-core machine the
    # delivery ratio fell to 0.75; at 5 it is 0.99 on a quiet machine, but 0.74-0.79
    # once on 3 Dec 2026 on a slow one)
    monitor = await run_in_memory(scenario, mode, speed=4.0, seed=1)
    result = monitor.result
    assert result is not None and monitor.exit_code == 0
    reference = simulate(scenario, SimOptions(mode=mode, seed=1))
    assert result.harness == "daemons" and result.mode is mode
    assert result.collisions == 0 and result.all_finished
    assert result.start_times == reference.start_times
    for vid, ref in reference.vehicles.items():
        got = result.vehicles[vid].passing_time_s
        assert got == pytest.approx(ref.passing_time_s, rel=0.10), vid
    assert result.sim_s == pytest.approx(reference.sim_s, abs=2.0)
    network = result.network
    assert network is not None
    fp = network.stream("fp")
    assert fp is not None
    receivers = 1 if mode is RunMode.FP_ONLY else 2
    # the memory bus loses nothing: what was not received was dropped as stale (a stalled
    # loop) or sent while the other car was not in the world (issue 12: insertion, removal)
    assert 0.5 * fp.msgs * receivers <= fp.msgs_rx + fp.dropped_stale <= fp.msgs * receivers
    assert fp.delivery_ratio is not None and fp.delivery_ratio > 0.9 and fp.malformed == 0
    assert fp.msgs > 0 and network.total_kbps_per_vehicle > 0
    streams = {"fp", "ap", "cmd", "beacon"} if mode is RunMode.RSU else {"fp"}
    assert streams <= set(network.streams)
    assert result.truth is not None and result.truth.gaps == 0


async def test_standalone_run_sends_no_v2x() -> None:
    scenario = load_scenario(PAPER)
    monitor = await run_in_memory(scenario, RunMode.STANDALONE, speed=20.0)
    result = monitor.result
    assert result is not None
    assert result.policy is None and result.all_finished
    assert result.network is not None and result.network.streams == {}
    assert result.network.total_kbps_per_vehicle == 0.0
    assert set(result.to_dict()["network"]) == {"total_kbps_per_vehicle"}


async def test_the_stats_carry_the_ticks_p99_lag_beside_the_max_and_a_new_run_resets_them() -> None:
    shell = DaemonShell(
        config(VehicleDaemonConfig, node_id="B", scenario=str(PAPER)),
        "test",
        MemoryTransport(MemoryBus()),
    )
    await shell.open()
    shell.begin_run("run-1", time.time(), 1.0)
    lags = [0.001] * 199 + [0.004, 0.25]  # one stall sets the max, not the p99
    for step, lag in enumerate(lags):
        shell.on_tick(step * 0.05, step * 0.05 + lag, 0.05)
    snapshot = shell.stats_report(final=False).snapshot
    assert snapshot["max_tick_lag_s"] == 0.25 and snapshot["late_ticks"] == 1
    assert 0.001 <= snapshot["tick_lag_s_p99"] < 0.005  # the 199th of 201 lags, bucketed
    await shell.end_run(0.0)
    shell.begin_run("run-2", time.time(), 1.0)
    snapshot = shell.stats_report(final=False).snapshot
    assert snapshot["max_tick_lag_s"] == 0.0 and "tick_lag_s_p99" not in snapshot
    await shell.close()


async def test_the_shell_names_a_due_tick_until_it_runs() -> None:
    shell = DaemonShell(
        config(VehicleDaemonConfig, node_id="B", scenario=str(PAPER)),
        "test",
        MemoryTransport(MemoryBus()),
    )
    await shell.open()
    shell.subscribe_v2x(keyexpr.all_future_paths(), Stream.FP, lambda *_: None)
    shell.subscribe_plumbing("crosspath/sim/truth/*", lambda *_: None)
    assert shell.tick_due() is None  # no run
    shell.begin_run("run-1", time.time() - 1.0, 1.0)  # run time about 1 s now
    shell.next_tick_s = 100.0
    assert shell.tick_due() is None  # not due yet
    shell.next_tick_s = 0.5
    assert shell.tick_due() == 0.5  # due, not run
    assert len(shell.receive) == 2  # V2X and plumbing inboxes both hold for a due tick
    assert all(p.tick_due == shell.tick_due for p in shell.receive.values())
    shell.on_tick(0.5, 1.0, 0.1)
    assert shell.tick_due() is None  # it ran
    shell.next_tick_s = 0.6
    await shell.end_run(0.0)
    assert shell.tick_due() is None  # no more ticks after the run
    await shell.close()
