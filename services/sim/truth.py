"""The monitor's pure core: truth-step assembly and the run's control decisions.

Sans-IO like the RSU core (``services.rsu.core``): ``now`` and inputs in,
actions and the next deadline out; no clock reads, no asyncio, no Zenoh. The
monitor daemon (``services.daemons.monitor``) is a thin shell over it: it turns
what arrives on the network into calls here, and what comes out into messages.

:class:`TruthSteps` gathers the cars' ground-truth reports of one run into a table
of physics steps (step -> car -> report) and decides, step by step in order,
when a step is *closed*:

- a step is closed as soon as every car of the run reported it;
- a step still missing a car :data:`TRUTH_WAIT_S` wall seconds after its time,
  or once another car is :data:`AHEAD_S` run seconds ahead, is closed without
  that car; nothing is closed before any car has reported at all;
- a report for a step already closed is ``late``: counted, and still kept in
  the table (it is that step's truth); a second report of a car for a step
  replaces the first (``duplicate``);
- what a peer sent wrong is counted and dropped, never raised: a car that is not
  in the run (``unknown_vehicle``), a step more than :data:`FUTURE_TOLERANCE_S`
  wall seconds ahead of now (``future``: it would otherwise force every step up
  to it to be closed at once);
- the run is over (``done_reason``) when a closed step reaches ``max_sim_s``, when
  every car has left the world, or when every car stands at its goal
  (``services.sim.car.all_at_goal``, all cars present).

Insertion and removal (issue 12), as the in-process harness (``services.sim.harness``):
a car is in the world only between its insertion and its removal, and each report
says where it is (``presence``): ``waiting`` (arrived at its start time but its entry
is not clear yet: it is out of the world, the report only keeps the steps closing),
``in``, or ``left`` (it stands at its goal: that step's truth is its last, then it
sends no more). So a car is *expected* at step ``k`` from its arrival step (its start
time, given as ``start_times``; without them every car is expected from step 0) up to
its ``left`` step; a step nobody is expected at closes once run time reaches it. The
replay records only ``in`` and ``left`` reports, and calls
``MetricsRecorder.inserted`` at a car's first one, so a daemon run's ``delay_s``,
``insertion_delay_s`` and summary are computed by the same code as the harness's.

Safety metrics never mix steps (issue 16): :meth:`TruthSteps.metrics` replays
the table of the closed steps into a fresh ``MetricsRecorder``, each step with
exactly the cars whose truth *of that step* is in the table. A car missing at
a closed step is never filled in from an older step: the step is recorded
without it (its pairs are not measured there) and counted in
:meth:`TruthSteps.truth_gaps` (per car), which makes the run ``degraded``. A
report that arrives late, after its step was closed, is still that step's
truth: it is in the replay, so an overlap at that step is reported as a
collision once the report arrives (before the result is built); only a report
that never arrives is a gap. The replay is what makes the result, its
``trace`` and ``crosspath results rebuild`` agree exactly.

:class:`MonitorCore` decides the rest of a run's life, in phases:

1. ``waiting``: until every actor's liveliness token is present
   (``wait_actors_s`` from the first :meth:`MonitorCore.poll`, else the run fails
   naming the missing ones);
2. ``running``: the run starts (epoch ``epoch_unix``, or now + ``start_delay_s``);
   the start is repeated every :data:`START_REPEAT_S` until every actor
   acknowledged it (for the whole run when ``may_crash`` names nodes, so a
   restarted daemon can join); the run fails when an actor has not acknowledged
   ``ack_timeout_s`` after the epoch, when an actor (not in ``may_crash``) loses
   its liveliness, or when the monitor is stopped (:meth:`MonitorCore.abort`);
   liveliness changes of ``may_crash`` nodes are listed in ``crashes``;
3. ``ending``: the stop message goes out; waits up to ``stats_wait_s`` for every
   actor's final stats report (not for a lost actor's, nor for a crashed node's
   that is not back); no step is closed any more, late truth of closed steps is
   still taken;
4. ``over``: the shell builds the result (when the run started).

Times: ``now`` is wall-clock time in Unix seconds (what the daemons' run clock
reads, ``services.edge.clock``); run time is ``(now - epoch) * speed`` [s].
"""

