"""The in-process harness: every actor of a scenario in one process, on a virtual clock.

The same pure cores as the daemons (``VehicleAgent``, ``RsuCore``), a seeded
in-memory channel with loss, latency and jitter, and every message crossing it
as bytes through the real codec. Deterministic per seed; far faster than real
time. Physics runs at ``physics_hz`` (20 Hz), planning, V2X and the RSU at
``planning_hz`` (10 Hz).

:meth:`Simulation.run` returns the typed run result
(``services.model.results.RunResult``); its provenance takes the package
version, git commit and scenario digest from an ``Origin`` the caller found
(``services.api.simulate`` does), as this module does no I/O beyond
:func:`write_trace_csv`. The options refuse what they cannot run:
``SimOptions(mode="rsu")`` is the rsu mode, ``SimOptions(mode="bogus")`` a
``ValueError`` naming the modes.

Demand: the scenario's flows are drawn from the run's seed (``Scenario.for_seed``).
A car exists in the world only between insertion and removal. It is inserted at its
route's start once it has arrived (its start time) and the entry is clear
(``services.sim.car.entry_clear``); until then it waits outside the network: it has
no truth, is not sensed, sends nothing and is in no metrics pair (its radio listens,
as a car approaching the network would), and the wait is its ``insertion_delay_s``.
Waiting cars enter in arrival order (a blocked car holds back later ones at the same
entry). A car standing at its goal (``services.sim.car.at_goal``) is removed after that
step's metrics: no longer sensed, it stops sending and receiving; the RSU forgets it
when its reservation expires. The run ends when every car has left, or at ``max_sim_s``.
"""

from __future__ import annotations

import csv
import logging
import math
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from protocol import DecodeError, decode, encode
from protocol import keys as keyexpr
from protocol.keys import Stream
from protocol.messages import Message
from services.model.kinematics import TruthState
from services.model.results import ChannelParams, Origin, RunResult
from services.model.scenario import Scenario
from services.model.types import Policy, RunMode, parse_mode, parse_policy
from services.rsu.config import rsu_config
from services.rsu.core import Outgoing, RsuCore
from services.sim.car import CarBody, at_goal, entry_clear
from services.sim.membus import ChannelModel, MemoryChannel
from services.sim.metrics import MetricsRecorder
from services.sim.results import provenance, run_result, run_summary
from services.sim.sensors import perceive
from services.vehicle.agent import VehicleAgent, vehicle_agent
from services.vehicle.planner import Reason

log = logging.getLogger("crosspath.sim")

TRACE_FIELDS = ("t", "vehicle", "s", "x", "y", "speed", "accel", "reason", "detail", "mode")


@dataclass(frozen=True, slots=True)
class RsuOutage:
    """RSU ``rsu`` is down from ``crash_s`` [run s]: it receives, ticks and sends
    nothing, and its state is lost; at ``restart_s`` (None: never) a fresh ``RsuCore``
    takes its place, as a restarted daemon would."""

    rsu: str
    crash_s: float
    restart_s: float | None = None

    def __post_init__(self) -> None:
        if not (_is_number(self.crash_s) and math.isfinite(self.crash_s) and self.crash_s >= 0):
            raise ValueError(f"crash_s must be a finite number >= 0 [s], got {self.crash_s!r}")
        if self.restart_s is not None and not (
            _is_number(self.restart_s)
            and math.isfinite(self.restart_s)
            and self.restart_s > self.crash_s
        ):
            raise ValueError(f"restart_s must be after crash_s, got {self.restart_s!r}")


