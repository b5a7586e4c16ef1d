"""``crosspath monitor --config FILE``: owns a daemon run, records ground truth, writes the result.

The monitor stands for the simulator's bookkeeping: it never takes part in
V2X. Every decision below (which step is complete, late and missing reports,
when to repeat the start, when the run fails or is over) is made by the pure
:class:`~services.sim.truth.MonitorCore`; this daemon is its shell: it turns
truth, stats and liveliness into calls of the core, polls it at its deadlines
and sends what it says. One run, step by step:

1. **Wait for the actors.** It watches the liveliness tokens
   ``{prefix}/sim/alive/{node}`` until every expected actor is present: every
   car of the scenario, and in ``rsu`` mode every RSU (``wait_actors_s`` at
   most, else the run fails naming the missing ones). With credentials (issue 13)
   a token is not enough, since tokens carry no signature: an actor is present
   only once its token is up *and* a stats report signed by its own key arrived
   since the token appeared (every actor publishes one as soon as it is up, then
   every ``stats_period_s``: its "hello"); losing the token forgets it. So a bare
   token (a forged ``rsu1``) never makes the run start. Without credentials
   (``--insecure``) nothing can be authenticated and the token alone counts.
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
   ``{prefix}/sim/truth/{car}``. The monitor's core (``services.sim.truth``)
   keeps the reports in a table of steps and closes the steps in order; a step
   still missing a car :data:`TRUTH_WAIT_S` wall seconds after its time (or once
   another car is a second ahead) is closed *without* it. The metrics are the
   table replayed into ``MetricsRecorder`` with only same-step truth, as the
   in-process harness records them: a missing report is never filled in from an
   older step (per car in ``truth_gaps``, the run ``degraded``), and a late one
   still counts as the truth of its step. Each actor's stats carry
   ``late_ticks``, the ticks its control loop ran more than one period behind the
   run clock (``services.edge.shell``); any makes the run ``degraded`` too.
4. **End.** When every car has left the world at its goal (its ``left`` truth report;
   as the harness, cars are inserted and removed: ``services.sim.truth``) or
   run time reaches ``max_sim_s`` (the scenario's unless configured), it
   publishes :class:`~services.edge.plumbing.StopRun`, waits up to
   ``stats_wait_s`` for every actor's final stats report, and builds the run
   result of DESIGN.md (a ``services.model.results.RunResult``, ``harness``
   ``"daemons"``, its provenance's channel ``zenoh``, per-car ``delay_s`` and
   ``insertion_delay_s`` and the ``summary``, by the harness's metrics code) with the
   ``network`` section
   (:func:`network_summary`), writes it as JSON to ``json_out`` if set, prints it
   as tables, and exits 0.

**If the monitor dies** (SIGKILL: no chance to write anything at the end), the
run is not lost: with ``json_out`` set the monitor appends, as the run goes, every
truth and stats report it keeps to a step log beside it
(``services.daemons.steplog``, ``<json_out stem>.steps.jsonl``), and
``crosspath results rebuild RUN_DIR`` (:func:`rebuild_result`) replays it through
the same core into a partial result (``error`` says so, ``rebuilt_from`` names
the log); late ticks an actor logged at the end of its run (``late_ticks=N`` in
``<node>.log``) count too. Decision: no periodic partial ``result.json`` (a
second writer of the same numbers); the log plus the rebuild is the one way.

The run fails (exit 1, a partial result with ``error`` is still written) when
an actor is missing at the start, does not acknowledge, or loses its
liveliness token during the run (crashed or disconnected), or when the monitor
is stopped by SIGTERM/SIGINT; the actors are told with a stop message. A bad
truth or stats report is counted and dropped (``services.edge.shell``); a bug
of ours in a handler is logged with its traceback, fails the run the same way
(``monitor hit an internal error ...``) and the monitor exits 1.

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
car; with cars in the world only between insertion and removal, "every car" is
the cars in the world, averaged over the run (``TruthSteps.expected_receivers``).
"""

from __future__ import annotations

import argparse
import asyncio
import json
import logging
import math
import re
import secrets
import sys
import time
from collections.abc import Callable, Mapping
from pathlib import Path
from typing import Annotated, Any, Final

