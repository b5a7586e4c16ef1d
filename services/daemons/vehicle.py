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
sensors are part of the simulated world (``services.daemons.world.TruthBoard``; a
multi-car host, ``services.daemons.host``, subscribes it once per process and shares
it among its cars). Mode, policy, seed, start times and
the run clock all come from the start message, so a host needs only the
scenario file and its vehicle id. On SIGTERM/SIGINT the car stops sending at
once, publishes its final stats and closes.

Insertion and removal (issue 12, as the in-process harness): the car sleeps until
its start time (its arrival); then it waits outside the network until its entry is
clear (``services.daemons.world``: ``entry_clear`` against the other cars' truth,
cars entering an entry in arrival order), publishing a ``waiting`` truth report
each step (no truth, no V2X: its V2X subscriptions are undeclared from the run's
start until it enters; an idle daemon, between runs, listens). Inserted, it runs
the loop above; the step it stands at its goal
(``services.sim.car.at_goal``) is its last: that truth report says ``left``, its V2X
subscriptions are undeclared and it sends nothing more until the run ends. Its
stats report ``inserted_s``, ``insertion_wait_s`` and ``left_s`` [run s]. Decision:
unlike the harness, where a waiting car's radio already listens, a daemon car
receives V2X only from its insertion (a car outside the network costs no CPU).

