"""``crosspath experiment paper``: the paper's Table I and Fig. 5-6 for our system.

Runs the paper's three scenarios (§V: stand-alone, future paths only, future
path with RSU), plus the RSU with our ``slot`` policy as a fourth column, for
N trials each. Trial ``i`` uses seed ``base_seed + i`` in every column, so the
columns of one trial share car B's start offset δ ~ U(0, 1) s (drawn from the
seed by the scenario), as the paper's trials differed by when the cars were
launched.

Writes into the output directory:

``results.json``
    every run result, the planner-trace analysis of every trial, per-column
    aggregates and the paper's own numbers;
``table.md``
    Table I for our system beside the paper's, plus safety rows;
``runs.csv``
    one row per run: every parameter (column, mode, policy, loss, seed) and metric;
``speed_profiles.png`` (and ``.pdf``, ``.svg``)
    speed against position relative to the intersection centre, one panel per
    column (the paper's Fig. 6);
``passing_times.png`` (and ``.pdf``, ``.svg``)
    every car's passing time in every trial, per column, with the mean and its 95 %
    t-interval (the paper's Fig. 5);
``REPORT.md``
    the table, the figures, and why each mode behaves as it does, in sentences
    generated from the numbers of the planner traces.

Decisions where the issue is silent:

- The behaviour analysis looks at the *approach*: from ``APPROACH_M`` (60 m)
  before the intersection centre to the centre, position of the car's centre
  along its route. Shares of time are per physics step (20 Hz).
- A stop is counted as the metrics count it (speed under 0.1 m/s after having
  exceeded 1.0 m/s, not at the goal); its place is reported as the distance of
  the car's centre before the centre, and of its front bumper behind the stop
  line.
- Figures are PNG at 300 dpi plus PDF and SVG; every mark is explained in the
  figure's own legend. Means carry a 95 % Student-t interval over trials (none from
  a single trial); counts are given "out of N trials" beside the paper's own.
- Safety rows aggregate over trials: total collisions, and the worst (smallest)
  minimum gap and PET of any trial.
- The paper's table gives car A first 6 times with the RSU while its text says
  4; we quote the table.
- With ``--daemons`` trials run one after another with real daemons
  (``services.api.run_daemons``, what ``crosspath up`` runs; a daemon run keeps
  wall-clock time, so parallel runs would compete for the CPU and distort each
  other); the daemons' logs go to ``DIR/daemons/``. Their per-tick trace is the
  monitor's record of every car's reported truth (``accel`` derived from the
  speed; no planner ``detail``, so the report does not say whom a car yielded
  to), which feeds the speed profiles and the behaviour analysis as in-process.
"""

from __future__ import annotations

import argparse
import logging
import os
import sys
import time
import warnings
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from services.edge.args import (
    add_scenario_option,
    non_negative_int,
    output_dir,
    positive_int,
    run_speed,
)
from services.experiments.common import (
    Column,
    DaemonRunner,
    ExperimentError,
    Runner,
    Stopwatch,
    VehicleTrace,
    binned_mean,
    collect_errors,
    fmt_ci,
    fmt_num,
    fmt_signed_pct,
    markdown_table,
    pyplot,
    run_in_process,
    run_trials,
    save_figure,
    split_trace,
    summarize,
    t_interval95,
    trials_for,
    vehicle_color,
    write_json,
    write_runs_csv,
    write_trace_csv,
)
from services.model.catalog import default_scenario
from services.model.limits import STOP_ARM_ABOVE_MPS, STOP_COUNT_BELOW_MPS
from services.model.results import RunResult
from services.model.scenario import Crossing, Scenario, ScenarioError, load_scenario
from services.model.types import Policy, RunMode

__all__ = [
    "APPROACH_M",
    "COLUMNS",
    "DEFAULT_OUT",
    "DEFAULT_SCENARIO",
    "PAPER_REFERENCE",
    "aggregate_behaviour",
    "aggregate_column",
    "analyse_trial",
    "analyse_vehicle",
    "configure",
    "plot_passing_times",
    "plot_speed_profiles",
    "render_report",
    "render_table",
    "run",
    "run_paper_experiment",
    "runs_rows",
    "table_rows",
]

log = logging.getLogger("crosspath.experiment")

DEFAULT_SCENARIO = default_scenario()
"""The packaged paper scenario (``services.model.catalog``), wherever crosspath is installed."""
DEFAULT_OUT = Path("results") / "paper"
DEFAULT_TRIALS = 10

APPROACH_M = 60.0
"""The behaviour analysis covers the last this many metres before the centre [m]."""

PROFILE_RANGE_M = (-100.0, 50.0)
"""Speed profiles span this position range relative to the intersection centre [m]."""

PROFILE_BIN_M = 1.0
"""Bin width of the mean speed profile [m]."""

REASONS = ("cruise", "caution", "yield", "coordinated", "emergency", "goal")
"""Planner reasons in the order reports list them (``services.vehicle.planner.Reason``)."""

COLUMNS: tuple[Column, ...] = (
    Column("standalone", "Stand-alone", RunMode.STANDALONE),
    Column("fp-only", "Future paths only", RunMode.FP_ONLY),
    Column("rsu-paper", "Future path with RSU", RunMode.RSU, Policy.PAPER),
    Column("rsu-slot", "RSU, slot policy (ours)", RunMode.RSU, Policy.SLOT),
)
"""The paper's three scenarios and our slot policy; the first is the baseline."""

PAPER_REFERENCE: dict[str, Any] = {
    "source": "future-path-sharing.tex, Table I (10 trials per scenario, LGSVL + Autoware)",
    "trials": 10,
    "note": (
        "The table gives car A first 6 times with the RSU; the text says 4. The table is quoted."
    ),
    "columns": {
        "standalone": {
            "title": "Stand-alone",
            "first_through": {"A": 10, "B": 0},
            "passing_time_s": {"A": 31.04, "B": 41.97},
            "average_passing_time_s": 36.51,
        },
        "fp-only": {
            "title": "Future paths only",
            "first_through": {"A": 6, "B": 4},
            "passing_time_s": {"A": 38.03, "B": 36.32},
            "average_passing_time_s": 37.17,
        },
        "rsu-paper": {
            "title": "Future path with RSU",
            "first_through": {"A": 6, "B": 4},
            "passing_time_s": {"A": 23.93, "B": 30.18},
            "average_passing_time_s": 27.05,
        },
    },
}
"""The paper's own numbers, keyed by our column keys."""


