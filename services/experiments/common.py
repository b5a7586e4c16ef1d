"""Shared machinery of the ``crosspath experiment`` commands: trials, aggregates, tables, plots.

An experiment is a set of *columns* (a run mode, a policy, a V2X channel) times a
set of *trials*: trial ``i`` runs every column with seed ``base_seed + i``, so the
columns of one trial share the scenario's random draws (the start offsets) and
differ only by what the column changes.

:func:`run_trials` runs trials either with the in-process harness in a process
pool (:func:`run_in_process`, deterministic per seed) or with real daemons one
after another (:class:`DaemonRunner`), showing a rich progress bar when attached to
a terminal and one plain line per finished trial otherwise. Both call the Python
API (``services.api.simulate`` / ``run_daemons``), never the ``crosspath``
command. A trial's outcome is the typed run result
(``services.model.results.RunResult``, without its trace) plus, when asked for,
its per-tick trace (rows of ``services.sim.harness.TRACE_FIELDS``; from the
daemons, ``accel`` is derived from the speed and ``detail`` is empty).

Everything else here is small and reusable: summaries of per-trial numbers,
markdown tables, JSON output that can be compared across runs once wall-clock
fields are stripped, per-vehicle views of a trace, and matplotlib (Agg) helpers.
"""

from __future__ import annotations

import contextlib
import csv
import json
import logging
import math
import multiprocessing
import os
import sys
import time
import traceback
from collections.abc import Iterator, Mapping, Sequence
from concurrent.futures import Future, ProcessPoolExecutor, as_completed
from dataclasses import dataclass, field
from functools import lru_cache
from pathlib import Path
from typing import Any, Protocol, TextIO

import numpy as np
import numpy.typing as npt
from rich.console import Console
from rich.progress import (
    BarColumn,
    MofNCompleteColumn,
    Progress,
    TextColumn,
    TimeElapsedColumn,
    TimeRemainingColumn,
)

from services.api import run_daemons, simulate
from services.model.results import RunResult
from services.model.scenario import Scenario, load_scenario
from services.model.types import Policy, RunMode
from services.sim.harness import write_trace_csv
from services.sim.membus import ChannelModel

__all__ = [
    "VEHICLE_COLORS",
    "WALL_CLOCK_KEYS",
    "Column",
    "DaemonRunner",
    "ExperimentError",
    "Runner",
    "Stopwatch",
    "Trial",
    "TrialOutcome",
    "VehicleTrace",
    "binned_mean",
    "collect_errors",
    "fmt_ci",
    "fmt_num",
    "fmt_signed_pct",
    "markdown_table",
    "out_of",
    "pyplot",
    "read_trace_csv",
    "run_in_process",
    "run_trials",
    "save_figure",
    "split_trace",
    "strip_wall_clock",
    "summarize",
    "t_interval95",
    "t_quantile_975",
    "trials_for",
    "vehicle_color",
    "write_json",
    "write_runs_csv",
    "write_trace_csv",
]

log = logging.getLogger("crosspath.experiment")

FloatArray = npt.NDArray[np.float64]

WALL_CLOCK_KEYS = frozenset({"wall_s", "speedup_vs_real_time", "timing"})
"""Result keys that depend on the machine's speed, not on the seed: everything
else in an in-process result is reproduced exactly by the same seed."""

VEHICLE_COLORS = ("tab:green", "tab:orange", "tab:blue", "tab:red", "tab:purple", "tab:brown")
"""Car colours in figures, in vehicle order (the paper draws car A green, car B orange)."""


class ExperimentError(RuntimeError):
    """An experiment could not produce its results (a trial failed); bad arguments
    raise ``ValueError``."""


# --------------------------------------------------------------------------- trials


@dataclass(frozen=True, slots=True)
class Column:
    """One column of an experiment: what every trial runs.

    ``key`` is a short machine name (``rsu-slot``), ``title`` the heading shown in
    tables and figures; ``loss`` [0..1], ``latency_s`` and ``jitter_s`` [s] set the
    in-process V2X channel (the sim CLI's defaults).
    """

    key: str
    title: str
    mode: RunMode
    policy: Policy = Policy.PAPER
    loss: float = 0.0
    latency_s: float = 0.002
    jitter_s: float = 0.001

    def channel(self) -> ChannelModel:
        return ChannelModel(loss=self.loss, latency_s=self.latency_s, jitter_s=self.jitter_s)


