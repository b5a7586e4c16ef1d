"""Issue 13's load and plumbing attacks against the real daemon classes, in process.

Every daemon of the paper scenario (cars, RSU, monitor) runs in this event loop over one
memory bus (faster than processes; ``tests/edge/test_flood_zenoh.py`` floods real Zenoh
and ``services.bench.flood`` real daemon processes), signed with a throw-away
authority unless a test says ``insecure``. An attacker on the same bus:

- floods future paths from 500 fake ids, or from a new id each time (:data:`RATE_HZ`);
- sends a truth report with ``x = 1e300`` (unsigned, and signed by car A's own key);
- sends forged StopRun messages for the current run;
- announces a liveliness token for ``rsu1`` and forges its stats, with no RSU running.

Each is refused and counted, and the run is unharmed (no collision, the cars finish),
or, for the fake RSU, the monitor refuses to report an rsu-mode run as a success.
Assertions are on counts and bounded sizes, never on wall-clock time.
"""

from __future__ import annotations

import asyncio
import threading
import time
from collections.abc import Awaitable, Callable
from pathlib import Path
from typing import Any, TypeVar

import msgpack
import pytest

from protocol import keys as keyexpr
from services.bench.flood import FloodSpec, flood_datagrams
from services.daemons.monitor import MonitorConfig, MonitorService
from services.daemons.rsu import RsuDaemon, RsuDaemonConfig
from services.daemons.vehicle import VehicleDaemon, VehicleDaemonConfig
from services.edge import shell as shell_module
from services.edge.lifecycle import serve
from services.edge.plumbing import (
    PlumbingAuth,
    StatsReport,
    StopRun,
    control_key,
    encode_control,
    encode_stats,
    truth_key,
)
from services.edge.settings import CommonDaemonConfig, load_config
from services.edge.transport import RELIABLE_QOS, V2X_QOS, MemoryBus, MemoryTransport
from services.edge.trust import Authority
from services.model.kinematics import TruthState
from services.model.scenario import Scenario, load_scenario
from services.sim.sensors import perceive
from services.supervise.launcher import make_run_authority

REPO = Path(__file__).resolve().parents[2]
PAPER = REPO / "scenarios" / "paper-blind-intersection.toml"
SPEED = 4.0
"""Run speed: every daemon shares this one event loop with the flood's inboxes; at 8 a
2-core machine running Python at half the usual speed fell so far behind the run clock
that one run in about ten collided (the run was no longer a real one)."""
RATE_HZ = 1000.0
"""In process the flooder shares the GIL with every daemon, so it floods at 1000/s here;
5000/s over real Zenoh: ``tests/edge/test_flood_zenoh.py`` and ``bench`` (processes)."""

C = TypeVar("C", bound=CommonDaemonConfig)
Attack = Callable[[MemoryBus, asyncio.Event], Awaitable[Any]]


def config(model: type[C], keys: Path | None, node: str, **fields: object) -> C:
    if keys is not None:
        fields |= {
            "security.key": str(keys / f"{node}.key"),
            "security.certificate": str(keys / f"{node}.cert"),
            "security.root": str(keys / "root.pub"),
        }
    return load_config(model, None, {"node_id": node, **fields}, env={})


