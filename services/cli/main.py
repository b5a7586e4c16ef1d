"""The ``crosspath`` command line: one entry point, subcommands.

Each subcommand lives in its own module exposing ``configure(parser)`` and
``run(args) -> int``; this file only wires them together, so importing the CLI
stays cheap and one broken command cannot hide the others.
"""

from __future__ import annotations

import argparse
import importlib
import sys
from collections.abc import Sequence

# (command words) -> (module, help)
COMMANDS: dict[tuple[str, ...], tuple[str, str]] = {
    ("sim",): ("services.cli.sim", "one in-process run of a scenario"),
    ("up",): ("services.supervise.launcher", "one run with one OS process per actor over Zenoh"),
    ("vehicle",): ("services.daemons.vehicle", "run one car daemon"),
    ("rsu",): ("services.daemons.rsu", "run one roadside unit daemon"),
    ("monitor",): ("services.daemons.monitor", "run the monitor daemon (ground truth, results)"),
    ("router",): ("services.daemons.router", "run a Zenoh router for multi-host setups"),
    ("demo",): ("services.cli.demo", "the paper's scenario in 3 modes, real daemons"),
    ("bench", "codec"): ("services.bench.codec", "codec micro-benchmark against JSON"),
    ("bench", "rsu"): ("services.bench.rsu", "RSU conflict-check benchmark against naive"),
    ("bench", "sim"): ("services.bench.sim", "in-process harness speed against real time"),
    ("experiment", "paper"): ("services.experiments.paper", "the paper's table, figures"),
    ("experiment", "loss-sweep"): (
        "services.experiments.loss_sweep",
        "passing time and safety against packet loss, in the lab",
    ),
    ("lab", "up"): ("services.cli.lab", "create the network lab"),
    ("lab", "run"): ("services.cli.lab", "one run in the network lab"),
    ("lab", "down"): ("services.cli.lab", "remove everything the lab made"),
}


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="crosspath",
        description="Roadside-assisted cooperative planning with future path sharing.",
    )
    top = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")
    groups: dict[str, argparse._SubParsersAction[argparse.ArgumentParser]] = {}
    for words, (module_name, help_text) in COMMANDS.items():
        try:
            module = importlib.import_module(module_name)
        except ModuleNotFoundError as exc:
            if exc.name is not None and module_name.startswith(exc.name):
                continue  # command not built yet
            raise
        if len(words) == 1:
            sub = top.add_parser(words[0], help=help_text, description=help_text)
        else:
            if words[0] not in groups:
                group_parser = top.add_parser(words[0], help=f"{words[0]} commands")
                groups[words[0]] = group_parser.add_subparsers(
                    dest=f"{words[0]}_command", required=True, metavar="SUBCOMMAND"
                )
            sub = groups[words[0]].add_parser(words[1], help=help_text, description=help_text)
        configure = module.configure
        if len(words) > 1 and hasattr(module, f"configure_{words[1].replace('-', '_')}"):
            configure = getattr(module, f"configure_{words[1].replace('-', '_')}")
        configure(sub)
        run = module.run
        if len(words) > 1 and hasattr(module, f"run_{words[1].replace('-', '_')}"):
            run = getattr(module, f"run_{words[1].replace('-', '_')}")
        sub.set_defaults(_run=run)
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    result: int = args._run(args)
    return result


if __name__ == "__main__":
    sys.exit(main())