from pydantic import Field, field_validator

from protocol import keys
from services.daemons.steplog import StepLog, StepLogError, read_step_log, step_log_path
from services.edge.args import (
    non_negative_float,
    non_negative_int,
    output_file,
    positive_float,
    run_speed,
)
from services.edge.plumbing import (
    PlumbingError,
    StartRun,
    StatsReport,
    StopRun,
    all_truths,
    control_key,
    decode_stats,
    encode_control,
)
from services.edge.provenance import origin
from services.edge.settings import CommonDaemonConfig, ConfigError
from services.edge.shell import DaemonBase, DaemonCommand, add_daemon_arguments, wait_any
from services.edge.stats import merge_snapshots, network_section
from services.model.results import ChannelParams, NetworkSection, Origin, RunResult
from services.model.scenario import Scenario, ScenarioError, load_scenario
from services.model.types import Policy, RunMode
from services.sim.metrics import RunMetrics
from services.sim.results import provenance, run_result, run_summary
from services.sim.truth import (
    START_REPEAT_S,
    TRACE_FIELDS,
    TRUTH_WAIT_S,
    MonitorCore,
    MonitorRules,
    TraceRow,
    TruthSteps,
)

__all__ = [
    "START_REPEAT_S",
    "TRACE_FIELDS",
    "TRUTH_WAIT_S",
    "V2X_STREAMS",
    "MonitorConfig",
    "MonitorService",
    "StatsBook",
    "assemble_result",
    "command",
    "configure",
    "expected_receivers",
    "format_degraded",
    "format_network",
    "load_monitor",
    "network_summary",
    "new_run_id",
    "rebuild_result",
    "run",
]

log = logging.getLogger("crosspath.monitor")

MAX_WAIT_S: Final = 1.0
"""Longest wall-second wait of the monitor's loop between two polls of its core."""

V2X_STREAMS: Final = ("fp", "ap", "cmd", "beacon")
"""The streams of the ``network`` section, in table order."""

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
    step_log: Path | None = None
    """The append-only step log (``services.daemons.steplog``); None: beside ``json_out``
    (``<stem>.steps.jsonl``), none without ``json_out``."""

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
    snapshots: list[Mapping[str, Any]],
    n_vehicles: int,
    n_rsus: int,
    sim_s: float,
    receivers: Mapping[str, float] | None = None,
) -> dict[str, Any]:
    """The ``network`` section: :func:`stats.network_section` per stream plus the total.
    ``receivers``: expected receivers per stream (default :func:`expected_receivers`;
    a run with insertion and removal passes ``TruthSteps.expected_receivers``)."""
    if not snapshots or not (math.isfinite(sim_s) and sim_s > 0.0):
        return {"total_kbps_per_vehicle": 0.0}
    expect: Mapping[str, float] = (
        receivers if receivers is not None else expected_receivers(n_vehicles, n_rsus)
    )
    section: dict[str, Any] = dict(network_section(snapshots, n_vehicles, sim_s, expect))
    total = sum(float(entry["kbps_per_vehicle"]) for entry in section.values())
    section["total_kbps_per_vehicle"] = total
    return section


def format_degraded(result: RunResult) -> str | None:
    """One line saying why a run is ``degraded`` (its safety metrics may miss something);
    None for a clean run."""
    if not result.degraded:
        return None
    parts = []
    gaps = {k: n for k, n in (result.truth_gaps or {}).items() if n}
    late = {k: n for k, n in (result.late_ticks or {}).items() if n}
    if gaps:
        parts.append("truth missing at " + ", ".join(f"{k} {n} steps" for k, n in gaps.items()))
    if late:
        parts.append("late ticks " + ", ".join(f"{k} {n}" for k, n in late.items()))
    return "run DEGRADED (safety metrics may miss something): " + "; ".join(parts)