async def run(
    scenario: Scenario,
    keys: Path | None,
    attack: Attack | None = None,
    *,
    rsu: bool = True,
    **monitor_fields: object,
) -> tuple[MonitorService, list[VehicleDaemon | RsuDaemon]]:
    """One rsu-mode run of every daemon (no RSU daemon unless ``rsu``) with ``attack``
    running beside it until the monitor is done."""
    bus = MemoryBus()
    stop = asyncio.Event()
    actors: list[VehicleDaemon | RsuDaemon] = []
    for v in scenario.vehicles:
        cfg = config(VehicleDaemonConfig, keys, v.id, scenario=str(PAPER), stats_period_s=0.5)
        actors.append(VehicleDaemon(cfg, scenario, MemoryTransport(bus)))
    if rsu:
        for r in scenario.rsus:
            rcfg = config(RsuDaemonConfig, keys, r.id, scenario=str(PAPER), stats_period_s=0.5)
            actors.append(RsuDaemon(rcfg, scenario, MemoryTransport(bus)))
    fields: dict[str, object] = {
        "scenario": str(PAPER),
        "mode": "rsu",
        "start_delay_s": 0.3,
        "stats_wait_s": 2.0,
        "ack_timeout_s": 15.0,  # a loaded machine; the fake-RSU test sets its own
        "time.speed": SPEED,
    }
    mcfg = config(MonitorConfig, keys, "monitor", **(fields | monitor_fields))
    monitor = MonitorService(mcfg, scenario, MemoryTransport(bus))
    tasks = [asyncio.ensure_future(serve(a, install_signals=False, stop=stop)) for a in actors]
    done = asyncio.Event()
    attacker = asyncio.ensure_future(attack(bus, done)) if attack is not None else None
    try:
        await serve(monitor, install_signals=False)
    finally:
        done.set()
        if attacker is not None:
            await attacker
        stop.set()
        await asyncio.gather(*tasks)
    return monitor, actors


@pytest.fixture
def keys(tmp_path: Path) -> Path:
    return make_run_authority(tmp_path / "keys", load_scenario(PAPER))


class Flooder(threading.Thread):
    """Publishes ``spec``'s datagrams from its own thread (the network's side of the
    inboxes), paced in 10 ms slices, until ``done`` or ``spec.max_count``."""

    def __init__(self, bus: MemoryBus, spec: FloodSpec) -> None:
        super().__init__(daemon=True)
        self.transport = MemoryTransport(bus, loop=asyncio.get_running_loop())
        self.transport.open()
        self.spec = spec
        self.pool = flood_datagrams(spec)
        self.done = threading.Event()
        self.sent = 0

    def run(self) -> None:
        start = time.monotonic()
        while not self.done.is_set() and self.sent < self.spec.max_count:
            due = min(self.spec.max_count, int((time.monotonic() - start) * self.spec.rate_hz))
            while self.sent < due:
                key, data = self.pool[self.sent % len(self.pool)]
                self.transport.publish(key, data, V2X_QOS)
                self.sent += 1
            time.sleep(0.01)


def started_run(payload: bytes) -> str | None:
    """The run id of a start message, signed or not (a signed blob begins with it)."""
    unpacker = msgpack.Unpacker(raw=False)
    unpacker.feed(payload)
    try:
        body = unpacker.unpack()
    except Exception:
        return None
    if isinstance(body, dict) and body.get("type") == "start":
        run_id = body.get("run_id")
        return run_id if isinstance(run_id, str) else None
    return None


def listen_for_runs(peer: MemoryTransport, runs: list[str]) -> None:
    def on_control(key: str, payload: bytes) -> None:
        run_id = started_run(payload)
        if run_id is not None and run_id not in runs:
            runs.append(run_id)

    peer.subscribe(control_key(), on_control)


def unharmed(monitor: MonitorService) -> dict[str, Any]:
    result = monitor.result
    assert result is not None and monitor.exit_code == 0, monitor.failure
    assert result.collisions == 0 and result.all_finished
    return result.actors or {}


