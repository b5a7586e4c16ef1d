"""``crosspath demo``: the paper's scenario in its three modes, with real daemons over Zenoh.

Each mode is one ``crosspath up`` (monitor, RSU and cars as separate OS
processes on loopback); the demo then prints the paper's comparison: who
passed first, passing times, safety and the V2X load per car. What ``make
demo`` runs.
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

from services.model.types import RunMode

DEFAULT_SCENARIO = (
    Path(__file__).resolve().parents[3] / "scenarios" / "paper-blind-intersection.toml"
)

PAPER_MEAN_S = {"standalone": 36.51, "fp-only": 37.17, "rsu": 27.05}
"""The paper's average passing times (Table I), for reference."""


def configure(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--scenario", type=Path, default=DEFAULT_SCENARIO)
    parser.add_argument("--seed", type=int, default=1)
    parser.add_argument("--speed", type=float, default=1.0, help="run seconds per wall second")
    parser.add_argument("--policy", choices=["paper", "slot"], default="paper")
    parser.add_argument("--out", type=Path, default=Path("results") / "demo")
    parser.add_argument(
        "--modes", nargs="+", default=[m.value for m in RunMode], choices=[m.value for m in RunMode]
    )


def _cell(value: float | None, unit: str = "") -> str:
    return "-" if value is None else f"{value:.2f}{unit}"


def format_table(results: dict[str, dict[str, Any]]) -> str:
    """The comparison of the modes, one column each."""
    modes = list(results)
    width = 14
    lines = ["".ljust(26) + "".join(m.rjust(width) for m in modes)]

    def row(label: str, cells: list[str]) -> None:
        lines.append(label.ljust(26) + "".join(c.rjust(width) for c in cells))

    cars = sorted({vid for r in results.values() for vid in r["vehicles"]})
    for vid in cars:
        row(
            f"car {vid} passing time [s]",
            [_cell(r["vehicles"][vid]["passing_time_s"]) for r in results.values()],
        )
    for vid in cars:
        row(
            f"car {vid} first / stops",
            [
                f"{'yes' if r['vehicles'][vid]['first_through'] else 'no'} / "
                f"{r['vehicles'][vid]['stops']}"
                for r in results.values()
            ],
        )
    row("average passing [s]", [_cell(r.get("mean_passing_time_s")) for r in results.values()])
    row("paper's average [s]", [_cell(PAPER_MEAN_S.get(m)) for m in modes])
    row("collisions", [str(r["collisions"]) for r in results.values()])
    row("min gap [m]", [_cell(r["min_gap_m"]) for r in results.values()])
    row("min PET [s]", [_cell(r["min_pet_s"]) for r in results.values()])
    row(
        "V2X kbps per car",
        [_cell((r.get("network") or {}).get("total_kbps_per_vehicle")) for r in results.values()],
    )
    fp_lat = [
        ((r.get("network") or {}).get("fp") or {}).get("latency_ms_p50") for r in results.values()
    ]
    row("fp latency p50 [ms]", [_cell(x) for x in fp_lat])
    return "\n".join(lines)


def run(args: argparse.Namespace) -> int:
    out: Path = args.out
    out.mkdir(parents=True, exist_ok=True)
    results: dict[str, dict[str, Any]] = {}
    for mode in args.modes:
        path = out / f"{mode}.json"
        argv = [
            sys.executable,
            "-m",
            "services.cli.main",
            "up",
            str(args.scenario),
            "--mode",
            mode,
            "--policy",
            args.policy,
            "--seed",
            str(args.seed),
            "--speed",
            str(args.speed),
            "--json",
            str(path),
            "--run-dir",
            str(out / mode),
        ]
        print(f"== crosspath demo: {mode} (real daemons over Zenoh) ==", flush=True)
        started = time.monotonic()
        code = subprocess.call(argv)
        if code != 0 or not path.exists():
            print(f"crosspath demo: the {mode} run failed (exit {code})", file=sys.stderr)
            return 1
        results[mode] = json.loads(path.read_text())
        print(f"   ({time.monotonic() - started:.0f} s wall)\n", flush=True)
    print("== crosspath demo: the paper's scenario, seed", args.seed, "==")
    print(format_table(results))
    (out / "table.txt").write_text(format_table(results) + "\n")
    return 0
