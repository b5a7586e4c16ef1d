"""The ``crosspath`` command line: one entry point, subcommands.

Each subcommand lives in its own module exposing ``configure(parser)`` and
``run(args) -> int``; this file only wires them together, so importing the CLI
stays cheap and one broken command cannot hide the others.

Bad input is refused while parsing, before any work starts: every option has
an argparse ``type=`` from :mod:`services.edge.args`, and :class:`CliParser`
prints argparse's complaint as exactly one line, ``crosspath <cmd>: <option>:
<reason>``, with exit code 2 (no usage block: ``--help`` has it). Every
command's ``--help`` shows each option's default.
"""

from __future__ import annotations

import argparse
import importlib
import re
import sys
import textwrap
from collections.abc import Sequence
from typing import NoReturn

from services.edge.provenance import package_version

# (command words) -> (module, help)
COMMANDS: dict[tuple[str, ...], tuple[str, str]] = {
    ("sim",): ("services.cli.sim", "one in-process run of a scenario"),
    ("sumo",): (
        "services.cli.sumo",
        "co-simulation: SUMO's network, demand and physics, crosspath's connected cars and RSUs",
    ),
    ("up",): ("services.supervise.launcher", "one run with one OS process per actor over Zenoh"),
    ("vehicle",): ("services.daemons.vehicle", "run one car daemon"),
    ("rsu",): ("services.daemons.rsu", "run one roadside unit daemon"),
    ("monitor",): ("services.daemons.monitor", "run the monitor daemon (ground truth, results)"),
    ("router",): ("services.daemons.router", "run a Zenoh router for multi-host setups"),
    ("view",): ("services.cli.view", "watch a run in the browser, live or replayed"),
    ("demo",): ("services.cli.demo", "the paper's scenario in 3 modes, real daemons"),
    ("results", "rebuild"): (
        "services.cli.results",
        "a run's (partial) result from its run dir, e.g. after the monitor died",
    ),
    ("bench", "codec"): ("services.bench.codec", "codec micro-benchmark against JSON"),
    ("bench", "rsu"): ("services.bench.rsu", "RSU conflict-check benchmark against naive"),
    ("bench", "sim"): ("services.bench.sim", "in-process harness speed against real time"),
    ("bench", "latency"): (
        "services.bench.latency",
        "V2X transport latency and age at use per stream, loopback Zenoh",
    ),
    ("bench", "security"): ("services.bench.security", "cost of signing and verifying V2X"),
    ("experiment", "paper"): ("services.experiments.paper", "the paper's table, figures"),
    ("experiment", "loss-sweep"): (
        "services.experiments.loss_sweep",
        "passing time and safety against packet loss, in the lab",
    ),
    ("keys", "init"): ("services.cli.keys", "a new authority (root), optionally for a scenario"),
    ("keys", "issue-vehicle"): ("services.cli.keys", "key and certificate for a car"),
    ("keys", "issue-rsu"): ("services.cli.keys", "key and certificate for an RSU"),
    ("keys", "issue-monitor"): ("services.cli.keys", "key and certificate for a monitor"),
    ("keys", "revoke"): ("services.cli.keys", "add a key to the revocation list"),
    ("keys", "tls"): ("services.cli.keys", "mutual-TLS certificates for Zenoh"),
    ("keys", "acl"): ("services.cli.keys", "Zenoh access control for routers"),
    ("keys", "show"): ("services.cli.keys", "what a certificate says"),
    ("experiment", "demand"): (
        "services.experiments.demand",
        "delay against demand at a 4-way, crosspath beside SUMO's junction controls",
    ),
    ("scenario", "from-sumo"): (
        "services.cli.scenario",
        "a crosspath scenario from a SUMO network (.net.xml)",
    ),
    ("lab", "up"): ("services.cli.lab", "create the network lab"),
    ("lab", "run"): ("services.cli.lab", "one run in the network lab"),
    ("lab", "down"): ("services.cli.lab", "remove everything the lab made"),
}