@dataclass(frozen=True, slots=True)
class SimOptions:
    """One in-process run.

    ``mode`` and ``policy`` take the enums or their names (``"rsu"``, ``"slot"``)
    and are stored as the enums; anything else is a ``ValueError`` naming the
    allowed values. ``seed`` >= 0; ``start_times`` [run s, >= 0] per car override
    the scenario's draw; ``max_sim_s`` [s, > 0] overrides the scenario's limit;
    ``trace`` keeps every physics step in ``Simulation.trace_rows``.
    """

    mode: RunMode = RunMode.RSU
    policy: Policy = Policy.PAPER
    seed: int = 0
    channel: ChannelModel = field(default_factory=ChannelModel)
    start_times: dict[str, float] | None = None  # overrides the scenario's draw
    trace: bool = False
    max_sim_s: float | None = None
    rsu_outages: tuple[RsuOutage, ...] = ()
    """RSU crashes (and restarts with a fresh, empty core) on the run clock."""

    def __post_init__(self) -> None:
        object.__setattr__(self, "mode", parse_mode(self.mode))
        object.__setattr__(self, "rsu_outages", tuple(self.rsu_outages))
        if not all(isinstance(o, RsuOutage) for o in self.rsu_outages):
            raise TypeError(f"rsu_outages must be RsuOutage values, got {self.rsu_outages!r}")
        object.__setattr__(self, "policy", parse_policy(self.policy))
        if isinstance(self.seed, bool) or not isinstance(self.seed, int) or self.seed < 0:
            raise ValueError(f"seed must be an int >= 0, got {self.seed!r}")
        if not isinstance(self.channel, ChannelModel):
            raise TypeError(f"channel must be a ChannelModel, got {self.channel!r}")
        if self.max_sim_s is not None and not (
            _is_number(self.max_sim_s) and math.isfinite(self.max_sim_s) and self.max_sim_s > 0
        ):
            raise ValueError(f"max_sim_s must be a finite number > 0, got {self.max_sim_s!r}")
        if self.start_times is not None:
            bad = {
                k: v
                for k, v in self.start_times.items()
                if not (_is_number(v) and math.isfinite(v) and v >= 0.0)
            }
            if bad:
                raise ValueError(f"start times must be finite numbers >= 0 [s], got {bad}")


def _is_number(value: object) -> bool:
    return isinstance(value, int | float) and not isinstance(value, bool)


