"""Co-simulation with real RSU daemons (``crosspath sumo NET ROUTES --daemons [--speed X]``).

SUMO stays the world in one process, the *world process* (the ``crosspath sumo`` process
itself, as in-process): SUMO's network, demand, insertion, physics and the cars it
drives, and crosspath's agents of the connected cars. What changes against the
in-process co-simulation (``services.sumo.cosim``, whose loop, physics and result this
module shares: :class:`DaemonsCosimulation` overrides only its radio and pacing hooks)
is the radio and the clock:

- every RSU is a real ``crosspath rsu`` daemon OS process (``services.daemons.rsu``), its
  command line built by ``services.supervise.launcher.actor_commands`` (as ``crosspath
  up``), started and stopped by the world process with the launcher's ``Launcher``
  (own process group, SIGTERM then SIGKILL after the grace period, a final sweep of
  any process carrying the run id, SIGTERM from the kernel if the world process dies).
  Its scenario is the network's base scenario (``services.sumo.from_sumo``: the map,
  the junction zones, one RSU per junction) written to ``<run dir>/scenario.toml``;
- V2X between the connected cars' agents and the RSU daemons travels over real Zenoh
  (``services.edge.transport`` through a ``services.edge.shell.DaemonShell``: bounded
  inboxes, sender admission, stale and malformed checks, counters): the world process
  is one Zenoh peer, node ``monitor``, listening on loopback; each RSU listens on its
  own endpoints and connects to the world and to the RSUs before it (the full mesh of
  ``crosspath up``). The cars' future paths and autonomous paths go out signed with
  each car's own key (a throw-away authority in ``<run dir>/keys``,
  ``launcher.make_run_authority``, plus a key and certificate per connected car of the
  demand), commands and beacons from the RSUs are verified (``services.edge.trust``)
  and then checked as a car daemon checks them (``services.vehicle.authorize.refusal``:
  may this RSU command this car here?). ``insecure`` turns signing off (as ``crosspath
  up --insecure``). Car-to-car future paths also travel over Zenoh: the world process
  receives its own publications (Zenoh delivers them locally) and hands each to the
  other connected cars on the road;
- the world process is the run's monitor: it publishes the run start
  (``services.edge.plumbing.StartRun``, signed with the monitor's certificate, repeated
  until every RSU acknowledged it with a stats report of the run) with the run clock
  (epoch ``start_delay_s`` after the start, ``speed``), mode, policy, seed and the node
  lists; at the end the run stop, waits for each RSU's final stats report (which goes
  into the result's ``actors`` and ``network``), and stops the daemons;
- pacing: SUMO steps on the run clock: after each SUMO step to run time ``t`` the world
  process runs its event loop (Zenoh receptions) until wall time ``epoch + t / speed``;
  a step that starts more than one physics step late counts in ``late_ticks``
  (``monitor``) and marks the run ``degraded``. What was received is delivered to the
  agents at the next step, dated by its reception time on the run clock.

Decisions where the issue is silent:

- One OS process per SUMO vehicle is not the design: SUMO creates and removes cars
  every step, while a daemon takes a second to start and its Zenoh node to join. The
  cars' agents stay in the world process (as the cars of a ``crosspath vehicle --ids``
  host share a process), each with its own key and V2X identity; the RSUs, which live
  as long as the run, are the daemons. The RSU daemon is unchanged.
- Cars of the run: an RSU daemon admits V2X only from the nodes the start names and
  commands only the cars it lists, and a start cannot change during a run. So before
  the run a *dry pass* of SUMO (the same network, demand, step, seed and extra
  options, SUMO driving everyone, to ``max_sim_s`` or until the demand is exhausted)
  lists every vehicle the demand loads; which vehicles load when does not depend on
  how they drive (flows draw from their own random stream). The crosspath ids are
  assigned in that order (a SUMO id whose cleaned id clashes with another's gets the
  same suffix in every run); the cars drawn connected are listed in the start (their
  ``start_times`` are their first appearance in the dry pass, for information). A car
  that departs in the run but was not listed is driven by SUMO (counted
  ``unlisted``). The start carries at most about 3000 cars (the plumbing's 256 KiB).
- Without an RSU daemon to run (``fp-only``/``standalone``, ``rsus=False``, no
  junction, or no car drawn connected) no daemon is started and no start is sent:
  the future paths still travel over Zenoh between the cars.
- ``network`` counts the world process as one node for all its cars: a datagram it
  receives counts once however many cars it is handed to, so the expected receivers
  are the world process plus every RSU for a future path and one for the rest.
- Errors: an RSU daemon that fails to start, to come up within
  :data:`ALIVE_TIMEOUT_S`, to acknowledge the start, or that exits during the run ends
  the run with :class:`DaemonsError` (with the last lines of its log); ``KeyboardInterrupt``
  and, in the main thread, SIGTERM (turned into a ``KeyboardInterrupt`` for the run)
  end it too. Every path stops the daemons (SIGTERM) and undeclares the world's Zenoh
  entities before its session closes.
- Files: ``<run dir>`` (``run_dir``, default ``results/sumo/<time>-<id>``) holds
  ``scenario.toml``, ``keys/``, each RSU's log ``<rsu>.log`` and ``children.json``.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import secrets
import signal
import threading
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from pathlib import Path
from types import FrameType, ModuleType
from typing import Any, Final

from protocol import CoordinatedPath, EncodeError, Message, ModeCommand, RsuBeacon, encode
from protocol import keys as keyexpr
from protocol.auth import Certificate
from protocol.keys import ParsedKey, Stream
from services.daemons.monitor import _actor_summary, network_summary
from services.edge.plumbing import (
    MAX_PLUMBING_BYTES,
    PlumbingError,
    StartRun,
    StatsReport,
    StopRun,
    control_key,
    decode_stats,
    encode_control,
)
from services.edge.settings import CommonDaemonConfig, SecuritySettings, ZenohSettings
from services.edge.shell import DaemonShell
from services.edge.transport import TransportError, ZenohTransport, qos_for
from services.edge.trust import Authority, Signer, TrustStore, run_tag
from services.model.results import ChannelParams, RunResult
from services.model.scenario import Crossing, load_scenario
from services.model.types import RunMode
from services.sumo.cosim import Cosimulation, _Car, _draw_connected
from services.sumo.from_sumo import write_scenario
from services.supervise.launcher import (
    GRACE_S,
    LEASE_MS,
    MONITOR,
    Launcher,
    actor_commands,
    loopback_endpoints,
    make_run_authority,
    node_order,
    tail_log,
)
from services.vehicle.agent import Outgoing as CarOutgoing
from services.vehicle.authorize import refusal

__all__ = ["ALIVE_TIMEOUT_S", "CarsTrust", "DaemonsCosimulation", "DaemonsError"]

log = logging.getLogger("crosspath.sumo.daemons")

ALIVE_TIMEOUT_S: Final = 30.0
"""Wall seconds the RSU daemons have to come up (their liveliness tokens seen)."""

ACK_TIMEOUT_S: Final = 15.0
"""Wall seconds the RSU daemons have to acknowledge the run start."""

START_REPEAT_S: Final = 0.25
"""Wall seconds between two publications of the run start until acknowledged."""

FINAL_WAIT_S: Final = 5.0
"""Wall seconds to wait for the RSUs' final stats reports after the run stop."""

