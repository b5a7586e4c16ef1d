"""``crosspath vehicle --config FILE``: one car as a daemon (its body, its autonomy stack).

The daemon drives the same pure objects as the in-process harness
(``services.sim.harness.Simulation``) and mirrors its loop, on the run clock
shared through the monitor's start message (``services.edge.plumbing``):

- physics at ``params.physics_hz`` (20 Hz): at step ``k`` (run time ``k * dt``,
  slept until with the run clock) the car's ground truth is taken, and every
  ``physics_hz / planning_hz``-th step (10 Hz), once the car's start time has
  come, its simulated sensors run (``perceive`` against the latest ground truth
  of the other cars, advanced at constant speed to now) and ``agent.tick``
  plans; then the truth is published on ``{prefix}/sim/truth/{vehicle}``
  (reliable, with the mode and planner reason of this step, as the in-process
  harness records them) and the body steps with ``agent.command``;
- V2X (not in ``standalone`` mode): the future path on
  ``{prefix}/v2x/fp/{me}`` every planning step, the autonomous path on
  ``{prefix}/v2x/rsu/{rsu}/ap/{me}`` while coordinated (``rsu`` mode only);
  received: every other car's future path, ``rsu/*/cmd/{me}`` (mode commands,
  coordinated paths) and RSU beacons, each handed to ``agent.on_message`` at
  its reception time on the run clock.

The other cars' ground truth travels on the reliable plumbing, not V2X: the
sensors are part of the simulated world. Mode, policy, seed, start times and
the run clock all come from the start message, so a host needs only the
scenario file and its vehicle id. On SIGTERM/SIGINT the car stops sending at
once, publishes its final stats and closes.

Configuration (:class:`VehicleDaemonConfig`): the common daemon settings
(``services.edge.settings``; ``node_id`` is the vehicle id) plus
``scenario``. The ``[time]`` table is not used: the monitor's start message
sets the epoch and speed.
"""

from __future__ import annotations

import argparse
import asyncio
import dataclasses
import math
import sys
from pathlib import Path
from typing import Final

from protocol import Message
from protocol import keys as keyexpr
from protocol.keys import ParsedKey, Stream
from services.edge.clock import RunClock
from services.edge.plumbing import (
    StartRun,
    TruthReport,
    all_truths,
    encode_truth,
    truth_key,
)
from services.edge.settings import CommonDaemonConfig
from services.edge.shell import ActorDaemon, DaemonCommand, add_daemon_arguments
from services.model.kinematics import TruthState
from services.model.types import RunMode
from services.sim.car import CarBody
from services.sim.sensors import perceive
from services.vehicle.agent import VehicleAgent, vehicle_agent
from services.vehicle.planner import Reason

__all__ = [
    "MAX_EXTRAPOLATION_S",
    "VehicleDaemon",
    "VehicleDaemonConfig",
    "command",
    "configure",
    "load_daemon",
    "run",
]

MAX_EXTRAPOLATION_S: Final = 0.2
"""Another car's ground truth is advanced at constant speed to the sensing instant by at
most this much [s, run time]; older truth is used as it is (the car is where it was
last seen)."""


class VehicleDaemonConfig(CommonDaemonConfig):
    """Settings of ``crosspath vehicle``: ``node_id`` is the vehicle id of the scenario."""

    scenario: Path
    """The scenario file (the same on every host of a run)."""


def advance(truth: TruthState, now: float) -> TruthState:
    """``truth`` moved along its heading at its speed to run time ``now`` (at most
    :data:`MAX_EXTRAPOLATION_S`): sensing happens at ``now`` as in the in-process harness."""
    age = now - truth.t
    if age <= 0.0 or age > MAX_EXTRAPOLATION_S:
        return truth
    d = truth.speed * age
    return dataclasses.replace(
        truth,
        t=now,
        x=truth.x + d * math.cos(truth.heading),
        y=truth.y + d * math.sin(truth.heading),
        s=truth.s + d,
    )


