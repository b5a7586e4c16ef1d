"""``crosspath monitor --config FILE``: owns a daemon run, records ground truth, writes the result.

The monitor stands for the simulator's bookkeeping: it never takes part in
V2X. One run, step by step:

1. **Wait for the actors.** It watches the liveliness tokens
   ``{prefix}/sim/alive/{node}`` until every expected actor is present: every
   car of the scenario, and in ``rsu`` mode every RSU (``wait_actors_s`` at
   most, else the run fails naming the missing ones).
2. **Start.** It publishes a :class:`~services.edge.plumbing.StartRun` on
   ``{prefix}/sim/control`` (reliable): run id, scenario name, mode, policy,
   seed, each car's start time (``Scenario.draw_start_times(seed)``, as the
   in-process harness), ``epoch_unix`` = now + ``start_delay_s`` (or
   ``time.epoch_unix`` when configured) and ``speed`` (``time.speed``). Each
   actor acknowledges with a stats report carrying the run id; the start is
   repeated every :data:`START_REPEAT_S` until all did (a daemon ignores a
   start it has seen), and the run fails if one has not ``ack_timeout_s`` wall
   seconds after the epoch.
3. **Record.** Every car publishes its ground truth at each physics step on
   ``{prefix}/sim/truth/{car}``. The monitor assembles the reports of one step
   and feeds them to ``MetricsRecorder.record`` in step order, exactly as the
   in-process harness does; a step still missing a car :data:`TRUTH_WAIT_S`
   wall seconds after its time (or once another car is a second ahead) is
   recorded with that car's latest known truth (counted in ``truth.gaps``).
4. **End.** When every car stands at its goal (``car.all_at_goal``, as the harness) or
   run time reaches ``max_sim_s`` (the scenario's unless configured), it
   publishes :class:`~services.edge.plumbing.StopRun`, waits up to
   ``stats_wait_s`` for every actor's final stats report, and builds the run
   result of DESIGN.md (``services.sim.results.run_result``, ``harness``
   ``"daemons"``) with the ``network`` section (:func:`network_summary`),
   writes it as JSON to ``json_out`` if set, prints it as tables, and exits 0.

The run fails (exit 1, a partial result with ``error`` is still written) when
an actor is missing at the start, does not acknowledge, or loses its
liveliness token during the run (crashed or disconnected), or when the monitor
is stopped by SIGTERM/SIGINT; the actors are told with a stop message.

Fault experiments (the network lab, ``services.supervise.lab``) use three
optional settings:

- ``expect_crash`` (``--expect-crash NODE``, repeatable): nodes that may crash
  and restart during the run. Losing such a node's liveliness token does not
  fail the run (the event is listed in ``crashes``), and the start message is
  repeated every :data:`START_REPEAT_S` for the whole run, so a restarted
  daemon joins the run in progress. A stats report whose ``boot`` differs from
  the node's previous one comes from a new incarnation: the previous
  incarnation's latest counters are kept and still count in ``network``.
- ``trace`` (``--trace``): the result gets ``trace``, one row per recorded
  physics step and car, fields :data:`TRACE_FIELDS` (run time, position, mode
  and planner reason as the car reported them).
- ``start_file`` (``--start-file FILE``): when the run starts, the monitor
  writes ``{"run_id", "epoch_unix", "speed"}`` there, so a controller can
  schedule faults on the run clock.

The result also lists per node (``actors``) its V2X totals and whatever
extra fields its latest stats report carried (the RSU daemon adds its
reservation table, ``services.daemons.rsu``), and ``epoch_unix``.

``network``: per V2X stream (``fp``, ``ap``, ``cmd``, ``beacon``) ``msgs``,
``bytes``, ``kbps_per_vehicle``, ``latency_ms_p50``, ``latency_ms_p99``,
``delivery_ratio`` and more (``services.edge.stats.network_section``), plus
``total_kbps_per_vehicle`` (the only entry that is not a stream). Rates are per
*run* second (what a car would need in real time, whatever ``--speed``);
latencies are one-way in *wall* milliseconds (the daemons divide run-time
latency by the speed). Expected receivers: a future path by every other car
and every RSU, an autonomous path and a command by one node, a beacon by every
car.
"""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import json
import logging
import math
import secrets
import sys
import time
from collections.abc import Callable, Mapping
from pathlib import Path
from typing import Annotated, Any, Final

from pydantic import Field, field_validator

