"""``crosspath lab up / run / down``: the network lab from the command line.

``crosspath lab up SCENARIO [--name N] [--mode M]``
    builds the lab (one network namespace per car, RSU and the monitor, an air
    and a wire bridge) and starts the car and RSU daemons in their namespaces,
    where they wait for runs; prints the nodes and the command that runs the
    monitor (one run per invocation) in its namespace. Optional ``--loss``,
    ``--burst`` and ``--rate`` put faults on the air once the daemons' UDP links
    are up. The daemons keep running until ``crosspath lab down``.
``crosspath lab run SCENARIO --mode M [--policy P] [--seed N] [--loss R] [--burst B]
[--rate MBIT] [--speed X] [--crash NODE@T] [--restart NODE@T] [--json OUT]``
    one whole run in a fresh lab (``services.supervise.lab.runner.run_lab``), torn
    down afterwards whatever happens; prints the result, the ``network`` table,
    the per-node air counters beside the daemons' own and, with crashes, the
    fallback and rebuild times. ``R`` is a fraction 0..1 (``0.3``, or ``30%``),
    as ``crosspath sim --loss`` and every probability in crosspath; ``T`` in run
    seconds. On a terminal a status line on stderr shows the phase and the
    elapsed time.
``crosspath lab down [--name N | --all]``
    removes every namespace, link, rule and process of lab ``N`` (or of every
    lab), also after a crash or Ctrl-C.

Names: ``lab up`` and ``lab down`` default to lab ``crosspath``; ``lab run`` makes
``r<8 hex>`` unless ``--name`` is given. A lab of the same name is removed
before a new one is built, so ``up`` works again after a failed or killed run.
Every daemon's command line carries its lab's name (``pgrep -f <name>``).

Exit codes: 0 done; 1 the run failed (its result says why in ``error``); 2 bad
arguments (one line, before anything is built) or the lab cannot be built here
(not root, ``ip``/``tc``/``nft`` missing); 128 + signal number when interrupted
(the lab is gone by then).
"""

from __future__ import annotations

import argparse
import sys
from collections.abc import Mapping
from pathlib import Path
from typing import Any, Final, get_args

from services.edge.args import (
    add_mode_and_policy,
    float_at_least,
    fraction,
    int_at_least,
    non_negative_int,
    output_dir,
    output_file,
    positive_float,
    run_speed,
)
from services.edge.progress import Ticker
from services.edge.settings import LogLevel
from services.model.scenario import ScenarioError
from services.model.types import Policy, RunMode
from services.supervise.lab.faults import Loss
from services.supervise.lab.netns import (
    Lab,
    LabError,
    down_all,
    lab_prefix,
    list_namespaces,
    prerequisites,
)
from services.supervise.lab.runner import (
    DEFAULT_RUN_ROOT,
    LabInterrupted,
    LabSession,
    TimedAction,
    parse_timed,
    run_lab,
    shell_command,
    wait_udp_links,
)
from services.supervise.launcher import MONITOR

__all__ = [
    "DEFAULT_NAME",
    "configure",
    "configure_down",
    "configure_run",
    "configure_up",
    "format_lab",
    "run",
    "run_down",
    "run_run",
    "run_up",
]

DEFAULT_NAME: Final = "crosspath"
"""Lab name of ``lab up`` / ``lab down`` when ``--name`` is not given."""


def _fail(command: str, message: str) -> int:
    sys.stderr.write(f"crosspath lab {command}: {message}\n")
    return 2


def _prerequisites(command: str) -> int | None:
    missing = prerequisites()
    if missing:
        return _fail(
            command,
            "cannot build a network lab here, missing: "
            + ", ".join(missing)
            + " (run as root; deploy/lab/install-sysdeps.sh installs the tools)",
        )
    return None


def _timed(text: str) -> TimedAction:
    try:
        return parse_timed(text)
    except ValueError as exc:
        raise argparse.ArgumentTypeError(str(exc)) from None


