"""The Python API: one run of a scenario, in-process or with real daemons, as a typed result.

For notebooks, scripts and the experiments themselves (``services.experiments``
call these, never the ``crosspath`` command)::

    from services.api import simulate, run_daemons

    r = simulate("paper-blind-intersection", mode="rsu", policy="slot", seed=3, loss=0.1)
    r.mean_passing_time_s, r.vehicles["B"].stops, r.provenance.scenario_sha256
    d = run_daemons("paper-blind-intersection", mode="fp-only", seed=3, speed=4.0)
    d.network.stream("fp").latency_ms_p99

Both return a :class:`~services.model.results.RunResult` (``to_json()`` gives
the JSON that ``crosspath sim/up --json`` write) with its provenance: package
version, git commit when the code runs from a checkout, the scenario's name,
file and sha256, the channel and the RSU policy with every knob.

Arguments: ``scenario`` is a path (``str`` or ``os.PathLike``), the name of a
packaged scenario, or a loaded :class:`~services.model.scenario.Scenario` (its
digest is that of its file as it is now; the daemons need it to come from a
file). ``mode`` and ``policy`` take the enums of ``services.model.types`` or
their names, and refuse anything else with a ``ValueError`` naming the allowed
values; so do out-of-range numbers (``loss`` is a fraction 0..1, times in the
units their names say). ``trace``: ``True`` keeps the per-step rows in the
result (``trace_fields``/``trace``, the columns of
``services.sim.harness.TRACE_FIELDS``); a path writes them there as CSV (the
format of ``crosspath sim --trace``) and leaves them out of the result.

:func:`run_daemons` starts one OS process per actor over Zenoh on loopback, as
``crosspath up`` does (in this process: it installs SIGINT/SIGTERM handlers for
the run when called from the main thread), and raises :class:`DaemonRunError`
(with the partial result, if any) when the run fails, :class:`RunInterrupted`
(a ``KeyboardInterrupt``) on Ctrl-C or SIGTERM; no daemon is left behind either
way.
"""

from __future__ import annotations

import math
import os
from collections.abc import Callable, Mapping
from pathlib import Path

from services.edge.provenance import origin
from services.model.results import RunResult
from services.model.scenario import Scenario, load_scenario
from services.model.types import Policy, RunMode, parse_mode, parse_policy
from services.sim.harness import TRACE_FIELDS, SimOptions, Simulation, write_trace_csv
from services.sim.membus import ChannelModel
from services.supervise.launcher import prepare_up

__all__ = ["DaemonRunError", "RunInterrupted", "ScenarioRef", "run_daemons", "simulate"]

ScenarioRef = Scenario | str | os.PathLike[str]
"""A scenario: a loaded one, a file path, or a packaged scenario's name."""

TraceOption = bool | str | os.PathLike[str] | None
"""``None``/``False``: no trace; ``True``: rows in the result; a path: a CSV file there."""


class DaemonRunError(RuntimeError):
    """A daemon run failed; ``result`` is what the monitor recorded (None if it wrote none),
    ``run_dir`` holds the daemons' logs."""

    def __init__(self, message: str, result: RunResult | None, run_dir: Path) -> None:
        super().__init__(message)
        self.result = result
        self.run_dir = run_dir


class RunInterrupted(KeyboardInterrupt):
    """SIGINT or SIGTERM arrived during a daemon run; every daemon was stopped."""

    def __init__(self, signum: int) -> None:
        super().__init__(signum)
        self.signum = signum


def _number(name: str, value: object, low: float, high: float = math.inf) -> float:
    """``value`` as a float within ``[low, high]``; one-line ``ValueError`` otherwise."""
    if isinstance(value, bool) or not isinstance(value, int | float):
        raise ValueError(f"{name} must be a number, got {value!r}")
    number = float(value)
    if not (math.isfinite(number) and low <= number <= high):
        span = f"within {low:g}..{high:g}" if math.isfinite(high) else f">= {low:g}"
        raise ValueError(f"{name} must be a finite number {span}, got {value!r}")
    return number


def _scenario(scenario: ScenarioRef) -> tuple[Scenario, str | None]:
    """The loaded scenario and the file it came from (None for one parsed from text)."""
    if isinstance(scenario, Scenario):
        return scenario, scenario.source if Path(scenario.source).is_file() else None
    if not isinstance(scenario, str | os.PathLike):
        raise TypeError(f"scenario must be a Scenario, a path or a name, got {scenario!r}")
    loaded = load_scenario(Path(scenario))
    return loaded, loaded.source


def _trace_path(trace: TraceOption) -> Path | None:
    if trace is None or isinstance(trace, bool):
        return None
    if not isinstance(trace, str | os.PathLike):
        raise TypeError(f"trace must be a bool or a path, got {trace!r}")
    return Path(trace)


