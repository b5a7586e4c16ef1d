"""``crosspath sim SCENARIO --mode M [--policy P] [--seed N] [--loss R] [--json OUT]``.

Also ``--trace OUT``: the per-tick CSV.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path
from typing import Any

from services.rsu.velocity import Policy
from services.runtime.membus import ChannelModel
from services.runtime.sim import SimOptions, Simulation
from services.world.results import RunMode
from services.world.scenario import ScenarioError, load_scenario


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


def format_summary(result: dict[str, Any]) -> str:
    """A short human summary of one run result."""
    lines = [
        f"scenario {result.get('scenario', '?')}  mode {result['mode']}"
        + (f"  policy {result['policy']}" if result.get("policy") else "")
        + f"  seed {result['seed']}  loss {result.get('loss', 0)}",
        f"{'car':<6}{'passing [s]':>12}{'first':>7}{'stops':>7}{'max v [m/s]':>13}",
    ]
    for vid, v in result["vehicles"].items():
        pt = "-" if v["passing_time_s"] is None else f"{v['passing_time_s']:.2f}"
        lines.append(
            f"{vid:<6}{pt:>12}{'yes' if v['first_through'] else 'no':>7}{v['stops']:>7}"
            f"{v['max_speed_mps'] or 0:>13.2f}"
        )
    mean = result.get("mean_passing_time_s")
    gap = result["min_gap_m"]
    pet = result["min_pet_s"]
    lines.append(
        f"mean passing {'-' if mean is None else f'{mean:.2f} s'}"
        f"  collisions {result['collisions']}"
        f"  min gap {'-' if gap is None else f'{gap:.2f} m'}"
        f"  min PET {'-' if pet is None else f'{pet:.2f} s'}"
    )
    lines.append(
        f"simulated {result['sim_s']:.1f} s in {result['wall_s']:.2f} s wall"
        f" ({result.get('speedup_vs_real_time', '?')}x real time)"
    )
    return "\n".join(lines)


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