from __future__ import annotations

import collections
import enum
import logging
import math
from collections.abc import Iterable, Iterator, Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any, Final, Protocol

from services.model.kinematics import TruthState
from services.model.scenario import Scenario
from services.sim.car import all_at_goal
from services.sim.metrics import MetricsRecorder, RunMetrics

__all__ = [
    "AHEAD_S",
    "FUTURE_TOLERANCE_S",
    "START_REPEAT_S",
    "TRACE_FIELDS",
    "TRUTH_WAIT_S",
    "Actions",
    "MonitorCore",
    "MonitorRules",
    "Phase",
    "TraceRow",
    "TruthSample",
    "TruthSteps",
    "arrival_step",
    "replay_metrics",
    "trace_row",
]

log = logging.getLogger("crosspath.monitor")

START_REPEAT_S: Final = 0.25
"""Wall seconds between repetitions of the start message until every actor acknowledged."""

TRUTH_WAIT_S: Final = 1.0
"""Wall seconds a step waits for a missing car's ground truth before it is recorded."""

AHEAD_S: Final = 1.0
"""Run seconds another car may be ahead of a step still missing a car before it is recorded."""

FUTURE_TOLERANCE_S: Final = 1.0
"""A truth report dated more than this many wall seconds after now is dropped (``future``)."""

TRACE_FIELDS: Final = ("t", "vehicle", "x", "y", "s", "speed", "mode", "reason")
"""Columns of the optional ``trace`` of the result (s, m, m, m, m/s, mode name, reason)."""

TraceRow = tuple[float, str, float, float, float, float, str, str]
"""One row of the trace, fields :data:`TRACE_FIELDS`."""


class TruthSample(Protocol):
    """One car's ground truth at one physics step (``services.edge.plumbing.TruthReport``)."""

    @property
    def vehicle(self) -> str: ...

    @property
    def step(self) -> int: ...

    @property
    def state(self) -> TruthState: ...

    @property
    def mode(self) -> str: ...

    @property
    def reason(self) -> str: ...


def arrival_step(start_time: float, dt: float) -> int:
    """The first physics step ``k`` whose run time ``k * dt`` [s] reaches ``start_time``
    [s] (1e-9 s slack, as the harness's insertion test)."""
    k = max(0, math.ceil(start_time / dt - 1e-6))
    while k > 0 and (k - 1) * dt + 1e-9 >= start_time:
        k -= 1
    while k * dt + 1e-9 < start_time:
        k += 1
    return k


def presence_of(r: TruthSample) -> str:
    """A report's ``presence`` (``TruthReport.presence``); a sample without one is ``in``."""
    value = getattr(r, "presence", "in")
    return value if isinstance(value, str) else "in"


def _present(r: TruthSample) -> bool:
    """The report is truth of a car in the world (``in``, or ``left`` at that step)."""
    return presence_of(r) != "waiting"


def _positive(name: str, value: float, *, zero: bool = False) -> None:
    ok = math.isfinite(value) and (value >= 0.0 if zero else value > 0.0)
    if not ok:
        raise ValueError(f"{name} must be a finite number {'>=' if zero else '>'} 0, got {value}")


