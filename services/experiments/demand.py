"""``crosspath experiment demand``: delay against demand at a 4-way, crosspath beside SUMO.

The geometry of ``scenarios/four-way-flows.toml`` (one lane per approach, 150 m
approaches, buildings on the corners, one RSU): every approach gets ``demand``
veh/h for ``horizon_s`` seconds, straight only or a turning mix (70 % straight, 15 %
left, 15 % right), Poisson arrivals drawn from the seed. Each (demand, mix, seed) runs

- crosspath in-process (``services.api.simulate``, trials in parallel processes) in
  the modes ``standalone``, ``fp-only``, ``rsu/paper`` and ``rsu/slot``;
- SUMO on the same geometry (``services.sumo.netgen``) and the **same arrivals** (the
  crosspath draw of that seed becomes SUMO's departures, car for car) with the junction
  controls priority, all-way stop and actuated traffic light
  (``services.sumo.baseline``; delay = timeLoss + departDelay - the route's free-flow
  timeLoss, crosspath's definition).

A run lasts until every car has finished or ``horizon_s + clearance_s`` (crosspath's
``max_sim_s``, SUMO's end). Per run: cars that arrived, were inserted, finished;
mean and p95 delay over the finished cars; collisions. Across seeds: the mean of the
per-run mean delays with its 95 % Student-t interval.

Writes into ``--out``: ``results.json`` (every run: crosspath run results without
trace, SUMO runs with their per-car delays), ``runs.csv`` (one row per run),
``table.md``, ``delay_vs_demand.png`` (+ ``.pdf``, ``.svg``, 300 dpi) and
``REPORT.md``; the generated scenarios in ``scenarios/`` and SUMO's files in ``sumo/``.

Decisions where the issue is silent: the default run (meant to take under 15 min on 2
idle cores; crosspath's cost grows with the cars in the world at once, so 800 veh/h,
where every control saturates, is left to ``--full``) is 200/400/600 veh/h (the demands
of the issue's SUMO reference), straight only, 2 seeds, 60 s of demand and 120 s to
clear (a run ends as soon as every car has finished: at 600 veh/h the RSU modes' last cars
finish at 126-139 s, so a 60 s clearance cut cars that were still driving and left them
out of the mean delay); ``--full`` is the issue's grid (200..800 veh/h, both mixes, 5 seeds, 600 s,
300 s clearance); ``--quick`` is one seed, 400 veh/h, straight, 30 s (the test).
Mean delay is over finished cars only (as ``RunSummary.mean_delay_s``); the table
always shows finished out of arrived beside it, so a run that strands cars cannot
look good unnoticed. The SUMO reference figures of the issue (SUMO 1.28, straight
only, a 290 m stretch) are drawn on the straight panel for comparison, not rerun.
"""

from __future__ import annotations

import argparse
import math
import multiprocessing
import os
import sys
import time
from collections.abc import Mapping, Sequence
from concurrent.futures import ProcessPoolExecutor, as_completed
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Final

import numpy as np

from services.edge.args import non_negative_int, output_dir, positive_float, positive_int
from services.experiments.common import (
    Column,
    Trial,
    TrialOutcome,
    collect_errors,
    fmt_ci,
    fmt_num,
    markdown_table,
    pyplot,
    run_in_process,
    save_figure,
    summarize,
    write_json,
    write_runs_csv,
)
from services.model.catalog import resolve_scenario
from services.model.scenario import FlowSpec, Scenario, ScenarioError, load_scenario
from services.model.types import Policy, RunMode
from services.sumo.baseline import SumoRun, free_time_loss, run_sumo
from services.sumo.netgen import JUNCTION_TYPES, Control, SumoNotFound
from services.supervise.expand import scenario_toml

__all__ = [
    "COLUMNS",
    "DEFAULT_OUT",
    "MIXES",
    "SUMO_REFERENCE",
    "DemandConfig",
    "configure",
    "demand_scenario",
    "run",
    "run_demand_experiment",
]

DEFAULT_OUT: Final = Path("results/demand")
TEMPLATE: Final = "four-way-flows"

COLUMNS: tuple[Column, ...] = (
    Column("standalone", "standalone", RunMode.STANDALONE),
    Column("fp-only", "fp-only", RunMode.FP_ONLY),
    Column("rsu-paper", "rsu/paper", RunMode.RSU, Policy.PAPER),
    Column("rsu-slot", "rsu/slot", RunMode.RSU, Policy.SLOT),
)
"""crosspath's modes in this experiment."""