def format_network(network: NetworkSection | None) -> str:
    """The ``network`` section as a table (one row per stream, then the total)."""

    def num(value: float | None, fmt: str) -> str:
        return "-" if value is None else format(value, fmt)

    lines = [
        f"{'stream':<8}{'msgs':>8}{'bytes':>10}{'kbps/veh':>10}{'p50 [ms]':>10}"
        f"{'p99 [ms]':>10}{'delivery':>10}{'malformed':>10}"
    ]
    streams = {} if network is None else network.streams
    names: list[str] = [s for s in V2X_STREAMS if s in streams]
    names += sorted(k for k in streams if k not in V2X_STREAMS)
    for name in names:
        e = streams[name]
        lines.append(
            f"{name:<8}{e.msgs:>8}{e.bytes:>10}{num(e.kbps_per_vehicle, '.1f'):>10}"
            f"{num(e.latency_ms_p50, '.2f'):>10}{num(e.latency_ms_p99, '.2f'):>10}"
            f"{num(e.delivery_ratio, '.3f'):>10}{e.malformed:>10}"
        )
    total = None if network is None else network.total_kbps_per_vehicle
    lines.append(f"total {num(total, '.1f')} kbps per vehicle")
    return "\n".join(lines)


class MonitorService(DaemonBase[MonitorConfig]):
    """The monitor daemon (see module docstring): a thin shell over the pure
    :class:`~services.sim.truth.MonitorCore`; ``result`` and ``exit_code`` after the run."""

    service = "monitor"
    periodic_stats = False

    def setup(self) -> None:
        cfg = self.config
        scenario = self.scenario
        self.mode = cfg.mode
        self.vehicles = tuple(v.id for v in scenario.vehicles)
        self.rsus = tuple(r.id for r in scenario.rsus) if cfg.mode is RunMode.RSU else ()
        self.expected = frozenset(self.vehicles + self.rsus)
        self.shell.actors = self.expected | {self.node}
        self.max_sim_s = cfg.max_sim_s if cfg.max_sim_s is not None else scenario.params.max_sim_s
        self.may_crash = frozenset(cfg.expect_crash)
        unknown = self.may_crash - self.expected
        if unknown:
            problem = f"not actors of this run: {', '.join(sorted(unknown))}"
            raise ConfigError([("expect_crash", problem)])
        rules = MonitorRules(
            run_id=cfg.run_id or new_run_id(self.time_fn),
            vehicles=self.vehicles,
            rsus=self.rsus,
            max_sim_s=self.max_sim_s,
            speed=cfg.time.speed,
            epoch_unix=cfg.time.epoch_unix,
            start_delay_s=cfg.start_delay_s,
            wait_actors_s=cfg.wait_actors_s,
            ack_timeout_s=cfg.ack_timeout_s,
            stats_wait_s=cfg.stats_wait_s,
            may_crash=self.may_crash,
            trace=cfg.trace,
            start_times=scenario.draw_start_times(cfg.seed),
        )
        try:
            self.core = MonitorCore(scenario, rules)
        except ValueError as exc:
            raise ConfigError([("scenario", str(exc))]) from None
        self.book = StatsBook(self.expected)
        self.reports = self.book.reports
        self.earlier_reports = self.book.earlier
        """Per node, the latest report of each earlier incarnation (see ``boot``)."""
        log_path = cfg.step_log
        if log_path is None and cfg.json_out is not None:
            log_path = step_log_path(cfg.json_out)
        self.step_log_path = log_path
        self.step_log: StepLog | None = None
        self.start: StartRun | None = None
        self.result: RunResult | None = None
        self.exit_code = 0
        self.veto: str | None = None
        """Why a run the core saw through still failed (:meth:`unheard_rsus`)."""
        self._start_payload = b""
        self.tokens: set[str] = set()
        """Actors whose liveliness token is up."""
        self.heard: set[str] = set()
        """Actors a signed stats report came from since their token appeared (issue 13:
        with credentials, presence needs both; :meth:`_present`)."""
        self._wake = asyncio.Event()
        self._halt_reason = "stopped by a signal"

    # ------------------------------------------------------------------ the core's state

    @property
    def failure(self) -> str | None:
        """Why the run failed, if it did."""
        return self.core.failure or self.veto

    def presence(self) -> list[str]:
        """Per expected actor not yet present, which half of presence it lacks (a run that
        never started: is the daemon unreachable, or unable to sign?)."""
        out = []
        for node in sorted(self.expected):
            if node not in self.tokens:
                out.append(f"{node}: no liveliness token (not running, or not connected)")
            elif self.shell.plumbing_auth is not None and node not in self.heard:
                out.append(f"{node}: liveliness token up, no signed stats report since")
        return out

    def unheard_rsus(self) -> list[str]:
        """RSUs of this ``rsu``-mode run that no car reported hearing (``rsus_heard`` in
        the cars' stats, ``services.daemons.vehicle``).

        Issue 13: a liveliness token and forged stats for ``rsu1`` made the monitor run
        an rsu-mode run with no RSU at all and report success. Signed stats refuse the
        forgery; this check also holds without signatures (``--insecure``) and when an
        RSU's stats are genuine but nothing it sent reached a car. Decision: such a run
        fails (an rsu-mode result without an RSU would be a wrong result, not a
        degraded one); an RSU that may crash (``expect_crash``) is not required, and
        unless some car reports ``rsus_heard`` and received V2X at all (a car loop too
        overloaded to receive anything hears nobody) there is nothing to check."""
        heard: set[str] = set()
        counted = False
        for vid in self.vehicles:
            report = self.reports.get(vid)
            if report is None:
                continue
            got = report.snapshot.get("rsus_heard")
            if isinstance(got, Mapping):
                heard.update(k for k, n in got.items() if isinstance(n, int) and n > 0)
                counted = counted or _v2x_totals(report.snapshot)["msgs_rx"] > 0
        if not counted:  # no car that counts and heard V2X at all (test doubles, a loop
            return []  # too overloaded to receive anything): nothing to check
        return [r for r in self.rsus if r not in heard and r not in self.may_crash]

    @property
    def done_reason(self) -> str | None:
        return self.core.done_reason

    @property
    def end_wall(self) -> float | None:
        return self.core.end_wall

    @property
    def crashes(self) -> list[dict[str, Any]]:
        return self.core.crashes

    @property
    def next_step(self) -> int:
        return self.core.truth.next_step

    @property
    def last_t(self) -> float | None:
        return self.core.truth.last_t

    @property
    def truth_gaps(self) -> int:
        return self.core.truth.gaps

    @property
    def truth_late(self) -> int:
        return self.core.truth.late

    def metrics(self) -> RunMetrics:
        """The run's metrics so far, from same-step truth only."""
        return self.core.truth.metrics()

    @property
    def trace_rows(self) -> list[TraceRow]:
        return self.core.truth.trace_rows

    # ------------------------------------------------------------------ DaemonBase

    def subscribe(self) -> None:
        p = self.prefix
        self.shell.subscribe_plumbing(all_truths(prefix=p), self._on_truth)
        self.shell.subscribe_plumbing(keys.all_stats(prefix=p), self._on_stats)
        self.shell.watch_alive(self._on_alive)

    def ready_message(self) -> str:
        return f"monitor ready: {self.mode} mode, waiting for {', '.join(sorted(self.expected))}"

    def halt(self, reason: str) -> None:
        self._halt_reason = reason
        self._wake.set()

    async def work(self, halt: asyncio.Event) -> None:
        """Poll the core after every input and at its deadlines; act on what it says."""
        cfg = self.config
        core = self.core
        try:
            while True:
                if halt.is_set():
                    core.abort(self._halt_reason)
                actions = core.poll(self.time_fn())
                if actions.start:
                    self._send_start()
                if actions.stop is not None:
                    self._send_stop(actions.stop)
                if actions.over:
                    unheard = self.unheard_rsus() if core.failure is None else []
                    if unheard and self.start is not None:
                        self.veto = (
                            f"no car heard {', '.join(unheard)}: an rsu-mode run without "
                            "its RSU (forged liveliness or stats?)"
                        )
                    break
                self._wake.clear()
                deadline = core.next_deadline()
                wait = MAX_WAIT_S if deadline is None else deadline - self.time_fn()
                events = (self._wake,) if halt.is_set() else (self._wake, halt)
                await wait_any(*events, timeout=min(max(wait, 0.0), MAX_WAIT_S))
        finally:
            if self.failure is not None:
                self.exit_code = 1
                log.error("run failed: %s", self.failure)
                if self.start is None:
                    for line in self.presence():
                        log.error("presence: %s", line)
        try:
            if self.start is None:
                return
            self.result = self.build_result()
            if cfg.json_out is not None:
                cfg.json_out.parent.mkdir(parents=True, exist_ok=True)
                cfg.json_out.write_text(self.result.to_json() + "\n")
            if self.step_log is not None:
                self.step_log.end(
                    self.time_fn(), self.done_reason, self.failure, self.core.truth.next_step
                )
        finally:
            if self.step_log is not None:
                self.step_log.close()

    def _send_start(self) -> None:
        """Publish the start message: made and logged the first time, then repeated."""
        if self.start is None:
            cfg = self.config
            epoch = self.core.epoch
            if epoch is None:  # the core says start only once it set the epoch
                raise RuntimeError("the run started without an epoch")
            start = StartRun(
                run_id=self.core.rules.run_id,
                scenario=self.scenario.name,
                mode=self.mode,
                policy=cfg.policy,
                seed=cfg.seed,
                start_times=self.scenario.draw_start_times(cfg.seed),
                epoch_unix=epoch,
                speed=cfg.time.speed,
                max_sim_s=self.max_sim_s,
                monitor=self.node,
                vehicles=self.vehicles,
                rsus=self.rsus,
            )
            self.start = start
            self._start_payload = encode_control(start)
            if self.step_log_path is not None:
                self.step_log = StepLog(self.step_log_path)
                self.step_log.start(
                    start, origin(cfg.scenario).scenario_file, sorted(self.may_crash)
                )
            if cfg.start_file is not None:
                _write_start_file(cfg.start_file, start)
            log.info(
                "starting run %s (%s, policy %s, seed %d, speed %g) in %.2f s",
                start.run_id,
                start.mode,
                start.policy,
                start.seed,
                start.speed,
                epoch - self.time_fn(),
            )
        self.shell.publish_plumbing(control_key(prefix=self.prefix), self._start_payload)

    def _send_stop(self, reason: str) -> None:
        start = self.start
        if start is None:
            return
        sim_s = self.last_t or 0.0
        stop_msg = StopRun(start.run_id, reason[:500], sim_s)
        self.shell.publish_plumbing(control_key(prefix=self.prefix), encode_control(stop_msg))
        log.info("run %s over at %.2f s: %s", start.run_id, sim_s, reason)

    # ------------------------------------------------------------------ inputs

    def _on_truth(self, key: str, payload: bytes) -> None:
        report = self.shell.run_truth(key, payload, self.start)
        if report is not None:
            now = self.time_fn()
            if self.core.on_truth(now, report) and self.step_log is not None:
                self.step_log.truth(now, report)
            if self.core.done_reason is not None:  # else nothing for the loop to do yet
                self._wake.set()

    def _on_stats(self, key: str, payload: bytes) -> None:
        report = decode_stats(payload)
        if key != keys.stats(report.node, prefix=self.prefix):
            raise PlumbingError(f"stats of {report.node!r} on {key}")
        if report.node in self.expected and report.node not in self.heard:
            # signed by the node's own key when we have credentials (PlumbingAuth.open)
            self.heard.add(report.node)
            self._present(report.node)
        start = self.start
        if start is None or report.run_id != start.run_id or report.node not in self.expected:
            return
        try:
            merge_snapshots([report.snapshot])
        except ValueError as exc:
            raise PlumbingError(f"stats of {report.node}: {exc}") from None
        if self.book.add(report) and self.step_log is not None:
            self.step_log.stats(self.time_fn(), report)
        self.core.on_stats(report.node, self.reports[report.node].final)
        self._wake.set()

    def _on_alive(self, node: str, alive: bool) -> None:
        if alive:
            self.tokens.add(node)
            self._present(node)
            return
        self.tokens.discard(node)
        self.heard.discard(node)  # a token that comes back must say hello again
        self.core.on_alive(self.time_fn(), node, False)
        self._wake.set()

    def _present(self, node: str) -> None:
        """Tell the core ``node`` is present once it is (module docstring, step 1): its
        token is up and, with credentials, a signed stats report of it came since."""
        if node not in self.tokens:
            return
        signed = self.shell.plumbing_auth is not None
        if signed and node in self.expected and node not in self.heard:
            log.debug("%s: liveliness token up, waiting for its signed stats", node)
            return
        self.core.on_alive(self.time_fn(), node, True)
        self._wake.set()

    # ------------------------------------------------------------------ result

    def build_result(self) -> RunResult:
        """The run result of DESIGN.md with ``network``; partial (``error``) after a failure."""
        start = self.start
        if start is None:
            raise RuntimeError("no run was started")
        end = self.end_wall if self.end_wall is not None else self.time_fn()
        return assemble_result(
            self.scenario,
            origin(self.config.scenario),
            start,
            self.core.truth,
            self.book,
            wall_s=max(0.0, end - start.epoch_unix),
            end_reason=self.done_reason or self.failure,
            error=self.failure,
            may_crash=self.may_crash,
            crashes=self.crashes,
            trace=self.config.trace,
        )