def _add_faults(parser: argparse.ArgumentParser) -> None:
    parser.add_argument(
        "--loss",
        type=fraction,
        default=0.0,
        metavar="R",
        help="air packet loss per receiver, a fraction 0..1 or 30%% (ingress on every car and RSU)",
    )
    parser.add_argument(
        "--burst",
        type=float_at_least(1.0),
        default=None,
        metavar="B",
        help="mean loss burst in packets (Gilbert model); default: independent losses",
    )
    parser.add_argument(
        "--rate",
        type=positive_float,
        default=None,
        metavar="MBIT",
        help="rate limit of every car's and RSU's air transmissions [Mbit/s] (DSRC: 6)",
    )


_LOG_LEVELS: Final = list(get_args(LogLevel))


def _add_run_choice(parser: argparse.ArgumentParser) -> None:
    add_mode_and_policy(parser)
    parser.add_argument(
        "--seed", type=non_negative_int, default=0, help="seed of the start times and flows"
    )
    parser.add_argument(
        "--speed", type=run_speed, default=1.0, help="run seconds per wall second, up to 1000"
    )
    parser.add_argument(
        "--no-tls",
        dest="tls",
        action="store_false",
        help="plain UDP and TCP Zenoh links instead of mutual TLS (for comparison; V2X and "
        "plumbing stay signed)",
    )
    parser.add_argument(
        "--cars-per-process",
        type=int_at_least(1),
        default=None,
        metavar="N",
        help="cars per daemon process, sharing its namespace (default as crosspath up)",
    )


def _add_log_level(parser: argparse.ArgumentParser) -> None:
    parser.add_argument(
        "--log-level",
        type=str.upper,
        choices=_LOG_LEVELS,
        default="INFO",
        help="log level of the daemons",
    )


# --------------------------------------------------------------------------- up


def configure_up(parser: argparse.ArgumentParser) -> None:
    """Options of ``crosspath lab up``."""
    parser.add_argument("scenario", type=Path, help="TOML file or packaged name")
    parser.add_argument("--name", default=DEFAULT_NAME, help="lab name, 1-12 of a-z 0-9")
    _add_run_choice(parser)
    _add_faults(parser)
    parser.add_argument(
        "--log-dir", type=output_dir, default=None, help="daemon logs (default results/lab/<name>)"
    )
    _add_log_level(parser)


def run_up(args: argparse.Namespace) -> int:
    """Build the lab, start the car and RSU daemons, print how to run the monitor."""
    code = _prerequisites("up")
    if code is not None:
        return code
    log_dir: Path = args.log_dir or DEFAULT_RUN_ROOT / args.name
    try:
        if args.loss > 0.0:
            Loss(args.loss, args.burst)  # an impossible loss model is refused before building
        session = LabSession(
            args.scenario,
            RunMode(args.mode),
            args.name,
            log_dir,
            tls=args.tls,
            seed=args.seed,
            cars_per_process=args.cars_per_process,
        )
    except (ScenarioError, ValueError) as exc:
        return _fail("up", str(exc))
    try:
        session.up()
        commands = session.commands(
            Policy(args.policy),
            args.seed,
            args.speed,
            json_out=log_dir / "result.json",
            log_level=args.log_level,
            monitor_last=True,
        )
        actors = [n for n in commands if n != MONITOR]
        for node in actors:
            session.start(node, commands[node])
        missing = wait_udp_links(
            session.lab,
            [n for n in session.ns_order if n != MONITOR],
            tls=args.tls,
            endpoints=session.endpoints(),
        )
        if missing:
            raise LabError(
                "UDP links not established: "
                + "; ".join(f"{n} lacks {', '.join(m)}" for n, m in missing.items())
                + f" (see the logs in {log_dir})"
            )
        faults = session.apply_faults(args.loss, args.burst, args.rate)
    except (LabError, ValueError) as exc:
        session.down()
        return _fail("up", str(exc))
    except BaseException:
        session.down()
        raise
    session.close_logs()
    plan = session.plan
    print(
        f"lab {plan.lab} up: {len(plan.nodes)} namespaces {plan.ns_prefix}*, "
        f"daemons {', '.join(actors)} running, logs in {log_dir}"
    )
    print(f"{'node':<10}{'role':<9}{'namespace':<28}{'air (V2X, UDP)':<24}wire (plumbing, TCP)")
    endpoints = session.endpoints()
    for entry in plan.nodes:
        e = endpoints[entry.name]
        print(f"{entry.name:<10}{entry.role!s:<9}{entry.netns:<28}{e.udp:<24}{e.tcp}")
    if faults:
        print(f"faults on the air: {', '.join(faults)}")
    print("\nstart a run (the monitor, one run per invocation; add --seed/--speed/--json):")
    print("  " + shell_command(commands[MONITOR], plan.node(MONITOR).netns))
    print(f"\nremove the lab:  crosspath lab down --name {plan.lab}")
    return 0