from protocol import keys
from services.edge.clock import RunClock
from services.edge.plumbing import (
    PlumbingError,
    StartRun,
    StatsReport,
    StopRun,
    TruthReport,
    all_alive,
    all_truths,
    control_key,
    decode_stats,
    decode_truth,
    encode_control,
    node_of_alive_key,
    truth_key,
)
from services.edge.settings import (
    CommonDaemonConfig,
    ConfigError,
    add_common_arguments,
    exit_on_config_error,
)
from services.edge.shell import (
    DaemonShell,
    load_daemon_config,
    load_daemon_scenario,
    run_daemon,
    wait_any,
    wait_event,
)
from services.edge.stats import merge_snapshots, network_section
from services.edge.transport import Transport
from services.model.scenario import Scenario
from services.model.types import Policy, RunMode
from services.sim.car import all_at_goal
from services.sim.metrics import MetricsRecorder
from services.sim.results import run_result

__all__ = [
    "START_REPEAT_S",
    "TRACE_FIELDS",
    "TRUTH_WAIT_S",
    "V2X_STREAMS",
    "MonitorConfig",
    "MonitorService",
    "configure",
    "expected_receivers",
    "format_network",
    "load_monitor",
    "network_summary",
    "new_run_id",
    "run",
]

log = logging.getLogger("crosspath.monitor")

START_REPEAT_S: Final = 0.25
"""Wall seconds between repetitions of the start message until every actor acknowledged."""

TRUTH_WAIT_S: Final = 1.0
"""Wall seconds a step waits for a missing car's ground truth before it is recorded."""

POLL_S: Final = 0.05
"""Wall seconds between two looks at timeouts in the monitor's loop."""

V2X_STREAMS: Final = ("fp", "ap", "cmd", "beacon")
"""The streams of the ``network`` section, in table order."""

TRACE_FIELDS: Final = ("t", "vehicle", "x", "y", "s", "speed", "mode", "reason")
"""Columns of the optional ``trace`` of the result (s, m, m, m, m/s, mode name, reason)."""

_SNAPSHOT_KEYS: Final = frozenset({"node", "time_s", "streams"})
"""Keys of a stats snapshot that are not extra per-node fields."""


class MonitorConfig(CommonDaemonConfig):
    """Settings of ``crosspath monitor``; ``time.speed`` is the run's speed."""

    node_id: str = "monitor"
    scenario: Path
    mode: RunMode = RunMode.RSU
    policy: Policy = Policy.PAPER
    seed: Annotated[int, Field(ge=0)] = 0
    max_sim_s: Annotated[float, Field(gt=0.0)] | None = None
    """Run time limit [s]; None: the scenario's ``params.max_sim_s``."""
    json_out: Path | None = None
    """Where to write the run result (JSON); None: only printed."""
    run_id: str | None = None
    """Id of the run (a key-safe id); None: generated from the time and a random part."""
    start_delay_s: Annotated[float, Field(ge=0.0, le=3600.0)] = 1.0
    """Wall seconds from the start message to run time 0 (unless ``time.epoch_unix``)."""
    wait_actors_s: Annotated[float, Field(gt=0.0)] = 30.0
    """How long to wait for every actor's liveliness token [wall s]."""
    ack_timeout_s: Annotated[float, Field(gt=0.0)] = 5.0
    """How long after the epoch every actor must have acknowledged the start [wall s]."""
    stats_wait_s: Annotated[float, Field(ge=0.0)] = 3.0
    """How long to wait for the actors' final stats reports after the stop [wall s]."""
    expect_crash: tuple[str, ...] = ()
    """Nodes that may crash (and restart) during the run without failing it."""
    trace: bool = False
    """Add the per-step ``trace`` (:data:`TRACE_FIELDS`) to the result."""
    start_file: Path | None = None
    """Write ``{run_id, epoch_unix, speed}`` here (JSON) when the run starts."""

    @field_validator("run_id")
    @classmethod
    def _run_id(cls, value: str | None) -> str | None:
        return None if value is None else keys.validate_id(value, "run id")

    @field_validator("expect_crash")
    @classmethod
    def _expect_crash(cls, value: tuple[str, ...]) -> tuple[str, ...]:
        return tuple(keys.validate_id(v, "node id") for v in value)


