"""``crosspath view``: watch a run in the browser, live or replayed.

Live, beside ``crosspath up SCENARIO --run-dir DIR``::

    crosspath view --run-dir DIR            # connects to every daemon of that run

or on any Zenoh network with ``--connect ENDPOINT`` (repeatable). Replay::

    crosspath view --replay trace.csv --scenario paper-blind-intersection
    crosspath view --replay results/up/<run>/   # the monitor's step log, map included

Then open the printed address. ``--run-dir`` reads the run's ``children.json``
(waiting up to :data:`RUN_DIR_WAIT_S` for it): every daemon's ``--listen``
endpoints, the scenario and the key prefix, and the run authority's public key
(``keys/root.pub``) to verify the signed plumbing. The server is in ``services.view``.
"""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import itertools
import json
import sys
import time
from pathlib import Path
from typing import Any, Final

from services.edge.args import finite_float, int_at_least, positive_float

RUN_DIR_WAIT_S: Final = 30.0
"""How long ``--run-dir`` waits for the run's ``children.json`` [wall s]."""


def _port(text: str) -> int:
    value = int_at_least(0)(text)
    if value > 65535:
        raise argparse.ArgumentTypeError(f"must be <= 65535, got {value}")
    return value


def _rate(text: str) -> float:
    value = positive_float(text)
    if value > 100.0:
        raise argparse.ArgumentTypeError(f"must be <= 100, got {finite_float(text):g}")
    return value


def configure(parser: argparse.ArgumentParser) -> None:
    parser.add_argument(
        "--replay",
        type=Path,
        default=None,
        metavar="TRACE",
        help="replay a trace: a `sim --trace` / `up --trace` CSV, a monitor step log "
        "(*.steps.jsonl) or an `up` run dir; without it, live over Zenoh",
    )
    parser.add_argument(
        "--scenario",
        type=Path,
        default=None,
        help="the map: TOML file or packaged name (default: the one the run or trace names)",
    )
    parser.add_argument(
        "--run-dir",
        type=Path,
        default=None,
        metavar="DIR",
        help="live: the run dir of a `crosspath up` run; connect to its daemons",
    )
    parser.add_argument(
        "--connect",
        action="append",
        default=[],
        metavar="ENDPOINT",
        help="live: Zenoh endpoint to connect to, e.g. tcp/127.0.0.1:7447; repeatable",
    )
    parser.add_argument(
        "--listen",
        action="append",
        default=[],
        metavar="ENDPOINT",
        help="live: Zenoh endpoint to listen on; repeatable",
    )
    parser.add_argument(
        "--root",
        type=Path,
        default=None,
        metavar="FILE",
        help="live: the run authority's public key, to verify signed plumbing "
        "(default with --run-dir: DIR/keys/root.pub when present)",
    )
    parser.add_argument("--prefix", default=None, help="live: key expression prefix (crosspath)")
    parser.add_argument("--host", default="127.0.0.1", help="address the web server binds")
    parser.add_argument("--port", type=_port, default=8765, help="web server port (0: any free)")
    parser.add_argument(
        "--rate", type=_rate, default=1.0, help="replay: run seconds per wall second (max 100)"
    )


def _from_run_dir(run_dir: Path) -> tuple[list[str], str | None, str | None, dict[str, Any]]:
    """(endpoints, scenario, prefix, run) of a ``crosspath up`` run dir's daemons; ``run``
    has the monitor's ``mode``, ``policy`` and ``seed`` (shown until the start arrives)."""
    path = run_dir / "children.json"
    deadline = time.monotonic() + RUN_DIR_WAIT_S
    while not path.is_file():
        if time.monotonic() > deadline:
            raise ValueError(f"{path}: not found (is `crosspath up --run-dir {run_dir}` running?)")
        time.sleep(0.2)
    data: Any = json.loads(path.read_text())
    endpoints: list[str] = []
    scenario: str | None = None
    prefix: str | None = None
    run: dict[str, Any] = {}
    for child in data.values():
        argv = [str(a) for a in child.get("argv", [])]
        for flag, value in itertools.pairwise(argv):
            if "monitor" in argv and flag in ("--mode", "--policy", "--seed"):
                run[flag[2:]] = int(value) if flag == "--seed" else value
            if flag == "--listen" and value not in endpoints:
                endpoints.append(value)
            elif flag == "--scenario" and scenario is None:
                scenario = value
            elif flag == "--prefix" and prefix is None:
                prefix = value
    if not endpoints:
        raise ValueError(f"{path}: no daemon endpoints in it")
    return endpoints, scenario, prefix, run


