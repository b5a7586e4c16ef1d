"""``crosspath rsu --config FILE``: one roadside unit as a daemon.

The daemon drives the RSU's pure core (``services.rsu.core.RsuCore``, built
with ``services.sim.harness.rsu_config`` exactly as the in-process harness
does) on the run clock shared through the monitor's start message:

- received: every car's future path (``{prefix}/v2x/fp/*``) and the autonomous
  paths addressed to this RSU (``{prefix}/v2x/rsu/{me}/ap/*``); each decoded
  one goes to ``RsuCore.on_message`` at its reception time, and what the core
  returns is sent at once;
- ``RsuCore.tick`` at ``params.planning_hz`` (10 Hz, run times ``k / 10``):
  command repeats, expiry, and the beacon;
- sent: mode commands and coordinated paths on ``{prefix}/v2x/rsu/{me}/cmd/{car}``
  (only to the cars of the run), beacons on ``{prefix}/v2x/rsu/{me}/beacon``.

The RSU takes part only in ``rsu``-mode runs that list it; otherwise it stays
idle. When a run ends (the monitor's stop, or SIGTERM/SIGINT) it sends a
termination (``ModeCommand`` TERMINATE, mode AUTO) to every car it holds in a
coordinated mode or still has a command pending for, and repeats it
:data:`TERMINATION_ROUNDS` times :data:`TERMINATION_INTERVAL_S` apart unless the
car's future path already shows AUTO: the cars return to their autonomous
planner instead of waiting out the coordinated-path timeout.

Joining late: when the start message arrives after the run's epoch (the daemon
was restarted during a run, which the monitor allows with ``expect_crash``), the
RSU starts at the current planning step instead of replaying the past, and
rebuilds its reservation table from the future paths the cars keep
broadcasting.

Its stats reports (``{prefix}/stats/{me}``) carry, beside the V2X counters:
``boot`` (a random id per process, so the monitor tells a restarted RSU from
the one before), ``joined_s`` (run time at which this process began the run),
``table`` / ``table_size`` (the cars in the reservation table now),
``vehicles_seen`` (distinct cars heard in coverage this run) and
``table_log``, every change of the table's set of cars as ``[t, [cars]]`` (run
time; at most :data:`TABLE_LOG_MAX` entries).

Configuration (:class:`RsuDaemonConfig`): the common daemon settings
(``node_id`` is the RSU id of the scenario), ``scenario``, and an optional
``policy`` that overrides the start message's. The ``[time]`` table is not
used: the monitor's start message sets the epoch and speed.
"""

from __future__ import annotations

import argparse
import asyncio
import math
import secrets
import sys
from collections.abc import Iterable
from pathlib import Path
from typing import Any, Final

from protocol import FuturePath, Message, Mode, ModeCommand, VehiclePath
from protocol import keys as keyexpr
from protocol.keys import ParsedKey, Stream
from services.edge.clock import RunClock
from services.edge.metrics import CoreView
from services.edge.plumbing import StartRun
from services.edge.settings import CommonDaemonConfig
from services.edge.shell import ActorDaemon, DaemonCommand, add_daemon_arguments
from services.model.types import Policy, RunMode
from services.rsu.config import rsu_config
from services.rsu.core import Outgoing, RsuCore
from services.rsu.plausibility import Bounds, Seen, check_path

__all__ = [
    "TABLE_LOG_MAX",
    "TERMINATION_INTERVAL_S",
    "TERMINATION_ROUNDS",
    "RsuDaemon",
    "RsuDaemonConfig",
    "command",
    "configure",
    "load_daemon",
    "run",
]

TERMINATION_ROUNDS: Final = 3
"""How often the final terminations are sent (best effort V2X can lose one)."""

TERMINATION_INTERVAL_S: Final = 0.1
"""Wall seconds between two rounds of final terminations."""

TABLE_LOG_MAX: Final = 2000
"""Most changes of the reservation table's cars kept per run for the stats reports."""


class RsuDaemonConfig(CommonDaemonConfig):
    """Settings of ``crosspath rsu``: ``node_id`` is the RSU id of the scenario."""

    scenario: Path
    """The scenario file (the same on every host of a run)."""
    policy: Policy | None = None
    """Velocity manager policy; None: the one in the monitor's start message."""