def new_run_id(time_fn: Callable[[], float] = time.time) -> str:
    """A fresh run id, e.g. ``r20250101-120000-a1b2c3`` (sortable, key-safe)."""
    stamp = time.strftime("%Y%m%d-%H%M%S", time.gmtime(time_fn()))
    return f"r{stamp}-{secrets.token_hex(3)}"


def expected_receivers(n_vehicles: int, n_rsus: int) -> dict[str, int]:
    """How many nodes should receive each datagram of a stream (see module docstring)."""
    return {"fp": n_vehicles - 1 + n_rsus, "ap": 1, "cmd": 1, "beacon": n_vehicles}


def network_summary(
    snapshots: list[Mapping[str, Any]], n_vehicles: int, n_rsus: int, sim_s: float
) -> dict[str, Any]:
    """The ``network`` section: :func:`stats.network_section` per stream plus the total."""
    if not snapshots or not (math.isfinite(sim_s) and sim_s > 0.0):
        return {"total_kbps_per_vehicle": 0.0}
    section: dict[str, Any] = dict(
        network_section(snapshots, n_vehicles, sim_s, expected_receivers(n_vehicles, n_rsus))
    )
    total = sum(float(entry["kbps_per_vehicle"]) for entry in section.values())
    section["total_kbps_per_vehicle"] = total
    return section


def format_network(network: Mapping[str, Any]) -> str:
    """The ``network`` section as a table (one row per stream, then the total)."""

    def num(value: object, fmt: str) -> str:
        return "-" if value is None else format(value, fmt)

    lines = [
        f"{'stream':<8}{'msgs':>8}{'bytes':>10}{'kbps/veh':>10}{'p50 [ms]':>10}"
        f"{'p99 [ms]':>10}{'delivery':>10}{'malformed':>10}"
    ]
    names = [s for s in V2X_STREAMS if s in network]
    names += sorted(k for k in network if k not in V2X_STREAMS and isinstance(network[k], Mapping))
    for name in names:
        e = network[name]
        lines.append(
            f"{name:<8}{e['msgs']:>8}{e['bytes']:>10}{num(e['kbps_per_vehicle'], '.1f'):>10}"
            f"{num(e['latency_ms_p50'], '.2f'):>10}{num(e['latency_ms_p99'], '.2f'):>10}"
            f"{num(e['delivery_ratio'], '.3f'):>10}{e.get('malformed', 0):>10}"
        )
    lines.append(f"total {num(network.get('total_kbps_per_vehicle'), '.1f')} kbps per vehicle")
    return "\n".join(lines)