@pytest.mark.parametrize("scoped", [True, False], ids=["run-keys", "wildcard"])
@pytest.mark.parametrize("new_ids", [False, True], ids=["500-ids", "new-id-each"])
async def test_a_flood_of_future_paths_is_refused_and_the_run_unharmed(
    keys: Path, new_ids: bool, scoped: bool, monkeypatch: pytest.MonkeyPatch
) -> None:
    """``run-keys``: in a run every daemon declares only the run's senders' keys, so the
    flood never reaches it; ``wildcard`` (a run with more senders than
    ``MAX_SCOPED_KEYS``, here forced): every datagram reaches it and is refused on the
    network thread, counted."""
    if not scoped:
        monkeypatch.setattr(shell_module, "MAX_SCOPED_KEYS", 0)
    flooders: list[Flooder] = []

    async def attack(bus: MemoryBus, done: asyncio.Event) -> None:
        # From the run's start on (a daemon admits only the run's nodes once its start
        # message has arrived; before a run it has no list to admit by, and its lanes are
        # bounded by max_lanes alone): a flood begun first gave the fakes lanes.
        peer = MemoryTransport(bus)
        peer.open()
        runs: list[str] = []
        listen_for_runs(peer, runs)
        while not runs and not done.is_set():
            await asyncio.sleep(0.01)
        await asyncio.sleep(0.5)  # every daemon has handled the start message
        # unsigned from new ids (signing 20 000 of them takes seconds), else wrongly signed
        spec = FloodSpec(rate_hz=RATE_HZ, new_ids=new_ids, duration_s=60.0, signed=not new_ids)
        flooder = Flooder(bus, spec)
        flooders.append(flooder)
        flooder.start()
        await done.wait()
        flooder.done.set()
        await asyncio.to_thread(flooder.join)
        peer.close()

    monitor, daemons = await run(load_scenario(PAPER), keys, attack)
    actors = unharmed(monitor)
    sent = flooders[0].sent
    assert sent > 1000
    rsu = actors["rsu1"]
    # only the real cars ever were in the RSU's reservation table
    assert {car for _t, cars in rsu["table_log"] for car in cars} <= {"A", "B"}
    for node in ("rsu1", "A", "B"):
        fp = actors[node]["receive"]["fp"]
        if scoped:  # not one flooding datagram reached the daemon in the run
            assert fp["refused"] == 0, node
            assert fp["offered"] < sent / 10, node  # the genuine cars' datagrams only
        else:
            assert fp["refused"] > 0, node  # counted (the last report of the run)
        # the fakes never got a lane (no per-sender state): at most the two real cars,
        # each with a lane for its certificate-carrying datagrams
        assert fp["max_lanes"] <= 4, node
    for daemon in daemons:  # the subscriptions' inboxes are empty and bounded
        for policy in daemon.shell.receive.values():
            assert policy.stats.max_lanes <= policy.max_lanes


async def test_a_truth_report_with_x_1e300_is_refused_and_counted() -> None:
    """Unsigned daemons (``--insecure``), so that the value itself is what is refused (a
    signed run refuses it earlier, unsigned: see the forged stop); also what a car whose
    own key signs it would meet."""
    sent = 0

    async def attack(bus: MemoryBus, done: asyncio.Event) -> None:
        nonlocal sent
        peer = MemoryTransport(bus)
        peer.open()
        runs: list[str] = []
        listen_for_runs(peer, runs)
        while not done.is_set():
            if runs:
                body = {
                    "v": 1,
                    "type": "truth",
                    "run_id": runs[0],
                    "vehicle": "A",
                    "step": 20,
                    "state": [1.0, 1e300, -1.75, 0.0, 5.0, 0.0, 10.0, 4.5, 1.8],
                    "mode": "AUTO",
                    "reason": "",
                }
                raw: bytes = msgpack.packb(body, use_bin_type=True)
                peer.publish(truth_key("A"), raw, RELIABLE_QOS)
                sent += 1
            await asyncio.sleep(0.2)
        peer.close()

    monitor, daemons = await run(load_scenario(PAPER), None, attack)
    unharmed(monitor)
    assert sent > 3
    car_b = next(d for d in daemons if d.node == "B")
    assert car_b.shell.internal_errors == 0 and monitor.shell.internal_errors == 0
    # refused during the run (before its start and after its end they are ignored)
    assert car_b.shell.plumbing_malformed >= 3 and monitor.shell.plumbing_malformed >= 3
    # and the sensors never overflow on such a value
    far = TruthState("X", 0.0, 1e300, 0.0, 0.0, 1.0, 0.0, 0.0, 4.5, 1.8)
    ego = TruthState("B", 0.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 4.5, 1.8)
    assert perceive(ego, [far], [], 100.0) == []