class RsuDaemon(ActorDaemon[RsuDaemonConfig]):
    """One RSU: ``RsuCore`` behind a :class:`DaemonShell`."""

    service = "rsu"
    role = "RSU"

    def setup(self) -> None:
        self.boot = secrets.token_hex(6)
        self.bounds = Bounds.from_scenario(self.scenario)
        self.plausible: dict[str, Seen] = {}
        """What the plausibility check keeps of each car's last path (this run)."""
        self.implausible: dict[str, int] = {}
        """Paths refused as physically implausible, by reason (this run)."""
        self.joined_s: float | None = None
        self.table_log: list[tuple[float, tuple[str, ...]]] = []
        self._table: tuple[str, ...] = ()
        self._seen = 0
        self.policy_override = self.config.policy
        self.core: RsuCore | None = None
        self.vehicles: frozenset[str] = frozenset()
        self.reported: dict[str, Mode] = {}
        """Each car's mode as its latest future path shows it."""
        self.terminations_sent = 0

    def subscribe_v2x(self) -> None:
        p = self.prefix
        me = self.node
        # in a run, only the run's cars' keys are declared: nothing else reaches this RSU
        self.shell.subscribe_v2x(
            keyexpr.all_future_paths(prefix=p),
            Stream.FP,
            self._on_v2x,
            scope=lambda start: [keyexpr.future_path(v, prefix=p) for v in start.vehicles],
        )
        self.shell.subscribe_v2x(
            keyexpr.all_autonomous_paths(me, prefix=p),
            Stream.AP,
            self._on_v2x,
            scope=lambda start: [keyexpr.autonomous_path(me, v, prefix=p) for v in start.vehicles],
        )

    def takes_part(self, start: StartRun) -> bool:
        return start.mode is RunMode.RSU and self.node in start.rsus

    def _on_v2x(self, parsed: ParsedKey, message: Message, now: float) -> None:
        if isinstance(message, VehiclePath):  # issue 13: physically possible at all?
            sender = message.header.sender
            why, seen = check_path(message, self.plausible.get(sender), self.bounds)
            self.plausible[sender] = seen  # bounded: only cars of the run are admitted
            if why is not None:
                self.implausible[why] = self.implausible.get(why, 0) + 1
                return
        if isinstance(message, FuturePath):
            self.reported[message.header.sender] = message.mode
        core = self.core
        if core is not None:
            self._send(core.on_message(now, message, parsed.rsu))
            self._note_table(now)

    def _note_table(self, now: float) -> None:
        """Log a change of the set of cars in the reservation table (run time ``now``)."""
        core = self.core
        if core is None:
            return
        self._seen = core.counters["vehicles_seen"]
        cars = tuple(sorted(core.table))
        if cars != self._table:
            self._table = cars
            if len(self.table_log) < TABLE_LOG_MAX:
                self.table_log.append((round(now, 4), cars))
            self.log.debug("reservation table at %.3f s: %s", now, ", ".join(cars) or "empty")

    def stats_extras(self) -> dict[str, Any]:
        """The extra fields of this RSU's stats reports (see the module docstring)."""
        return {
            "boot": self.boot,
            "joined_s": self.joined_s,
            "table": list(self._table),
            "table_size": len(self._table),
            "vehicles_seen": self._seen,
            "table_log": [[t, list(cars)] for t, cars in self.table_log],
            "implausible": dict(sorted(self.implausible.items())),
        }

    def core_view(self) -> CoreView | None:
        """The core's counters (decisions, conflicts...) and table size, for the metrics."""
        core = self.core
        return None if core is None else CoreView(core.counters, table_size=len(core.table))

    def _send(self, outgoing: Iterable[Outgoing]) -> None:
        for og in outgoing:
            if og.vehicle is None:
                key = keyexpr.rsu_beacon(self.node, prefix=self.prefix)
            elif og.vehicle in self.vehicles:
                key = keyexpr.rsu_command(self.node, og.vehicle, prefix=self.prefix)
            else:
                continue
            self.shell.publish_v2x(key, og.message)

    async def episode(self, start: StartRun, clock: RunClock, halt: asyncio.Event) -> None:
        sc = self.scenario
        policy = self.policy_override or start.policy
        core = RsuCore(rsu_config(sc, self.node, policy))
        self.vehicles = frozenset(start.vehicles)
        self.reported = {}
        self.table_log = []
        self._table = ()
        self._seen = 0
        self.core = core
        self.plausible, self.implausible = {}, {}
        hz = sc.params.planning_hz
        # A daemon restarted during a run joins at the current step, not at step 0.
        first = max(0, math.ceil(clock.now() * hz - 1e-9))
        self.joined_s = round(first / hz, 4)
        if first > 0:
            self.log.warning("joining run %s late, at run time %.2f s", start.run_id, first / hz)
        async for _step, now in self.ticks(start, clock, halt, hz, first):
            self._send(core.tick(now))
            self._note_table(now)

    def coordinated(self) -> list[str]:
        """Cars of the run this RSU holds in a coordinated mode or still commands."""
        core = self.core
        if core is None:
            return []
        return [
            v
            for v in sorted(self.vehicles)
            if core.mode_of(v) is not Mode.AUTO or core.pending(v) is not None
        ]

    async def on_episode_end(self, start: StartRun, clock: RunClock) -> None:
        targets = self.coordinated()
        core, self.core = self.core, None  # no more decisions; receptions update ``reported``
        if core is None:
            return
        for round_ in range(TERMINATION_ROUNDS):
            if round_ > 0:
                targets = [v for v in targets if self.reported.get(v) is not Mode.AUTO]
            if not targets:
                break
            for vehicle in targets:
                self._terminate(core.termination(clock.now(), vehicle))
            self.log.info("terminations sent to %s (round %d)", ", ".join(targets), round_ + 1)
            for vehicle in targets:
                self.reported.pop(vehicle, None)
            await asyncio.sleep(TERMINATION_INTERVAL_S)

    def _terminate(self, message: ModeCommand) -> None:
        if self.shell.publish_v2x(
            keyexpr.rsu_command(self.node, message.vehicle, prefix=self.prefix), message
        ):
            self.terminations_sent += 1


# --------------------------------------------------------------------------- CLI


def configure(parser: argparse.ArgumentParser) -> None:
    """Options of ``crosspath rsu``."""
    group = add_daemon_arguments(parser, "rsu", "RSU")
    group.add_argument(
        "--policy",
        choices=[p.value for p in Policy],
        help="velocity manager policy (default: the monitor's)",
    )


command = DaemonCommand(
    "rsu",
    RsuDaemonConfig,
    RsuDaemon,
    {"scenario": "scenario", "node_id": "node_id", "policy": "policy"},
)
load_daemon = command.load
"""Config and scenario from the command line; :class:`ConfigError` naming the field."""
run = command.run
"""Run the RSU daemon until a signal; exit 2 on a configuration error."""


if __name__ == "__main__":  # pragma: no cover
    sys.exit(command.main(configure))