def _paper_change_pct(key: str) -> float | None:
    cols = PAPER_REFERENCE["columns"]
    if key not in cols or key == COLUMNS[0].key:
        return None
    base = float(cols[COLUMNS[0].key]["average_passing_time_s"])
    return round(100.0 * (float(cols[key]["average_passing_time_s"]) - base) / base, 2)


# --------------------------------------------------------------------------- trace analysis


def _first(mask: np.ndarray[Any, np.dtype[np.bool_]]) -> int | None:
    idx = np.flatnonzero(mask)
    return int(idx[0]) if idx.size else None


def _r(x: float, digits: int = 3) -> float:
    return round(float(x), digits)


def analyse_vehicle(
    tr: VehicleTrace, crossing: Crossing, goal_s: float, goal_tolerance_m: float
) -> dict[str, Any]:
    """What one car's planner did around one intersection, from its trace.

    Positions are distances of the car's centre *before* the intersection centre
    [m] (negative: past it); times are run time [s]; shares are fractions of the
    physics steps spent within ``APPROACH_M`` before the centre.
    """
    rel = tr.s - crossing.center_s
    dt = tr.dt
    reasons = np.array(tr.reason)
    modes = np.array(tr.mode)
    window = (rel >= -APPROACH_M) & (rel <= 0.0)
    n_win = int(window.sum())

    def shares(values: np.ndarray[Any, Any], names: Sequence[str]) -> dict[str, float]:
        if n_win == 0:
            return {k: 0.0 for k in names}
        w = values[window]
        out = {k: _r(np.count_nonzero(w == k) / n_win, 4) for k in names}
        for k in sorted(set(w.tolist()) - set(names)):
            out[str(k)] = _r(np.count_nonzero(w == k) / n_win, 4)
        return out

    def at(i: int | None, **extra: Any) -> dict[str, Any] | None:
        if i is None:
            return None
        return {
            "t_s": _r(tr.t[i]),
            "distance_m": _r(-rel[i], 2),
            "speed_mps": _r(tr.speed[i], 2),
            **extra,
        }

    iy = _first(reasons == "yield")
    ic = _first(reasons == "caution")
    ie = _first(reasons == "emergency")

    # stops, counted as the metrics count them (thresholds in services.model.limits)
    stops: list[dict[str, Any]] = []
    armed = False
    start: int | None = None
    for i in range(tr.t.size):
        v = tr.speed[i]
        if start is None:
            if v > STOP_ARM_ABOVE_MPS:
                armed = True
            if armed and v < STOP_COUNT_BELOW_MPS and tr.s[i] < goal_s - goal_tolerance_m:
                start = i
                armed = False
        elif v >= STOP_COUNT_BELOW_MPS:
            stops.append(_stop(tr, rel, crossing, start, i))
            start = None
            armed = v > STOP_ARM_ABOVE_MPS
    if start is not None:
        stops.append(_stop(tr, rel, crossing, start, tr.t.size - 1))

    changes: list[dict[str, Any]] = []
    for i in range(1, modes.size):
        if modes[i] != modes[i - 1]:
            changes.append(
                {
                    "t_s": _r(tr.t[i]),
                    "distance_m": _r(-rel[i], 2),
                    "from": str(modes[i - 1]),
                    "to": str(modes[i]),
                }
            )
    i_fast = _first(modes == "C_FAST")
    i_slow = _first(modes == "C_SLOW")
    past = np.flatnonzero(rel >= 0.0)
    speed_at_centre = (
        float(np.interp(0.0, rel[past[0] - 1 : past[0] + 1], tr.speed[past[0] - 1 : past[0] + 1]))
        if past.size and past[0] > 0
        else None
    )
    return {
        "approach_time_s": _r(n_win * dt),
        "reason_share": shares(reasons, REASONS),
        "mode_share": shares(modes, ("AUTO", "C_SLOW", "C_FAST")),
        "yield_time_s": _r(np.count_nonzero(reasons == "yield") * dt),
        "first_yield": at(iy, to=tr.detail[iy] if iy is not None else ""),
        "first_caution": at(ic),
        "first_emergency": at(ie, to=tr.detail[ie] if ie is not None else ""),
        "mode_sequence": _sequence(modes),
        "stops": stops,
        "mode_changes": changes,
        "first_c_fast": at(i_fast),
        "first_c_slow": at(i_slow),
        "min_speed_approach_mps": _r(tr.speed[window].min(), 2) if n_win else None,
        "speed_at_centre_mps": None if speed_at_centre is None else _r(speed_at_centre, 2),
    }


def _stop(
    tr: VehicleTrace, rel: np.ndarray[Any, Any], crossing: Crossing, i0: int, i1: int
) -> dict[str, Any]:
    return {
        "t_s": _r(tr.t[i0]),
        "distance_m": _r(-rel[i0], 2),
        "behind_stop_line_m": _r(crossing.s_stop - tr.s[i0], 2),
        "duration_s": _r(tr.t[i1] - tr.t[i0]),
    }


def _sequence(modes: np.ndarray[Any, Any]) -> str:
    """The coordination modes a car went through, e.g. ``AUTO→C_FAST→AUTO``."""
    seq: list[str] = []
    for m in modes.tolist():
        if not seq or seq[-1] != m:
            seq.append(str(m))
    return "→".join(seq)


def analyse_trial(scenario: Scenario, rows: Sequence[tuple[Any, ...]]) -> dict[str, Any]:
    """:func:`analyse_vehicle` for every car of one trial (at its first intersection)."""
    traces = split_trace(rows)
    out: dict[str, Any] = {}
    for v in scenario.vehicles:
        crossings = scenario.vehicle_crossings(v.id)
        if v.id not in traces or not crossings:
            continue
        out[v.id] = analyse_vehicle(
            traces[v.id], crossings[0], scenario.goal_m(v.id), scenario.params.goal_tolerance_m
        )
    return out


def _mean(values: Sequence[float | None]) -> float | None:
    return summarize(values)["mean"]  # type: ignore[no-any-return]