class MonitorService:
    """The monitor daemon (see module docstring); ``result`` and ``exit_code`` after the run."""

    def __init__(
        self,
        config: MonitorConfig,
        scenario: Scenario,
        transport: Transport | None = None,
        *,
        time_fn: Callable[[], float] = time.time,
    ) -> None:
        self.config = config
        self.scenario = scenario
        self.shell = DaemonShell(config, "monitor", transport, time_fn=time_fn)
        self.time_fn = time_fn
        self.prefix = config.key_prefix
        params = scenario.params
        self.mode = config.mode
        self.vehicles = tuple(v.id for v in scenario.vehicles)
        self.rsus = tuple(r.id for r in scenario.rsus) if config.mode is RunMode.RSU else ()
        self.expected = frozenset(self.vehicles + self.rsus)
        self.max_sim_s = config.max_sim_s if config.max_sim_s is not None else params.max_sim_s
        self.dt = 1.0 / params.physics_hz
        self.alive: set[str] = set()
        self.acked: set[str] = set()
        self.reports: dict[str, StatsReport] = {}
        self.start: StartRun | None = None
        self.clock: RunClock | None = None
        self.metrics = MetricsRecorder(scenario)
        self.pending: dict[int, dict[str, TruthReport]] = {}
        self.latest: dict[str, TruthReport] = {}
        self.next_step = 0
        self.max_step_seen = -1
        self.last_t: float | None = None
        self.truth_gaps = 0
        self.truth_late = 0
        self.done_reason: str | None = None
        self.failure: str | None = None
        self.result: dict[str, Any] | None = None
        self.exit_code = 0
        self.end_wall: float | None = None
        self.may_crash = frozenset(config.expect_crash)
        self.crashes: list[dict[str, Any]] = []
        """Liveliness losses and returns of ``expect_crash`` nodes during the run."""
        self.earlier_reports: dict[str, list[StatsReport]] = {}
        """Per node, the latest report of each earlier incarnation (see ``boot``)."""
        self.trace_rows: list[tuple[float, str, float, float, float, float, str, str]] = []
        self._changed = asyncio.Event()

    # ------------------------------------------------------------------ Service

    async def startup(self) -> None:
        if set(self.vehicles) & set(self.rsus):
            raise ValueError("a vehicle and an RSU share an id: stats keys would collide")
        unknown = self.may_crash - self.expected
        if unknown:
            raise ValueError(
                f"expect_crash names nodes that are not actors of this run: {sorted(unknown)}"
            )
        await self.shell.open()
        p = self.prefix
        self.shell.subscribe_plumbing(all_truths(prefix=p), self._on_truth)
        self.shell.subscribe_plumbing(keys.all_stats(prefix=p), self._on_stats)
        self.shell.transport.watch_liveliness(all_alive(prefix=p), self._on_liveliness)
        self.shell.announce()
        log.info(
            "monitor ready: %s mode, waiting for %s", self.mode, ", ".join(sorted(self.expected))
        )

    async def run(self, stop: asyncio.Event) -> None:
        try:
            await self._run(stop)
        finally:
            if self.failure is not None:
                self.exit_code = 1
                log.error("run failed: %s", self.failure)

    async def shutdown(self) -> None:
        await self.shell.close()

    # ------------------------------------------------------------------ the run

    async def _run(self, stop: asyncio.Event) -> None:
        cfg = self.config
        loop = asyncio.get_running_loop()
        deadline = loop.time() + cfg.wait_actors_s
        while not self.expected <= self.alive:
            if stop.is_set():
                self.failure = "stopped before the run started"
                return
            if loop.time() > deadline:
                missing = ", ".join(sorted(self.expected - self.alive))
                self.failure = (
                    f"actors not present after {cfg.wait_actors_s:g} s: {missing} "
                    "(no liveliness token; are their daemons running and connected?)"
                )
                return
            self._changed.clear()
            await _wait_any_for(self._changed, stop, 0.2)
        now_wall = self.time_fn()
        epoch = (
            cfg.time.epoch_unix
            if cfg.time.epoch_unix is not None
            else (now_wall + cfg.start_delay_s)
        )
        start = StartRun(
            run_id=cfg.run_id or new_run_id(self.time_fn),
            scenario=self.scenario.name,
            mode=self.mode,
            policy=cfg.policy,
            seed=cfg.seed,
            start_times=self.scenario.draw_start_times(cfg.seed),
            epoch_unix=epoch,
            speed=cfg.time.speed,
            max_sim_s=self.max_sim_s,
            monitor=self.shell.node,
            vehicles=self.vehicles,
            rsus=self.rsus,
        )
        self.start = start
        self.clock = RunClock(epoch, cfg.time.speed, time_fn=self.time_fn)
        if cfg.start_file is not None:
            _write_start_file(cfg.start_file, start)
        log.info(
            "starting run %s (%s, policy %s, seed %d, speed %g) in %.2f s",
            start.run_id,
            start.mode,
            start.policy,
            start.seed,
            start.speed,
            epoch - now_wall,
        )
        payload = encode_control(start)
        self.shell.publish_plumbing(control_key(prefix=self.prefix), payload)
        last_sent = loop.time()
        while self.done_reason is None and self.failure is None:
            await wait_event(stop, POLL_S)
            if stop.is_set():
                self.failure = "monitor stopped by a signal before the run was over"
                break
            unacked = self.expected - self.acked
            if unacked and self.time_fn() > epoch + cfg.ack_timeout_s:
                self.failure = (
                    f"no acknowledgement of run {start.run_id} from "
                    f"{', '.join(sorted(unacked))} within {cfg.ack_timeout_s:g} s of its start"
                )
                break
            if (unacked or self.may_crash) and loop.time() - last_sent >= START_REPEAT_S:
                # With expected crashes the start is repeated all run long: a restarted
                # daemon joins the run in progress (the others ignore a start they have seen).
                self.shell.publish_plumbing(control_key(prefix=self.prefix), payload)
                last_sent = loop.time()
            self._advance()
        self.end_wall = self.time_fn()
        sim_s = self.last_t or 0.0
        reason = self.done_reason or self.failure or "stopped"
        stop_msg = StopRun(start.run_id, reason[:500], sim_s)
        self.shell.publish_plumbing(control_key(prefix=self.prefix), encode_control(stop_msg))
        log.info("run %s over at %.2f s: %s", start.run_id, sim_s, reason)
        await self._wait_final_stats(stop)
        self.result = self.build_result()
        if cfg.json_out is not None:
            cfg.json_out.parent.mkdir(parents=True, exist_ok=True)
            cfg.json_out.write_text(json.dumps(self.result, indent=2) + "\n")

    async def _wait_final_stats(self, stop: asyncio.Event) -> None:
        loop = asyncio.get_running_loop()
        deadline = loop.time() + self.config.stats_wait_s
        while loop.time() < deadline:
            finals = {n for n, r in self.reports.items() if r.final}
            if self.expected <= finals:
                return
            # a lost actor sends no final report: do not wait for it
            if self.failure is not None and (self.expected & self.alive) <= finals:
                return
            # a node that crashed as expected and is not back sends none either
            gone = self.may_crash - self.alive
            if gone and self.expected - gone <= finals:
                return
            await asyncio.sleep(POLL_S)
        missing = sorted(self.expected - {n for n, r in self.reports.items() if r.final})
        if missing:
            log.warning("no final stats from %s; using their latest", ", ".join(missing))

    # ------------------------------------------------------------------ ground truth

    def _on_truth(self, key: str, payload: bytes) -> None:
        start = self.start
        if start is None:
            return
        report = decode_truth(payload)
        vid = report.vehicle
        if report.run_id != start.run_id:
            return
        if vid not in self.vehicles or key != truth_key(vid, prefix=self.prefix):
            raise PlumbingError(f"truth of {vid!r} on {key}: not a car of this run")
        prev = self.latest.get(vid)
        if prev is None or report.step > prev.step:
            self.latest[vid] = report
        if report.step < self.next_step:
            self.truth_late += 1
            return
        self.pending.setdefault(report.step, {})[vid] = report
        self.max_step_seen = max(self.max_step_seen, report.step)
        self._advance()

    def _advance(self) -> None:
        """Record every step that is complete (or waited for long enough), in order."""
        clock = self.clock
        if clock is None:
            return
        lag_steps = max(1, round(1.0 / self.dt))
        while self.done_reason is None and self.failure is None:
            k = self.next_step
            reports = self.pending.get(k, {})
            complete = len(reports) == len(self.vehicles)
            if not complete:
                overdue = (clock.now() - k * self.dt) / clock.speed > TRUTH_WAIT_S
                ahead = self.max_step_seen >= k + lag_steps
                if not (overdue or ahead) or (not reports and not self.latest):
                    return
            self.pending.pop(k, None)
            self._record(k, reports)
            self.next_step = k + 1

    def _record(self, k: int, reports: Mapping[str, TruthReport]) -> None:
        now = k * self.dt
        rows: list[TruthReport] = []
        for vid in self.vehicles:
            report = reports.get(vid)
            if report is None:
                report = self.latest.get(vid)
                if report is None:
                    continue
                self.truth_gaps += 1
            rows.append(report)
        states = [r.state for r in rows]
        if self.config.trace:
            self.trace_rows.extend(
                (
                    round(now, 3),
                    r.vehicle,
                    round(r.state.x, 3),
                    round(r.state.y, 3),
                    round(r.state.s, 3),
                    round(r.state.speed, 3),
                    r.mode,
                    r.reason,
                )
                for r in rows
            )
        self.metrics.record(
            now,
            states,
            {r.vehicle: r.mode for r in rows},
            {r.vehicle: r.reason for r in rows},
        )
        self.last_t = now
        if now >= self.max_sim_s:
            self.done_reason = f"max_sim_s ({self.max_sim_s:g} s) reached"
        elif len(states) == len(self.vehicles) and all_at_goal(self.scenario, states):
            self.done_reason = "every car stands at its goal"

    # ------------------------------------------------------------------ stats, liveliness

    def _on_stats(self, key: str, payload: bytes) -> None:
        report = decode_stats(payload)
        if key != keys.stats(report.node, prefix=self.prefix):
            raise PlumbingError(f"stats of {report.node!r} on {key}")
        start = self.start
        if start is None or report.run_id != start.run_id or report.node not in self.expected:
            return
        try:
            merge_snapshots([report.snapshot])
        except ValueError as exc:
            raise PlumbingError(f"stats of {report.node}: {exc}") from None
        self.acked.add(report.node)
        prev = self.reports.get(report.node)
        boot = report.snapshot.get("boot")
        prev_boot = None if prev is None else prev.snapshot.get("boot")
        if prev is not None and None not in (boot, prev_boot) and prev_boot != boot:
            # A restarted daemon: keep what its earlier incarnation counted.
            self.earlier_reports.setdefault(report.node, []).append(prev)
            prev = None
        if prev is None or not prev.final:
            self.reports[report.node] = report

    def _on_liveliness(self, key: str, alive: bool) -> None:
        try:
            node = node_of_alive_key(key, prefix=self.prefix)
        except keys.BadKey:
            return
        self._changed.set()
        running = self.start is not None and self.done_reason is None and self.failure is None
        if running and node in self.may_crash and (alive != (node in self.alive)):
            clock = self.clock
            t = None if clock is None else round(clock.now(), 3)
            self.crashes.append({"node": node, "event": "back" if alive else "lost", "t_s": t})
            log.warning("%s %s at run time %s", node, "is back" if alive else "lost", t)
        if alive:
            self.alive.add(node)
            return
        self.alive.discard(node)
        if running and node in self.expected and node not in self.may_crash:
            self.failure = (
                f"{node} lost: its liveliness token disappeared during the run "
                "(daemon crashed, was stopped or lost its connection)"
            )

    # ------------------------------------------------------------------ result

    def build_result(self) -> dict[str, Any]:
        """The run result of DESIGN.md with ``network``; partial (``error``) after a failure."""
        start = self.start
        if start is None:
            raise RuntimeError("no run was started")
        sim_s = self.last_t or 0.0
        end = self.end_wall if self.end_wall is not None else self.time_fn()
        wall_s = max(0.0, end - start.epoch_unix)
        snapshots = [r.snapshot for n, r in sorted(self.reports.items()) if n in self.expected]
        snapshots += [
            r.snapshot
            for n, reports in sorted(self.earlier_reports.items())
            if n in self.expected
            for r in reports
        ]
        network = network_summary(snapshots, len(self.vehicles), len(self.rsus), sim_s)
        extra: dict[str, Any] = {
            "scenario": self.scenario.name,
            "run_id": start.run_id,
            "harness": "daemons",
            "speed": start.speed,
            "start_times": {vid: round(t, 4) for vid, t in start.start_times.items()},
            "speedup_vs_real_time": round(sim_s / wall_s, 1) if wall_s > 0 else None,
            "end_reason": self.done_reason or self.failure,
            "truth": {
                "steps": self.next_step,
                "gaps": self.truth_gaps,
                "late": self.truth_late,
            },
            "final_stats": sorted(n for n, r in self.reports.items() if r.final),
            "network": network,
            "epoch_unix": start.epoch_unix,
            "actors": {
                n: _actor_summary(r, self.earlier_reports.get(n, []))
                for n, r in sorted(self.reports.items())
                if n in self.expected
            },
        }
        if self.may_crash:
            extra["expect_crash"] = sorted(self.may_crash)
            extra["crashes"] = list(self.crashes)
        if self.config.trace:
            extra["trace_fields"] = list(TRACE_FIELDS)
            extra["trace"] = [list(row) for row in self.trace_rows]
        if self.failure is not None:
            extra["error"] = self.failure
        policy = str(start.policy) if start.mode is RunMode.RSU else None
        return run_result(
            self.metrics.result(),
            mode=start.mode,
            policy=policy,
            seed=start.seed,
            sim_s=sim_s,
            wall_s=wall_s,
            extra=extra,
        )


