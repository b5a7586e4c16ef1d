"""``crosspath bench sim [--json OUT]``: how much faster than real time the in-process harness runs.

The baseline is real time itself: simulated seconds over this process's CPU
seconds (``time.process_time``: on a shared 2-core machine wall time also counts
other processes' turns; the wall figure is kept beside it as ``x_real_time_wall``),
median over seeds 0..``seeds``-1, on this machine, in this run. Cases:

- the paper's scenario in every mode and RSU policy, whole runs (issue 14: at
  least 100x real time in every mode);
- traffic: ``four-way-flows-40`` (one 4-way intersection, straight and turning
  cars, uniform arrivals over 120 s) with every flow's ``vehicles_per_hour``
  scaled so that the run has about 50, 100 and 200 cars (issue 14: at least 10x
  real time with 200 cars). A whole traffic run takes minutes of CPU, so these
  cases run the first ``TRAFFIC_WINDOW_S`` simulated seconds only (one seed):
  ``cars`` is the cars of the scenario, ``cars_started`` those that had
  arrived by the end of the window.

``x_real_time`` is the median of simulated over CPU seconds per run.
"""

from __future__ import annotations

import argparse
import json
import statistics
import time
from pathlib import Path
from typing import Any

from services.edge.args import add_scenario_option, output_file, positive_int
from services.edge.progress import Ticker
from services.model import geometry
from services.model.catalog import default_scenario, packaged_scenario
from services.model.scenario import Scenario, load_scenario
from services.model.types import Policy, RunMode
from services.sim.harness import SimOptions, simulate

DEFAULT_SCENARIO = default_scenario()
"""The packaged paper scenario (``services.model.catalog``), wherever crosspath is installed."""

TRAFFIC_SCENARIO = "four-way-flows-40"
"""Packaged scenario the traffic cases scale: exactly 40 cars over 120 s."""

TRAFFIC_CARS: tuple[int, ...] = (50, 100, 200)
"""Cars of the traffic cases (about: flows are scaled, arrivals stay uniform)."""

TRAFFIC_MODES: tuple[RunMode, ...] = (RunMode.STANDALONE, RunMode.FP_ONLY, RunMode.RSU)
"""Modes of the traffic cases: the cars alone, with future paths, and with the RSU."""

TRAFFIC_WINDOW_S = 20.0
"""Simulated seconds of each traffic case [s]."""

TARGET_PAPER_X = 100.0
TARGET_TRAFFIC_X_AT_200 = 10.0

CASES: tuple[tuple[str, RunMode, Policy], ...] = (
    ("standalone", RunMode.STANDALONE, Policy.PAPER),
    ("fp-only", RunMode.FP_ONLY, Policy.PAPER),
    ("rsu-paper", RunMode.RSU, Policy.PAPER),
    ("rsu-slot", RunMode.RSU, Policy.SLOT),
)
"""The paper scenario's cases: name, mode, RSU policy."""


def _cars(scenario: Scenario) -> int:
    """Cars of a run with seed 0: named vehicles plus every flow's arrivals."""
    return len(scenario.spec.vehicles) + sum(len(v) for v in scenario.draw_arrivals(0).values())


def scaled_traffic(cars: int, base: Scenario | None = None) -> Scenario:
    """``four-way-flows-40`` with every flow's rate scaled by ``cars`` / 40."""
    if cars < 1:
        raise ValueError(f"cars must be >= 1, got {cars}")
    scenario = base or load_scenario(packaged_scenario(TRAFFIC_SCENARIO))
    spec = scenario.spec
    k = cars / max(_cars(scenario), 1)
    flows = [
        f.model_copy(update={"vehicles_per_hour": f.vehicles_per_hour * k}) for f in spec.flows
    ]
    name = f"{spec.scenario.name}-x{cars}"
    info = spec.scenario.model_copy(update={"name": name})
    return Scenario(spec.model_copy(update={"flows": flows, "scenario": info}), scenario.source)


def _run(
    scenario: Scenario, options: SimOptions, window: float | None
) -> tuple[float, float, float, int]:
    """(simulated s, CPU s, wall s, cars started) of one run."""
    c0, w0 = time.process_time(), time.perf_counter()
    result = simulate(scenario, options)
    cpu, wall = time.process_time() - c0, time.perf_counter() - w0
    return result.sim_s, cpu, wall, len(result.vehicles)