MIXES: dict[str, tuple[float, float, float]] = {
    "straight": (1.0, 0.0, 0.0),
    "turning": (0.70, 0.15, 0.15),
}
"""Mix name -> shares (straight, left, right) of each approach's demand."""

# side -> (straight, left, right) route ids of scenarios/four-way-flows.toml
_MOVES: dict[str, tuple[str, str, str]] = {
    "w": ("we", "wn", "ws"),
    "e": ("ew", "es", "en"),
    "s": ("sn", "sw", "se"),
    "n": ("ns", "ne", "nw"),
}

SUMO_REFERENCE: dict[str, dict[int, float]] = {
    "priority": {200: 5.3, 400: 15.7, 600: 68.4},
    "allway_stop": {200: 10.8, 400: 23.5, 600: 122.5},
    "traffic_light": {200: 15.3, 400: 17.7, 600: 18.6},
}
"""The issue's reference mean delays [s] (SUMO 1.28, straight only, 290 m stretch)."""


@dataclass(frozen=True, slots=True)
class DemandConfig:
    """The grid: demands [veh/h per approach], mixes, seeds ``base_seed ..
    base_seed + seeds - 1``, flows over ``[0, horizon_s)``, runs end at ``horizon_s +
    clearance_s`` [s]; which crosspath columns and SUMO controls run; ``jobs`` processes."""

    demands: tuple[float, ...] = (200.0, 400.0, 600.0)
    mixes: tuple[str, ...] = ("straight",)
    seeds: int = 2
    base_seed: int = 0
    horizon_s: float = 60.0
    clearance_s: float = 120.0
    columns: tuple[str, ...] = tuple(c.key for c in COLUMNS)
    controls: tuple[str, ...] = tuple(c.value for c in JUNCTION_TYPES)
    jobs: int | None = None

    def __post_init__(self) -> None:
        if not self.demands or any(not (math.isfinite(d) and d > 0) for d in self.demands):
            raise ValueError(f"demands must be > 0 veh/h, got {self.demands}")
        unknown = [m for m in self.mixes if m not in MIXES]
        if unknown or not self.mixes:
            raise ValueError(f"unknown mix {unknown} (known: {', '.join(MIXES)})")
        if self.seeds < 1 or self.base_seed < 0:
            raise ValueError("seeds must be >= 1 and base_seed >= 0")
        if not (self.horizon_s > 0 and self.clearance_s >= 0):
            raise ValueError("horizon_s must be > 0 and clearance_s >= 0")
        keys = {c.key for c in COLUMNS}
        if any(c not in keys for c in self.columns):
            raise ValueError(f"unknown mode {self.columns} (known: {', '.join(sorted(keys))})")
        known = {c.value for c in JUNCTION_TYPES}
        if any(c not in known for c in self.controls):
            raise ValueError(f"unknown control {self.controls} (known: {', '.join(known)})")

    @property
    def max_sim_s(self) -> float:
        return self.horizon_s + self.clearance_s

    @classmethod
    def full(cls, jobs: int | None = None) -> DemandConfig:
        """The issue's whole grid: 200..800 veh/h, both mixes, seeds 0..4, 600 s of demand,
        300 s to clear."""
        return cls(
            demands=(200.0, 400.0, 600.0, 800.0), mixes=("straight", "turning"), seeds=5,
            horizon_s=600.0, clearance_s=300.0, jobs=jobs,
        )  # fmt: skip

    @classmethod
    def quick(cls, jobs: int | None = None) -> DemandConfig:
        """One seed, 400 veh/h straight for 30 s: every mode and control, for the test."""
        return cls(
            demands=(400.0,), mixes=("straight",), seeds=1, horizon_s=30.0, clearance_s=40.0,
            jobs=jobs,
        )  # fmt: skip


def demand_scenario(
    template: Scenario, demand_vph: float, mix: str, horizon_s: float, max_sim_s: float
) -> Scenario:
    """``template`` (the 4-way of ``four-way-flows.toml``) with its flows replaced:
    ``demand_vph`` per approach split by ``MIXES[mix]``, over ``[0, horizon_s)``; flow ids
    are the route ids (so a car ``we-3`` is on route ``we`` in crosspath and SUMO)."""
    shares = MIXES[mix]
    flows = [
        FlowSpec(id=route, route=route, vehicles_per_hour=demand_vph * share, end_s=horizon_s)
        for side in "wesn"
        for route, share in zip(_MOVES[side], shares, strict=True)
        if share > 0
    ]
    spec = template.spec.model_copy(
        update={
            "flows": flows,
            "vehicles": [],
            "params": template.params.model_copy(update={"max_sim_s": max_sim_s}),
            "scenario": template.spec.scenario.model_copy(
                update={
                    "name": f"four-way-demand-{demand_vph:g}-{mix}",
                    "description": f"4-way, {demand_vph:g} veh/h per approach, {mix}, "
                    f"{horizon_s:g} s of demand",
                }
            ),
        }
    )
    return Scenario(spec, template.source)