@dataclass(frozen=True, slots=True)
class Trial:
    """One run: a column with one seed. ``index`` counts trials from 0."""

    column: Column
    index: int
    seed: int
    scenario: str  # path of the scenario file
    trace: bool = True


TraceRow = tuple[Any, ...]


@dataclass(frozen=True, slots=True)
class TrialOutcome:
    """What one trial produced: the run result (None if it failed, then ``error``
    says why), the trace rows if recorded, and the wall time it took [s]."""

    trial: Trial
    result: RunResult | None
    trace: tuple[TraceRow, ...] | None = None
    error: str | None = None
    wall_s: float = 0.0


class Runner(Protocol):
    """Runs one trial; must be picklable to run in a process pool."""

    def __call__(self, trial: Trial) -> TrialOutcome: ...


def trials_for(
    columns: Sequence[Column],
    scenario: str | Path,
    trials: int,
    base_seed: int,
    *,
    trace: bool = True,
) -> list[Trial]:
    """Every column x every trial, trial ``i`` with seed ``base_seed + i`` (column-major)."""
    if isinstance(trials, bool) or not isinstance(trials, int) or trials < 1:
        raise ValueError(f"trials must be an int >= 1, got {trials!r}")
    if isinstance(base_seed, bool) or not isinstance(base_seed, int) or base_seed < 0:
        raise ValueError(f"seed must be an int >= 0, got {base_seed!r}")
    keys = [c.key for c in columns]
    if len(set(keys)) != len(keys):
        raise ValueError(f"duplicate column keys in {keys}")
    path = str(Path(scenario))
    return [
        Trial(column=c, index=i, seed=base_seed + i, scenario=path, trace=trace)
        for c in columns
        for i in range(trials)
    ]


@lru_cache(maxsize=8)
def _scenario(path: str) -> Scenario:
    """A worker loads each scenario file once."""
    return load_scenario(Path(path))


def run_in_process(trial: Trial) -> TrialOutcome:
    """One trial with the in-process harness (``services.api.simulate``).

    Exceptions become the outcome's ``error`` so that one failing trial does not
    hide the others' results.
    """
    t0 = time.perf_counter()
    col = trial.column
    try:
        result = simulate(
            _scenario(trial.scenario),
            mode=col.mode,
            policy=col.policy,
            seed=trial.seed,
            loss=col.loss,
            latency_ms=col.latency_s * 1000.0,
            jitter_ms=col.jitter_s * 1000.0,
            trace=trial.trace,
        )
    except Exception as exc:  # a trial's failure is reported, not raised in the worker
        return TrialOutcome(
            trial,
            None,
            error=_describe(exc),
            wall_s=time.perf_counter() - t0,
        )
    return _outcome(trial, result, time.perf_counter() - t0)


def _outcome(trial: Trial, result: RunResult, wall_s: float) -> TrialOutcome:
    """The outcome of a finished trial: the result without its trace, the trace beside."""
    trace = tuple(result.trace) if trial.trace and result.trace is not None else None
    return TrialOutcome(trial, result.without_trace(), trace, None, wall_s)


def _describe(exc: BaseException) -> str:
    """The exception and the innermost frame that raised it, on one line."""
    tb = traceback.extract_tb(exc.__traceback__)
    where = f" ({Path(tb[-1].filename).name}:{tb[-1].lineno})" if tb else ""
    return f"{type(exc).__name__}: {exc}{where}"