class TruthSteps:
    """One run's truth reports, as a table of steps closed in order (module docstring).

    ``now`` arguments are run time [s]; ``speed`` (run seconds per wall second)
    converts the wall-second waits.
    """

    def __init__(
        self,
        scenario: Scenario,
        vehicles: Sequence[str],
        *,
        speed: float,
        max_sim_s: float,
        trace: bool = False,
        wait_s: float = TRUTH_WAIT_S,
        start_times: Mapping[str, float] | None = None,
    ) -> None:
        if not vehicles or len(set(vehicles)) != len(vehicles):
            raise ValueError(f"need distinct vehicles, got {list(vehicles)}")
        _positive("speed", speed)
        _positive("max_sim_s", max_sim_s)
        _positive("wait_s", wait_s, zero=True)
        self.scenario = scenario
        self.vehicles = tuple(vehicles)
        self.speed = speed
        self.max_sim_s = max_sim_s
        self.trace = trace
        self.wait_s = wait_s
        self.dt = 1.0 / scenario.params.physics_hz
        self.counters: collections.Counter[str] = collections.Counter()
        """``gaps`` (missing when closed), ``late``, ``duplicate``, ``future``,
        ``unknown_vehicle``, ``out_of_world`` (a step before the car's arrival or after
        its ``left`` report)."""
        self.next_step = 0
        """The first step not closed yet."""
        self.last_t: float | None = None
        """Run time of the last closed step [s]."""
        self.done_reason: str | None = None
        self.closed = False
        """No step is closed any more (:meth:`close`); late reports are still kept."""
        self._known = frozenset(self.vehicles)
        self._table: dict[int, dict[str, TruthSample]] = {}
        self._any_report = False
        self._max_step_seen = -1
        self._ahead_steps = max(1, round(AHEAD_S / self.dt))
        self.start_times = None if start_times is None else dict(start_times)
        """Each car's arrival [run s]: it is expected from then (None: from step 0)."""
        st = self.start_times or {}
        self._arrival = {v: arrival_step(float(st.get(v, 0.0)), self.dt) for v in self.vehicles}
        self._left: dict[str, int] = {}
        """Per car, the step of its ``left`` report (its last)."""

    def expected(self, k: int) -> list[str]:
        """The cars whose report step ``k`` waits for: arrived by then, not left before."""
        return [
            v
            for v in self.vehicles
            if self._arrival[v] <= k and (v not in self._left or k <= self._left[v])
        ]

    @property
    def gaps(self) -> int:
        """Car reports still missing at their step (the sum of :meth:`truth_gaps`)."""
        return sum(self.truth_gaps().values())

    @property
    def late(self) -> int:
        """Reports that came after their step was closed (kept: they are its truth)."""
        return self.counters["late"]

    def on_report(self, now: float, report: TruthSample) -> bool:
        """Take one car's report at run time ``now``; closes every step it completes.
        Whether the report was kept (the monitor's step log records exactly those)."""
        vid = report.vehicle
        if vid not in self._known:
            self.counters["unknown_vehicle"] += 1
            return False
        step = report.step
        if step < 0 or (step * self.dt - now) / self.speed > FUTURE_TOLERANCE_S:
            self.counters["future"] += 1
            return False
        if step >= self.next_step and (self.closed or self.done_reason is not None):
            return False  # after the end of the run
        if step < self._arrival[vid] or (vid in self._left and step > self._left[vid]):
            self.counters["out_of_world"] += 1  # before its arrival or after it left
            return False
        reports = self._table.setdefault(step, {})
        if vid in reports:
            if presence_of(report) == "left" and presence_of(reports[vid]) == "left":
                return False  # a car repeats its "left" report (the daemon's): nothing new
            self.counters["duplicate"] += 1
        reports[vid] = report
        self._any_report = True
        if presence_of(report) == "left":
            self._left[vid] = min(step, self._left.get(vid, step))
        if step < self.next_step:
            self.counters["late"] += 1
            return True
        self._max_step_seen = max(self._max_step_seen, step)
        self.advance(now)
        return True

    def close(self, steps: int | None = None) -> None:
        """The run is over (or failed): close no more steps; late reports of the closed
        ones are still taken. ``steps``: exactly that many steps count as closed (a
        rebuild from a step log ends where the monitor ended)."""
        self.closed = True
        if steps is not None:
            if steps < 0:
                raise ValueError(f"steps must be >= 0, got {steps}")
            self.next_step = steps
            self.last_t = (steps - 1) * self.dt if steps > 0 else None
        for k in [k for k in self._table if k >= self.next_step]:
            del self._table[k]

    def advance(self, now: float) -> None:
        """Close every step that is complete, or waited for long enough, in order."""
        while self.done_reason is None and not self.closed:
            k = self.next_step
            reports = self._table.get(k, {})
            need = self.expected(k)
            if not need:
                if now < k * self.dt:  # nobody in the world: close it when its time comes
                    return
            elif any(v not in reports for v in need):
                overdue = now >= self._overdue_at(k)
                ahead = self._max_step_seen >= k + self._ahead_steps
                if not (overdue or ahead) or not self._any_report:
                    return
            self._close_step(k, reports)
            self.next_step = k + 1

    def _overdue_at(self, k: int) -> float:
        return k * self.dt + self.wait_s * self.speed

    def next_deadline(self) -> float | None:
        """Run time [s] at which the next step is closed even if incomplete; None when
        over or when no car has reported yet (a report comes through :meth:`on_report`)."""
        if self.done_reason is not None or self.closed:
            return None
        k = self.next_step
        if not self.expected(k):
            return k * self.dt
        if not self._any_report:
            return None
        return self._overdue_at(k)

    def _close_step(self, k: int, reports: Mapping[str, TruthSample]) -> None:
        t = k * self.dt
        self.counters["gaps"] += sum(1 for v in self.expected(k) if v not in reports)
        self.last_t = t
        states = [r.state for r in reports.values() if _present(r)]
        if t >= self.max_sim_s:
            self.done_reason = f"max_sim_s ({self.max_sim_s:g} s) reached"
        elif len(self._left) == len(self.vehicles) and max(self._left.values()) <= k:
            self.done_reason = "every car has left at its goal"
        elif len(states) == len(self.vehicles) and all_at_goal(self.scenario, states):
            self.done_reason = "every car stands at its goal"

    # -- what the result is made of ------------------------------------------------

    def steps(self) -> Iterator[tuple[int, list[TruthSample]]]:
        """Every closed step with the reports of that very step of the cars in the world
        (``waiting`` ones left out), cars in run order."""
        for k in range(self.next_step):
            reports = self._table.get(k, {})
            yield k, [reports[v] for v in self.vehicles if v in reports and _present(reports[v])]

    def truth_gaps(self) -> dict[str, int]:
        """Per car, the closed steps it was expected at whose report is missing (never
        filled in)."""
        gaps = dict.fromkeys(self.vehicles, 0)
        for k in range(self.next_step):
            reports = self._table.get(k, {})
            for vid in self.expected(k):
                if vid not in reports:
                    gaps[vid] += 1
        return gaps

    def expected_receivers(self, n_rsus: int) -> dict[str, float]:
        """How many nodes should receive each datagram of a stream, with cars in the world
        only part of the run (a car listens from its insertion to its removal): a future
        path reaches the other cars in the world when it is sent, averaged over the car
        steps of the run (sum n(n - 1) / sum n over closed steps with n cars in the world),
        and every RSU; a beacon the cars in the world, averaged over the closed steps; an
        autonomous path and a command one node. With every car in the world all run long
        this is ``services.daemons.monitor.expected_receivers``."""
        counts = [len(rows) for _k, rows in self.steps()]
        car_steps = sum(counts)
        fp = sum(n * (n - 1) for n in counts) / car_steps if car_steps else 0.0
        beacon = car_steps / len(counts) if counts else 0.0
        return {"fp": fp + n_rsus, "ap": 1.0, "cmd": 1.0, "beacon": beacon}

    @property
    def degraded(self) -> bool:
        """Some car's truth is missing at some closed step."""
        return any(self.truth_gaps().values())

    def metrics(self) -> RunMetrics:
        """The run's metrics from same-step truth only (see the module docstring)."""
        return replay_metrics(self.scenario, self.dt, self.steps(), self.start_times)

    @property
    def trace_rows(self) -> list[TraceRow]:
        """One row per closed step and car present (:data:`TRACE_FIELDS`)."""
        return [trace_row(k * self.dt, r) for k, rows in self.steps() for r in rows]