# --------------------------------------------------------------------------- running


@dataclass(frozen=True, slots=True)
class _SumoTask:
    """One SUMO run, picklable for the process pool."""

    demand: float
    mix: str
    seed: int
    control: str
    departures: dict[str, list[float]]
    max_sim_s: float
    free: dict[str, float]
    workdir: str

    def __call__(self) -> dict[str, Any]:
        tag = f"{self.demand:g}-{self.mix}-s{self.seed}"
        run = run_sumo(
            Path(self.workdir) / self.control / tag,  # its own network: runs in parallel
            Control(self.control),
            self.departures,
            self.max_sim_s,
            self.free,
            tag=tag,
        )
        return {"demand_vph": self.demand, "mix": self.mix, "seed": self.seed, "run": run}


def _call(task: _SumoTask) -> dict[str, Any]:
    return task()


def _sumo_runs(
    cfg: DemandConfig,
    scenarios: Mapping[tuple[float, str], Scenario],
    workdir: Path,
    progress: bool,
) -> list[dict[str, Any]]:
    """Every SUMO run of the grid, in ``cfg.jobs`` processes (libsumo runs one
    simulation per process), in grid order."""
    free = free_time_loss(workdir / "free")
    tasks = [
        _SumoTask(demand, mix, cfg.base_seed + i, control, sc.draw_arrivals(cfg.base_seed + i),
                  cfg.max_sim_s, free, str(workdir))
        for (demand, mix), sc in scenarios.items()
        for i in range(cfg.seeds)
        for control in cfg.controls
    ]  # fmt: skip
    n_jobs = max(1, min(cfg.jobs if cfg.jobs is not None else (os.cpu_count() or 1), len(tasks)))
    methods = multiprocessing.get_all_start_methods()
    ctx = multiprocessing.get_context("forkserver" if "forkserver" in methods else "spawn")
    rows: list[dict[str, Any] | None] = [None] * len(tasks)
    with ProcessPoolExecutor(max_workers=n_jobs, mp_context=ctx) as pool:
        futures = {pool.submit(_call, t): k for k, t in enumerate(tasks)}
        for n, fut in enumerate(as_completed(futures), 1):
            row = fut.result()
            rows[futures[fut]] = row
            if progress:
                run: SumoRun = row["run"]
                print(
                    f"[sumo {n}/{len(tasks)}] {run.control} {row['demand_vph']:g}-{row['mix']} "
                    f"seed {row['seed']}: mean delay {fmt_num(run.mean_delay_s, 's', 1)}, "
                    f"finished {run.finished} of {run.loaded} ({run.wall_s:.0f} s)",
                    file=sys.stderr,
                    flush=True,
                )
    return [r for r in rows if r is not None]


def _timed(trial: Trial) -> tuple[TrialOutcome, float]:
    """One in-process trial and the CPU time it took [s] (wall time depends on the load)."""
    t0 = time.process_time()
    outcome = run_in_process(trial)
    return outcome, time.process_time() - t0


def _run_pool(
    trials: Sequence[Trial], jobs: int | None, progress: bool
) -> list[tuple[TrialOutcome, float]]:
    """Every trial in ``jobs`` worker processes (forkserver, as ``run_trials``), in the
    order of ``trials``; one line per finished run on stderr when ``progress``."""
    n_jobs = max(1, min(jobs if jobs is not None else (os.cpu_count() or 1), len(trials)))
    done: list[tuple[TrialOutcome, float] | None] = [None] * len(trials)
    if n_jobs == 1:
        futures_done = ((i, _timed(t)) for i, t in enumerate(trials))
        for k, (i, res) in enumerate(futures_done, 1):
            done[i] = res
            _say(progress, k, len(trials), res)
    else:
        methods = multiprocessing.get_all_start_methods()
        ctx = multiprocessing.get_context("forkserver" if "forkserver" in methods else "spawn")
        with ProcessPoolExecutor(max_workers=n_jobs, mp_context=ctx) as pool:
            futures = {pool.submit(_timed, t): i for i, t in enumerate(trials)}
            for k, fut in enumerate(as_completed(futures), 1):
                done[futures[fut]] = fut.result()
                _say(progress, k, len(trials), fut.result())
    return [d for d in done if d is not None]