@dataclass(frozen=True, slots=True)
class DaemonRunner:
    """One trial with real daemons (one OS process per actor over Zenoh), through
    ``services.api.run_daemons`` (what ``crosspath up`` runs), in this process.

    ``speed`` is the run seconds per wall second (default 1); ``run_dir_root`` gets
    one run directory per trial (``{column}-seed{N}``, the daemons' logs; default a
    fresh ``results/up/...``); ``timeout_s`` bounds one run in wall seconds. The trace,
    when the trial asks for one, is the monitor's record of every car's truth.
    """

    speed: float | None = None
    timeout_s: float = 600.0
    run_dir_root: str | None = None

    def __call__(self, trial: Trial) -> TrialOutcome:
        t0 = time.perf_counter()
        run_dir = (
            None
            if self.run_dir_root is None
            else Path(self.run_dir_root) / f"{trial.column.key}-seed{trial.seed}"
        )
        try:
            result = run_daemons(
                trial.scenario,
                mode=trial.column.mode,
                policy=trial.column.policy,
                seed=trial.seed,
                speed=self.speed if self.speed is not None else 1.0,
                timeout=self.timeout_s,
                run_dir=run_dir,
                trace=trial.trace,
            )
        except Exception as exc:  # one failed trial is reported; Ctrl-C is not swallowed
            return TrialOutcome(trial, None, error=_describe(exc), wall_s=time.perf_counter() - t0)
        return _outcome(trial, result, time.perf_counter() - t0)


# --------------------------------------------------------------------------- progress


class _Reporter(Protocol):
    def advance(self, outcome: TrialOutcome) -> None: ...


def _outcome_line(outcome: TrialOutcome) -> str:
    t = outcome.trial
    head = f"{t.column.key} seed {t.seed}"
    if outcome.result is None:
        return f"{head}: FAILED {outcome.error}"
    mean = outcome.result.mean_passing_time_s
    mean_s = "-" if mean is None else f"{mean:.2f} s"
    return (
        f"{head}: mean passing {mean_s}, collisions {outcome.result.collisions}"
        f" ({outcome.wall_s:.2f} s)"
    )


@dataclass(slots=True)
class _LineReporter:
    total: int
    stream: TextIO
    done: int = 0

    def advance(self, outcome: TrialOutcome) -> None:
        self.done += 1
        self.stream.write(f"[{self.done}/{self.total}] {_outcome_line(outcome)}\n")
        self.stream.flush()


@dataclass(slots=True)
class _SilentReporter:
    def advance(self, outcome: TrialOutcome) -> None:
        if outcome.result is None:
            log.warning("%s", _outcome_line(outcome))


@contextlib.contextmanager
def _reporter(total: int, description: str, enabled: bool, stream: TextIO) -> Iterator[_Reporter]:
    if not enabled:
        yield _SilentReporter()
        return
    if not stream.isatty():
        yield _LineReporter(total, stream)
        return
    progress = Progress(
        TextColumn("[bold]{task.description}"),
        BarColumn(),
        MofNCompleteColumn(),
        TimeElapsedColumn(),
        TimeRemainingColumn(),
        TextColumn("{task.fields[last]}"),
        console=Console(file=stream),
    )
    with progress:
        task = progress.add_task(description, total=total, last="")

        @dataclass(slots=True)
        class _Rich:
            def advance(self, outcome: TrialOutcome) -> None:
                progress.update(task, advance=1, last=_outcome_line(outcome))

        yield _Rich()


# --------------------------------------------------------------------------- running


def run_trials(
    trials: Sequence[Trial],
    runner: Runner = run_in_process,
    *,
    jobs: int | None = None,
    progress: bool = True,
    description: str = "trials",
    stream: TextIO | None = None,
) -> list[TrialOutcome]:
    """Run every trial, return the outcomes in the order of ``trials``.

    ``jobs`` worker processes (default: the machine's cores; 1 runs in this
    process, as daemon runs must). Workers are started by ``forkserver`` so that no
    thread of this process (the progress bar's, a test runner's) is forked.
    Progress goes to ``stream`` (default stderr): a rich bar on a terminal, one line
    per trial otherwise, nothing with ``progress=False``.
    """
    out_stream = stream if stream is not None else sys.stderr
    n_jobs = jobs if jobs is not None else (os.cpu_count() or 1)
    if n_jobs < 1:
        raise ValueError(f"jobs must be >= 1, got {n_jobs}")
    n_jobs = min(n_jobs, max(len(trials), 1))
    outcomes: list[TrialOutcome | None] = [None] * len(trials)
    if n_jobs == 1:
        with _reporter(len(trials), description, progress, out_stream) as rep:
            for i, trial in enumerate(trials):
                outcomes[i] = runner(trial)
                rep.advance(outcomes[i])  # type: ignore[arg-type]
    else:
        methods = multiprocessing.get_all_start_methods()
        ctx = multiprocessing.get_context("forkserver" if "forkserver" in methods else "spawn")
        with ProcessPoolExecutor(max_workers=n_jobs, mp_context=ctx) as pool:
            futures: dict[Future[TrialOutcome], int] = {
                pool.submit(runner, trial): i for i, trial in enumerate(trials)
            }
            with _reporter(len(trials), description, progress, out_stream) as rep:
                for fut in as_completed(futures):
                    outcome = fut.result()
                    outcomes[futures[fut]] = outcome
                    rep.advance(outcome)
    return [o for o in outcomes if o is not None]