def _v2x_totals(snapshot: Mapping[str, Any]) -> dict[str, int]:
    """Datagrams and payload bytes sent and received over every stream of one snapshot."""
    totals = {"msgs_tx": 0, "bytes_tx": 0, "msgs_rx": 0, "bytes_rx": 0}
    streams = snapshot.get("streams")
    if isinstance(streams, Mapping):
        for data in streams.values():
            if isinstance(data, Mapping):
                for name in totals:
                    value = data.get(name, 0)
                    if isinstance(value, int) and not isinstance(value, bool):
                        totals[name] += value
    return totals


def _actor_summary(report: StatsReport, earlier: list[StatsReport]) -> dict[str, Any]:
    """One node's entry of ``actors``: V2X totals (all incarnations) and its extra fields."""
    totals = _v2x_totals(report.snapshot)
    for old in earlier:
        for name, value in _v2x_totals(old.snapshot).items():
            totals[name] += value
    entry: dict[str, Any] = {"final": report.final, "v2x": totals}
    entry.update((k, v) for k, v in report.snapshot.items() if k not in _SNAPSHOT_KEYS)
    if earlier:
        entry["incarnations"] = len(earlier) + 1
    return entry


def _write_start_file(path: Path, start: StartRun) -> None:
    """``{run_id, epoch_unix, speed}`` as JSON, replaced atomically (readers never see half)."""
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(path.name + ".tmp")
    data = {"run_id": start.run_id, "epoch_unix": start.epoch_unix, "speed": start.speed}
    tmp.write_text(json.dumps(data) + "\n")
    tmp.replace(path)