def _say(progress: bool, k: int, n: int, res: tuple[TrialOutcome, float]) -> None:
    if not progress:
        return
    o, cpu = res
    t = o.trial
    what = f"{t.column.key} seed {t.seed} {Path(t.scenario).stem.removeprefix('four-way-demand-')}"
    if o.result is None:
        print(f"[{k}/{n}] {what}: FAILED {o.error}", file=sys.stderr, flush=True)
        return
    s = o.result.summary
    mean = None if s is None else s.mean_delay_s
    print(
        f"[{k}/{n}] {what}: mean delay {fmt_num(mean, 's', 1)}, collisions "
        f"{o.result.collisions}, finished {None if s is None else s.vehicles_finished}"
        f" ({o.wall_s:.0f} s wall, {cpu:.0f} s CPU)",
        file=sys.stderr,
        flush=True,
    )


def _p95(values: Sequence[float]) -> float | None:
    return round(float(np.percentile(values, 95)), 4) if values else None


def _row_crosspath(
    o: TrialOutcome, demand: float, mix: str, arrived: int, cfg: DemandConfig
) -> dict[str, Any]:
    col = o.trial.column
    row: dict[str, Any] = {
        "tool": "crosspath",
        "mode": col.key,
        "title": col.title,
        "demand_vph": demand,
        "mix": mix,
        "seed": o.trial.seed,
        "horizon_s": cfg.horizon_s,
        "max_sim_s": cfg.max_sim_s,
        "arrived": arrived,
        "error": o.error,
    }
    r = o.result
    if r is None:
        return row
    s = r.summary
    row.update(
        inserted=None if s is None else s.vehicles_inserted,
        finished=None if s is None else s.vehicles_finished,
        all_finished=r.all_finished,
        mean_delay_s=None if s is None else s.mean_delay_s,
        p95_delay_s=None if s is None else s.p95_delay_s,
        collisions=r.collisions,
        min_gap_m=r.min_gap_m,
        min_pet_s=r.min_pet_s,
        throughput_vph=None if s is None else s.throughput_vph,
        stops_per_vehicle=None if s is None else s.stops_per_vehicle,
        sim_s=r.sim_s,
        wall_s=round(o.wall_s, 3),
    )
    return row


def _row_sumo(
    demand: float, mix: str, seed: int, run: SumoRun, cfg: DemandConfig
) -> dict[str, Any]:
    delays = list(run.delays_s.values())
    return {
        "tool": "sumo",
        "mode": f"sumo-{run.control}",
        "title": Control(run.control).label,
        "demand_vph": demand,
        "mix": mix,
        "seed": seed,
        "horizon_s": cfg.horizon_s,
        "max_sim_s": cfg.max_sim_s,
        "arrived": run.loaded,
        "error": None,
        "inserted": run.inserted,
        "finished": run.finished,
        "all_finished": run.all_finished,
        "mean_delay_s": None if run.mean_delay_s is None else round(run.mean_delay_s, 4),
        "p95_delay_s": _p95(delays),
        "collisions": run.collisions,
        "min_gap_m": None,
        "min_pet_s": None,
        "throughput_vph": round(run.finished * 3600.0 / run.sim_s, 4) if run.sim_s > 0 else None,
        "stops_per_vehicle": None,
        "sim_s": run.sim_s,
        "wall_s": run.wall_s,
        "mean_time_loss_s": (
            round(sum(run.time_loss_s.values()) / len(run.time_loss_s), 4)
            if run.time_loss_s
            else None
        ),
    }