@dataclass(slots=True)
class Simulation:
    """One run of a scenario in one mode; ``run()`` returns the run result."""

    scenario: Scenario
    options: SimOptions
    bodies: dict[str, CarBody] = field(init=False)
    agents: dict[str, VehicleAgent] = field(init=False)
    rsus: dict[str, RsuCore] = field(init=False)
    channel: MemoryChannel = field(init=False)
    metrics: MetricsRecorder = field(init=False)
    trace_rows: list[tuple[Any, ...]] = field(init=False, default_factory=list)
    counters: dict[str, int] = field(init=False, default_factory=dict)
    on_step: Callable[[float, dict[str, TruthState]], None] | None = None
    origin: Origin = field(default_factory=Origin)
    """Version, commit and scenario digest for the result's provenance (found by the caller)."""
    waiting: list[str] = field(init=False, default_factory=list)
    """Cars not yet inserted, in arrival order."""
    present: dict[str, None] = field(init=False, default_factory=dict)
    """Cars in the world, in insertion order."""
    left: set[str] = field(init=False, default_factory=set)
    """Cars removed at their goal."""

    def __post_init__(self) -> None:
        o = self.options
        self.scenario = sc = self.scenario.for_seed(o.seed)
        starts = o.start_times if o.start_times is not None else sc.draw_start_times(o.seed)
        missing = [v.id for v in sc.vehicles if v.id not in starts]
        if missing:
            raise ValueError(f"start_times lacks the car(s) {', '.join(missing)}")
        v2x = o.mode is not RunMode.STANDALONE
        self.bodies = {v.id: CarBody.from_scenario(sc, v.id, starts[v.id]) for v in sc.vehicles}
        self.agents = {v.id: vehicle_agent(sc, v.id, v2x) for v in sc.vehicles}
        self.rsus = (
            {r.id: RsuCore(rsu_config(sc, r.id, o.policy)) for r in sc.rsus}
            if o.mode is RunMode.RSU
            else {}
        )
        unknown = sorted({out.rsu for out in o.rsu_outages} - set(self.rsus))
        if unknown:
            raise ValueError(f"rsu_outages name no RSU of this {o.mode} run: {unknown}")
        self.channel = MemoryChannel(o.channel, seed=o.seed * 7919 + 17)
        self.metrics = MetricsRecorder(sc)
        order = {v.id: k for k, v in enumerate(sc.vehicles)}
        self.waiting = sorted(order, key=lambda vid: (self.bodies[vid].start_time, order[vid]))

    # ------------------------------------------------------------------ V2X
    def _send(self, now: float, key: str, message: Message, receivers: list[str]) -> None:
        payload = encode(message)
        self.channel.send(now, key, payload, receivers)

    def _deliver(self, now: float) -> None:
        # One datagram goes to every listener: decode and parse it once per batch and
        # share the result (messages are frozen, their arrays read-only). With N cars
        # this is N decodes per planning tick instead of N² (issue 14).
        decoded: dict[int, tuple[bytes, str, tuple[Message, keyexpr.ParsedKey] | None]] = {}
        agents, rsus, left = self.agents, self.rsus, self.left
        for _at, _order, receiver, key, payload in self.channel.due(now):
            memo = decoded.get(id(payload))
            if memo is None or memo[0] is not payload or memo[1] != key:
                try:
                    memo = (payload, key, (decode(payload), keyexpr.parse(key)))
                except (DecodeError, ValueError):
                    memo = (payload, key, None)
                decoded[id(payload)] = memo
            parsed_message = memo[2]
            if parsed_message is None:
                self.counters["malformed"] = self.counters.get("malformed", 0) + 1
                continue
            if receiver in left:
                continue  # gone from the network
            message, parsed = parsed_message
            agent = agents.get(receiver)
            if agent is not None:
                agent.on_message(now, message, parsed.rsu)
            elif receiver in rsus:
                for og in rsus[receiver].on_message(now, message, parsed.rsu):
                    self._send_rsu(now, receiver, og)

    def _send_rsu(self, now: float, rsu_id: str, og: Outgoing) -> None:
        if og.vehicle is None:
            self._send(now, keyexpr.rsu_beacon(rsu_id), og.message, self._listeners())
        elif og.vehicle in self.agents and og.vehicle not in self.left:
            self._send(now, keyexpr.rsu_command(rsu_id, og.vehicle), og.message, [og.vehicle])

    def _listeners(self) -> list[str]:
        """Cars whose radio is on: every car that has not left."""
        return [v for v in self.agents if v not in self.left]

    def _fp_receivers(self, sender: str) -> list[str]:
        return [v for v in self._listeners() if v != sender] + list(self.rsus)

    # ------------------------------------------------------------------ world
    def _insert(self, now: float) -> None:
        """Insert, in arrival order, every car that has arrived and whose entry is clear."""
        p = self.scenario.params
        inside = [self.bodies[vid].truth(now) for vid in self.present]
        still: list[str] = []
        blocked = False
        for vid in self.waiting:
            body = self.bodies[vid]
            if blocked or now + 1e-9 < body.start_time:
                still.append(vid)
                continue
            entry = body.truth(now)
            if entry_clear(entry, inside, p.headway_s, body.limits.decel_comfort):
                self.present[vid] = None
                inside.append(entry)
                self.metrics.inserted(vid, body.start_time, now)
            else:
                still.append(vid)
        self.waiting = still

    def _remove(self, now: float, truths: dict[str, TruthState]) -> None:
        """Remove every car standing at its goal (after this step's metrics)."""
        for vid, t in truths.items():
            if at_goal(self.scenario, t):
                del self.present[vid]
                self.left.add(vid)
                log.debug("car %s left at %.2f s", vid, now)

    # ------------------------------------------------------------------ loop
    def run(self) -> RunResult:
        """Run to the end (every car at its goal, or the time limit); the run result."""
        sc = self.scenario
        p = sc.params
        o = self.options
        dt = 1.0 / p.physics_hz
        plan_every = max(round(p.physics_hz / p.planning_hz), 1)
        max_t = o.max_sim_s if o.max_sim_s is not None else p.max_sim_s
        wall0 = time.perf_counter()
        step = 0
        now = 0.0
        reasons: dict[str, str] = {v: Reason.WAITING.value for v in self.agents}
        details: dict[str, str] = {v: "" for v in self.agents}
        while True:
            now = step * dt
            self._insert(now)
            truths = {vid: self.bodies[vid].truth(now) for vid in self.present}
            self._deliver(now)
            if step % plan_every == 0:
                for vid in self.present:
                    agent = self.agents[vid]
                    ego = truths[vid]
                    others = [t for k, t in truths.items() if k != vid]
                    sensed = perceive(ego, others, sc.building_polygons, p.sensor_range_m)
                    result = agent.tick(now, ego, sensed)
                    reasons[vid] = result.plan.reason.value
                    details[vid] = result.plan.detail
                    for out in result.outbound:
                        if out.stream is Stream.FP:
                            self._send(
                                now, keyexpr.future_path(vid), out.message, self._fp_receivers(vid)
                            )
                        elif out.stream is Stream.AP and out.rsu in self.rsus:
                            self._send(
                                now, keyexpr.autonomous_path(out.rsu, vid), out.message, [out.rsu]
                            )
                for rid, rsu in self.rsus.items():
                    for og in rsu.tick(now):
                        self._send_rsu(now, rid, og)
            modes = {vid: self.agents[vid].mode.name for vid in self.present}
            self.metrics.record(now, list(truths.values()), modes, reasons)
            if o.trace:
                for vid, t in truths.items():
                    self.trace_rows.append(
                        (
                            round(now, 3),
                            vid,
                            round(t.s, 3),
                            round(t.x, 3),
                            round(t.y, 3),
                            round(t.speed, 3),
                            round(t.accel, 3),
                            reasons[vid],
                            details[vid],
                            modes[vid],
                        )
                    )
            if self.on_step is not None:
                self.on_step(now, truths)
            if o.rsu_outages:
                self._outages(now, dt)
            self._remove(now, truths)
            if now >= max_t or not (self.present or self.waiting):
                break
            for vid in self.present:
                body = self.bodies[vid]
                body.step(now, dt, self.agents[vid].command(body.state))
            step += 1
        wall = time.perf_counter() - wall0
        channel = ChannelParams(
            kind="memory",
            loss=o.channel.loss,
            latency_s=o.channel.latency_s,
            jitter_s=o.channel.jitter_s,
        )
        metrics = self.metrics.result()
        return run_result(
            metrics,
            mode=o.mode,
            policy=o.policy if o.mode is RunMode.RSU else None,
            seed=o.seed,
            sim_s=now,
            wall_s=wall,
            scenario=sc.name,
            start_times={vid: b.start_time for vid, b in self.bodies.items()},
            harness="in-process",
            provenance=provenance(sc, self.origin, channel, o.mode, o.policy),
            loss=o.channel.loss,
            summary=run_summary(metrics, now),
        )

    def _outages(self, now: float, dt: float) -> None:
        """Crash and restart the RSUs of ``options.rsu_outages`` due in ``[now, now + dt)``
        (after this step's ticks: the next step sees the change)."""

        def due(t: float) -> bool:  # 1e-9: step * dt is not exact (6.3 is 126 * 0.05 + ulp)
            return now - 1e-9 <= t < now + dt - 1e-9

        for outage in self.options.rsu_outages:
            if due(outage.crash_s) and outage.rsu in self.rsus:
                del self.rsus[outage.rsu]  # in-flight messages to it are dropped
                log.info("rsu %s crashed at %.2f s", outage.rsu, now)
            restart = outage.restart_s
            if restart is not None and due(restart) and outage.rsu not in self.rsus:
                config = rsu_config(self.scenario, outage.rsu, self.options.policy)
                self.rsus[outage.rsu] = RsuCore(config)
                log.info("rsu %s restarted at %.2f s", outage.rsu, now)

    def write_trace(self, path: Path) -> None:
        """The per-tick table as CSV (pandas reads it as is)."""
        write_trace_csv(path, self.trace_rows)