class StatsBook:
    """The stats reports of one run that count: per expected node the latest (the final
    one once it came) and the latest of each earlier incarnation (another ``boot``)."""

    def __init__(self, expected: frozenset[str]) -> None:
        self.expected = expected
        self.reports: dict[str, StatsReport] = {}
        self.earlier: dict[str, list[StatsReport]] = {}

    def add(self, report: StatsReport) -> bool:
        """Take a (validated) report of the run; whether it was kept."""
        prev = self.reports.get(report.node)
        boot = report.snapshot.get("boot")
        prev_boot = None if prev is None else prev.snapshot.get("boot")
        if prev is not None and None not in (boot, prev_boot) and prev_boot != boot:
            # A restarted daemon: keep what its earlier incarnation counted.
            self.earlier.setdefault(report.node, []).append(prev)
            prev = None
        if prev is None or not prev.final:
            self.reports[report.node] = report
            return True
        return False

    def snapshots(self) -> list[Mapping[str, Any]]:
        """The latest snapshot of every incarnation of every expected node."""
        out = [r.snapshot for n, r in sorted(self.reports.items()) if n in self.expected]
        out += [
            r.snapshot
            for n, reports in sorted(self.earlier.items())
            if n in self.expected
            for r in reports
        ]
        return out

    def late_ticks(self) -> dict[str, int]:
        """Per node that reported, its ``late_ticks`` summed over its incarnations."""
        out: dict[str, int] = {}
        for node, report in sorted(self.reports.items()):
            if node in self.expected:
                reports = [report, *self.earlier.get(node, [])]
                out[node] = sum(_count(r.snapshot.get("late_ticks")) for r in reports)
        return out