def trace_row(t: float, r: TruthSample) -> TraceRow:
    """One row of the trace: car ``r`` at run time ``t`` [s] (values rounded to mm)."""
    st = r.state
    return (
        round(t, 3),
        r.vehicle,
        round(st.x, 3),
        round(st.y, 3),
        round(st.s, 3),
        round(st.speed, 3),
        r.mode,
        r.reason,
    )


def replay_metrics(
    scenario: Scenario,
    dt: float,
    steps: Iterable[tuple[int, Sequence[TruthSample]]],
    start_times: Mapping[str, float] | None = None,
) -> RunMetrics:
    """Metrics of ``steps`` (step index, that step's reports) fed in order to a fresh
    ``MetricsRecorder`` at run time ``step * dt`` [s]; a step without any car is skipped.
    With ``start_times`` (arrivals [run s]) a car's first report is its insertion
    (``MetricsRecorder.inserted``: insertion and travel delay, as the harness)."""
    recorder = MetricsRecorder(scenario)
    seen: set[str] = set()
    for k, rows in steps:
        if start_times is not None:
            for r in rows:
                if r.vehicle not in seen:
                    seen.add(r.vehicle)
                    recorder.inserted(r.vehicle, float(start_times.get(r.vehicle, 0.0)), k * dt)
        if rows:
            recorder.record(
                k * dt,
                [r.state for r in rows],
                {r.vehicle: r.mode for r in rows},
                {r.vehicle: r.reason for r in rows},
            )
    return recorder.result()