class VehicleDaemon(ActorDaemon[VehicleDaemonConfig]):
    """One car: body + ``VehicleAgent`` behind a :class:`DaemonShell`."""

    service = "vehicle"
    role = "vehicle"

    def setup(self) -> None:
        self.agent: VehicleAgent | None = None
        self.body: CarBody | None = None
        self.others: dict[str, TruthReport] = {}
        self.steps = 0

    # -- subscriptions

    def subscribe_v2x(self) -> None:
        p = self.prefix
        me = self.node
        self.shell.subscribe_v2x(
            keyexpr.all_future_paths(prefix=p), Stream.FP, self._on_v2x, ignore_vehicle=me
        )
        self.shell.subscribe_v2x(keyexpr.all_commands(me, prefix=p), Stream.CMD, self._on_v2x)
        self.shell.subscribe_v2x(keyexpr.all_beacons(prefix=p), Stream.BEACON, self._on_v2x)
        self.shell.subscribe_plumbing(all_truths(prefix=p), self._on_truth)

    def takes_part(self, start: StartRun) -> bool:
        return self.node in start.vehicles

    def _on_v2x(self, parsed: ParsedKey, message: Message, now: float) -> None:
        agent = self.agent
        if agent is not None:
            agent.on_message(now, message, parsed.rsu)

    def _on_truth(self, key: str, payload: bytes) -> None:
        report = self.shell.run_truth(key, payload, self.active)
        if report is None or report.vehicle == self.node:
            return
        vid = report.vehicle
        prev = self.others.get(vid)
        if prev is None or report.step > prev.step:
            self.others[vid] = report

    # -- the loop (mirrors services.sim.harness.Simulation.run)

    async def episode(self, start: StartRun, clock: RunClock, halt: asyncio.Event) -> None:
        sc = self.scenario
        p = sc.params
        me = self.node
        dt = 1.0 / p.physics_hz
        plan_every = max(round(p.physics_hz / p.planning_hz), 1)
        v2x = start.mode is not RunMode.STANDALONE
        send_ap = start.mode is RunMode.RSU
        body = CarBody.from_scenario(sc, me, start.start_times[me])
        agent = vehicle_agent(sc, me, v2x)
        self.others = {}
        self.body, self.agent = body, agent
        reason = Reason.WAITING.value
        fp_key = keyexpr.future_path(me, prefix=self.prefix)
        my_truth_key = truth_key(me, prefix=self.prefix)
        try:
            async for step, now in self.ticks(start, clock, halt, p.physics_hz):
                truth = body.truth(now)
                if step % plan_every == 0 and now + 1e-9 >= body.start_time:
                    others = [advance(r.state, now) for r in self.others.values()]
                    sensed = perceive(truth, others, sc.building_polygons, p.sensor_range_m)
                    result = agent.tick(now, truth, sensed)
                    reason = result.plan.reason.value
                    for out in result.outbound:
                        if out.stream is Stream.FP:
                            self.shell.publish_v2x(fp_key, out.message)
                        elif out.stream is Stream.AP and send_ap and out.rsu in start.rsus:
                            self.shell.publish_v2x(
                                keyexpr.autonomous_path(out.rsu, me, prefix=self.prefix),
                                out.message,
                            )
                report = TruthReport(start.run_id, step, truth, agent.mode.name, reason)
                self.shell.publish_plumbing(my_truth_key, encode_truth(report))
                body.step(now, dt, agent.command(body.state))
                self.steps = step + 1
        finally:
            self.agent = None


# --------------------------------------------------------------------------- CLI


def configure(parser: argparse.ArgumentParser) -> None:
    """Options of ``crosspath vehicle``."""
    add_daemon_arguments(parser, "vehicle", "VEHICLE")


command = DaemonCommand(
    "vehicle", VehicleDaemonConfig, VehicleDaemon, {"scenario": "scenario", "node_id": "node_id"}
)
load_daemon = command.load
"""Config and scenario from the command line; :class:`ConfigError` naming the field."""
run = command.run
"""Run the car daemon until a signal; exit 2 on a configuration error."""


if __name__ == "__main__":  # pragma: no cover
    sys.exit(command.main(configure))