def _count(value: object) -> int:
    """A non-negative int counter from a peer's snapshot (anything else counts 0)."""
    if isinstance(value, int) and not isinstance(value, bool) and value >= 0:
        return value
    return 0


def assemble_result(
    scenario: Scenario,
    scenario_origin: Origin,
    start: StartRun,
    truth: TruthSteps,
    book: StatsBook,
    *,
    wall_s: float,
    end_reason: str | None,
    error: str | None,
    may_crash: frozenset[str] = frozenset(),
    crashes: list[dict[str, Any]] | None = None,
    trace: bool = False,
    late_ticks: Mapping[str, int] | None = None,
    rebuilt_from: str | None = None,
) -> RunResult:
    """A daemon run's result from the core's truth table and the kept stats reports (the
    monitor at the end of a run, and :func:`rebuild_result` from a step log).

    ``late_ticks`` (per node) raise what the stats say (an actor's own log may know
    more than its last report that arrived). ``degraded``: a truth gap or a late tick.
    """
    sim_s = truth.last_t or 0.0
    vehicles = start.vehicles
    network = network_summary(
        book.snapshots(),
        len(vehicles),
        len(start.rsus),
        sim_s,
        truth.expected_receivers(len(start.rsus)),
    )
    late = book.late_ticks()
    for node, n in (late_ticks or {}).items():
        if node in book.expected:
            late[node] = max(late.get(node, 0), n)
    gaps = truth.truth_gaps()
    extra: dict[str, Any] = {
        "run_id": start.run_id,
        "speed": start.speed,
        "end_reason": end_reason,
        "truth": {"steps": truth.next_step, "gaps": sum(gaps.values()), "late": truth.late},
        "final_stats": sorted(n for n, r in book.reports.items() if r.final),
        "network": network,
        "epoch_unix": start.epoch_unix,
        "actors": {
            n: _actor_summary(r, book.earlier.get(n, []))
            for n, r in sorted(book.reports.items())
            if n in book.expected
        },
        "degraded": any(gaps.values()) or any(late.values()),
        "truth_gaps": gaps,
        "late_ticks": late,
    }
    if may_crash:
        extra["expect_crash"] = sorted(may_crash)
        extra["crashes"] = list(crashes or [])
    if trace:
        extra["trace_fields"] = list(TRACE_FIELDS)
        extra["trace"] = [list(row) for row in truth.trace_rows]
    if error is not None:
        extra["error"] = error
    if rebuilt_from is not None:
        extra["rebuilt_from"] = rebuilt_from
    metrics = truth.metrics()
    extra["summary"] = run_summary(metrics, sim_s)
    return run_result(
        metrics,
        mode=start.mode,
        policy=start.policy if start.mode is RunMode.RSU else None,
        seed=start.seed,
        sim_s=sim_s,
        wall_s=wall_s,
        scenario=scenario.name,
        start_times=dict(start.start_times),
        harness="daemons",
        provenance=provenance(
            scenario, scenario_origin, ChannelParams(kind="zenoh"), start.mode, start.policy
        ),
        **extra,
    )