class Phase(enum.Enum):
    """Where a monitored run is (see the module docstring)."""

    WAITING = "waiting"
    RUNNING = "running"
    ENDING = "ending"
    OVER = "over"


@dataclass(frozen=True, slots=True)
class MonitorRules:
    """What a monitored run is and how long each wait may last (wall seconds)."""

    run_id: str
    vehicles: tuple[str, ...]
    rsus: tuple[str, ...]
    max_sim_s: float
    speed: float = 1.0
    epoch_unix: float | None = None
    """Unix time of run time 0; None: ``start_delay_s`` after the start."""
    start_delay_s: float = 1.0
    wait_actors_s: float = 30.0
    ack_timeout_s: float = 5.0
    stats_wait_s: float = 3.0
    may_crash: frozenset[str] = field(default_factory=frozenset)
    trace: bool = False
    start_repeat_s: float = START_REPEAT_S
    truth_wait_s: float = TRUTH_WAIT_S
    start_times: Mapping[str, float] | None = None
    """Each car's arrival [run s] (``TruthSteps``); None: every car from step 0."""

    @property
    def expected(self) -> frozenset[str]:
        """Every actor of the run: the cars and the RSUs."""
        return frozenset(self.vehicles + self.rsus)


@dataclass(frozen=True, slots=True)
class Actions:
    """What the shell does after a :meth:`MonitorCore.poll`."""

    start: bool = False
    """Publish the start message (the first time, the run starts: read ``epoch``)."""
    stop: str | None = None
    """Publish the stop message with this reason (once)."""
    over: bool = False
    """The run is over: build the result when it started, then exit."""


