"""The in-process harness: every actor of a scenario in one process, on a virtual clock.

The same pure cores as the daemons (``VehicleAgent``, ``RsuCore``), a seeded
in-memory channel with loss, latency and jitter, and every message crossing it
as bytes through the real codec. Deterministic per seed; far faster than real
time. Physics runs at ``physics_hz`` (20 Hz), planning, V2X and the RSU at
``planning_hz`` (10 Hz).
"""

from __future__ import annotations

import csv
import logging
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from protocol import DecodeError, decode, encode
from protocol import keys as keyexpr
from protocol.keys import Stream
from protocol.messages import Message
from services.model.kinematics import TruthState
from services.model.scenario import Scenario
from services.model.types import Policy, RunMode
from services.rsu.config import rsu_config
from services.rsu.core import Outgoing, RsuCore
from services.sim.car import CarBody, all_at_goal
from services.sim.membus import ChannelModel, MemoryChannel
from services.sim.metrics import MetricsRecorder
from services.sim.results import run_result
from services.sim.sensors import perceive
from services.vehicle.agent import VehicleAgent, vehicle_agent
from services.vehicle.planner import Reason

log = logging.getLogger("crosspath.sim")

TRACE_FIELDS = ("t", "vehicle", "s", "x", "y", "speed", "accel", "reason", "detail", "mode")


@dataclass(frozen=True, slots=True)
class SimOptions:
    """One in-process run."""

    mode: RunMode = RunMode.RSU
    policy: Policy = Policy.PAPER
    seed: int = 0
    channel: ChannelModel = field(default_factory=ChannelModel)
    start_times: dict[str, float] | None = None  # overrides the scenario's draw
    trace: bool = False
    max_sim_s: float | None = None


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

    def __post_init__(self) -> None:
        sc = self.scenario
        o = self.options
        starts = o.start_times if o.start_times is not None else sc.draw_start_times(o.seed)
        v2x = o.mode is not RunMode.STANDALONE
        self.bodies = {v.id: CarBody.from_scenario(sc, v.id, starts[v.id]) for v in sc.vehicles}
        self.agents = {v.id: vehicle_agent(sc, v.id, v2x) for v in sc.vehicles}
        self.rsus = (
            {r.id: RsuCore(rsu_config(sc, r.id, o.policy)) for r in sc.rsus}
            if o.mode is RunMode.RSU
            else {}
        )
        self.channel = MemoryChannel(o.channel, seed=o.seed * 7919 + 17)
        self.metrics = MetricsRecorder(sc)

    # ------------------------------------------------------------------ V2X
    def _send(self, now: float, key: str, message: Message, receivers: list[str]) -> None:
        payload = encode(message)
        self.channel.send(now, key, payload, receivers)

    def _deliver(self, now: float) -> None:
        for d in self.channel.due(now):
            try:
                message = decode(d.payload)
                parsed = keyexpr.parse(d.key)
            except (DecodeError, ValueError):
                self.counters["malformed"] = self.counters.get("malformed", 0) + 1
                continue
            if d.receiver in self.agents:
                self.agents[d.receiver].on_message(now, message, parsed.rsu)
            elif d.receiver in self.rsus:
                for og in self.rsus[d.receiver].on_message(now, message, parsed.rsu):
                    self._send_rsu(now, d.receiver, og)

    def _send_rsu(self, now: float, rsu_id: str, og: Outgoing) -> None:
        if og.vehicle is None:
            self._send(now, keyexpr.rsu_beacon(rsu_id), og.message, list(self.agents))
        elif og.vehicle in self.agents:
            self._send(now, keyexpr.rsu_command(rsu_id, og.vehicle), og.message, [og.vehicle])

    def _fp_receivers(self, sender: str) -> list[str]:
        return [v for v in self.agents if v != sender] + list(self.rsus)

    # ------------------------------------------------------------------ loop
    def run(self) -> dict[str, Any]:
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
            truths = {vid: b.truth(now) for vid, b in self.bodies.items()}
            self._deliver(now)
            if step % plan_every == 0:
                for vid, agent in self.agents.items():
                    body = self.bodies[vid]
                    if now + 1e-9 < body.start_time:
                        continue
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
            modes = {vid: a.mode.name for vid, a in self.agents.items()}
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
            if now >= max_t or all_at_goal(sc, truths.values()):
                break
            for vid, body in self.bodies.items():
                body.step(now, dt, self.agents[vid].command(body.state))
            step += 1
        wall = time.perf_counter() - wall0
        extra = {
            "scenario": sc.name,
            "loss": o.channel.loss,
            "start_times": {vid: round(b.start_time, 4) for vid, b in self.bodies.items()},
            "harness": "in-process",
            "speedup_vs_real_time": round(now / wall, 1) if wall > 0 else None,
        }
        policy = str(o.policy) if o.mode is RunMode.RSU else None
        return run_result(
            self.metrics.result(),
            mode=o.mode,
            policy=policy,
            seed=o.seed,
            sim_s=now,
            wall_s=wall,
            extra=extra,
        )

    def write_trace(self, path: Path) -> None:
        """The per-tick table as CSV (pandas reads it as is)."""
        with path.open("w", newline="") as fh:
            w = csv.writer(fh)
            w.writerow(TRACE_FIELDS)
            w.writerows(self.trace_rows)


def simulate(scenario: Scenario, options: SimOptions) -> dict[str, Any]:
    """One in-process run; the run result of DESIGN.md."""
    return Simulation(scenario, options).run()