# --------------------------------------------------------------------------- run


def configure_run(parser: argparse.ArgumentParser) -> None:
    """Options of ``crosspath lab run``."""
    parser.add_argument("scenario", type=Path, help="TOML file or packaged name")
    _add_run_choice(parser)
    _add_faults(parser)
    parser.add_argument(
        "--crash",
        type=_timed,
        action="append",
        default=[],
        metavar="NODE@T",
        help="SIGKILL the daemon of NODE (car or RSU) at run time T [s] (repeatable)",
    )
    parser.add_argument(
        "--restart",
        type=_timed,
        action="append",
        default=[],
        metavar="NODE@T",
        help="start the crashed RSU NODE again at run time T [s] (repeatable)",
    )
    parser.add_argument(
        "--json", type=output_file, default=None, metavar="OUT", help="write the run result here"
    )
    parser.add_argument("--name", default=None, help="lab name (default: random r<hex>)")
    parser.add_argument(
        "--run-dir", type=output_dir, default=None, help="logs (default results/lab/<time>-<name>)"
    )
    parser.add_argument(
        "--max-sim-s",
        type=positive_float,
        default=None,
        help="run time limit [s] (default: the scenario's)",
    )
    parser.add_argument(
        "--timeout",
        type=positive_float,
        default=None,
        help="wall s (default: max_sim_s / speed + 60)",
    )
    parser.add_argument("--trace", action="store_true", help="keep the per-step trace in --json")
    _add_log_level(parser)


def run_run(args: argparse.Namespace) -> int:
    """One run in a fresh lab, then tear it down; print the result."""
    from services.daemons.monitor import format_network
    from services.sim.results import format_summary

    code = _prerequisites("run")
    if code is not None:
        return code
    phase = ["starting"]
    ticker = Ticker("crosspath lab run", lambda: phase[0])

    def say(message: str) -> None:
        phase[0] = message
        ticker.say(message)

    try:
        with ticker:
            result = run_lab(
                args.scenario,
                args.mode,
                args.policy,
                args.seed,
                args.loss,
                burst=args.burst,
                rate_mbit=args.rate,
                speed=args.speed,
                crash_at=args.crash,
                restart_at=args.restart,
                name=args.name,
                run_dir=args.run_dir,
                json_out=args.json,
                max_sim_s=args.max_sim_s,
                timeout_s=args.timeout,
                trace=args.trace,
                log_level=args.log_level,
                tls=args.tls,
                cars_per_process=args.cars_per_process,
                say=say,
            )
    except LabInterrupted as exc:
        print(f"crosspath lab run: interrupted by {exc}; the lab is removed", file=sys.stderr)
        return 128 + exc.signum
    except (ScenarioError, ValueError, LabError) as exc:
        return _fail("run", str(exc))
    if result.vehicles:
        print(format_summary(result))
        print(format_network(result.network))
    print(format_lab(result.lab or {}))
    if result.error is not None:
        print(f"crosspath lab run: run failed: {result.error}", file=sys.stderr)
        return 1
    return 0


def _num(value: object, fmt: str) -> str:
    return "-" if not isinstance(value, int | float) else format(value, fmt)