def aggregate_behaviour(per_trial: Sequence[Mapping[str, Any]], vehicle: str) -> dict[str, Any]:
    """Means and counts over trials of one car's :func:`analyse_vehicle` results."""
    items = [t[vehicle] for t in per_trial if vehicle in t]
    n = len(items)
    reason_keys = sorted({k for it in items for k in it["reason_share"]}, key=_reason_order)
    yields = [it["first_yield"] for it in items if it["first_yield"] is not None]
    stopped = [it for it in items if it["stops"]]
    first_stops = [it["stops"][0] for it in stopped]
    fast = [it["first_c_fast"] for it in items if it["first_c_fast"] is not None]
    slow = [it["first_c_slow"] for it in items if it["first_c_slow"] is not None]
    cautions = [it["first_caution"] for it in items if it["first_caution"] is not None]
    emergencies = [it["first_emergency"] for it in items if it["first_emergency"] is not None]
    sequences: dict[str, int] = {}
    for it in items:
        sequences[it["mode_sequence"]] = sequences.get(it["mode_sequence"], 0) + 1
    return {
        "trials": n,
        "reason_share": {
            k: _mean([it["reason_share"].get(k, 0.0) for it in items]) for k in reason_keys
        },
        "mode_share": {
            k: _mean([it["mode_share"].get(k, 0.0) for it in items])
            for k in ("AUTO", "C_SLOW", "C_FAST")
        },
        "yield_trials": len(yields),
        "first_yield_distance_m": summarize([y["distance_m"] for y in yields]),
        "first_yield_speed_mps": summarize([y["speed_mps"] for y in yields]),
        "first_yield_t_s": summarize([y["t_s"] for y in yields]),
        "yield_time_s": summarize([it["yield_time_s"] for it in items]),
        "caution_trials": len(cautions),
        "first_caution_distance_m": summarize([c["distance_m"] for c in cautions]),
        "stop_trials": len(stopped),
        "stops_total": sum(len(it["stops"]) for it in items),
        "first_stop_distance_m": summarize([s["distance_m"] for s in first_stops]),
        "first_stop_behind_line_m": summarize([s["behind_stop_line_m"] for s in first_stops]),
        "stopped_time_s": summarize([sum(s["duration_s"] for s in it["stops"]) for it in stopped]),
        "mode_changes": summarize([len(it["mode_changes"]) for it in items]),
        "c_fast_trials": len(fast),
        "first_c_fast_distance_m": summarize([f["distance_m"] for f in fast]),
        "c_slow_trials": len(slow),
        "first_c_slow_distance_m": summarize([s["distance_m"] for s in slow]),
        "emergency_trials": len(emergencies),
        "first_emergency_distance_m": summarize([e["distance_m"] for e in emergencies]),
        "emergency_for": sorted({e["to"] for e in emergencies if e["to"]}),
        "mode_sequences": dict(sorted(sequences.items(), key=lambda kv: (-kv[1], kv[0]))),
        "min_speed_approach_mps": summarize([it["min_speed_approach_mps"] for it in items]),
        "speed_at_centre_mps": summarize([it["speed_at_centre_mps"] for it in items]),
    }


def _reason_order(k: str) -> tuple[int, str]:
    return (REASONS.index(k) if k in REASONS else len(REASONS), k)


# --------------------------------------------------------------------------- aggregates


def aggregate_column(
    runs: Sequence[Mapping[str, Any]], vehicles: Sequence[str], baseline_avg: float | None
) -> dict[str, Any]:
    """Table I's numbers for one column from its per-trial runs (``result``: a run result
    or its JSON form, ``behaviour``: :func:`analyse_trial` or None)."""
    results = [_result(r["result"]) for r in runs]
    first = {v: sum(1 for r in results if r.vehicles[v].first_through) for v in vehicles}
    first["none"] = sum(
        1 for r in results if not any(r.vehicles[v].first_through for v in vehicles)
    )
    passing = {v: summarize([r.vehicles[v].passing_time_s for r in results]) for v in vehicles}
    every = [r.vehicles[v].passing_time_s for r in results for v in vehicles]
    avg = summarize(every)
    change = (
        None
        if baseline_avg is None or avg["mean"] is None
        else round(100.0 * (avg["mean"] - baseline_avg) / baseline_avg, 2)
    )
    out: dict[str, Any] = {
        "trials": len(results),
        "first_through": first,
        "passing_time_s": passing,
        "average_passing_time_s": avg,
        "change_vs_standalone_pct": change,
        "stops": {v: summarize([r.vehicles[v].stops for r in results]) for v in vehicles},
        "collisions": sum(r.collisions for r in results),
        "trials_with_collision": sum(1 for r in results if r.collisions),
        "min_gap_m": summarize([r.min_gap_m for r in results]),
        "min_pet_s": summarize([r.min_pet_s for r in results]),
        "all_finished_trials": sum(1 for r in results if r.all_finished),
    }
    traced = [r["behaviour"] for r in runs if r.get("behaviour") is not None]
    out["behaviour"] = (
        {v: aggregate_behaviour(traced, v) for v in vehicles} if len(traced) == len(runs) else None
    )
    return out


def _result(value: RunResult | Mapping[str, Any]) -> RunResult:
    """A run result, from the document's JSON form if need be."""
    return value if isinstance(value, RunResult) else RunResult.model_validate(value)


def _column_results(doc: Mapping[str, Any], key: str) -> list[RunResult]:
    """The run results of one column of the document, in trial order."""
    return [_result(r["result"]) for r in doc["runs"][key]]


# --------------------------------------------------------------------------- table


def table_rows(
    columns: Sequence[Column], aggregates: Mapping[str, Any], vehicles: Sequence[str]
) -> tuple[list[str], list[list[str]]]:
    """Header and rows of Table I: each of our columns, followed by the paper's
    number for it when the paper has that column."""
    ref = PAPER_REFERENCE["columns"]
    header = [""]
    for c in columns:
        header.append(c.title)
        if c.key in ref:
            header.append("paper")
    rows: list[list[str]] = []

    def row(label: str, ours: Any, paper: Any) -> None:
        cells = [label]
        for c in columns:
            cells.append(ours(aggregates[c.key]))
            if c.key in ref:
                cells.append(paper(c.key, ref[c.key]))
        rows.append(cells)

    def dash(_k: str, _p: Any) -> str:
        return "–"

    def pm(s: Mapping[str, Any], unit: str) -> str:
        text = fmt_ci(s, unit)
        return text + (f" ({s['missing']} missing)" if s["missing"] and s["mean"] else "")

    paper_trials = PAPER_REFERENCE["trials"]
    for v in vehicles:
        row(
            f"Car {v} passes first",
            lambda a, v=v: f"{a['first_through'][v]} / {a['trials']}",
            lambda _k, p, v=v: (
                f"{p['first_through'][v]} / {paper_trials}" if v in p["first_through"] else "–"
            ),
        )
    for v in vehicles:
        row(
            f"Car {v} passing time",
            lambda a, v=v: pm(a["passing_time_s"][v], "s"),
            lambda _k, p, v=v: fmt_num(p["passing_time_s"].get(v), "s"),
        )
    row(
        "Average passing time",
        lambda a: pm(a["average_passing_time_s"], "s"),
        lambda _k, p: fmt_num(p["average_passing_time_s"], "s"),
    )
    row(
        "Change vs stand-alone",
        lambda a: (
            fmt_signed_pct(a["change_vs_standalone_pct"])
            if a is not aggregates[columns[0].key]
            else "–"
        ),
        lambda k, _p: fmt_signed_pct(_paper_change_pct(k)),
    )
    for v in vehicles:
        row(
            f"Car {v} stops per trial",
            lambda a, v=v: fmt_num(a["stops"][v]["mean"], digits=1),
            dash,
        )
    row(
        "Collisions (trials with one)",
        lambda a: f"{a['collisions']} ({a['trials_with_collision']} / {a['trials']})",
        dash,
    )
    row("Min gap (worst trial)", lambda a: fmt_num(a["min_gap_m"]["min"], "m"), dash)
    row("Min PET (worst trial)", lambda a: fmt_num(a["min_pet_s"]["min"], "s"), dash)
    return header, rows