_ARGUMENT = re.compile(r"^argument (\S+): ")
_REQUIRED = re.compile(r"^the following arguments are required: (.+)$")
_UNRECOGNIZED = re.compile(r"^unrecognized arguments: (.+)$")


def one_line(message: str) -> str:
    """argparse's complaint as ``<option>: <reason>`` on one line."""
    text = " ".join(message.split())
    if m := _REQUIRED.match(text):
        return f"{m.group(1)}: required"
    if m := _UNRECOGNIZED.match(text):
        return f"{m.group(1)}: unrecognized argument{'s' if ' ' in m.group(1) else ''}"
    return _ARGUMENT.sub(r"\1: ", text)


class CliParser(argparse.ArgumentParser):
    """An argument parser whose errors are one line on stderr and exit code 2."""

    def error(self, message: str) -> NoReturn:
        self.exit(2, f"{self.prog}: {one_line(message)}\n")


class HelpFormatter(argparse.ArgumentDefaultsHelpFormatter):
    """Shows every option's default; not when there is nothing to show (``None``,
    ``False``, an empty list) or the help already says it."""

    def _get_help_string(self, action: argparse.Action) -> str:
        text = action.help or ""
        default = action.default
        if (
            default is None
            or default is False
            or default is argparse.SUPPRESS
            or (isinstance(default, list | tuple) and not default)
            or "default" in text.lower()
            or not (action.option_strings or action.nargs in ("?", "*"))
        ):
            return text
        if isinstance(default, list | tuple):
            shown = " ".join(str(v) for v in default)
        else:
            shown = str(default)
        return f"{text} (default: {shown.replace('%', '%%')})".lstrip()

    def _split_lines(self, text: str, width: int) -> list[str]:
        """Wrap at spaces only: a default path or name (``paper-blind-intersection``)
        stays whole, so it can be copied from the help."""
        text = " ".join(text.split())
        return textwrap.wrap(text, width, break_on_hyphens=False, break_long_words=False)


def _add_parser(
    group: argparse._SubParsersAction[CliParser], name: str, help_text: str
) -> CliParser:
    return group.add_parser(
        name, help=help_text, description=help_text, formatter_class=HelpFormatter
    )


def build_parser() -> argparse.ArgumentParser:
    parser = CliParser(
        prog="crosspath",
        description="Roadside-assisted cooperative planning with future path sharing.",
        formatter_class=HelpFormatter,
    )
    parser.add_argument("--version", action="version", version=f"%(prog)s {package_version()}")
    top = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")
    groups: dict[str, argparse._SubParsersAction[CliParser]] = {}
    for words, (module_name, help_text) in COMMANDS.items():
        try:
            module = importlib.import_module(module_name)
        except ModuleNotFoundError as exc:
            if exc.name is not None and module_name.startswith(exc.name):
                continue  # command not built yet
            raise
        if len(words) == 1:
            sub = _add_parser(top, words[0], help_text)
        else:
            if words[0] not in groups:
                group_parser = _add_parser(top, words[0], f"{words[0]} commands")
                groups[words[0]] = group_parser.add_subparsers(
                    dest=f"{words[0]}_command", required=True, metavar="SUBCOMMAND"
                )
            sub = _add_parser(groups[words[0]], words[1], help_text)
        configure = module.configure
        if len(words) > 1 and hasattr(module, f"configure_{words[1].replace('-', '_')}"):
            configure = getattr(module, f"configure_{words[1].replace('-', '_')}")
        configure(sub)
        run = module.run
        if len(words) > 1 and hasattr(module, f"run_{words[1].replace('-', '_')}"):
            run = getattr(module, f"run_{words[1].replace('-', '_')}")
        sub.set_defaults(_run=run, _parser=sub)
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    parser = build_parser()
    args, extra = parser.parse_known_args(argv)
    if extra:
        # Named by the command it was given to, not by ``crosspath``.
        command: argparse.ArgumentParser = getattr(args, "_parser", parser)
        command.error(f"unrecognized arguments: {' '.join(extra)}")
    result: int = args._run(args)
    return result


if __name__ == "__main__":
    sys.exit(main())
