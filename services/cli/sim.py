"""``crosspath sim SCENARIO --mode M [--policy P] [--seed N] [--loss R] [--json OUT]``.

Also ``--trace OUT``: the per-tick CSV.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from services.api import simulate
from services.edge.args import (
    add_mode_and_policy,
    fraction,
    non_negative_float,
    non_negative_int,
    output_file,
)
from services.model.scenario import ScenarioError, load_scenario
from services.sim.results import format_summary


def configure(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("scenario", type=Path, help="TOML file or packaged name")
    add_mode_and_policy(parser)
    parser.add_argument(
        "--seed", type=non_negative_int, default=0, help="seed of the start offsets and the channel"
    )
    parser.add_argument(
        "--loss",
        type=fraction,
        default=0.0,
        help="V2X loss probability per receiver, a fraction 0..1 (or 30%%)",
    )
    parser.add_argument(
        "--latency-ms", type=non_negative_float, default=2.0, help="one-way V2X latency [ms]"
    )
    parser.add_argument(
        "--jitter-ms", type=non_negative_float, default=1.0, help="uniform extra latency [ms]"
    )
    parser.add_argument(
        "--json", type=output_file, default=None, metavar="OUT", help="write the run result here"
    )
    parser.add_argument(
        "--trace", type=output_file, default=None, metavar="OUT", help="write the per-tick CSV here"
    )


def run(args: argparse.Namespace) -> int:
    """One in-process run through the Python API (``services.api.simulate``); 2 when the
    scenario is unusable (the options were checked while parsing)."""
    try:
        scenario = load_scenario(args.scenario)
    except ScenarioError as exc:
        print(f"crosspath sim: {exc}", file=sys.stderr)
        return 2
    result = simulate(
        scenario,
        mode=args.mode,
        policy=args.policy,
        seed=args.seed,
        loss=args.loss,
        latency_ms=args.latency_ms,
        jitter_ms=args.jitter_ms,
        trace=args.trace,
    )
    print(format_summary(result))
    if args.json is not None:
        args.json.parent.mkdir(parents=True, exist_ok=True)
        args.json.write_text(result.to_json() + "\n")
    return 0