def format_lab(lab: Mapping[str, Any]) -> str:
    """The ``lab`` section as text: faults, per-node air counters, checks, timeline."""
    lines: list[str] = []
    faults = lab.get("faults") or {}
    lines.append(
        f"lab {lab.get('name', '?')}: loss {faults.get('loss', 0):g} "
        f"(burst {faults.get('burst') or '-'}), rate {faults.get('rate_mbit') or '-'} Mbit/s, "
        f"from run time {_num(faults.get('applied_at_s'), '.2f')} s; "
        + ("mutual TLS" if lab.get("tls") else "no TLS")
    )
    air = lab.get("air") or {}
    if air:
        lines.append(
            f"{'node':<10}{'air tx kB':>10}{'rx kB':>9}{'tx kbps':>9}{'rx kbps':>9}"
            f"{'v2x tx kbps':>13}{'rx kbps':>9}{'lost':>7}{'rate drop':>11}"
        )
        for node, e in air.items():
            lines.append(
                f"{node:<10}{e['tx_bytes'] / 1000:>10.1f}{e['rx_bytes'] / 1000:>9.1f}"
                f"{_num(e.get('tx_kbps'), '.1f'):>9}{_num(e.get('rx_kbps'), '.1f'):>9}"
                f"{_num(e.get('daemon_tx_kbps'), '.1f'):>13}"
                f"{_num(e.get('daemon_rx_kbps'), '.1f'):>9}"
                f"{e.get('loss_dropped', 0):>7}{e.get('rate_dropped', 0):>11}"
            )
        lines.append(
            "(air: interface bytes incl. headers and one copy per receiver; v2x: the "
            "daemons' payload bytes; kbps per run second)"
        )
    checks = lab.get("checks")
    if checks:
        lines.append(
            f"TCP bytes on the air: {checks['air_tcp_bytes']}, "
            f"UDP bytes on the wire: {checks['wire_udp_bytes']}"
        )
    timeline = lab.get("timeline") or {}
    for c in timeline.get("crashes", []):
        per_car = ", ".join(
            f"{car} {_num(v, '.3f')} s" for car, v in (c.get("fallback_s") or {}).items()
        )
        lines.append(
            f"crash {c['node']} at {c['crash_s']:.2f} s: coordinated "
            f"{', '.join(c.get('coordinated') or []) or 'none'}; fallback to AUTO "
            f"{per_car or '-'}"
        )
    for r in timeline.get("restarts", []):
        lines.append(
            f"restart {r['node']} at {r['restart_s']:.2f} s, joined the run at "
            f"{_num(r.get('joined_s'), '.2f')} s; table holds {', '.join(r.get('cars') or [])} "
            f"after {_num(r.get('rebuild_s'), '.3f')} s "
            f"({_num(r.get('rebuild_from_restart_s'), '.2f')} s after the restart)"
        )
    return "\n".join(lines)


# --------------------------------------------------------------------------- down


def configure_down(parser: argparse.ArgumentParser) -> None:
    """Options of ``crosspath lab down``."""
    group = parser.add_mutually_exclusive_group()
    group.add_argument("--name", default=None, help=f"lab name (default {DEFAULT_NAME})")
    group.add_argument("--all", action="store_true", help="every lab (namespaces cpl-*)")


def run_down(args: argparse.Namespace) -> int:
    """Remove one lab (or all) and print what was removed."""
    code = _prerequisites("down")
    if code is not None:
        return code
    try:
        if args.all:
            removed = down_all()
        else:
            name = args.name or DEFAULT_NAME
            removed = list_namespaces(lab_prefix(name))
            Lab(name).down()
    except (LabError, ValueError) as exc:
        return _fail("down", str(exc))
    print("removed " + (", ".join(removed) if removed else "nothing (no such lab)"))
    return 0


# ``cli.py`` looks these up first, then prefers ``configure_<word>`` / ``run_<word>``.
configure = configure_run
run = run_run
