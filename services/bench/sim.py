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

from services.model.scenario import load_scenario
from services.model.types import Policy, RunMode
from services.sim.harness import SimOptions, simulate

DEFAULT_SCENARIO = (
    Path(__file__).resolve().parents[3] / "scenarios" / "paper-blind-intersection.toml"
)

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
            sims.append(float(r["sim_s"]))
            ratios.append(float(r["sim_s"]) / wall)
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
    parser.add_argument("--scenario", type=Path, default=DEFAULT_SCENARIO)
    parser.add_argument("--seeds", type=int, default=3)
    parser.add_argument("--json", type=Path, default=None)


def run(args: argparse.Namespace) -> int:
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