async def _wait_any_for(a: asyncio.Event, b: asyncio.Event, timeout: float) -> None:
    with contextlib.suppress(TimeoutError):
        await asyncio.wait_for(wait_any(a, b), timeout)


# --------------------------------------------------------------------------- CLI


def configure(parser: argparse.ArgumentParser) -> None:
    """Options of ``crosspath monitor``."""
    add_common_arguments(parser)
    group = parser.add_argument_group("run")
    group.add_argument("--scenario", type=Path, metavar="FILE", help="scenario file (TOML)")
    group.add_argument("--mode", choices=[m.value for m in RunMode], help="default rsu")
    group.add_argument("--policy", choices=[p.value for p in Policy], help="default paper")
    group.add_argument("--seed", type=int, metavar="N", help="seed of the start times")
    group.add_argument("--speed", type=float, metavar="X", help="run seconds per wall second")
    group.add_argument("--max-sim-s", type=float, metavar="S", help="run time limit [s]")
    group.add_argument("--json", type=Path, metavar="OUT", help="write the run result here")
    group.add_argument("--run-id", metavar="ID", help="id of the run (default: generated)")
    group.add_argument("--start-delay", type=float, metavar="S", help="wall s before run time 0")
    group.add_argument("--wait-actors", type=float, metavar="S", help="wall s to wait for actors")
    group.add_argument(
        "--expect-crash",
        action="append",
        metavar="NODE",
        help="a node that may crash and restart without failing the run (repeatable)",
    )
    group.add_argument(
        "--trace", action="store_true", default=None, help="add the per-step trace to the result"
    )
    group.add_argument(
        "--start-file", type=Path, metavar="FILE", help="write run id and epoch here at the start"
    )


