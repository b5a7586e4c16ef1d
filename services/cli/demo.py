"""``crosspath demo``: the paper's scenario in its three modes, with real daemons over Zenoh.

Each mode is one run as ``crosspath up`` makes it (monitor, RSU and cars as
separate OS processes on loopback; ``services.api.run_daemons``), its result
written to ``OUT/<mode>.json`` and the daemons' logs to ``OUT/<mode>/``; the
demo then prints the paper's comparison: who passed first, passing times,
safety and the V2X load per car. What ``make demo`` runs.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

from services.api import DaemonRunError, RunInterrupted, run_daemons
from services.daemons.monitor import format_network
from services.edge.args import add_scenario_option, non_negative_int, output_dir, run_speed
from services.model.results import RunResult
from services.model.types import Policy, RunMode

"""The packaged paper scenario (``services.model.catalog``), wherever crosspath is installed."""

PAPER_MEAN_S = {"standalone": 36.51, "fp-only": 37.17, "rsu": 27.05}
"""The paper's average passing times (Table I), for reference."""


def configure(parser: argparse.ArgumentParser) -> None:
    """Options of ``crosspath demo``; bad values are refused while parsing."""
    add_scenario_option(parser)
    parser.add_argument("--seed", type=non_negative_int, default=1, help="seed of the start times")
    parser.add_argument(
        "--speed", type=run_speed, default=1.0, help="run seconds per wall second, up to 1000"
    )
    parser.add_argument(
        "--policy",
        choices=[p.value for p in Policy],
        default=Policy.PAPER.value,
        help="the RSU's velocity manager",
    )
    parser.add_argument(
        "--out",
        type=output_dir,
        default=Path("results") / "demo",
        help="results and daemon logs (one run dir per mode)",
    )
    parser.add_argument(
        "--modes",
        nargs="+",
        default=[m.value for m in RunMode],
        choices=[m.value for m in RunMode],
        help="the modes to run, in this order",
    )
    parser.add_argument(
        "--insecure",
        action="store_true",
        help="unsigned V2X, for comparison only (default: signed, a new authority per run)",
    )


def _cell(value: float | None, unit: str = "") -> str:
    return "-" if value is None else f"{value:.2f}{unit}"


def format_table(results: dict[str, RunResult]) -> str:
    """The comparison of the modes, one column each."""
    modes = list(results)
    width = 14
    lines = ["".ljust(26) + "".join(m.rjust(width) for m in modes)]

    def row(label: str, cells: list[str]) -> None:
        lines.append(label.ljust(26) + "".join(c.rjust(width) for c in cells))

    cars = sorted({vid for r in results.values() for vid in r.vehicles})
    for vid in cars:
        row(
            f"car {vid} passing time [s]",
            [_cell(r.vehicles[vid].passing_time_s) for r in results.values()],
        )
    for vid in cars:
        row(
            f"car {vid} first / stops",
            [
                f"{'yes' if r.vehicles[vid].first_through else 'no'} / {r.vehicles[vid].stops}"
                for r in results.values()
            ],
        )
    row("average passing [s]", [_cell(r.mean_passing_time_s) for r in results.values()])
    row("paper's average [s]", [_cell(PAPER_MEAN_S.get(m)) for m in modes])
    row("collisions", [str(r.collisions) for r in results.values()])
    row("min gap [m]", [_cell(r.min_gap_m) for r in results.values()])
    row("min PET [s]", [_cell(r.min_pet_s) for r in results.values()])
    row(
        "V2X kbps per car",
        [_cell(r.network.total_kbps_per_vehicle if r.network else None) for r in results.values()],
    )
    fp = [r.network.stream("fp") if r.network else None for r in results.values()]
    row("fp latency p50 [ms]", [_cell(f.latency_ms_p50 if f else None) for f in fp])
    return "\n".join(lines)


def run(args: argparse.Namespace) -> int:
    """Every mode with real daemons, one after another; 0 when all completed, 1 when one
    failed, 128 + signal when interrupted."""
    from services.sim.results import format_summary

    out: Path = args.out
    out.mkdir(parents=True, exist_ok=True)
    if args.insecure:
        print(
            "crosspath demo: WARNING --insecure: V2X is neither signed nor verified "
            "(comparison only)",
            file=sys.stderr,
            flush=True,
        )
    results: dict[str, RunResult] = {}
    for mode in args.modes:
        print(f"== crosspath demo: {mode} (real daemons over Zenoh) ==", flush=True)
        started = time.monotonic()
        try:
            result = run_daemons(
                args.scenario,
                mode=mode,
                policy=args.policy,
                seed=args.seed,
                speed=args.speed,
                run_dir=out / mode,
                say=lambda line: print(f"crosspath demo: {line}", flush=True),
                insecure=args.insecure,
            )
        except DaemonRunError as exc:
            print(f"crosspath demo: the {mode} run failed: {exc}", file=sys.stderr)
            return 1
        except RunInterrupted as exc:
            print(f"crosspath demo: interrupted during the {mode} run", file=sys.stderr)
            return 128 + exc.signum
        (out / f"{mode}.json").write_text(result.to_json() + "\n")
        results[mode] = result
        print(format_summary(result))
        print(format_network(result.network))
        print(f"   ({time.monotonic() - started:.0f} s wall)\n", flush=True)
    print("== crosspath demo: the paper's scenario, seed", args.seed, "==")
    print(format_table(results))
    (out / "table.txt").write_text(format_table(results) + "\n")
    return 0