_LATE_LINE: Final = re.compile(r"run (\S+) ticks: late_ticks=(\d+)")
"""The line an actor logs at the end of a run (``services.edge.shell.DaemonShell.end_run``)."""


def logged_late_ticks(run_dir: Path, run_id: str) -> dict[str, int]:
    """Per node, the ``late_ticks`` its log ``<run_dir>/<node>.log`` reported for ``run_id``
    (the largest, over incarnations: a restarted daemon appends to the same log)."""
    out: dict[str, int] = {}
    for path in sorted(run_dir.glob("*.log")):
        try:
            text = path.read_text(encoding="utf-8", errors="replace")
        except OSError:
            continue
        for m in _LATE_LINE.finditer(text):
            if m.group(1) == run_id:
                out[path.stem] = out.get(path.stem, 0) + int(m.group(2))
    return out


def rebuild_result(run_dir: Path, step_log: Path | None = None) -> RunResult:
    """A run's result rebuilt from what is in ``run_dir``: the monitor's step log
    (``step_log``, default the one ``*.steps.jsonl`` there, ``result.steps.jsonl`` first)
    replayed through the monitor's core, the stats reports it kept, and the late ticks
    the actors logged. Partial (``error``) unless the log has the monitor's ``end``.

    Raises ``StepLogError`` (a ``ValueError``) when there is no usable step log or
    its scenario cannot be loaded.
    """
    path = step_log if step_log is not None else _find_step_log(run_dir)
    record = read_step_log(path)
    head = record.start
    try:
        start = StartRun(
            run_id=str(head["run_id"]),
            scenario=str(head["scenario"]),
            mode=RunMode(head["mode"]),
            policy=Policy(head["policy"]),
            seed=int(head["seed"]),
            start_times={str(k): float(v) for k, v in dict(head["start_times"]).items()},
            epoch_unix=float(head["epoch_unix"]),
            speed=float(head["speed"]),
            max_sim_s=float(head["max_sim_s"]),
            monitor="monitor",
            vehicles=tuple(str(v) for v in head["vehicles"]),
            rsus=tuple(str(r) for r in head["rsus"]),
        )
    except (KeyError, TypeError, ValueError) as exc:
        raise StepLogError(f"{path}: bad start line ({exc})") from None
    where = head.get("scenario_file") or start.scenario
    try:
        scenario = load_scenario(where)
    except ScenarioError as exc:
        raise StepLogError(f"{path}: scenario {where}: {exc}") from None
    truth = TruthSteps(
        scenario,
        start.vehicles,
        speed=start.speed,
        max_sim_s=start.max_sim_s,
        start_times=start.start_times,
    )
    book = StatsBook(frozenset(start.vehicles + start.rsus))
    last_wall = start.epoch_unix
    for wall, event in record.events:
        last_wall = max(last_wall, wall)
        if isinstance(event, StatsReport):
            book.add(event)
            continue
        run_t = (wall - start.epoch_unix) * start.speed
        truth.advance(run_t)  # the steps the monitor closed at its deadlines meanwhile
        truth.on_report(run_t, event)
    end = record.end
    steps = None if end is None else end.get("steps")
    truth.close(steps if isinstance(steps, int) and steps >= 0 else None)
    if end is not None:
        error = end.get("error")
        reason = end.get("reason") or error
    else:
        error = (
            f"the monitor ended before the run was over (no end in {path.name}); "
            "partial result rebuilt from its step log"
        )
        reason = error
    return assemble_result(
        scenario,
        origin(where),
        start,
        truth,
        book,
        wall_s=max(0.0, last_wall - start.epoch_unix),
        end_reason=None if reason is None else str(reason),
        error=None if error is None else str(error),
        may_crash=frozenset(str(n) for n in head.get("expect_crash") or ()),
        trace=True,
        late_ticks=logged_late_ticks(run_dir, start.run_id),
        rebuilt_from=str(path),
    )


