"""``crosspath results rebuild RUN_DIR``: a run's result from what its run directory holds.

Why: when the monitor dies (SIGKILL, OOM) it writes no result, but it has been
appending every truth and stats report it kept to its step log
(``<run dir>/result.steps.jsonl``, ``services.daemons.steplog``), and each actor
logged its late ticks at the end of its run (``<run dir>/<node>.log``). This
command replays them through the monitor's own core
(``services.daemons.monitor.rebuild_result``) and writes the result, with its
per-step ``trace``, to ``--json OUT`` (default ``<RUN_DIR>/result.rebuilt.json``;
never over ``result.json``, which is the monitor's own). The result is partial
(``error`` says so) unless the monitor finished the log; its safety metrics come
from same-step truth only, as the monitor's would (``truth_gaps``, ``degraded``).

Exit status: 0 when a result was written, 1 when there is no usable step log.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from services.daemons.monitor import format_degraded, format_network, rebuild_result
from services.daemons.steplog import StepLogError
from services.edge.args import output_file
from services.sim.results import format_summary

__all__ = ["configure", "configure_rebuild", "run", "run_rebuild"]


def configure_rebuild(parser: argparse.ArgumentParser) -> None:
    """Options of ``crosspath results rebuild``."""
    parser.add_argument("run_dir", type=Path, metavar="RUN_DIR", help="the run's directory")
    parser.add_argument(
        "--json",
        type=output_file,
        metavar="OUT",
        help="write the rebuilt result here (default: RUN_DIR/result.rebuilt.json)",
    )
    parser.add_argument(
        "--step-log",
        type=Path,
        metavar="FILE",
        help="the monitor's step log (default: the *.steps.jsonl in RUN_DIR)",
    )


def run_rebuild(args: argparse.Namespace) -> int:
    """Rebuild, write and summarise one run's result."""
    run_dir: Path = args.run_dir
    try:
        result = rebuild_result(run_dir, args.step_log)
    except (StepLogError, OSError) as exc:
        sys.stderr.write(f"crosspath results rebuild: {exc}\n")
        return 1
    out: Path = args.json if args.json is not None else run_dir / "result.rebuilt.json"
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(result.to_json() + "\n")
    print(format_summary(result))
    print(format_network(result.network))
    degraded = format_degraded(result)
    if degraded is not None:
        print(degraded)
    if result.error is not None:
        print(f"PARTIAL: {result.error}")
    print(f"result written to {out}")
    return 0


configure = configure_rebuild
run = run_rebuild