def run_demand_experiment(
    cfg: DemandConfig, out: Path, *, template: str | Path = TEMPLATE, progress: bool = True
) -> dict[str, Any]:
    """Run the grid, write every artefact into ``out``; the results document."""
    t0 = time.perf_counter()
    base = load_scenario(resolve_scenario(template))
    scen_dir = out / "scenarios"
    scen_dir.mkdir(parents=True, exist_ok=True)
    scenarios: dict[tuple[float, str], Scenario] = {}
    paths: dict[tuple[float, str], Path] = {}
    for demand in cfg.demands:
        for mix in cfg.mixes:
            sc = demand_scenario(base, demand, mix, cfg.horizon_s, cfg.max_sim_s)
            path = scen_dir / f"four-way-demand-{demand:g}-{mix}.toml"
            path.write_text(f"# {sc.description}\n\n" + scenario_toml(sc))
            scenarios[(demand, mix)] = load_scenario(path)
            paths[(demand, mix)] = path
    sumo_t0 = time.perf_counter()
    sumo_rows = _sumo_runs(cfg, scenarios, out / "sumo", progress) if cfg.controls else []
    sumo_wall = time.perf_counter() - sumo_t0

    columns = [c for c in COLUMNS if c.key in cfg.columns]
    trials: list[Trial] = []
    where: list[tuple[float, str]] = []
    for key, path in paths.items():
        for c in columns:
            for i in range(cfg.seeds):
                trials.append(Trial(c, i, cfg.base_seed + i, str(path), trace=False))
                where.append(key)
    cp_t0 = time.perf_counter()
    timed = _run_pool(trials, cfg.jobs, progress)
    outcomes = [o for o, _ in timed]
    cp_cpu = sum(c for _, c in timed)
    cp_wall = time.perf_counter() - cp_t0

    arrived = {
        (key, s): sum(len(v) for v in sc.draw_arrivals(s).values())
        for key, sc in scenarios.items()
        for s in range(cfg.base_seed, cfg.base_seed + cfg.seeds)
    }
    rows = [
        _row_crosspath(o, d, m, arrived[((d, m), o.trial.seed)], cfg)
        for o, (d, m) in zip(outcomes, where, strict=True)
    ]
    rows += [_row_sumo(r["demand_vph"], r["mix"], r["seed"], r["run"], cfg) for r in sumo_rows]
    doc: dict[str, Any] = {
        "experiment": "demand",
        "config": {
            "demands_vph": list(cfg.demands),
            "mixes": {m: list(MIXES[m]) for m in cfg.mixes},
            "seeds": list(range(cfg.base_seed, cfg.base_seed + cfg.seeds)),
            "horizon_s": cfg.horizon_s,
            "clearance_s": cfg.clearance_s,
            "max_sim_s": cfg.max_sim_s,
            "modes": [c.key for c in columns],
            "sumo_controls": list(cfg.controls),
            "template": str(base.source),
        },
        "aggregates": _aggregates(rows),
        "sumo_reference": SUMO_REFERENCE,
        "runs": rows,
        "crosspath_results": [None if o.result is None else o.result.to_json() for o in outcomes],
        "sumo_runs": [r["run"].to_json() for r in sumo_rows],
        "errors": collect_errors(outcomes),
        "timing": {
            "wall_s": round(time.perf_counter() - t0, 3),
            "sumo_wall_s": round(sumo_wall, 3),
            "crosspath_wall_s": round(cp_wall, 3),
            "crosspath_cpu_s": round(cp_cpu, 3),
            "jobs": cfg.jobs,
        },
    }
    out.mkdir(parents=True, exist_ok=True)
    write_json(out / "results.json", doc)
    write_runs_csv(out / "runs.csv", rows)
    (out / "table.md").write_text(render_table(doc) + "\n")
    figures = plot_delay(doc, out / "delay_vs_demand.png")
    (out / "REPORT.md").write_text(render_report(doc, figures))
    return doc


# --------------------------------------------------------------------------- aggregates


def _series_order(rows: Sequence[Mapping[str, Any]]) -> list[tuple[str, str]]:
    """(mode key, title) in the order they first appear: crosspath, then SUMO."""
    seen: dict[str, str] = {}
    for r in rows:
        seen.setdefault(r["mode"], r["title"])
    return list(seen.items())


def _aggregates(rows: Sequence[Mapping[str, Any]]) -> list[dict[str, Any]]:
    """Per (mix, demand, mode): the seeds' mean delay [95 % t-interval], collisions,
    cars finished out of arrived, runs with a collision and runs that finished all."""
    groups: dict[tuple[str, float, str], list[Mapping[str, Any]]] = {}
    for r in rows:
        groups.setdefault((r["mix"], r["demand_vph"], r["mode"]), []).append(r)
    out = []
    for (mix, demand, mode), rs in groups.items():
        ok = [r for r in rs if r.get("error") is None and "finished" in r]
        out.append(
            {
                "mix": mix,
                "demand_vph": demand,
                "mode": mode,
                "title": rs[0]["title"],
                "tool": rs[0]["tool"],
                "runs": len(rs),
                "failed_runs": len(rs) - len(ok),
                "mean_delay_s": summarize([r.get("mean_delay_s") for r in ok]),
                "p95_delay_s": summarize([r.get("p95_delay_s") for r in ok]),
                "collisions": sum(int(r["collisions"]) for r in ok),
                "runs_with_collision": sum(1 for r in ok if r["collisions"] > 0),
                "arrived": sum(int(r["arrived"]) for r in ok),
                "inserted": sum(int(r["inserted"] or 0) for r in ok),
                "finished": sum(int(r["finished"] or 0) for r in ok),
                "runs_all_finished": sum(1 for r in ok if r["all_finished"]),
            }
        )
    return out


