"""``crosspath bench sim [--json OUT]``: how much faster than real time the in-process harness runs.

The baseline is real time itself: simulated seconds over wall seconds, for
each mode of the paper's scenario, on this machine, in this run (median of a
few seeds). The issue's target is 100x.
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
from services.model.catalog import default_scenario
from services.model.scenario import load_scenario
from services.model.types import Policy, RunMode
from services.sim.harness import SimOptions, simulate

DEFAULT_SCENARIO = default_scenario()
"""The packaged paper scenario (``services.model.catalog``), wherever crosspath is installed."""

CASES: tuple[tuple[str, RunMode, Policy], ...] = (
    ("standalone", RunMode.STANDALONE, Policy.PAPER),
    ("fp-only", RunMode.FP_ONLY, Policy.PAPER),
    ("rsu-paper", RunMode.RSU, Policy.PAPER),
    ("rsu-slot", RunMode.RSU, Policy.SLOT),
)


def measure(scenario_path: Path = DEFAULT_SCENARIO, seeds: int = 3) -> dict[str, Any]:
    """Per case: simulated seconds, wall seconds and their ratio (median over ``seeds`` runs)."""
    scenario = load_scenario(scenario_path)
    results: list[dict[str, Any]] = []
    for name, mode, policy in CASES:
        ratios, walls, sims = [], [], []
        for seed in range(seeds):
            t0 = time.perf_counter()
            r = simulate(scenario, SimOptions(mode=mode, policy=policy, seed=seed))
            wall = time.perf_counter() - t0
            walls.append(wall)
            sims.append(r.sim_s)
            ratios.append(r.sim_s / wall)
        results.append(
            {
                "case": name,
                "sim_s": statistics.median(sims),
                "wall_s": round(statistics.median(walls), 4),
                "speedup_vs_real_time": round(statistics.median(ratios), 1),
            }
        )
    return {"scenario": scenario.name, "seeds": seeds, "results": results}


def configure(parser: argparse.ArgumentParser) -> None:
    """Options of ``crosspath bench sim``; bad values are refused while parsing."""
    add_scenario_option(parser)
    parser.add_argument(
        "--seeds", type=positive_int, default=3, help="runs per case (seeds 0..N-1; median)"
    )
    parser.add_argument(
        "--json", type=output_file, default=None, metavar="OUT", help="write the results as JSON"
    )


def run(args: argparse.Namespace) -> int:
    """Measure and print; a status line on stderr while it runs (on a terminal only)."""
    label = f"{len(CASES)} cases x {args.seeds} seeds"
    with Ticker("crosspath bench sim", lambda: label):
        report = measure(args.scenario, args.seeds)
    print(f"{'case':<12}{'sim [s]':>9}{'wall [s]':>10}{'x real time':>13}")
    for r in report["results"]:
        print(
            f"{r['case']:<12}{r['sim_s']:>9.1f}{r['wall_s']:>10.3f}{r['speedup_vs_real_time']:>13.1f}"
        )
    if args.json is not None:
        args.json.parent.mkdir(parents=True, exist_ok=True)
        args.json.write_text(json.dumps(report, indent=2) + "\n")
    return 0