async def test_a_forged_stop_is_refused_and_counted(keys: Path) -> None:
    forged = 0

    async def attack(bus: MemoryBus, done: asyncio.Event) -> None:
        nonlocal forged
        peer = MemoryTransport(bus)
        peer.open()
        car_a = PlumbingAuth(Authority.open(keys).credentials("A"))
        runs: list[str] = []
        listen_for_runs(peer, runs)
        while not done.is_set():
            if runs:
                stop = encode_control(StopRun(runs[0], "forged", 1.0))
                peer.publish(control_key(), stop, RELIABLE_QOS)  # unsigned
                peer.publish(control_key(), car_a.seal(stop), RELIABLE_QOS)  # a car's key
                forged += 2
            await asyncio.sleep(0.5)
        peer.close()

    monitor, daemons = await run(load_scenario(PAPER), keys, attack)
    unharmed(monitor)
    assert forged >= 4
    for daemon in daemons:
        auth = daemon.shell.plumbing_auth
        assert auth is not None
        assert auth.refused.get("bad_trailer", 0) >= 1, daemon.node
        assert auth.refused.get("wrong_role", 0) >= 1, daemon.node


class FakeRsu:
    """A liveliness token for ``rsu1`` and its stats every 0.2 s (a "hello" before a run,
    then acknowledging every run), signed by a key of another authority when ``forger``
    is given, else unsigned."""

    def __init__(self, forger: PlumbingAuth | None) -> None:
        self.forger = forger
        self.runs: list[str] = []
        self.stats_sent = 0

    async def __call__(self, bus: MemoryBus, done: asyncio.Event) -> None:
        peer = MemoryTransport(bus)
        peer.open()
        listen_for_runs(peer, self.runs)
        peer.declare_liveliness(f"{keyexpr.DEFAULT_PREFIX}/sim/alive/rsu1")
        while not done.is_set():
            run_id = self.runs[-1] if self.runs else None
            report = StatsReport("rsu1", run_id, False, {"streams": {}})
            data = encode_stats(report)
            if self.forger is not None:
                data = self.forger.seal(data)
            peer.publish(keyexpr.stats("rsu1"), data, RELIABLE_QOS)
            self.stats_sent += 1
            await asyncio.sleep(0.2)
        peer.close()


async def test_forged_liveliness_and_stats_cannot_fake_an_rsu_insecure() -> None:
    fake = FakeRsu(None)
    monitor, _ = await run(load_scenario(PAPER), None, fake, rsu=False)
    assert fake.stats_sent > 0 and fake.runs
    result = monitor.result
    assert monitor.exit_code == 1 and result is not None
    assert result.error is not None and "no car heard rsu1" in result.error


async def test_forged_liveliness_and_stats_cannot_fake_an_rsu_signed(
    keys: Path, tmp_path: Path
) -> None:
    scenario = load_scenario(PAPER)
    other = Authority.open(make_run_authority(tmp_path / "other", scenario))
    fake = FakeRsu(PlumbingAuth(other.credentials("rsu1")))
    monitor, _ = await run(scenario, keys, fake, rsu=False, wait_actors_s=2.0)
    assert fake.stats_sent > 0
    # the token alone never counts: no run starts, the RSU is reported missing
    assert not fake.runs and monitor.start is None and monitor.result is None
    assert monitor.exit_code == 1 and monitor.failure is not None
    assert "not present" in monitor.failure and "rsu1" in monitor.failure
    assert "A" not in monitor.failure and "B" not in monitor.failure  # the cars said hello
    assert "rsu1" in monitor.tokens and "rsu1" not in monitor.heard
    auth = monitor.shell.plumbing_auth
    assert auth is not None and auth.refused.get("bad_certificate", 0) >= 1