def _find_step_log(run_dir: Path) -> Path:
    preferred = run_dir / "result.steps.jsonl"
    if preferred.is_file():
        return preferred
    found = sorted(run_dir.glob("*.steps.jsonl"))
    if len(found) != 1:
        what = "no" if not found else f"{len(found)}"
        raise StepLogError(f"{what} step log (*.steps.jsonl) in {run_dir}")
    return found[0]


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


# --------------------------------------------------------------------------- CLI


def configure(parser: argparse.ArgumentParser) -> None:
    """Options of ``crosspath monitor``."""
    group = add_daemon_arguments(parser, "run")
    group.add_argument("--mode", choices=[m.value for m in RunMode], help="default rsu")
    group.add_argument("--policy", choices=[p.value for p in Policy], help="default paper")
    fields = MonitorConfig.model_fields  # the defaults, unless --config, env or --set say else
    group.add_argument(
        "--seed",
        type=non_negative_int,
        metavar="N",
        help=f"seed of the start times (default {fields['seed'].default})",
    )
    group.add_argument(
        "--speed",
        type=run_speed,
        metavar="X",
        help="run seconds per wall second, up to 1000 (default 1)",
    )
    group.add_argument(
        "--max-sim-s",
        type=positive_float,
        metavar="S",
        help="run time limit [s] (default: the scenario's)",
    )
    group.add_argument("--json", type=output_file, metavar="OUT", help="write the run result here")
    group.add_argument("--run-id", metavar="ID", help="id of the run (default: generated)")
    group.add_argument(
        "--start-delay",
        type=non_negative_float,
        metavar="S",
        help=f"wall s before run time 0 (default {fields['start_delay_s'].default:g})",
    )
    group.add_argument(
        "--wait-actors",
        type=positive_float,
        metavar="S",
        help=f"wall s to wait for actors (default {fields['wait_actors_s'].default:g})",
    )
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
        "--step-log",
        type=output_file,
        metavar="FILE",
        help="append every kept truth/stats report here (default: <json stem>.steps.jsonl)",
    )
    group.add_argument(
        "--start-file",
        type=output_file,
        metavar="FILE",
        help="write run id and epoch here at the start",
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
    "step_log": "step_log",
}


command = DaemonCommand("monitor", MonitorConfig, MonitorService, _FLAGS)
load_monitor = command.load
"""Config and scenario from the command line; :class:`ConfigError` naming the field."""


def run(args: argparse.Namespace) -> int:
    """Run one monitored run; print its result; 0 when it completed, 1 when it failed."""
    from services.sim.results import format_summary

    code, service = command.serve(args)
    if service is None:
        return code
    if service.result is not None:
        sys.stdout.write(format_summary(service.result) + "\n")
        sys.stdout.write(format_network(service.result.network) + "\n")
        degraded = format_degraded(service.result)
        if degraded is not None:
            sys.stdout.write(degraded + "\n")
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
