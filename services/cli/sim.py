"""``crosspath sim SCENARIO --mode M [--policy P] [--seed N] [--loss R] [--json OUT]``.

Also ``--trace OUT``: the per-tick CSV.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

from services.model.scenario import ScenarioError, load_scenario
from services.model.types import Policy, RunMode
from services.sim.harness import SimOptions, Simulation
from services.sim.membus import ChannelModel
from services.sim.results import format_summary


def configure(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("scenario", type=Path, help="scenario file (TOML)")
    parser.add_argument("--mode", choices=[m.value for m in RunMode], default=RunMode.RSU.value)
    parser.add_argument("--policy", choices=[p.value for p in Policy], default=Policy.PAPER.value)
    parser.add_argument(
        "--seed", type=int, default=0, help="seed of the start offsets and the channel"
    )
    parser.add_argument(
        "--loss", type=float, default=0.0, help="V2X loss probability per receiver, 0..1"
    )
    parser.add_argument("--latency-ms", type=float, default=2.0, help="one-way V2X latency [ms]")
    parser.add_argument("--jitter-ms", type=float, default=1.0, help="uniform extra latency [ms]")
    parser.add_argument("--json", type=Path, default=None, help="write the run result here")
    parser.add_argument("--trace", type=Path, default=None, help="write the per-tick CSV here")


def run(args: argparse.Namespace) -> int:
    try:
        scenario = load_scenario(args.scenario)
        channel = ChannelModel(
            loss=args.loss, latency_s=args.latency_ms / 1000.0, jitter_s=args.jitter_ms / 1000.0
        )
    except (ScenarioError, ValueError) as exc:
        print(f"crosspath sim: {exc}", file=sys.stderr)
        return 2
    options = SimOptions(
        mode=RunMode(args.mode),
        policy=Policy(args.policy),
        seed=args.seed,
        channel=channel,
        trace=args.trace is not None,
    )
    sim = Simulation(scenario, options)
    result = sim.run()
    print(format_summary(result))
    if args.json is not None:
        args.json.parent.mkdir(parents=True, exist_ok=True)
        args.json.write_text(json.dumps(result, indent=2) + "\n")
    if args.trace is not None:
        args.trace.parent.mkdir(parents=True, exist_ok=True)
        sim.write_trace(args.trace)
    return 0