def simulate(scenario: Scenario, options: SimOptions, origin: Origin | None = None) -> RunResult:
    """One in-process run; the run result of DESIGN.md."""
    return Simulation(scenario, options, origin=origin or Origin()).run()


def write_trace_csv(path: Path, rows: Sequence[Sequence[Any]]) -> None:
    """Trace rows as CSV with the :data:`TRACE_FIELDS` header (``crosspath sim --trace``)."""
    path.parent.mkdir(parents=True, exist_ok=True)
    with path.open("w", newline="") as fh:
        w = csv.writer(fh)
        w.writerow(TRACE_FIELDS)
        w.writerows(rows)


def harness_trace(
    fields: Sequence[str], rows: Sequence[Sequence[Any]]
) -> list[tuple[float | str, ...]]:
    """Trace rows with other columns (e.g. the monitor's ``trace``) as rows of
    :data:`TRACE_FIELDS`, matched by name. A missing ``accel`` [m/s²] is the speed's
    backward difference per car (0 at a car's first row); a missing ``detail``,
    ``reason`` or ``mode`` is empty. ``ValueError`` when ``t``, ``vehicle``, ``s``,
    ``x``, ``y`` or ``speed`` is missing."""
    col = {name: i for i, name in enumerate(fields)}
    need = [name for name in ("t", "vehicle", "s", "x", "y", "speed") if name not in col]
    if need:
        raise ValueError(f"trace lacks the column(s) {', '.join(need)}")
    last: dict[str, tuple[float, float]] = {}
    out: list[tuple[float | str, ...]] = []
    for row in sorted(rows, key=lambda r: (float(r[col["t"]]), str(r[col["vehicle"]]))):
        t, vid, speed = float(row[col["t"]]), str(row[col["vehicle"]]), float(row[col["speed"]])
        if "accel" in col:
            accel = float(row[col["accel"]])
        else:
            prev = last.get(vid)
            accel = (speed - prev[1]) / (t - prev[0]) if prev and t > prev[0] else 0.0
            last[vid] = (t, speed)
        out.append(
            (
                round(t, 3),
                vid,
                round(float(row[col["s"]]), 3),
                round(float(row[col["x"]]), 3),
                round(float(row[col["y"]]), 3),
                round(speed, 3),
                round(accel, 3),
                str(row[col["reason"]]) if "reason" in col else "",
                str(row[col["detail"]]) if "detail" in col else "",
                str(row[col["mode"]]) if "mode" in col else "",
            )
        )
    return out