def run(args: argparse.Namespace) -> int:
    """Serve until Ctrl-C; 2 when the trace, the scenario or the run dir is unusable."""
    from protocol.keys import DEFAULT_PREFIX, BadKey
    from services.edge.settings import ZenohSettings
    from services.edge.transport import TransportError
    from services.model.scenario import Scenario, ScenarioError, load_scenario
    from services.view.server import ViewServer, plumbing_opener
    from services.view.state import Replay, ViewState
    from services.view.traces import TraceError, load_trace

    def fail(message: str) -> int:
        print(f"crosspath view: {message}", file=sys.stderr)
        return 2

    scenario_arg: str | None = None if args.scenario is None else str(args.scenario)
    connect: list[str] = list(args.connect)
    prefix: str | None = args.prefix
    replay_rows = None
    run_info: dict[str, Any] = {}
    if args.replay is not None:
        try:
            trace = load_trace(args.replay)
        except TraceError as exc:
            return fail(f"--replay: {exc}")
        replay_rows = trace.rows
        scenario_arg = scenario_arg or trace.scenario
    elif args.run_dir is not None:
        try:
            endpoints, named, run_prefix, run_info = _from_run_dir(args.run_dir)
        except (ValueError, OSError, AttributeError) as exc:
            return fail(f"--run-dir: {exc}")
        connect += endpoints
        scenario_arg = scenario_arg or named
        prefix = prefix or run_prefix
    scenario: Scenario | None = None
    if scenario_arg is not None:
        try:
            scenario = load_scenario(scenario_arg)
        except ScenarioError as exc:
            return fail(f"--scenario: {exc}")
    root: Path | None = args.root
    if root is None and args.run_dir is not None and replay_rows is None:
        guess = args.run_dir / "keys" / "root.pub"
        root = guess if guess.is_file() else None
    opener = None
    if root is not None and replay_rows is None:
        try:
            opener = plumbing_opener(root)
        except (OSError, ValueError) as exc:
            return fail(f"--root: {root}: {exc}")
    try:
        state = ViewState(prefix=prefix or DEFAULT_PREFIX, opener=opener)
    except BadKey as exc:
        return fail(f"--prefix: {exc}")
    state.run = dict(run_info)
    replay = None if replay_rows is None else Replay(replay_rows, state)
    server = ViewServer(
        state,
        replay=replay,
        scenario=scenario,
        rate=args.rate,
        source="live" if replay is None else "replay",
    )

    async def serve() -> int:
        if replay is None:
            try:
                await server.attach_zenoh(ZenohSettings(listen=args.listen, connect=connect))
            except (TransportError, ValueError) as exc:
                await server.stop()
                return fail(f"zenoh: {exc}")
        try:
            host, port = await server.start(args.host, args.port)
        except OSError as exc:
            await server.stop()
            return fail(f"--port: cannot listen on {args.host}:{args.port}: {exc.strerror}")
        what = "live" if replay is None else f"replay of {args.replay}"
        print(f"crosspath view: {what} at http://{host}:{port}/ (Ctrl-C to stop)", flush=True)
        try:
            await asyncio.Event().wait()
        finally:
            await server.stop()
        return 0

    with contextlib.suppress(KeyboardInterrupt):
        return asyncio.run(serve())
    return 0