def render_table(doc: Mapping[str, Any]) -> str:
    """``table.md``: per mix, one row per (demand, mode/control)."""
    cfg = doc["config"]
    parts = [
        f"Mean delay per car [s] over finished cars, mean of {len(cfg['seeds'])} seed(s) "
        f"[95 % t-interval]; {cfg['horizon_s']:g} s of demand, runs end by "
        f"{cfg['max_sim_s']:g} s. Collisions summed over the seeds; finished out of the "
        "cars that arrived (summed)."
    ]
    order = _series_order(doc["runs"])
    for mix in cfg["mixes"]:
        body = []
        for demand in cfg["demands_vph"]:
            for mode, title in order:
                agg = next(
                    (
                        a
                        for a in doc["aggregates"]
                        if a["mix"] == mix and a["demand_vph"] == demand and a["mode"] == mode
                    ),
                    None,
                )
                if agg is None:
                    continue
                ref = SUMO_REFERENCE.get(mode.removeprefix("sumo-"), {}).get(int(demand))
                body.append(
                    [
                        f"{demand:g}",
                        title,
                        fmt_ci(agg["mean_delay_s"], "s", 1),
                        fmt_num(agg["p95_delay_s"]["mean"], "s", 1),
                        f"{agg['collisions']} ({agg['runs_with_collision']} of "
                        f"{agg['runs']} runs)",
                        f"{agg['finished']} of {agg['arrived']}"
                        + (f" ({agg['inserted']} inserted)" if agg["inserted"] != agg["arrived"]
                           else ""),
                        "–" if ref is None or mix != "straight" else f"{ref:.1f} s",
                    ]
                )  # fmt: skip
        parts.append(f"\n### {mix} ({', '.join(f'{100 * s:g} %' for s in MIXES[mix])}"
                     " straight/left/right)\n")  # fmt: skip
        parts.append(
            markdown_table(
                [
                    "veh/h per approach",
                    "mode / control",
                    "mean delay [95 % CI]",
                    "p95 delay",
                    "collisions",
                    "finished",
                    "issue's SUMO ref.",
                ],
                body,
                ["r", "l", "r", "r", "r", "r", "r"],
            )
        )
    return "\n".join(parts)


_STYLE: dict[str, tuple[str, str, str]] = {
    # mode key -> colour, marker, linestyle
    "standalone": ("tab:gray", "o", "-"),
    "fp-only": ("tab:blue", "s", "-"),
    "rsu-paper": ("tab:orange", "^", "-"),
    "rsu-slot": ("tab:green", "D", "-"),
    "sumo-priority": ("tab:purple", "v", "--"),
    "sumo-allway_stop": ("tab:red", "P", "--"),
    "sumo-traffic_light": ("tab:brown", "X", "--"),
}