DRY_CHUNK_S: Final = 1.0
"""Run seconds SUMO advances per call in the dry pass (its lists accumulate)."""


class DaemonsError(RuntimeError):
    """A daemon of the co-simulation failed; ``run_dir`` holds the logs."""

    def __init__(self, message: str, run_dir: Path) -> None:
        super().__init__(f"{message} (logs in {run_dir})")
        self.run_dir = run_dir


def _interrupt(signum: int, _frame: FrameType | None) -> None:
    raise KeyboardInterrupt(signum)


class CarsTrust(TrustStore):
    """The world process's trust store: the RSUs' commands to a car are verified by that
    car's own store (one replay window per car, as in a car daemon), beacons by a store
    of their own, the cars' paths by this one. One window over an RSU's messages to
    every car refused older ones delivered after 64 newer ones to other cars (the
    inbox takes its lanes round robin) as replays. The stores share the checked
    certificates and the counters."""

    def __init__(self, base: TrustStore) -> None:
        super().__init__(base.root, revocation=base.revocation, run=base.run)
        self._stores: dict[str, TrustStore] = {}

    def _store(self, name: str) -> TrustStore:
        store = self._stores.get(name)
        if store is None:
            store = self._stores[name] = TrustStore(
                self.root, revocation=self.revocation, run=self.run
            )
            store.share_certificates(self)
            store.counters = self.counters
        return store

    def begin_run(self, run_id: str | None) -> None:
        super().begin_run(run_id)
        self._stores.clear()

    def verify_datagram(self, datagram: bytes, message: Message) -> Certificate:
        if isinstance(message, ModeCommand | CoordinatedPath):
            return self._store(message.vehicle).verify_datagram(datagram, message)
        if isinstance(message, RsuBeacon):
            return self._store("*beacons").verify_datagram(datagram, message)
        return super().verify_datagram(datagram, message)