def render_table(doc: Mapping[str, Any]) -> str:
    """``table.md``: Table I for our system beside the paper's numbers."""
    columns = _columns_of(doc)
    header, rows = table_rows(columns, doc["aggregates"], doc["vehicles"])
    trials = doc["trials"]
    seeds = f"{doc['base_seed']}..{doc['base_seed'] + trials - 1}"
    return (
        f"# Passing time at the blind intersection ({_plural(trials, 'trial')} per column)\n\n"
        + markdown_table(header, rows)
        + "\n\n"
        + f"Ours: {doc['harness']} harness, scenario `{doc['scenario_name']}`, seeds {seeds}"
        " (trial i uses seed base + i in every column); passing times are the mean over"
        " trials [its 95 % Student-t interval]. Counts are k / N trials (the paper's"
        f" N = {PAPER_REFERENCE['trials']}). Average passing time: mean over every car and"
        " trial. Min gap and PET: the smallest of any trial.\n"
        + f"Paper: {PAPER_REFERENCE['source']}. {PAPER_REFERENCE['note']}\n"
    )


def _columns_of(doc: Mapping[str, Any]) -> list[Column]:
    by_key = {c.key: c for c in COLUMNS}
    out = []
    for c in doc["columns"]:
        if c["key"] in by_key:
            out.append(by_key[c["key"]])
        else:
            out.append(Column(c["key"], c["title"], RunMode(c["mode"]), Policy(c["policy"])))
    return out


# --------------------------------------------------------------------------- figures


LINE_STYLES: tuple[str, ...] = ("-", "--", "-.", ":")
MARKERS: tuple[str, ...] = ("o", "s", "^", "D", "v", "P")
"""Each car its own line style and marker besides its colour, so lines that lie on top
of each other (or are printed in grey) stay distinguishable."""


def _figure_legend(fig: Any, handles: Sequence[Any], ncol: int) -> None:
    """One legend for the whole figure, below the panels, explaining every mark."""
    fig.legend(
        handles=list(handles),
        loc="lower center",
        ncol=ncol,
        fontsize=8,
        frameon=False,
        bbox_to_anchor=(0.5, 0.0),
    )