def plot_delay(doc: Mapping[str, Any], path: Path) -> list[str]:
    """``delay_vs_demand``: one panel per mix, mean delay [95 % CI] against demand, one
    line per mode and SUMO control (log scale: delays span two decades); the issue's
    SUMO reference as faint dotted lines on the straight panel. PNG, PDF, SVG."""
    plt = pyplot()
    cfg = doc["config"]
    mixes = cfg["mixes"]
    fig, axes = plt.subplots(
        1, len(mixes), figsize=(max(5.2 * len(mixes), 8.0), 4.8), squeeze=False, sharey=True
    )
    order = _series_order(doc["runs"])
    demands = [float(d) for d in cfg["demands_vph"]]
    step = (max(demands) - min(demands)) / max(len(demands) - 1, 1) if len(demands) > 1 else 100
    dodge = 0.018 * step * (len(order) - 1) / 2.0
    for ax, mix in zip(axes[0], mixes, strict=True):
        for k, (mode, title) in enumerate(order):
            xs, ys, lo, hi = [], [], [], []
            for d in demands:
                agg = next(
                    (
                        a
                        for a in doc["aggregates"]
                        if a["mix"] == mix and a["demand_vph"] == d and a["mode"] == mode
                    ),
                    None,
                )
                if agg is None or agg["mean_delay_s"]["mean"] is None:
                    continue
                s = agg["mean_delay_s"]
                m = max(float(s["mean"]), 0.05)
                xs.append(d - dodge + k * 0.036 * step)
                ys.append(m)
                # a log axis cannot show an interval reaching 0 or below: cut at m / 10
                lo.append(m - max(s["ci95_low"] if s["ci95_low"] is not None else m, m / 10))
                hi.append((s["ci95_high"] if s["ci95_high"] is not None else m) - m)
            colour, marker, ls = _STYLE.get(mode, ("black", "o", ":"))
            ax.errorbar(
                xs, ys, yerr=[lo, hi], color=colour, marker=marker, linestyle=ls,
                capsize=3, markersize=6, linewidth=1.5, label=title,
            )  # fmt: skip
        if mix == "straight":
            for ctrl, ref in SUMO_REFERENCE.items():
                colour = _STYLE[f"sumo-{ctrl}"][0]
                rx = sorted(ref)
                ax.plot(
                    rx, [ref[x] for x in rx], color=colour, linestyle=":", linewidth=1.0,
                    alpha=0.6, marker=".", label=f"issue's ref.: {Control(ctrl).label}",
                )  # fmt: skip
        ax.set_yscale("log")
        ax.set_xticks(demands)
        ax.set_xlabel("demand per approach [veh/h]")
        ax.set_title(
            f"{mix}: {', '.join(f'{100 * s:g}' for s in MIXES[mix])} % straight/left/right"
        )
        ax.grid(True, which="both", alpha=0.3)
    axes[0][0].set_ylabel("mean delay per car [s]\n(95 % CI over seeds, cut at mean / 10)")
    handles: dict[str, Any] = {}
    for ax in axes[0]:
        for h, lab in zip(*ax.get_legend_handles_labels(), strict=True):
            handles.setdefault(lab, h)
    fig.legend(
        list(handles.values()), list(handles.keys()), loc="lower center", ncol=4,
        bbox_to_anchor=(0.5, -0.02), frameon=False, fontsize=8,
    )  # fmt: skip
    fig.suptitle(
        f"4-way, one lane per approach: {cfg['horizon_s']:g} s of demand, "
        f"{len(cfg['seeds'])} seed(s); delay = travel beyond free flow + insertion wait"
    )
    fig.tight_layout(rect=(0, 0.12, 1, 1))
    return save_figure(fig, path)


def render_report(doc: Mapping[str, Any], figures: Sequence[str]) -> str:
    """``REPORT.md``: set-up, the table, the figure, safety and completion in words."""
    cfg = doc["config"]
    cp = [r for r in doc["runs"] if r["tool"] == "crosspath" and r.get("error") is None]
    collided = [r for r in cp if r.get("collisions")]
    stranded = [r for r in cp if not r.get("all_finished")]
    t = doc["timing"]
    lines = [
        "# Demand experiment: delay against demand at a 4-way intersection",
        "",
        f"Demand {', '.join(f'{d:g}' for d in cfg['demands_vph'])} veh/h per approach for "
        f"{cfg['horizon_s']:g} s, mixes {', '.join(cfg['mixes'])}, seeds {cfg['seeds']}; "
        f"runs end when every car finished or at {cfg['max_sim_s']:g} s. crosspath modes: "
        f"{', '.join(cfg['modes'])} (in-process); SUMO controls: "
        f"{', '.join(cfg['sumo_controls'])}, on the same geometry and the same arrivals, "
        "car for car. Delay: travel time beyond the route's free flow plus the insertion "
        "wait (SUMO: timeLoss + departDelay - the route's free-flow timeLoss).",
        "",
        f"![delay against demand]({figures[0] if figures else 'delay_vs_demand.png'})",
        "",
        render_table(doc),
        "",
        "## Safety and completion",
        "",
        f"- crosspath runs with a collision: {len(collided)} of {len(cp)}"
        + (
            " (" + ", ".join(
                f"{r['mode']} {r['demand_vph']:g} {r['mix']} seed {r['seed']}: "
                f"{r['collisions']}" for r in collided[:12]
            ) + ("…" if len(collided) > 12 else "") + ")"
            if collided else ""
        ),
        f"- crosspath runs that did not finish every car: {len(stranded)} of {len(cp)}",
        f"- failed runs: {len(doc['errors'])}" + (": " + "; ".join(doc["errors"]) if doc[
            "errors"] else ""),
        "",
        f"Wall time {t['wall_s']:.0f} s (SUMO {t['sumo_wall_s']:.0f} s, crosspath "
        f"{t['crosspath_wall_s']:.0f} s).",
        "",
    ]  # fmt: skip
    return "\n".join(lines)