Configuration (:class:`VehicleDaemonConfig`): the common daemon settings
(``services.edge.settings``; ``node_id`` is the vehicle id) plus
``scenario``. The ``[time]`` table is not used: the monitor's start message
sets the epoch and speed.
"""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import dataclasses
import math
import sys
from pathlib import Path
from typing import Final

from protocol import Message
from protocol import keys as keyexpr
from protocol.keys import ParsedKey, Stream
from services.daemons.host import serve_cars
from services.daemons.world import TruthBoard, entry_predecessors
from services.edge.clock import RunClock
from services.edge.metrics import CoreView
from services.edge.plumbing import (
    StartRun,
    TruthReport,
    all_truths,
    encode_truth,
    truth_key,
)
from services.edge.settings import CommonDaemonConfig
from services.edge.shell import ActorDaemon, DaemonCommand, add_daemon_arguments
from services.edge.transport import Subscription, TransportError
from services.model.kinematics import TruthState
from services.model.types import RunMode
from services.sim.car import CarBody, at_goal, entry_clear
from services.sim.sensors import perceive
from services.sim.truth import arrival_step
from services.vehicle.agent import VehicleAgent, vehicle_agent
from services.vehicle.authorize import refusal
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


LEFT_REPEATS: Final = 10
"""Times a car repeats its "left" truth report after leaving the world (the monitor takes
the first that arrives and ignores the rest)."""
LEFT_REPEAT_S: Final = 0.5
"""Run seconds between those repeats [s] (a fast run ends within a wall second)."""


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
        self.world = TruthBoard()
        """The other cars' truth; a multi-car host replaces it by one shared board."""
        self.world_owner = True
        """This car subscribes the world's truth (in a host, only its first car does)."""
        self.steps = 0
        self.inserted_s: float | None = None
        self.left_s: float | None = None
        self.arrival_s: float | None = None
        self._radio: list[Subscription] = []
        self.rsus_heard: dict[str, int] = {}
        """Per RSU, its messages this car accepted this run (beacons, commands): the
        monitor fails an rsu-mode run that no car heard an RSU of (issue 13: a forged
        liveliness token and stats must not fake an RSU). Keys are run actors only
        (the shell refuses other senders), so the map is bounded."""

    @property
    def others(self) -> dict[str, TruthReport]:
        """The other cars in the world: their latest truth reports."""
        return {v: r for v, r in self.world.latest.items() if v != self.node}

    def stats_extras(self) -> dict[str, float | dict[str, int] | None]:
        wait = None
        if self.inserted_s is not None and self.arrival_s is not None:
            wait = round(self.inserted_s - self.arrival_s, 3)
        return {
            "inserted_s": self.inserted_s,
            "insertion_wait_s": wait,
            "left_s": self.left_s,
            "rsus_heard": dict(sorted(self.rsus_heard.items())),
        }

    def core_view(self) -> CoreView | None:
        """The agent's counters (mode changes...) and mode, for the metrics."""
        agent = self.agent
        return None if agent is None else CoreView(agent.counters, mode=agent.mode.name)

    # -- subscriptions

    def subscribe_v2x(self) -> None:
        if self.world_owner:
            self.shell.subscribe_plumbing(all_truths(prefix=self.prefix), self._on_truth)
        self._radio_on()  # an idle car listens (and counts what is malformed)

    def _radio_on(self) -> None:
        """Declare the V2X subscriptions (idle, and at insertion)."""
        if self._radio:
            return
        p = self.prefix
        me = self.node
        # in a run, only the keys of the run's other cars and RSUs are declared: nothing
        # else reaches this car (``DaemonShell.scope_v2x``)
        self._radio = [
            self.shell.subscribe_v2x(
                keyexpr.all_future_paths(prefix=p),
                Stream.FP,
                self._on_v2x,
                ignore_vehicle=me,
                scope=lambda start: [
                    keyexpr.future_path(v, prefix=p) for v in start.vehicles if v != me
                ],
            ),
            self.shell.subscribe_v2x(
                keyexpr.all_commands(me, prefix=p),
                Stream.CMD,
                self._on_v2x,
                scope=lambda start: [keyexpr.rsu_command(r, me, prefix=p) for r in start.rsus],
            ),
            self.shell.subscribe_v2x(
                keyexpr.all_beacons(prefix=p),
                Stream.BEACON,
                self._on_v2x,
                scope=lambda start: [keyexpr.rsu_beacon(r, prefix=p) for r in start.rsus],
            ),
        ]

    def _radio_off(self) -> None:
        """Undeclare the V2X subscriptions (from a run's start to the car's insertion, and
        from its removal to the run's end)."""
        radio, self._radio = self._radio, []
        for sub in radio:
            sub.close()

    def takes_part(self, start: StartRun) -> bool:
        return self.node in start.vehicles

    def _on_v2x(self, parsed: ParsedKey, message: Message, now: float) -> None:
        agent = self.agent
        if agent is None:
            return
        trust, body = self.shell.trust, self.body
        if trust is not None and body is not None:  # issue 13: may this RSU command me here?
            truth = body.truth(now)
            crossings = self.scenario.vehicle_crossings(self.node)
            why = refusal(message, self.shell.verified, crossings, truth.s, truth.x, truth.y)
            if why is not None:  # counted in the stats' ``auth`` section
                trust.counters[why] = trust.counters.get(why, 0) + 1
                return
        if parsed.rsu is not None:
            self.rsus_heard[parsed.rsu] = self.rsus_heard.get(parsed.rsu, 0) + 1
        agent.on_message(now, message, parsed.rsu)

    def _on_truth(self, key: str, payload: bytes) -> None:
        report = self.shell.run_truth(key, payload, self.active)
        if report is not None:
            self.world.take(report)

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
        world = self.world
        world.reset(start.run_id)
        self.body, self.agent = body, agent
        self.arrival_s, self.inserted_s, self.left_s = body.start_time, None, None
        self.rsus_heard = {}
        ahead = entry_predecessors(sc, me, start.start_times)
        reason = Reason.WAITING.value
        fp_key = keyexpr.future_path(me, prefix=self.prefix)
        my_truth_key = truth_key(me, prefix=self.prefix)
        first = arrival_step(body.start_time, dt)
        left = False
        self._radio_off()  # outside the network until its insertion
        try:
            async for step, now in self.ticks(start, clock, halt, p.physics_hz, first):
                truth = body.truth(now)
                if self.inserted_s is None:
                    states = world.states_at(now, advance)
                    inside = [st for v, st in states.items() if v != me]
                    clear = all(v in world.entered for v in ahead) and entry_clear(
                        truth, inside, p.headway_s, body.limits.decel_comfort
                    )
                    if not clear:
                        report = TruthReport(start.run_id, step, truth, "AUTO", reason, "waiting")
                        self.shell.publish_plumbing(my_truth_key, encode_truth(report))
                        continue
                    self.inserted_s = now
                    if v2x:
                        self._radio_on()
                if step % plan_every == 0:
                    states = world.states_at(now, advance)
                    others = [st for v, st in states.items() if v != me]
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
                left = at_goal(sc, truth)
                presence = "left" if left else "in"
                report = TruthReport(start.run_id, step, truth, agent.mode.name, reason, presence)
                self.shell.publish_plumbing(my_truth_key, encode_truth(report))
                self.steps = step + 1
                if left:
                    self.left_s = now
                    self._radio_off()
                    break
                body.step(now, dt, agent.command(body.state))
            if left:
                # out of the world: silent until the run ends, but for its "left" report,
                # repeated (the monitor's inbox may have dropped the one under load, and
                # would then count the car missing until the end; it ignores repeats)
                for _ in range(LEFT_REPEATS):
                    with contextlib.suppress(TimeoutError):
                        await asyncio.wait_for(halt.wait(), LEFT_REPEAT_S / clock.speed)
                    if halt.is_set():
                        break
                    self.shell.publish_plumbing(my_truth_key, encode_truth(report))
                await halt.wait()
        finally:
            self._radio_off()
            self.agent = None
            with contextlib.suppress(TransportError):
                self._radio_on()  # idle again: listening


# --------------------------------------------------------------------------- CLI


def configure(parser: argparse.ArgumentParser) -> None:
    """Options of ``crosspath vehicle``."""
    group = add_daemon_arguments(parser, "vehicle", "VEHICLE")
    group.add_argument(
        "--ids",
        metavar="A,B,...",
        help="run these cars in this process, each its own Zenoh node (services.daemons.host);"
        " the --listen endpoints are split evenly among them",
    )


command = DaemonCommand(
    "vehicle", VehicleDaemonConfig, VehicleDaemon, {"scenario": "scenario", "node_id": "node_id"}
)
load_daemon = command.load
"""Config and scenario from the command line; :class:`ConfigError` naming the field."""


def run(args: argparse.Namespace) -> int:
    """Run the car daemon (or, with ``--ids``, several cars: ``services.daemons.host``)
    until a signal; exit 2 on a configuration error."""
    if getattr(args, "ids", None):
        return serve_cars("vehicle", command.load, VehicleDaemon, args)
    return command.run(args)


if __name__ == "__main__":  # pragma: no cover
    _parser = argparse.ArgumentParser(prog="crosspath vehicle")
    configure(_parser)
    sys.exit(run(_parser.parse_args()))