def plot_speed_profiles(
    doc: Mapping[str, Any],
    traces: Mapping[str, Sequence[Mapping[str, VehicleTrace]]],
    scenario: Scenario,
    path: Path,
) -> list[str]:
    """Speed against position relative to the intersection centre, one panel per
    column: each trial a thin transparent line, the binned mean a thick one with the
    car's own style and markers; one legend for the figure explains every mark.
    Returns the files written (PNG, PDF, SVG)."""
    from matplotlib.lines import Line2D
    from matplotlib.patches import Patch

    plt = pyplot()
    columns = _columns_of(doc)
    vehicles: list[str] = list(doc["vehicles"])
    crossing = {v: scenario.vehicle_crossings(v)[0] for v in vehicles}
    lo, hi = PROFILE_RANGE_M
    edges = np.arange(lo, hi + PROFILE_BIN_M, PROFILE_BIN_M)
    mids = 0.5 * (edges[:-1] + edges[1:])
    ncols = min(len(columns), 2)
    nrows = -(-len(columns) // ncols)
    fig, axes = plt.subplots(
        nrows,
        ncols,
        figsize=(7.0, 2.5 * nrows + 0.7),
        sharex=True,
        sharey=True,
        squeeze=False,
    )
    v_max = scenario.params.v_max_mps
    every = max(int(len(mids) / 8), 1)
    for i, col in enumerate(columns):
        ax = axes[i // ncols][i % ncols]
        agg = doc["aggregates"][col.key]
        mean_pt = agg["average_passing_time_s"]["mean"]
        ax.set_title(
            f"{col.title}\navg passing {fmt_num(mean_pt, 's')}, n = {agg['trials']}",
            fontsize=8.5,
        )
        c0 = crossing[vehicles[0]]
        ax.axvspan(c0.s_in - c0.center_s, c0.s_out - c0.center_s, color="0.88", lw=0)
        for x in sorted({round(c.s_stop - c.center_s, 2) for c in crossing.values()}):
            ax.axvline(x, color="0.35", lw=0.8, ls=":")
        ax.axhline(v_max, color="0.55", lw=0.7, ls="--")
        col_traces = traces.get(col.key, [])
        if not col_traces:
            ax.text(0.5, 0.5, "no trace", ha="center", va="center", transform=ax.transAxes)
        for k, v in enumerate(vehicles):
            colour = vehicle_color(k)
            binned = []
            for trial in col_traces:
                tr = trial.get(v)
                if tr is None:
                    continue
                rel = tr.s - crossing[v].center_s
                keep = (rel >= lo) & (rel <= hi)
                ax.plot(rel[keep], tr.speed[keep], color=colour, lw=0.5, alpha=0.25)
                binned.append(binned_mean(rel, tr.speed, edges))
            if binned:
                with warnings.catch_warnings():
                    warnings.simplefilter("ignore", category=RuntimeWarning)
                    mean = np.nanmean(np.vstack(binned), axis=0)
                ax.plot(
                    mids,
                    mean,
                    color=colour,
                    lw=1.8,
                    ls=LINE_STYLES[k % len(LINE_STYLES)],
                    marker=MARKERS[k % len(MARKERS)],
                    markevery=(k * every // max(len(vehicles), 1), every),
                    ms=4,
                    mfc="white",
                )
        ax.set_xlim(lo, hi)
        ax.set_ylim(0.0, v_max * 1.12)
        ax.grid(True, lw=0.3, alpha=0.5)
        ax.tick_params(labelsize=8)
    for j in range(len(columns), nrows * ncols):
        axes[j // ncols][j % ncols].set_visible(False)
    for ax in axes[-1]:
        ax.set_xlabel("car centre rel. to the intersection centre [m]", fontsize=8)
    for row in axes:
        row[0].set_ylabel("speed [m/s]", fontsize=9)
    handles: list[Any] = [
        Line2D(
            [],
            [],
            color=vehicle_color(k),
            lw=1.8,
            ls=LINE_STYLES[k % len(LINE_STYLES)],
            marker=MARKERS[k % len(MARKERS)],
            mfc="white",
            label=f"car {v}, mean per {PROFILE_BIN_M:g} m",
        )
        for k, v in enumerate(vehicles)
    ]
    handles += [
        Line2D([], [], color="0.4", lw=0.5, alpha=0.5, label="single trial"),
        Patch(color="0.88", label="conflict zone"),
        Line2D([], [], color="0.35", lw=0.8, ls=":", label="front bumper on the stop line"),
        Line2D([], [], color="0.55", lw=0.7, ls="--", label=f"V_max {v_max:.1f} m/s"),
    ]
    _figure_legend(fig, handles, ncol=3)
    fig.tight_layout(rect=(0.0, 0.12 if nrows == 1 else 0.08, 1.0, 1.0))
    return save_figure(fig, path)


def plot_passing_times(doc: Mapping[str, Any], path: Path) -> list[str]:
    """Every car's passing time in every trial, per column (points), the mean with its
    95 % t-interval (bar), the paper's mean (open diamond) where the paper has the
    column; a box plot is drawn only from 10 trials up. Returns the files written."""
    from matplotlib.lines import Line2D

    plt = pyplot()
    columns = _columns_of(doc)
    vehicles: list[str] = list(doc["vehicles"])
    ref = PAPER_REFERENCE["columns"]
    fig, ax = plt.subplots(figsize=(7.0, 3.6))
    width = 0.8 / max(len(vehicles), 1)
    rng = np.random.default_rng(0)  # deterministic jitter
    for ci, col in enumerate(columns):
        results = _column_results(doc, col.key)
        for k, v in enumerate(vehicles):
            x0 = ci - 0.4 + width * (k + 0.5)
            ys = [pt for r in results if (pt := r.vehicles[v].passing_time_s) is not None]
            colour = vehicle_color(k)
            if len(ys) >= 10:
                ax.boxplot(
                    [ys],
                    positions=[x0],
                    widths=width * 0.7,
                    showfliers=False,
                    medianprops={"color": colour, "lw": 1.0},
                    boxprops={"color": colour, "lw": 0.7},
                    whiskerprops={"color": colour, "lw": 0.7},
                    capprops={"color": colour, "lw": 0.7},
                )
            if ys:
                jitter = rng.uniform(-0.3, 0.3, size=len(ys)) * width
                ax.scatter(
                    x0 - 0.15 * width + jitter * 0.5,
                    ys,
                    s=10,
                    color=colour,
                    alpha=0.55,
                    marker=MARKERS[k % len(MARKERS)],
                    zorder=3,
                    lw=0,
                )
                mean = float(np.mean(ys))
                ci95 = t_interval95(ys)
                yerr = None if ci95 is None else [[mean - ci95[0]], [ci95[1] - mean]]
                ax.errorbar(
                    [x0 + 0.25 * width],
                    [mean],
                    yerr=yerr,
                    fmt=MARKERS[k % len(MARKERS)],
                    color=colour,
                    mfc="white",
                    ms=5,
                    capsize=3,
                    lw=1.2,
                    zorder=4,
                )
            pref = ref.get(col.key, {}).get("passing_time_s", {}).get(v)
            if pref is not None:
                ax.scatter(
                    [x0 + 0.25 * width],
                    [pref],
                    marker="D",
                    s=34,
                    facecolor="none",
                    edgecolor="black",
                    lw=0.9,
                    zorder=5,
                )
    ax.set_xticks(range(len(columns)))
    ax.set_xticklabels([c.title for c in columns], fontsize=8)
    ax.set_xlim(-0.6, len(columns) - 0.4)
    ax.set_ylabel("passing time [s]", fontsize=9)
    ax.set_title(
        f"Passing time per car ({_plural(doc['trials'], 'trial')} per column)", fontsize=10
    )
    ax.grid(True, axis="y", lw=0.3, alpha=0.5)
    ax.tick_params(labelsize=8)
    handles: list[Any] = [
        Line2D(
            [],
            [],
            color=vehicle_color(k),
            marker=MARKERS[k % len(MARKERS)],
            ls="",
            mfc="white",
            label=f"car {v}: mean, 95 % CI; dots: trials",
        )
        for k, v in enumerate(vehicles)
    ]
    handles.append(
        Line2D([], [], color="black", marker="D", mfc="none", ls="", label="paper's mean")
    )
    _figure_legend(fig, handles, ncol=len(handles))
    fig.tight_layout(rect=(0.0, 0.08, 1.0, 1.0))
    return save_figure(fig, path)


def runs_rows(doc: Mapping[str, Any]) -> list[dict[str, Any]]:
    """``runs.csv``'s rows: one per run, its parameters and every metric, per car too."""
    vehicles: list[str] = doc["vehicles"]
    rows: list[dict[str, Any]] = []
    for col in _columns_of(doc):
        for trial, res in enumerate(_column_results(doc, col.key)):
            row: dict[str, Any] = {
                "experiment": "paper",
                "scenario": doc["scenario_name"],
                "harness": doc["harness"],
                "column": col.key,
                "mode": str(col.mode),
                "policy": str(col.policy),
                "loss": col.loss,
                "trial": trial,
                "seed": res.seed,
                "collisions": res.collisions,
                "min_gap_m": res.min_gap_m,
                "min_pet_s": res.min_pet_s,
                "all_finished": res.all_finished,
                "mean_passing_time_s": res.mean_passing_time_s,
                "sim_s": res.sim_s,
            }
            for v in vehicles:
                veh = res.vehicles[v]
                row[f"{v}_start_s"] = res.start_times.get(v)
                row[f"{v}_passing_time_s"] = veh.passing_time_s
                row[f"{v}_first_through"] = veh.first_through
                row[f"{v}_stops"] = veh.stops
            rows.append(row)
    return rows


# --------------------------------------------------------------------------- report


def _plural(n: int, word: str, plural: str | None = None) -> str:
    return f"{n} {word if n == 1 else (plural or word + 's')}"


def _pct(x: float | None) -> str:
    return "–" if x is None else f"{100.0 * x:.0f} %"


def _m(s: Mapping[str, Any], unit: str, digits: int = 1) -> str:
    return fmt_num(s["mean"], unit, digits)


def _count(k: int, n: int) -> str:
    return f"{k} of {n} trials" if k not in (0, n) else ("every trial" if k == n else "no trial")


def _vehicle_sentences(v: str, b: Mapping[str, Any]) -> list[str]:
    """What one car did in one column, from its aggregated trace analysis."""
    n = b["trials"]
    out: list[str] = []
    shares = {k: x for k, x in b["reason_share"].items() if x}
    ranked = sorted(shares.items(), key=lambda kv: -kv[1])
    if ranked:
        parts = ", ".join(f"{k} {_pct(x)}" for k, x in ranked)
        out.append(
            f"In its last {APPROACH_M:.0f} m before the centre, car {v}'s speed was set by: {parts}"
            " of the time."
        )
    if b["caution_trials"]:
        out.append(
            f"Blind-corner caution bound it in {_count(b['caution_trials'], n)}, first at"
            f" {_m(b['first_caution_distance_m'], 'm')} before the centre."
        )
    if b["yield_trials"]:
        out.append(
            f"It yielded in {_count(b['yield_trials'], n)}: first at"
            f" {_m(b['first_yield_distance_m'], 'm')} before the centre, at"
            f" {_m(b['first_yield_speed_mps'], 'm/s')} and t = {_m(b['first_yield_t_s'], 's')},"
            f" yielding for {_m(b['yield_time_s'], 's')} in all (mean per trial)."
        )
    else:
        out.append("It never yielded.")
    if b["stop_trials"]:
        behind = b["first_stop_behind_line_m"]["mean"]
        where = (
            f"{abs(behind):.1f} m {'behind' if behind >= 0 else 'past'} its stop line"
            if behind is not None
            else ""
        )
        out.append(
            f"It stopped in {_count(b['stop_trials'], n)} ({b['stops_total']} stops), first at"
            f" {_m(b['first_stop_distance_m'], 'm')} before the centre ({where}), standing"
            f" {_m(b['stopped_time_s'], 's')} per stopping trial."
        )
    else:
        out.append("It never stopped before its goal.")
    coord = b["mode_share"]
    if b["c_fast_trials"] or b["c_slow_trials"]:
        bits = []
        if b["c_fast_trials"]:
            bits.append(
                f"`C_FAST` in {_count(b['c_fast_trials'], n)} (first at"
                f" {_m(b['first_c_fast_distance_m'], 'm')} before the centre)"
            )
        if b["c_slow_trials"]:
            bits.append(
                f"`C_SLOW` in {_count(b['c_slow_trials'], n)} (first at"
                f" {_m(b['first_c_slow_distance_m'], 'm')} before the centre)"
            )
        seq, k = next(iter(b["mode_sequences"].items()))
        out.append(
            f"The RSU put it in {' and '.join(bits)}; it changed mode"
            f" {_m(b['mode_changes'], '', 1).strip()} times per trial on average"
            f" (most often {seq.replace('→', ' → ')}, in {_count(k, n)}) and spent"
            f" {_pct(coord.get('C_FAST'))} of its approach in `C_FAST`,"
            f" {_pct(coord.get('C_SLOW'))} in `C_SLOW`."
        )
    if b["emergency_trials"]:
        whom = " and ".join(f"car {x}" for x in b["emergency_for"])
        out.append(
            f"Its emergency rule fired in {_count(b['emergency_trials'], n)}"
            + (f", for {whom}" if whom else "")
            + f", first at {_m(b['first_emergency_distance_m'], 'm')} before the centre."
        )
    out.append(
        f"It crossed the centre at {_m(b['speed_at_centre_mps'], 'm/s')} on average, its"
        f" slowest approach speed averaging {_m(b['min_speed_approach_mps'], 'm/s')}."
    )
    return out


def _compare(v: str, base: Mapping[str, Any], b: Mapping[str, Any], base_title: str) -> str | None:
    """One sentence contrasting a car's yield onset and passing speed with the baseline."""
    bits = []
    dy0, dy1 = base["first_yield_distance_m"]["mean"], b["first_yield_distance_m"]["mean"]
    if dy0 is not None and dy1 is not None and abs(dy1 - dy0) >= 0.5:
        word = "earlier" if dy1 > dy0 else "later"
        bits.append(
            f"started yielding {abs(dy1 - dy0):.1f} m {word} ({dy1:.1f} m vs {dy0:.1f} m"
            " before the centre)"
        )
    elif dy0 is not None and dy1 is None:
        bits.append("no longer yielded")
    elif dy0 is None and dy1 is not None:
        bits.append(f"yielded where it did not before ({dy1:.1f} m before the centre)")
    s0, s1 = base["stop_trials"], b["stop_trials"]
    if s0 != s1:
        bits.append(f"stopped in {s1} trials instead of {s0}")
    c0, c1 = base["speed_at_centre_mps"]["mean"], b["speed_at_centre_mps"]["mean"]
    if c0 is not None and c1 is not None and abs(c1 - c0) >= 0.2:
        bits.append(
            f"crossed the centre {abs(c1 - c0):.1f} m/s {'faster' if c1 > c0 else 'slower'}"
        )
    if not bits:
        return None
    return f"Against {base_title.lower()}, car {v} " + ", ".join(bits) + "."


def _column_paragraph(doc: Mapping[str, Any], col: Column) -> str:
    agg = doc["aggregates"][col.key]
    vehicles: list[str] = doc["vehicles"]
    n = agg["trials"]
    firsts = ", ".join(f"car {v} first in {agg['first_through'][v]}" for v in vehicles)
    lines = [f"### {col.title}", ""]
    what = {
        RunMode.STANDALONE: "No V2X: each car knows of the other only through its sensors,"
        " which the corner buildings block.",
        RunMode.FP_ONLY: "Cars broadcast their future paths to each other (no occlusion),"
        " each planner still decides alone.",
        RunMode.RSU: f"Future paths plus the RSU's coordinated paths ({col.policy} policy).",
    }[col.mode]
    change = agg["change_vs_standalone_pct"]
    head = (
        f"{what} Over {n} trials: {firsts}; average passing time"
        f" {fmt_num(agg['average_passing_time_s']['mean'], 's')}"
    )
    if col.key != COLUMNS[0].key and change is not None:
        head += f" ({fmt_signed_pct(change)} against stand-alone)"
    head += (
        f"; {agg['collisions']} collisions, min gap {fmt_num(agg['min_gap_m']['min'], 'm')},"
        f" min PET {fmt_num(agg['min_pet_s']['min'], 's')}."
    )
    lines.append(head)
    lines.append("")
    beh = agg["behaviour"]
    base_beh = doc["aggregates"].get(COLUMNS[0].key, {}).get("behaviour")  # None: no baseline
    if beh is None:
        lines.append("No planner trace was recorded for this column (daemon harness).")
        return "\n".join(lines)
    for v in vehicles:
        sentences = _vehicle_sentences(v, beh[v])
        if col.key != COLUMNS[0].key and base_beh is not None:
            cmp = _compare(v, base_beh[v], beh[v], COLUMNS[0].title)
            if cmp:
                sentences.append(cmp)
        pt = agg["passing_time_s"][v]["mean"]
        sentences.append(f"Its passing time: {fmt_num(pt, 's')}.")
        lines.append("- " + " ".join(sentences))
    return "\n".join(lines)


def _against_paper(doc: Mapping[str, Any]) -> str:
    lines = []
    for col in _columns_of(doc):
        if col.key == COLUMNS[0].key or col.key not in PAPER_REFERENCE["columns"]:
            continue
        ours = doc["aggregates"][col.key]["change_vs_standalone_pct"]
        paper = _paper_change_pct(col.key)
        if ours is None or paper is None:
            continue
        same = (ours < 0) == (paper < 0) and abs(ours) >= 0.05
        verdict = (
            f"the direction agrees (ours is {abs(ours) / abs(paper) * 100:.0f} % of the"
            " paper's magnitude)"
            if same
            else "the direction differs"
        )
        lines.append(
            f"- {col.title}: paper {fmt_signed_pct(paper)}, ours {fmt_signed_pct(ours)} against"
            f" stand-alone: {verdict}."
        )
    for col in _columns_of(doc):
        if col.key in PAPER_REFERENCE["columns"] or col.key == COLUMNS[0].key:
            continue
        ours = doc["aggregates"][col.key]["change_vs_standalone_pct"]
        lines.append(
            f"- {col.title}: {fmt_signed_pct(ours)} against stand-alone (the paper has no such"
            " column)."
        )
    return "\n".join(lines)


def _per_trial_table(doc: Mapping[str, Any]) -> str:
    vehicles: list[str] = doc["vehicles"]
    header = ["column", "seed", *(f"start {v} [s]" for v in vehicles)]
    header += [f"{v} passing [s]" for v in vehicles] + ["first", "stops", "min gap", "min PET"]
    rows = []
    for col in _columns_of(doc):
        for res in _column_results(doc, col.key):
            veh = res.vehicles
            first = ",".join(v for v in vehicles if veh[v].first_through) or "–"
            rows.append(
                [
                    col.key,
                    str(res.seed),
                    *(fmt_num(res.start_times.get(v), digits=3) for v in vehicles),
                    *(fmt_num(veh[v].passing_time_s) for v in vehicles),
                    first,
                    "/".join(str(veh[v].stops) for v in vehicles),
                    fmt_num(res.min_gap_m, "m"),
                    fmt_num(res.min_pet_s, "s"),
                ]
            )
    return markdown_table(header, rows, ["l"] + ["r"] * (len(header) - 1))


def render_report(doc: Mapping[str, Any], figures: Sequence[str]) -> str:
    """``REPORT.md``: table, figures, and the behaviour of each mode from the traces."""
    trials = doc["trials"]
    timing = doc.get("timing", {})
    header, rows = table_rows(_columns_of(doc), doc["aggregates"], doc["vehicles"])
    parts = [
        "# The paper's experiment, reproduced",
        "",
        f"Scenario `{doc['scenario_name']}`, {_plural(trials, 'trial')} per column, seeds"
        f" {doc['base_seed']}..{doc['base_seed'] + trials - 1}, {doc['harness']} harness."
        + (
            f" The whole run took {timing['wall_s']:.1f} s wall time with"
            f" {_plural(timing['jobs'], 'worker process', 'worker processes')}."
            if "wall_s" in timing
            else ""
        ),
        f"Regenerate: `crosspath experiment paper --trials {trials} --seed {doc['base_seed']}`.",
        "",
        "## Table I",
        "",
        markdown_table(header, rows),
        "",
        f"Paper: {PAPER_REFERENCE['source']}. {PAPER_REFERENCE['note']} Ours: mean over"
        " trials [95 % Student-t interval]; counts k / N trials. Every run, one row each:"
        " `runs.csv`.",
        "",
        "## Figures",
        "",
        "Each figure is also written as PDF and SVG beside the PNG.",
        "",
    ]
    if "speed_profiles.png" in figures:
        parts += [
            "![speed profiles](speed_profiles.png)",
            "",
            "Speed against the position of the car's centre relative to the intersection"
            f" centre; thin lines: single trials, thick: the mean per {PROFILE_BIN_M:g} m bin."
            " Grey band: the conflict zone; dotted: where the centre is when the front bumper"
            " is on the stop line; dashed: V_max.",
            "",
        ]
    parts += [
        "![passing times](passing_times.png)",
        "",
        "Each car's passing time in each trial (dots), the mean with its 95 % t-interval,"
        " box plots from 10 trials up; open diamonds: the paper's means.",
        "",
        "## Why each mode behaves as it does",
        "",
        "From the planner reasons and coordination modes recorded every physics step"
        f" (the last {APPROACH_M:.0f} m before the centre unless said otherwise).",
        "",
    ]
    for col in _columns_of(doc):
        parts += [_column_paragraph(doc, col), ""]
    parts += ["## Against the paper", "", _against_paper(doc), ""]
    parts += ["## Every trial", "", _per_trial_table(doc), ""]
    return "\n".join(parts)


# --------------------------------------------------------------------------- experiment


def run_paper_experiment(
    scenario_path: str | Path,
    trials: int,
    seed: int,
    out_dir: str | Path,
    daemons: bool = False,
    jobs: int | None = None,
    progress: bool = True,
    *,
    save_traces: bool = False,
    speed: float | None = None,
    columns: Sequence[Column] = COLUMNS,
) -> dict[str, Any]:
    """Run every column for ``trials`` trials and write the artefacts into ``out_dir``.

    Returns the document written as ``results.json``. Raises
    :class:`ExperimentError` if any trial fails (nothing is written then) and
    ``ScenarioError`` for an unusable scenario file.
    """
    watch = Stopwatch()
    t0 = time.perf_counter()
    scenario_file = Path(scenario_path)
    scenario = load_scenario(scenario_file)
    vehicles = [v.id for v in scenario.vehicles]
    out = Path(out_dir)
    if daemons:
        runner: Runner = DaemonRunner(speed=speed, run_dir_root=str(out / "daemons"))
        n_jobs = 1
    else:
        runner = run_in_process
        n_jobs = jobs if jobs is not None else _default_jobs()
    plan = trials_for(columns, scenario_file, trials, seed, trace=True)
    with watch.phase("runs_s"):
        outcomes = run_trials(
            plan, runner, jobs=n_jobs, progress=progress, description="paper experiment"
        )
    errors = collect_errors(outcomes)
    if errors:
        raise ExperimentError(
            f"{len(errors)} of {len(outcomes)} trials failed:\n  " + "\n  ".join(errors)
        )
    with watch.phase("analysis_s"):
        runs: dict[str, list[dict[str, Any]]] = {c.key: [] for c in columns}
        traces: dict[str, list[dict[str, VehicleTrace]]] = {c.key: [] for c in columns}
        for o in outcomes:
            if o.result is None:  # pragma: no cover (errors raised above)
                continue
            behaviour = analyse_trial(scenario, o.trace) if o.trace is not None else None
            runs[o.trial.column.key].append(
                {"trial": o.trial.index, "result": o.result.to_dict(), "behaviour": behaviour}
            )
            if o.trace is not None:
                traces[o.trial.column.key].append(split_trace(o.trace))
        aggregates: dict[str, Any] = {}
        baseline: float | None = None
        for c in columns:
            aggregates[c.key] = aggregate_column(runs[c.key], vehicles, baseline)
            if c is columns[0]:
                baseline = aggregates[c.key]["average_passing_time_s"]["mean"]
                aggregates[c.key]["change_vs_standalone_pct"] = None
    doc: dict[str, Any] = {
        "experiment": "paper",
        "scenario": str(scenario_file),
        "scenario_name": scenario.name,
        "harness": "daemons" if daemons else "in-process",
        "trials": trials,
        "base_seed": seed,
        "vehicles": vehicles,
        "approach_window_m": APPROACH_M,
        "columns": [
            {
                "key": c.key,
                "title": c.title,
                "mode": str(c.mode),
                "policy": str(c.policy),
                "loss": c.loss,
            }
            for c in columns
        ],
        "paper_reference": PAPER_REFERENCE,
        "aggregates": aggregates,
        "runs": runs,
    }
    out.mkdir(parents=True, exist_ok=True)
    figures: list[str] = []
    with watch.phase("figures_s"):
        if any(traces.values()):
            figures += plot_speed_profiles(doc, traces, scenario, out / "speed_profiles.png")
        figures += plot_passing_times(doc, out / "passing_times.png")
    write_runs_csv(out / "runs.csv", runs_rows(doc))
    if save_traces:
        for o in outcomes:
            if o.trace is not None:
                write_trace_csv(
                    out / "traces" / f"{o.trial.column.key}-seed{o.trial.seed}.csv", o.trace
                )
    doc["timing"] = {
        "wall_s": round(time.perf_counter() - t0, 3),
        "jobs": n_jobs,
        "sum_of_run_wall_s": round(sum(o.wall_s for o in outcomes), 3),
        **watch.phases,
    }
    (out / "table.md").write_text(render_table(doc))
    (out / "REPORT.md").write_text(render_report(doc, figures))
    write_json(out / "results.json", doc)
    return doc


def _default_jobs() -> int:
    return os.cpu_count() or 1


# --------------------------------------------------------------------------- CLI


def configure(parser: argparse.ArgumentParser) -> None:
    """Options of ``crosspath experiment paper``; bad values are refused while parsing."""
    parser.add_argument(
        "--trials", type=positive_int, default=DEFAULT_TRIALS, help="trials per column"
    )
    parser.add_argument("--out", type=output_dir, default=DEFAULT_OUT, help="output directory")
    parser.add_argument(
        "--seed", type=non_negative_int, default=0, help="base seed: trial i uses seed + i"
    )
    parser.add_argument(
        "--jobs", type=positive_int, default=None, help="worker processes (default: all cores)"
    )
    add_scenario_option(parser)
    parser.add_argument(
        "--daemons",
        action="store_true",
        help="run each trial with real daemons over Zenoh (as crosspath up), one after another",
    )
    parser.add_argument(
        "--speed",
        type=run_speed,
        default=None,
        help="with --daemons: run seconds per wall second (default: the launcher's)",
    )
    parser.add_argument(
        "--traces", action="store_true", help="also write every trial's per-tick CSV"
    )


def run(args: argparse.Namespace) -> int:
    if args.trials < 1:
        print("crosspath experiment paper: --trials must be >= 1", file=sys.stderr)
        return 2
    if args.seed < 0:
        print("crosspath experiment paper: --seed must be >= 0", file=sys.stderr)
        return 2
    if args.jobs is not None and args.jobs < 1:
        print("crosspath experiment paper: --jobs must be >= 1", file=sys.stderr)
        return 2
    try:
        doc = run_paper_experiment(
            args.scenario,
            args.trials,
            args.seed,
            args.out,
            daemons=args.daemons,
            jobs=args.jobs,
            progress=True,
            save_traces=args.traces,
            speed=args.speed,
        )
    except ScenarioError as exc:
        print(f"crosspath experiment paper: {exc}", file=sys.stderr)
        return 2
    except ExperimentError as exc:
        print(f"crosspath experiment paper: {exc}", file=sys.stderr)
        return 1
    print(render_table(doc))
    t = doc["timing"]
    print(
        f"{len(doc['columns'])} columns x {_plural(doc['trials'], 'trial')} in {t['wall_s']:.1f} s"
        f" ({_plural(t['jobs'], 'worker process', 'worker processes')});"
        f" wrote results.json, table.md, REPORT.md and figures to {args.out}"
    )
    return 0