@dataclass(slots=True)
class DaemonsCosimulation(Cosimulation):
    """A co-simulation whose RSUs are daemons over Zenoh (module docstring); ``run()``
    returns the run result (``harness`` ``daemons``)."""

    harness = "daemons"
    run_id: str = field(init=False, default="")
    run_dir: Path = field(init=False, default=Path())
    rsu_ids: tuple[str, ...] = field(init=False, default=())
    """The RSU daemons of the run (none outside ``rsu`` mode)."""
    listed: set[str] = field(init=False, default_factory=set)
    """Crosspath ids of the cars the start lists (drawn connected)."""
    first_seen: dict[str, float] = field(init=False, default_factory=dict)
    _planned: dict[str, str] = field(init=False, default_factory=dict)
    launcher: Launcher | None = field(init=False, default=None)
    shell: DaemonShell | None = field(init=False, default=None)
    loop: asyncio.AbstractEventLoop | None = field(init=False, default=None)
    authority: Authority | None = field(init=False, default=None)
    start: StartRun | None = field(init=False, default=None)
    epoch_unix: float = field(init=False, default=0.0)
    _signers: dict[str, Signer] = field(init=False, default_factory=dict)
    _crossings: dict[str, list[Crossing]] = field(init=False, default_factory=dict)
    _inbox: list[tuple[float, ParsedKey, Message, Certificate | None]] = field(
        init=False, default_factory=list
    )
    _alive: set[str] = field(init=False, default_factory=set)
    rsu_reports: dict[str, StatsReport] = field(init=False, default_factory=dict)
    """Each RSU's latest stats report of the run (the final one once it came)."""
    world_report: StatsReport | None = field(init=False, default=None)
    rsus_heard: dict[str, int] = field(init=False, default_factory=dict)
    """Per RSU, its messages (beacons, commands) handed to the cars."""
    refused: dict[str, int] = field(init=False, default_factory=dict)
    """Commands the cars refused, by reason (``services.vehicle.authorize``)."""
    fp_receivers: list[int] = field(init=False, default_factory=lambda: [0, 0])

    def __post_init__(self) -> None:
        Cosimulation.__post_init__(self)
        self.rsus = {}  # no RSU core in this process: they are daemons
        o = self.options
        if o.mode is RunMode.RSU:
            self.rsu_ids = tuple(r.id for r in self.base.rsus)
        self._ids.used.add(MONITOR)

    # ------------------------------------------------------------------ run
    def run(self) -> RunResult:
        """:meth:`Cosimulation.run` with SIGTERM as a ``KeyboardInterrupt`` (main thread),
        so that the daemons are stopped on the way out."""
        main = threading.current_thread() is threading.main_thread()
        previous = signal.signal(signal.SIGTERM, _interrupt) if main else None
        try:
            return Cosimulation.run(self)
        finally:
            if previous is not None:
                signal.signal(signal.SIGTERM, previous)

    # ------------------------------------------------------------------ hooks
    def _car_id(self, sumo_id: str) -> str:
        cid = self._planned.get(sumo_id)
        return self._ids(sumo_id) if cid is None else cid

    def _may_connect(self, cid: str) -> bool:
        if cid in self.listed:
            return True
        self._count("unlisted")
        log.warning("%s was not in the dry pass: SUMO drives it", cid)
        return False

    def _channel_params(self) -> ChannelParams:
        return ChannelParams(kind="zenoh")

    def _open_radio(self) -> None:
        o = self.options
        stamp = time.strftime("%Y%m%d-%H%M%S")
        token = secrets.token_hex(3)
        self.run_id = f"sumo-{stamp}-{token}"
        self.run_dir = (
            o.run_dir if o.run_dir is not None else Path("results") / "sumo" / f"{stamp}-{token}"
        )
        self.run_dir.mkdir(parents=True, exist_ok=True)
        self._dry_pass()
        scenario_path = write_scenario(self.base, self.run_dir / "scenario.toml")
        scenario = load_scenario(scenario_path)
        nodes = node_order(scenario, o.mode)
        endpoints = loopback_endpoints(nodes)
        keys_dir = None
        if not o.insecure:
            keys_dir = make_run_authority(self.run_dir / "keys", scenario)
            self.authority = Authority.open(keys_dir)
            self.authority.provision(sorted(self.listed), (), validity_s=86400)
        if not self.listed:
            self.rsu_ids = ()
        zenoh_options: dict[str, Any] = {
            "transport/link/tx/lease": LEASE_MS,
            "metadata": {"crosspath_run": self.run_id},  # the launcher's sweep finds it
        }
        if self.rsu_ids:
            commands = actor_commands(
                scenario_path,
                o.mode,
                o.policy,
                o.seed,
                o.speed,
                endpoints,
                run_id=self.run_id,
                zenoh_options=zenoh_options,
                keys_dir=keys_dir,
            )
            self.launcher = Launcher(
                {r: commands[r] for r in self.rsu_ids},
                self.run_dir,
                run_id=self.run_id,
                grace_s=GRACE_S,
            )
            self.launcher.start()
        security = (
            SecuritySettings(insecure=True)
            if keys_dir is None
            else SecuritySettings(
                key=keys_dir / f"{MONITOR}.key",
                certificate=keys_dir / f"{MONITOR}.cert",
                root=keys_dir / "root.pub",
                revocation=keys_dir / "revoked.txt",
            )
        )
        config = CommonDaemonConfig(
            node_id=MONITOR,
            zenoh=ZenohSettings(listen=endpoints[MONITOR].locators, options=zenoh_options),
            security=security,
        )
        loop = self.loop = asyncio.new_event_loop()
        shell = self.shell = DaemonShell(
            config,
            "sumo",
            ZenohTransport(config.zenoh, loop=loop),
            extras=self._world_extras,
        )
        if shell.trust is not None:
            shell.trust = CarsTrust(shell.trust)
        loop.run_until_complete(shell.open())
        p = shell.prefix
        shell.subscribe_v2x(keyexpr.all_future_paths(prefix=p), Stream.FP, self._on_v2x)
        shell.subscribe_v2x(keyexpr.all_commands(prefix=p), Stream.CMD, self._on_v2x)
        shell.subscribe_v2x(keyexpr.all_beacons(prefix=p), Stream.BEACON, self._on_v2x)
        shell.subscribe_plumbing(keyexpr.all_stats(prefix=p), self._on_stats)
        shell.watch_alive(self._on_alive)
        shell.announce()
        if self.rsu_ids:
            self._await("the RSU daemons to come up", ALIVE_TIMEOUT_S, self._all_alive)
        self.epoch_unix = time.time() + o.start_delay_s
        shell.actors = frozenset((*self.listed, *self.rsu_ids, MONITOR))
        clock = shell.begin_run(self.run_id, self.epoch_unix, o.speed)
        if self.rsu_ids:
            start = self.start = StartRun(
                run_id=self.run_id,
                scenario=scenario.name,
                mode=o.mode,
                policy=o.policy,
                seed=o.seed,
                start_times={c: self.first_seen.get(c, 0.0) for c in self.listed},
                epoch_unix=self.epoch_unix,
                speed=o.speed,
                max_sim_s=o.max_sim_s,
                monitor=MONITOR,
                vehicles=tuple(sorted(self.listed)),
                rsus=self.rsu_ids,
            )
            payload = encode_control(start)
            if len(payload) > MAX_PLUMBING_BYTES:
                raise DaemonsError(
                    f"the run start lists {len(self.listed)} cars: {len(payload)} B, more than "
                    f"the plumbing's {MAX_PLUMBING_BYTES} B (fewer cars or a shorter max_sim_s)",
                    self.run_dir,
                )
            self._await(
                "the RSU daemons to acknowledge the run start",
                ACK_TIMEOUT_S,
                lambda: set(self.rsu_reports) >= set(self.rsu_ids),
                lambda: shell.publish_plumbing(control_key(prefix=p), payload),
            )
        log.info(
            "run %s: %d cars listed, RSU daemons %s, run time 0 in %.2f s wall, speed %g",
            self.run_id,
            len(self.listed),
            ", ".join(self.rsu_ids) or "none",
            clock.to_wall(0.0) - time.time(),
            o.speed,
        )

    def _dry_pass(self) -> None:
        """List the vehicles the demand loads (module docstring) and fix their ids."""
        o = self.options
        api = self._open_sumo("cosim-dry", "--no-step-log", "true", "--no-warnings", "true")
        try:
            for t, sid in _loaded(api, o.max_sim_s):
                if sid in self._planned:
                    continue
                cid = self._planned[sid] = self._ids(sid)
                self.first_seen[cid] = t
                if _draw_connected(o.seed, sid, o.connected_share):
                    self.listed.add(cid)
        finally:
            api.close()

    def _pace(self, now: float) -> None:
        loop, shell = self.loop, self.shell
        if loop is None or shell is None:
            return
        self._check_daemons()
        lag = time.time() - (self.epoch_unix + now / self.options.speed)  # [wall s]
        if lag > 0:  # a step more than one physics step behind counts in late_ticks
            shell.on_tick(now, now + lag * self.options.speed, self.base.params.physics_dt_s)
        loop.run_until_complete(asyncio.sleep(max(0.0, -lag)))

    def _deliver(self, now: float) -> None:
        inbox, self._inbox = self._inbox, []
        listeners = self._listeners()
        for t_rx, parsed, message, cert in inbox:
            t = min(t_rx, now)
            if parsed.stream is Stream.FP:
                for cid in listeners:
                    agent = self.cars[cid].agent
                    if cid != parsed.vehicle and agent is not None:
                        agent.on_message(t, message, None)
            elif parsed.stream is Stream.BEACON and parsed.rsu is not None:
                for cid in listeners:
                    agent = self.cars[cid].agent
                    if agent is not None:
                        agent.on_message(t, message, parsed.rsu)
                        self._heard(parsed.rsu)
            elif parsed.stream is Stream.CMD and parsed.vehicle in self.present:
                car = self.cars[parsed.vehicle]
                if car.agent is None or parsed.rsu is None:
                    continue
                why = self._refusal(car, message, cert, now)
                if why is not None:
                    self.refused[why] = self.refused.get(why, 0) + 1
                    continue
                car.agent.on_message(t, message, parsed.rsu)
                self._heard(parsed.rsu)

    def _transmit(self, now: float, cid: str, out: CarOutgoing) -> None:
        shell = self.shell
        if shell is None:
            return
        p = shell.prefix
        if out.stream is Stream.FP:
            self.fp_receivers[0] += 1
            self.fp_receivers[1] += 1 + len(self.rsu_ids)
            self._publish(cid, keyexpr.future_path(cid, prefix=p), out.message)
        elif out.stream is Stream.AP and out.rsu in self.rsu_ids:
            self._publish(cid, keyexpr.autonomous_path(out.rsu, cid, prefix=p), out.message)

    def _tick_rsus(self, now: float) -> None:
        """The RSU daemons tick on their own clock."""

    def _close_radio(self) -> None:
        loop, shell, launcher = self.loop, self.shell, self.launcher
        try:
            if loop is not None and shell is not None:
                if self.start is not None:
                    self._stop_run(shell)
                self.world_report = shell.stats_report(final=True)
        finally:
            try:
                if launcher is not None:
                    launcher.stop_all()
                    for note in launcher.notes:
                        log.warning("%s", note)
            finally:
                if loop is not None:
                    try:
                        if shell is not None:
                            loop.run_until_complete(shell.close())
                    finally:
                        loop.close()
                self.loop = None

    def _result_sections(self, sim_s: float) -> dict[str, Any]:
        reports = dict(self.rsu_reports)
        if self.world_report is not None:
            reports[MONITOR] = self.world_report
        snapshots = [r.snapshot for _n, r in sorted(reports.items())]
        sent = self.fp_receivers[0]
        receivers = {
            "fp": self.fp_receivers[1] / sent if sent else 1.0 + len(self.rsu_ids),
            "ap": 1.0,
            "cmd": 1.0,
            "beacon": 1.0,
        }
        n_cars = sum(1 for c in self.cars.values() if c.agent is not None)
        network = network_summary(snapshots, max(n_cars, 1), len(self.rsu_ids), sim_s, receivers)
        late = {MONITOR: 0 if self.shell is None else self.shell.late_ticks}
        for node, report in sorted(self.rsu_reports.items()):
            value = report.snapshot.get("late_ticks")
            late[node] = value if isinstance(value, int) and value >= 0 else 0
        finished = self._now < self.options.max_sim_s - 1e-9
        return {
            "run_id": self.run_id,
            "speed": self.options.speed,
            "end_reason": "finished" if finished else "max_sim_s",
            "epoch_unix": self.epoch_unix,
            "final_stats": sorted(n for n, r in self.rsu_reports.items() if r.final),
            "network": network,
            "actors": {n: _actor_summary(r, []) for n, r in sorted(reports.items())},
            "late_ticks": late,
            "degraded": any(late.values()),
        }

    # ------------------------------------------------------------------ helpers
    def _world_extras(self) -> dict[str, Any]:
        """The world process's own fields in its ``actors`` entry."""
        return {
            "cars_listed": len(self.listed),
            "rsus_heard": dict(sorted(self.rsus_heard.items())),
            "cmd_refused": dict(sorted(self.refused.items())),
            "counters": dict(sorted(self.counters.items())),
        }

    def _heard(self, rsu: str) -> None:
        self.rsus_heard[rsu] = self.rsus_heard.get(rsu, 0) + 1

    def _refusal(
        self, car: _Car, message: Message, cert: Certificate | None, now: float
    ) -> str | None:
        """Why ``car`` must not obey ``message`` (None: it may); as a car daemon checks."""
        shell = self.shell
        if shell is None or shell.trust is None or car.lanes is None:
            return None
        crossings = self._crossings.get(car.cid)
        if crossings is None:
            rid, sc = self._route_scenarios[tuple(car.lanes)]
            crossings = self._crossings[car.cid] = sc.crossings(rid, car.length)
        t = self._truth(car, now)
        return refusal(message, cert, crossings, t.s, t.x, t.y)

    def _signer(self, cid: str) -> Signer | None:
        auth, shell = self.authority, self.shell
        if auth is None or shell is None or shell.trust is None:
            return None
        signer = self._signers.get(cid)
        if signer is None:
            signer = self._signers[cid] = Signer(auth.credentials(cid))
            signer.begin_run(run_tag(self.run_id), self.options.speed)
        return signer

    def _publish(self, cid: str, key: str, message: Message) -> None:
        """One car's V2X message on ``key``, signed with its key (as ``publish_v2x``)."""
        shell = self.shell
        if shell is None:
            return
        stream = keyexpr.STREAM_OF_KIND[message.kind]
        try:
            payload = encode(message)
            signer = self._signer(cid)
            if signer is not None:
                payload = signer.seal(payload)
            shell.transport.publish(key, payload, qos_for(stream))
        except (EncodeError, TransportError) as exc:
            self._count("send_failed")
            log.debug("%s: cannot send on %s: %s", cid, key, exc)
            return
        shell.stats.on_send(str(stream), len(payload))

    def _on_v2x(self, parsed: ParsedKey, message: Message, now: float) -> None:
        shell = self.shell
        self._inbox.append((now, parsed, message, None if shell is None else shell.verified))

    def _on_stats(self, key: str, payload: bytes) -> None:
        shell = self.shell
        report = decode_stats(payload)
        if shell is None or report.node not in self.rsu_ids or report.run_id != self.run_id:
            return
        if key != keyexpr.stats(report.node, prefix=shell.prefix):
            raise PlumbingError(f"stats of {report.node} on {key}")
        prev = self.rsu_reports.get(report.node)
        if prev is None or not prev.final:
            self.rsu_reports[report.node] = report

    def _on_alive(self, node: str, alive: bool) -> None:
        if alive:
            self._alive.add(node)
        else:
            self._alive.discard(node)

    def _all_alive(self) -> bool:
        return set(self.rsu_ids) <= self._alive

    def _check_daemons(self) -> None:
        """Raise :class:`DaemonsError` when an RSU daemon has exited."""
        launcher = self.launcher
        if launcher is None:
            return
        for child in launcher.children.values():
            code = child.process.poll()
            if code is not None:
                raise DaemonsError(
                    f"RSU daemon {child.node} exited with code {code}; last lines of "
                    f"{child.log_path}:\n{tail_log(child.log_path)}",
                    self.run_dir,
                )

    def _await(
        self,
        what: str,
        timeout_s: float,
        done: Callable[[], bool],
        repeat: Callable[[], object] | None = None,
    ) -> None:
        """Run the event loop until ``done()`` (calling ``repeat()`` every
        :data:`START_REPEAT_S`); :class:`DaemonsError` after ``timeout_s`` or when a daemon
        exits meanwhile."""
        loop = self.loop
        if loop is None:
            raise RuntimeError("the world's event loop is not running")
        deadline = time.monotonic() + timeout_s
        while not done():
            self._check_daemons()
            if time.monotonic() > deadline:
                raise DaemonsError(
                    f"timed out after {timeout_s:g} s waiting for {what}", self.run_dir
                )
            if repeat is not None:
                repeat()
            loop.run_until_complete(asyncio.sleep(START_REPEAT_S if repeat else 0.05))

    def _stop_run(self, shell: DaemonShell) -> None:
        """Publish the run stop and wait for every RSU's final stats report."""
        start = self.start
        if start is None:
            return
        stop = StopRun(start.run_id, "finished", round(self._now, 3))
        payload = encode_control(stop)
        with contextlib.suppress(DaemonsError):
            self._await(
                "the RSU daemons' final stats",
                FINAL_WAIT_S,
                lambda: all(
                    (r := self.rsu_reports.get(n)) is not None and r.final for n in self.rsu_ids
                ),
                lambda: shell.publish_plumbing(control_key(prefix=shell.prefix), payload),
            )
        missing = [n for n in self.rsu_ids if not (r := self.rsu_reports.get(n)) or not r.final]
        if missing:
            log.warning("no final stats report from %s", ", ".join(missing))


def _loaded(api: ModuleType, max_sim_s: float) -> Iterator[tuple[float, str]]:
    """(run time, SUMO id) of every vehicle SUMO loads, departs or holds pending, in
    order, until the demand is exhausted or ``max_sim_s``."""
    t = 0.0
    while t < max_sim_s - 1e-9:
        t = min(t + DRY_CHUNK_S, max_sim_s)
        api.simulationStep(t)
        sim = api.simulation
        for sid in (*sim.getDepartedIDList(), *sim.getLoadedIDList(), *sim.getPendingVehicles()):
            yield t, str(sid)
        if sim.getMinExpectedNumber() <= 0:
            return