_FLAGS: Final = {
    "scenario": "scenario",
    "mode": "mode",
    "policy": "policy",
    "seed": "seed",
    "speed": "time.speed",
    "max_sim_s": "max_sim_s",
    "json": "json_out",
    "run_id": "run_id",
    "start_delay": "start_delay_s",
    "wait_actors": "wait_actors_s",
    "expect_crash": "expect_crash",
    "trace": "trace",
    "start_file": "start_file",
}


def load_monitor(args: argparse.Namespace) -> tuple[MonitorConfig, Scenario]:
    """Config and scenario from the command line; :class:`ConfigError` naming the field."""
    extra: dict[str, object] = {}
    for flag, field in _FLAGS.items():
        value = getattr(args, flag, None)
        if value is not None:
            extra[field] = str(value) if isinstance(value, Path) else value
    config = load_daemon_config(MonitorConfig, args, extra)
    return config, load_daemon_scenario(config.scenario)


def run(args: argparse.Namespace) -> int:
    """Run one monitored run; print its result; 0 when it completed, 1 when it failed."""
    from services.sim.results import format_summary

    try:
        config, scenario = load_monitor(args)
    except ConfigError as exc:
        return exit_on_config_error("monitor", exc)
    service = MonitorService(config, scenario)
    code = run_daemon(config, service)
    if service.result is not None:
        sys.stdout.write(format_summary(service.result) + "\n")
        sys.stdout.write(format_network(service.result["network"]) + "\n")
        if service.failure is not None:
            sys.stdout.write(f"run FAILED: {service.failure}\n")
        sys.stdout.flush()
    elif service.failure is not None:
        sys.stderr.write(f"crosspath monitor: run failed: {service.failure}\n")
    return code or service.exit_code


if __name__ == "__main__":  # pragma: no cover
    _parser = argparse.ArgumentParser(prog="crosspath monitor")
    configure(_parser)
    sys.exit(run(_parser.parse_args()))