def simulate(
    scenario: ScenarioRef,
    *,
    mode: RunMode | str = RunMode.RSU,
    policy: Policy | str = Policy.PAPER,
    seed: int = 0,
    loss: float = 0.0,
    latency_ms: float = 2.0,
    jitter_ms: float = 1.0,
    trace: TraceOption = None,
    max_sim_s: float | None = None,
    start_times: Mapping[str, float] | None = None,
) -> RunResult:
    """One in-process run (``crosspath sim``): virtual clock, seeded in-memory channel.

    ``loss`` per receiver 0..1, ``latency_ms`` one-way and ``jitter_ms`` uniform extra
    delay [ms] (the defaults of ``crosspath sim``); ``max_sim_s`` [s] overrides the
    scenario's limit, ``start_times`` [run s] per car its draw from ``seed``. The same
    arguments give the same result, bar the wall-clock fields (``wall_s``,
    ``speedup_vs_real_time``). Raises ``ValueError`` (``ScenarioError`` included) for
    bad arguments, before the run.
    """
    run_mode, run_policy = parse_mode(mode), parse_policy(policy)
    channel = ChannelModel(
        loss=_number("loss", loss, 0.0, 1.0),
        latency_s=_number("latency_ms", latency_ms, 0.0) / 1000.0,
        jitter_s=_number("jitter_ms", jitter_ms, 0.0) / 1000.0,
    )
    csv_path = _trace_path(trace)
    sc, source = _scenario(scenario)
    options = SimOptions(
        mode=run_mode,
        policy=run_policy,
        seed=seed,
        channel=channel,
        start_times=None if start_times is None else dict(start_times),
        trace=bool(trace),
        max_sim_s=max_sim_s,
    )
    sim = Simulation(sc, options, origin=origin(source))
    result = sim.run()
    if csv_path is not None:
        write_trace_csv(csv_path, sim.trace_rows)
    elif trace:
        result = result.updated(trace_fields=list(TRACE_FIELDS), trace=sim.trace_rows)
    return result


def run_daemons(
    scenario: ScenarioRef,
    *,
    mode: RunMode | str = RunMode.RSU,
    policy: Policy | str = Policy.PAPER,
    seed: int = 0,
    speed: float = 1.0,
    timeout: float | None = None,
    trace: TraceOption = None,
    run_dir: str | os.PathLike[str] | None = None,
    max_sim_s: float | None = None,
    start_delay_s: float = 1.0,
    log_level: str = "INFO",
    say: Callable[[str], None] | None = None,
    cars_per_process: int | None = None,
    insecure: bool = False,
) -> RunResult:
    """One run with real daemons (``crosspath up``): monitor, RSUs and cars as OS processes
    (``cars_per_process`` cars to a process, each its own Zenoh node; None: the launcher's
    default, ``services.supervise.hosts``; flows are expanded for ``seed``).

    ``speed`` run seconds per wall second (0 < speed <= 1000), ``timeout`` [wall s] for
    the whole run (default ``max_sim_s / speed + 60``), ``run_dir`` where the daemons'
    logs and the monitor's ``result.json`` go (default ``results/up/<time>-<id>``),
    ``start_delay_s`` wall seconds from the start message to run time 0, ``log_level``
    the daemons'. ``say`` gets one line when the daemons start. The trace comes from the
    monitor: every car's reported truth per physics step, ``accel`` derived from the
    speed and ``detail`` empty (the cars do not report them). V2X is signed with a
    throw-away authority in the run dir unless ``insecure``. Raises ``ValueError`` for
    bad arguments, :class:`DaemonRunError` when the run fails, :class:`RunInterrupted` on
    a signal.
    """
    if isinstance(scenario, Scenario):
        if not Path(scenario.source).is_file():
            raise ValueError("the daemons read their scenario from a file: pass its path")
        scenario = scenario.source
    csv_path = _trace_path(trace)
    up = prepare_up(
        scenario,
        mode,
        policy,
        seed,
        speed,
        run_dir=None if run_dir is None else Path(run_dir),
        timeout_s=timeout,
        max_sim_s=max_sim_s,
        start_delay_s=start_delay_s,
        log_level=log_level,
        trace=bool(trace),
        cars_per_process=cars_per_process,
        insecure=insecure,
    )
    if say is not None:
        say(f"run {up.run_id}: {len(up.launcher.commands)} processes, logs in {up.run_dir}")
    outcome = up.execute()
    if outcome.interrupted:
        raise RunInterrupted(outcome.interrupted)
    result = outcome.result
    if not outcome.ok or result is None:
        raise DaemonRunError(outcome.failure(), result, outcome.run_dir)
    if csv_path is not None:
        write_trace_csv(csv_path, result.trace or [])
        result = result.without_trace()
    return result