def _case(
    scenario: Scenario,
    mode: RunMode,
    policy: Policy,
    seeds: int,
    cars: int,
    window: float | None = None,
) -> dict[str, Any]:
    runs = [
        _run(scenario, SimOptions(mode=mode, policy=policy, seed=s, max_sim_s=window), window)
        for s in range(seeds)
    ]
    sims, cpus, walls, started = zip(*runs, strict=True)
    return {
        "scenario": scenario.name,
        "mode": str(mode),
        "policy": str(policy),
        "cars": cars,
        "cars_started": int(statistics.median(started)),
        "seeds": seeds,
        "sim_s": round(statistics.median(sims), 3),
        "cpu_s": round(statistics.median(cpus), 3),
        "wall_s": round(statistics.median(walls), 3),
        "x_real_time": round(statistics.median(s / c for s, c in zip(sims, cpus, strict=True)), 1),
        "x_real_time_wall": round(
            statistics.median(s / w for s, w in zip(sims, walls, strict=True)), 1
        ),
    }


def measure(
    scenario_path: Path = DEFAULT_SCENARIO,
    seeds: int = 3,
    traffic_cars: tuple[int, ...] = TRAFFIC_CARS,
    window_s: float = TRAFFIC_WINDOW_S,
) -> dict[str, Any]:
    """Every case (module docstring); the JSON document ``bench sim`` writes."""
    if seeds < 1 or window_s <= 0:
        raise ValueError("seeds must be >= 1 and window_s > 0")
    paper = load_scenario(scenario_path)
    paper_cars = _cars(paper)
    cases: list[dict[str, Any]] = []
    for name, mode, policy in CASES:
        case = _case(paper, mode, policy, seeds, paper_cars)
        cases.append({"case": name, **case})
    base = load_scenario(packaged_scenario(TRAFFIC_SCENARIO)) if traffic_cars else None
    for cars in traffic_cars:
        traffic = scaled_traffic(cars, base)
        real = _cars(traffic)
        for mode in TRAFFIC_MODES:
            case = _case(traffic, mode, Policy.PAPER, 1, real, window_s)
            cases.append({"case": f"traffic-{cars}-{mode}", **case})
    paper_x = [c["x_real_time"] for c in cases if c["scenario"] == paper.name]
    at_200 = [c["x_real_time"] for c in cases if c["scenario"].endswith("-x200")]
    met = {"paper_every_mode": min(paper_x) >= TARGET_PAPER_X}
    if at_200:
        met["traffic_200_cars"] = min(at_200) >= TARGET_TRAFFIC_X_AT_200
    return {
        "bench": "sim",
        "scenario": paper.name,
        "seeds": seeds,
        "traffic_window_s": window_s,
        "clock": "process_time",
        "c_geometry": geometry.kernel_available(),  # a route's projection in C
        "targets": {
            "paper_x_real_time": TARGET_PAPER_X,
            "traffic_x_real_time_at_200": TARGET_TRAFFIC_X_AT_200,
            "met": met,
        },
        "cases": cases,
    }


def configure(parser: argparse.ArgumentParser) -> None:
    """Options of ``crosspath bench sim``; bad values are refused while parsing."""
    add_scenario_option(parser)
    parser.add_argument(
        "--seeds", type=positive_int, default=3, help="runs per paper case (seeds 0..N-1; median)"
    )
    parser.add_argument(
        "--traffic-cars",
        type=positive_int,
        nargs="*",
        default=list(TRAFFIC_CARS),
        metavar="N",
        help="cars of the traffic cases (none: paper scenario only)",
    )
    parser.add_argument(
        "--json", type=output_file, default=None, metavar="OUT", help="write the results as JSON"
    )


def run(args: argparse.Namespace) -> int:
    """Measure and print; a status line on stderr while it runs (on a terminal only)."""
    label = f"{len(CASES)} paper cases x {args.seeds} seeds, traffic {args.traffic_cars}"
    with Ticker("crosspath bench sim", lambda: label):
        report = measure(args.scenario, args.seeds, tuple(args.traffic_cars))
    print(f"{'case':<22}{'cars':>6}{'sim [s]':>9}{'cpu [s]':>9}{'x real time':>13}{'(wall)':>8}")
    for r in report["cases"]:
        print(
            f"{r['case']:<22}{r['cars']:>6}{r['sim_s']:>9.1f}{r['cpu_s']:>9.2f}"
            f"{r['x_real_time']:>13.1f}{r['x_real_time_wall']:>8.1f}"
        )
    for name, ok in report["targets"]["met"].items():
        print(f"target {name}: {'met' if ok else 'NOT met'}")
    if args.json is not None:
        args.json.parent.mkdir(parents=True, exist_ok=True)
        args.json.write_text(json.dumps(report, indent=2) + "\n")
    return 0