# --------------------------------------------------------------------------- aggregates


# Two-sided 95 % quantiles of Student's t, df = 1..30; beyond, a Cornish-Fisher expansion
# around the normal quantile (error < 1e-4). No scipy dependency for one number.
_T975: tuple[float, ...] = (
    12.7062, 4.3027, 3.1824, 2.7764, 2.5706, 2.4469, 2.3646, 2.3060, 2.2622, 2.2281,
    2.2010, 2.1788, 2.1604, 2.1448, 2.1314, 2.1199, 2.1098, 2.1009, 2.0930, 2.0860,
    2.0796, 2.0739, 2.0687, 2.0639, 2.0595, 2.0555, 2.0518, 2.0484, 2.0452, 2.0423,
)  # fmt: skip


def t_quantile_975(df: int) -> float:
    """The 0.975 quantile of Student's t with ``df`` degrees of freedom (``df >= 1``)."""
    if df < 1:
        raise ValueError(f"degrees of freedom must be >= 1, got {df}")
    if df <= len(_T975):
        return _T975[df - 1]
    z = 1.959964
    return z + (z**3 + z) / (4 * df) + (5 * z**5 + 16 * z**3 + 3 * z) / (96 * df**2)


def t_interval95(values: Sequence[float]) -> tuple[float, float] | None:
    """The 95 % t-interval of the mean of ``values`` [same unit]; None below two values
    (no spread to estimate), the point itself when every value is the same."""
    arr = np.asarray([float(v) for v in values], dtype=np.float64)
    if arr.size < 2:
        return None
    half = t_quantile_975(int(arr.size) - 1) * float(arr.std(ddof=1)) / math.sqrt(arr.size)
    mean = float(arr.mean())
    return mean - half, mean + half


def summarize(values: Sequence[float | None]) -> dict[str, Any]:
    """Mean, sample standard deviation, min, max and the 95 % t-interval of the mean
    (``ci95_low``/``ci95_high``) of the values that are not None.

    ``n`` counts those values, ``missing`` the None ones; the statistics are None
    when nothing was measured (std is 0.0 for a single value, whose interval is None).
    """
    got = [float(v) for v in values if v is not None and math.isfinite(v)]
    missing = len(values) - len(got)
    if not got:
        return {
            "n": 0,
            "missing": missing,
            "mean": None,
            "std": None,
            "min": None,
            "max": None,
            "ci95_low": None,
            "ci95_high": None,
        }
    arr = np.asarray(got, dtype=np.float64)
    std = float(arr.std(ddof=1)) if arr.size > 1 else 0.0
    ci = t_interval95(got)
    return {
        "n": int(arr.size),
        "missing": missing,
        "mean": round(float(arr.mean()), 4),
        "std": round(std, 4),
        "min": round(float(arr.min()), 4),
        "max": round(float(arr.max()), 4),
        "ci95_low": None if ci is None else round(ci[0], 4),
        "ci95_high": None if ci is None else round(ci[1], 4),
    }


def fmt_ci(s: Mapping[str, Any], unit: str = "", digits: int = 2) -> str:
    """``12.35 s [11.90, 12.80]``: a :func:`summarize` mean with its 95 % interval
    (the mean alone from one value; an en dash when nothing was measured)."""
    if s.get("mean") is None:
        return "–"
    text = fmt_num(s["mean"], unit, digits)
    if s.get("ci95_low") is not None:
        text += f" [{s['ci95_low']:.{digits}f}, {s['ci95_high']:.{digits}f}]"
    return text