# --------------------------------------------------------------------------- CLI


def _csv(kind: type[float] | type[str]) -> Any:
    def parse(text: str) -> tuple[Any, ...]:
        items = [x.strip() for x in text.split(",") if x.strip()]
        if not items:
            raise argparse.ArgumentTypeError("must be a comma-separated list")
        try:
            return tuple(kind(x) for x in items)
        except ValueError as exc:
            raise argparse.ArgumentTypeError(str(exc)) from None

    return parse


def configure(parser: argparse.ArgumentParser) -> None:
    """Options of ``crosspath experiment demand``."""
    parser.add_argument("--out", type=output_dir, default=DEFAULT_OUT, help="output directory")
    size = parser.add_mutually_exclusive_group()
    size.add_argument(
        "--full",
        action="store_true",
        help="the issue's grid: 200..800 veh/h, both mixes, 5 seeds, 600 s, 300 s clearance",
    )
    size.add_argument(
        "--quick", action="store_true", help="one seed, 400 veh/h straight, 30 s (a smoke run)"
    )
    parser.add_argument(
        "--demands", type=_csv(float), default=None, help="veh/h per approach, comma-separated"
    )
    parser.add_argument(
        "--mixes", type=_csv(str), default=None, help=f"of {', '.join(MIXES)}, comma-separated"
    )
    parser.add_argument("--seeds", type=positive_int, default=None, help="seeds per point")
    parser.add_argument("--seed", type=non_negative_int, default=0, help="first seed")
    parser.add_argument("--horizon", type=positive_float, default=None, help="demand s")
    parser.add_argument(
        "--clearance", type=positive_float, default=None, help="s after the demand ends"
    )
    parser.add_argument(
        "--modes",
        type=_csv(str),
        default=None,
        help=f"crosspath modes of {', '.join(c.key for c in COLUMNS)}, or none",
    )
    parser.add_argument(
        "--controls",
        type=_csv(str),
        default=None,
        help=f"SUMO controls of {', '.join(c.value for c in JUNCTION_TYPES)}, or none",
    )
    parser.add_argument(
        "--jobs", type=positive_int, default=None, help="worker processes (default: cores)"
    )


def config_from_args(args: argparse.Namespace) -> DemandConfig:
    """The :class:`DemandConfig` the options ask for (``ValueError`` if inconsistent)."""
    if args.full:
        base = DemandConfig.full()
    elif args.quick:
        base = DemandConfig.quick()
    else:
        base = DemandConfig()
    over: dict[str, Any] = {"jobs": args.jobs}
    for name, key in (
        ("demands", "demands"),
        ("mixes", "mixes"),
        ("seeds", "seeds"),
        ("horizon", "horizon_s"),
        ("clearance", "clearance_s"),
        ("modes", "columns"),
        ("controls", "controls"),
    ):
        value = getattr(args, name)
        if value is not None:
            over[key] = () if value == ("none",) else value
    fields = {f: getattr(base, f) for f in base.__dataclass_fields__}
    fields.update(over)
    fields["base_seed"] = args.seed
    return DemandConfig(**fields)


def run(args: argparse.Namespace) -> int:
    """The experiment; 0 when every run ran, 1 when some failed, 2 on bad arguments."""
    name = "crosspath experiment demand"
    try:
        cfg = config_from_args(args)
    except ValueError as exc:
        print(f"{name}: {exc}", file=sys.stderr)
        return 2
    try:
        doc = run_demand_experiment(cfg, args.out)
    except SumoNotFound as exc:
        print(f"{name}: {exc}", file=sys.stderr)
        return 2
    except (ScenarioError, ValueError) as exc:
        print(f"{name}: {exc}", file=sys.stderr)
        return 2
    print(render_table(doc))
    print(
        f"{len(doc['runs'])} runs in {doc['timing']['wall_s']:.0f} s; wrote results.json, "
        f"runs.csv, table.md, delay_vs_demand.png and REPORT.md to {args.out}"
    )
    if doc["errors"]:
        print(f"{name}: {len(doc['errors'])} run(s) failed:\n  " + "\n  ".join(doc["errors"]),
              file=sys.stderr)  # fmt: skip
        return 1
    return 0