class MonitorCore:
    """One monitored run's decisions (pure; see the module docstring)."""

    def __init__(self, scenario: Scenario, rules: MonitorRules) -> None:
        shared = set(rules.vehicles) & set(rules.rsus)
        if shared:
            raise ValueError(f"a vehicle and an RSU share an id: {sorted(shared)}")
        unknown = rules.may_crash - rules.expected
        if unknown:
            raise ValueError(f"may_crash names nodes that are not actors: {sorted(unknown)}")
        for name in ("wait_actors_s", "ack_timeout_s", "start_repeat_s"):
            _positive(name, getattr(rules, name))
        for name in ("start_delay_s", "stats_wait_s"):
            _positive(name, getattr(rules, name), zero=True)
        self.rules = rules
        self.expected = rules.expected
        self.truth = TruthSteps(
            scenario,
            rules.vehicles,
            speed=rules.speed,
            max_sim_s=rules.max_sim_s,
            trace=rules.trace,
            wait_s=rules.truth_wait_s,
            start_times=rules.start_times,
        )
        self.phase = Phase.WAITING
        self.alive: set[str] = set()
        self.acked: set[str] = set()
        self.finals: set[str] = set()
        self.epoch: float | None = None
        """Unix time of run time 0, once the run started."""
        self.failure: str | None = None
        self.crashes: list[dict[str, Any]] = []
        """Liveliness losses and returns of ``may_crash`` nodes during the run."""
        self.end_wall: float | None = None
        """When the stop went out (Unix s)."""
        self._waiting_since: float | None = None
        self._last_start = -math.inf
        self._abort: str | None = None

    # -- queries ---------------------------------------------------------------------

    @property
    def done_reason(self) -> str | None:
        """Why the run ended normally (``max_sim_s`` or every car at its goal)."""
        return self.truth.done_reason

    @property
    def started(self) -> bool:
        """The run has started (a result can be built)."""
        return self.epoch is not None

    def run_time(self, now: float) -> float:
        """Run time [s] at Unix time ``now``; 0 before the start."""
        return 0.0 if self.epoch is None else (now - self.epoch) * self.rules.speed

    def _running(self) -> bool:
        return self.phase is Phase.RUNNING and self.failure is None and self.done_reason is None

    def next_deadline(self) -> float | None:
        """Unix time at which :meth:`poll` next has work without new input; None: none."""
        rules = self.rules
        if self.phase is Phase.WAITING:
            since = self._waiting_since
            return None if since is None else since + rules.wait_actors_s
        if self.phase is Phase.ENDING:
            return None if self.end_wall is None else self.end_wall + rules.stats_wait_s
        if self.phase is Phase.OVER or self.epoch is None or not self._running():
            return None
        deadlines: list[float] = []
        unacked = self.expected - self.acked
        if unacked:
            deadlines.append(self.epoch + rules.ack_timeout_s)
        if unacked or rules.may_crash:
            deadlines.append(self._last_start + rules.start_repeat_s)
        step_at = self.truth.next_deadline()
        if step_at is not None:
            deadlines.append(self.epoch + step_at / rules.speed)
        return min(deadlines, default=None)

    # -- inputs ----------------------------------------------------------------------

    def on_alive(self, now: float, node: str, alive: bool) -> None:
        """A liveliness token appeared (``alive``) or disappeared."""
        running = self._running()
        if running and node in self.rules.may_crash and alive != (node in self.alive):
            t = round(self.run_time(now), 3)
            event = "back" if alive else "lost"
            self.crashes.append({"node": node, "event": event, "t_s": t})
            log.warning("%s %s at run time %s", node, "is back" if alive else "lost", t)
        if alive:
            self.alive.add(node)
            return
        self.alive.discard(node)
        if running and node in self.expected and node not in self.rules.may_crash:
            self.failure = (
                f"{node} lost: its liveliness token disappeared during the run "
                "(daemon crashed, was stopped or lost its connection)"
            )

    def on_stats(self, node: str, final: bool) -> None:
        """An actor's stats report of this run was kept; ``final``: the one it keeps is."""
        if node not in self.expected:
            return
        self.acked.add(node)
        if final:
            self.finals.add(node)
        else:
            self.finals.discard(node)

    def on_truth(self, now: float, report: TruthSample) -> bool:
        """A car's ground truth of this run; whether it was kept. While the run is
        running it may close steps; afterwards only late reports of closed steps are kept
        (they still count: see the module docstring)."""
        if self.epoch is None or self.phase not in (Phase.RUNNING, Phase.ENDING):
            return False
        if not self._running():
            self.truth.close()
        return self.truth.on_report(self.run_time(now), report)

    def abort(self, cause: str = "stopped by a signal") -> None:
        """The monitor has to stop (``cause``: a signal, an internal error): the run fails
        at the next poll, ``monitor <cause> before the run ...``."""
        if self._abort is None:
            self._abort = cause

    # -- decisions -------------------------------------------------------------------

    def poll(self, now: float) -> Actions:
        """Everything due at Unix time ``now``; call after every input and at deadlines."""
        if self.phase is Phase.WAITING:
            return self._poll_waiting(now)
        if self.phase is Phase.RUNNING:
            return self._poll_running(now)
        if self.phase is Phase.ENDING:
            return self._poll_ending(now)
        return Actions(over=True)

    def _poll_waiting(self, now: float) -> Actions:
        rules = self.rules
        if self._abort is not None:
            return self._fail_before_start(f"monitor {self._abort} before the run started")
        if self._waiting_since is None:
            self._waiting_since = now
        if self.expected <= self.alive:
            self.epoch = (
                rules.epoch_unix if rules.epoch_unix is not None else now + (rules.start_delay_s)
            )
            self.phase = Phase.RUNNING
            self._last_start = now
            return Actions(start=True)
        if now >= self._waiting_since + rules.wait_actors_s:
            missing = ", ".join(sorted(self.expected - self.alive))
            return self._fail_before_start(
                f"actors not present after {rules.wait_actors_s:g} s: {missing} "
                "(no liveliness token, or no signed stats report from it; are their "
                "daemons running and connected, with this run's credentials?)"
            )
        return Actions()

    def _fail_before_start(self, reason: str) -> Actions:
        self.failure = reason
        self.phase = Phase.OVER
        return Actions(over=True)

    def _poll_running(self, now: float) -> Actions:
        rules = self.rules
        epoch = self.epoch
        if epoch is None:  # cannot happen: the run started
            raise RuntimeError("running without an epoch")
        start = False
        if self._abort is not None and self._running():
            self.failure = f"monitor {self._abort} before the run was over"
        if self._running():
            unacked = self.expected - self.acked
            if unacked and now >= epoch + rules.ack_timeout_s:
                self.failure = (
                    f"no acknowledgement of run {rules.run_id} from "
                    f"{', '.join(sorted(unacked))} within {rules.ack_timeout_s:g} s of its start"
                )
            else:
                # With expected crashes the start is repeated all run long: a restarted
                # daemon joins the run in progress (the others ignore a start they have seen).
                repeat = unacked or rules.may_crash
                if repeat and now - self._last_start >= rules.start_repeat_s:
                    start = True
                    self._last_start = now
                self.truth.advance(self.run_time(now))
        if self._running():
            return Actions(start=start)
        self.phase = Phase.ENDING
        self.end_wall = now
        self.truth.close()
        reason = self.done_reason or self.failure or "stopped"
        return Actions(start=start, stop=reason)

    def _poll_ending(self, now: float) -> Actions:
        if self._finals_complete():
            self.phase = Phase.OVER
            return Actions(over=True)
        end = self.end_wall if self.end_wall is not None else now
        if now < end + self.rules.stats_wait_s:
            return Actions()
        missing = sorted(self.expected - self.finals)
        if missing:
            log.warning("no final stats from %s; using their latest", ", ".join(missing))
        self.phase = Phase.OVER
        return Actions(over=True)

    def _finals_complete(self) -> bool:
        """Every final stats report the run can still expect has come."""
        finals = self.finals
        if self.expected <= finals:
            return True
        # a lost actor sends no final report: do not wait for it
        if self.failure is not None and (self.expected & self.alive) <= finals:
            return True
        # a node that crashed as expected and is not back sends none either
        gone = self.rules.may_crash - self.alive
        return bool(gone) and self.expected - gone <= finals