def out_of(k: int, n: int, noun: str = "trial") -> str:
    """``3 out of 30 trials``: a count always beside the number it is out of."""
    return f"{k} out of {n} {noun if n == 1 else noun + 's'}"


def strip_wall_clock(obj: Any, keys: frozenset[str] = WALL_CLOCK_KEYS) -> Any:
    """A deep copy of a JSON-like value without the keys that depend on wall time."""
    if isinstance(obj, Mapping):
        return {k: strip_wall_clock(v, keys) for k, v in obj.items() if k not in keys}
    if isinstance(obj, list | tuple):
        return [strip_wall_clock(v, keys) for v in obj]
    return obj


def write_json(path: Path, obj: Any) -> None:
    """Indented strict JSON (no NaN or infinity) with a final newline."""
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(obj, indent=2, allow_nan=False) + "\n")


# --------------------------------------------------------------------------- text


def fmt_num(x: float | None, unit: str = "", digits: int = 2) -> str:
    """``12.35 s``; an en dash for a value that was not measured."""
    if x is None or not math.isfinite(x):
        return "–"
    return f"{x:.{digits}f}{' ' + unit if unit else ''}"


def fmt_signed_pct(x: float | None, digits: int = 1) -> str:
    """``+1.8 %`` / ``−25.9 %`` (a real minus sign); an en dash when unknown."""
    if x is None or not math.isfinite(x):
        return "–"
    text = f"{abs(x):.{digits}f} %"
    if round(x, digits) == 0:
        return f"±{text}"
    return ("+" if x > 0 else "−") + text


def markdown_table(
    header: Sequence[str], rows: Sequence[Sequence[str]], align: Sequence[str] | None = None
) -> str:
    """A GitHub markdown table; ``align`` per column is ``l``, ``r`` or ``c``."""
    n = len(header)
    if any(len(r) != n for r in rows):
        raise ValueError("every row needs one cell per header column")
    marks = {"l": ":--", "r": "--:", "c": ":-:"}
    al = list(align) if align is not None else ["l"] + ["r"] * (n - 1)
    if len(al) != n or any(a not in marks for a in al):
        raise ValueError("align needs one of l, r, c per column")

    def line(cells: Sequence[str]) -> str:
        return "| " + " | ".join(c.replace("|", "\\|") for c in cells) + " |"

    return "\n".join([line(header), line([marks[a] for a in al]), *(line(r) for r in rows)])


# --------------------------------------------------------------------------- traces


@dataclass(frozen=True, slots=True)
class VehicleTrace:
    """One car's rows of a trace, as arrays in time order (units of ``TRACE_FIELDS``:
    s, m, m/s, m/s²; ``reason`` the planner's reason, ``mode`` the coordination mode)."""

    vehicle: str
    t: FloatArray
    s: FloatArray
    x: FloatArray
    y: FloatArray
    speed: FloatArray
    accel: FloatArray
    reason: tuple[str, ...]
    detail: tuple[str, ...]
    mode: tuple[str, ...]

    @property
    def dt(self) -> float:
        """The trace's step [s] (0 with fewer than two rows)."""
        return float(np.median(np.diff(self.t))) if self.t.size > 1 else 0.0


def split_trace(rows: Sequence[TraceRow]) -> dict[str, VehicleTrace]:
    """Per-vehicle arrays from trace rows ``(t, vehicle, s, x, y, speed, accel, reason,
    detail, mode)``, vehicles in the order they first appear."""
    by: dict[str, list[TraceRow]] = {}
    for row in rows:
        by.setdefault(str(row[1]), []).append(row)
    out: dict[str, VehicleTrace] = {}
    for vid, rs in by.items():
        rs.sort(key=lambda r: float(r[0]))

        def col(i: int, rs: list[TraceRow] = rs) -> FloatArray:
            return np.fromiter((float(r[i]) for r in rs), dtype=np.float64, count=len(rs))

        out[vid] = VehicleTrace(
            vehicle=vid,
            t=col(0),
            s=col(2),
            x=col(3),
            y=col(4),
            speed=col(5),
            accel=col(6),
            reason=tuple(str(r[7]) for r in rs),
            detail=tuple(str(r[8]) for r in rs),
            mode=tuple(str(r[9]) for r in rs),
        )
    return out


def read_trace_csv(path: Path) -> tuple[TraceRow, ...]:
    """Rows of a trace CSV, numbers as floats (the inverse of :func:`write_trace_csv`)."""
    rows: list[TraceRow] = []
    with path.open(newline="") as fh:
        reader = csv.reader(fh)
        header = next(reader, None)
        if header is None:
            return ()
        for r in reader:
            if len(r) < 10:
                continue
            rows.append((float(r[0]), r[1], *(float(v) for v in r[2:7]), r[7], r[8], r[9]))
    return tuple(rows)


def binned_mean(x: FloatArray, y: FloatArray, edges: FloatArray) -> FloatArray:
    """Mean of ``y`` over the samples whose ``x`` falls in each bin (NaN where none)."""
    idx = np.digitize(x, edges) - 1
    ok = (idx >= 0) & (idx < edges.size - 1)
    sums = np.bincount(idx[ok], weights=y[ok], minlength=edges.size - 1)
    counts = np.bincount(idx[ok], minlength=edges.size - 1)
    with np.errstate(invalid="ignore", divide="ignore"):
        out: FloatArray = np.where(counts > 0, sums / np.maximum(counts, 1), np.nan)
    return out


# --------------------------------------------------------------------------- plots


def pyplot() -> Any:
    """``matplotlib.pyplot`` on the non-interactive Agg backend (no display needed)."""
    import matplotlib

    matplotlib.use("Agg", force=True)
    import matplotlib.pyplot as plt

    return plt


FIGURE_DPI = 300
FIGURE_FORMATS: tuple[str, ...] = ("png", "pdf", "svg")


def save_figure(fig: Any, path: Path, dpi: int = FIGURE_DPI) -> list[str]:
    """Write ``fig`` as ``path`` (PNG at ``dpi``) and beside it as PDF and SVG (vector,
    for a paper); closes the figure. Returns the file names written, PNG first."""
    plt = pyplot()
    path.parent.mkdir(parents=True, exist_ok=True)
    names = []
    try:
        for ext in FIGURE_FORMATS:
            target = path.with_suffix("." + ext)
            fig.savefig(target, dpi=dpi, bbox_inches="tight", metadata=_figure_metadata(ext))
            names.append(target.name)
    finally:
        plt.close(fig)
    return names


def _figure_metadata(ext: str) -> dict[str, Any]:
    """No creation date in PDF/SVG, so that the same run writes the same bytes."""
    if ext == "pdf":
        return {"CreationDate": None, "Creator": "crosspath"}
    if ext == "svg":
        return {"Date": None, "Creator": "crosspath"}
    return {"Software": "crosspath"}


def write_runs_csv(path: Path, rows: Sequence[Mapping[str, Any]]) -> None:
    """``runs.csv``: one row per run, the union of every row's keys as columns (in
    first-seen order), empty cells where a run has no value."""
    columns: dict[str, None] = {}
    for row in rows:
        columns.update(dict.fromkeys(row))
    path.parent.mkdir(parents=True, exist_ok=True)
    with path.open("w", newline="") as fh:
        writer = csv.DictWriter(fh, fieldnames=list(columns), restval="")
        writer.writeheader()
        for row in rows:
            writer.writerow({k: ("" if v is None else v) for k, v in row.items()})


def vehicle_color(index: int) -> str:
    """The colour of the ``index``-th car (see :data:`VEHICLE_COLORS`)."""
    return VEHICLE_COLORS[index % len(VEHICLE_COLORS)]


@dataclass(slots=True)
class Stopwatch:
    """Wall time of named phases [s] (reported, never asserted)."""

    phases: dict[str, float] = field(default_factory=dict)

    @contextlib.contextmanager
    def phase(self, name: str) -> Iterator[None]:
        t0 = time.perf_counter()
        try:
            yield
        finally:
            self.phases[name] = round(self.phases.get(name, 0.0) + time.perf_counter() - t0, 3)


def collect_errors(outcomes: Sequence[TrialOutcome]) -> list[str]:
    """One line per failed trial: column, seed and the error."""
    return [
        f"{o.trial.column.key} seed {o.trial.seed}: {o.error}" for o in outcomes if o.result is None
    ]
