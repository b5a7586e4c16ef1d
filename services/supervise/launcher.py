"""``crosspath up SCENARIO --mode M``: one run with every actor in its own OS process, over Zenoh.

The launcher starts, on loopback, the monitor, the RSU(s) (``rsu`` mode only)
and one process per car, each as ``python -m services.cli.main <command>``
(so it works without the console script on PATH), waits for the monitor's
result, prints the result table and a network table, and then terminates
every child: SIGTERM to its process group, SIGKILL after
:data:`GRACE_S` seconds. No process is left behind, also when a child crashes
(the launcher sees it exit, and the monitor sees its liveliness token go: the
run fails with a clear message and the last lines of the failed child's log),
on ``--timeout`` and when the launcher gets SIGINT (Ctrl-C) or SIGTERM; a second
signal skips the grace period. On Linux the children also get SIGTERM from the
kernel if the launcher itself dies (``PR_SET_PDEATHSIG``).

Network: every daemon is a Zenoh peer with multicast scouting off, listening
on one UDP and one TCP port of 127.0.0.1 (free ports picked at start) and
connecting to both endpoints of every node started before it (monitor, RSUs,
cars in that order). So every pair of nodes holds a direct UDP link, which
carries the best-effort V2X traffic, and a direct TCP link, which carries the
reliable plumbing (``max_links`` 2; see ``deploy/zenoh/README.md``).

Files: each child's stdout and stderr go to ``<run dir>/<node>.log``; the
monitor writes ``<run dir>/result.json``; ``<run dir>/children.json`` lists the
children's pids and command lines. The run dir defaults to
``results/up/<timestamp>/`` (git-ignored).

:func:`actor_commands` builds the same command lines for other addresses: the
network lab starts them inside network namespaces.
"""

from __future__ import annotations

import argparse
import contextlib
import json
import os
import secrets
import signal
import socket
import subprocess
import sys
import time
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from types import FrameType
from typing import IO, Any, Final

from services.model.scenario import Scenario, ScenarioError, load_scenario
from services.model.types import Policy, RunMode

__all__ = [
    "GRACE_S",
    "Child",
    "Endpoints",
    "Launcher",
    "actor_commands",
    "configure",
    "daemon_env",
    "free_ports",
    "loopback_endpoints",
    "node_order",
    "run",
]

GRACE_S: Final = 5.0
"""Seconds a child has to exit after SIGTERM before it is killed."""

LEASE_MS: Final = 2000
"""Zenoh link lease of the daemons ``crosspath up`` starts [ms] (Zenoh's default is 10 s): a
crashed peer's UDP link, and with it its liveliness token, is gone after at most this."""

CRASH_WAIT_S: Final = 4.0
"""After an actor exits during the run, how long the monitor gets to notice and fail."""

MONITOR: Final = "monitor"
"""Node id of the monitor."""

REPO_ROOT: Final = Path(__file__).resolve().parents[2]
"""The source tree (children import ``services`` from here)."""

TAIL_LINES: Final = 20
"""Lines of a failed child's log printed."""


@dataclass(frozen=True, slots=True)
class Endpoints:
    """A node's two Zenoh locators: ``udp/<addr>:<port>`` (V2X) and ``tcp/<addr>:<port>``
    (plumbing); it listens on both and the nodes after it connect to both."""

    udp: str
    tcp: str

    def __post_init__(self) -> None:
        for proto, locator in (("udp", self.udp), ("tcp", self.tcp)):
            head, sep, rest = locator.partition("/")
            if head != proto or not sep or ":" not in rest:
                raise ValueError(f"expected {proto}/<address>:<port>, got {locator!r}")

    @property
    def locators(self) -> list[str]:
        return [self.udp, self.tcp]


def node_order(scenario: Scenario, mode: RunMode, monitor: str = MONITOR) -> list[str]:
    """The nodes of a run in start order: the monitor, the RSUs (``rsu`` mode), the cars."""
    rsus = [r.id for r in scenario.rsus] if mode is RunMode.RSU else []
    return [monitor, *rsus, *(v.id for v in scenario.vehicles)]


def actor_commands(
    scenario_path: Path,
    mode: RunMode | str,
    policy: Policy | str,
    seed: int,
    speed: float,
    endpoints: Mapping[str, Endpoints],
    *,
    monitor: str = MONITOR,
    json_out: Path | None = None,
    run_id: str | None = None,
    max_sim_s: float | None = None,
    start_delay_s: float | None = None,
    log_level: str | None = None,
    prefix: str | None = None,
    python: str = sys.executable,
    zenoh_options: Mapping[str, object] | None = None,
) -> dict[str, list[str]]:
    """Command lines (argv) of every daemon of one run, in start order (see :func:`node_order`).

    ``endpoints`` gives every node's locators (monitor included); node ``i``
    listens on its own and connects to those of nodes ``0..i-1``. Nothing is
    started and nothing but the scenario file is read. Start each with
    :func:`daemon_env` and :data:`REPO_ROOT` as working directory (as
    :class:`Launcher` does); ``zenoh_options`` are raw Zenoh settings for every
    daemon (``crosspath up`` shortens the link lease, :data:`LEASE_MS`). Raises ``ValueError``
    (``ScenarioError`` included) when the scenario is unusable or an endpoint
    is missing.
    """
    mode = RunMode(mode)
    policy = Policy(policy)
    scenario = load_scenario(scenario_path)
    order = node_order(scenario, mode, monitor)
    missing = [n for n in order if n not in endpoints]
    if missing:
        raise ValueError(f"no endpoints for {', '.join(missing)}")
    scenario_arg = str(Path(scenario_path).resolve())
    rsus = {r.id for r in scenario.rsus}
    commands: dict[str, list[str]] = {}
    for index, node in enumerate(order):
        argv = [python, "-m", "services.cli.main"]
        if node == monitor:
            argv += ["monitor", "--scenario", scenario_arg, "--mode", str(mode)]
            argv += ["--policy", str(policy), "--seed", str(seed), "--speed", repr(float(speed))]
            argv += ["--set", f"node_id={node}"]
            if json_out is not None:
                argv += ["--json", str(Path(json_out).resolve())]
            if run_id is not None:
                argv += ["--run-id", run_id]
            if max_sim_s is not None:
                argv += ["--max-sim-s", repr(float(max_sim_s))]
            if start_delay_s is not None:
                argv += ["--start-delay", repr(float(start_delay_s))]
        elif node in rsus:
            argv += ["rsu", "--scenario", scenario_arg, "--id", node]
        else:
            argv += ["vehicle", "--scenario", scenario_arg, "--id", node]
        for locator in endpoints[node].locators:
            argv += ["--listen", locator]
        for earlier in order[:index]:
            for locator in endpoints[earlier].locators:
                argv += ["--connect", locator]
        if zenoh_options:
            argv += ["--set", f"zenoh.options={json.dumps(dict(zenoh_options))}"]
        if log_level is not None:
            argv += ["--log-level", log_level]
        if prefix is not None:
            argv += ["--prefix", prefix]
        commands[node] = argv
    return commands


def free_ports(count: int, host: str = "127.0.0.1") -> list[tuple[int, int]]:
    """``count`` (udp port, tcp port) pairs free on ``host`` right now (all held open
    together while picking, so they are distinct)."""
    held: list[socket.socket] = []
    pairs: list[tuple[int, int]] = []
    try:
        for _ in range(count):
            ports = []
            for kind in (socket.SOCK_DGRAM, socket.SOCK_STREAM):
                sock = socket.socket(socket.AF_INET, kind)
                held.append(sock)
                sock.bind((host, 0))
                ports.append(int(sock.getsockname()[1]))
            pairs.append((ports[0], ports[1]))
    finally:
        for sock in held:
            sock.close()
    return pairs


def loopback_endpoints(nodes: Sequence[str]) -> dict[str, Endpoints]:
    """Fresh loopback endpoints for every node."""
    return {
        node: Endpoints(f"udp/127.0.0.1:{udp}", f"tcp/127.0.0.1:{tcp}")
        for node, (udp, tcp) in zip(nodes, free_ports(len(nodes)), strict=True)
    }


def _die_with_parent() -> None:
    """In the child before exec (Linux): SIGTERM when the launcher dies, even by SIGKILL."""
    import ctypes

    pr_set_pdeathsig = 1
    with contextlib.suppress(OSError, AttributeError):
        ctypes.CDLL(None, use_errno=True).prctl(pr_set_pdeathsig, int(signal.SIGTERM))


def daemon_env(base: Mapping[str, str] | None = None) -> dict[str, str]:
    """The environment for a daemon started with :func:`actor_commands`' argv: ``base`` (or
    ours) with this source tree first on ``PYTHONPATH``, so ``-m services.cli.main``
    works without an installed package; run it with the source tree as working directory."""
    env = dict(os.environ if base is None else base)
    path = env.get("PYTHONPATH")
    env["PYTHONPATH"] = str(REPO_ROOT) + (os.pathsep + path if path else "")
    env.setdefault("PYTHONUNBUFFERED", "1")
    return env


def tail_log(path: Path, lines: int = TAIL_LINES) -> str:
    """The last ``lines`` lines of a daemon's log, for error messages."""
    try:
        text = path.read_text(errors="replace")
    except OSError:
        return "(no log)"
    return "\n".join(text.splitlines()[-lines:])


@dataclass(slots=True)
class Child:
    """One started daemon."""

    node: str
    argv: list[str]
    log_path: Path
    process: subprocess.Popen[bytes]
    log_file: IO[bytes]

    @property
    def pid(self) -> int:
        return self.process.pid


@dataclass(slots=True)
class Launcher:
    """Starts the daemons of one run, watches them, and cleans up (see module docstring)."""

    commands: Mapping[str, list[str]]
    run_dir: Path
    monitor: str = MONITOR
    grace_s: float = GRACE_S
    env: Mapping[str, str] | None = None
    children: dict[str, Child] = field(default_factory=dict)
    interrupted: int = 0
    signals: int = 0
    notes: list[str] = field(default_factory=list)

    # -- signals

    def _on_signal(self, signum: int, _frame: FrameType | None) -> None:
        self.signals += 1
        if not self.interrupted:
            self.interrupted = signum

    # -- children

    def start(self) -> None:
        """Start every command in order, each in its own session (process group)."""
        self.run_dir.mkdir(parents=True, exist_ok=True)
        env = daemon_env(self.env)
        for node, argv in self.commands.items():
            if self.interrupted:
                return
            log_path = self.run_dir / f"{node}.log"
            log_file = log_path.open("wb")
            try:
                process = subprocess.Popen(
                    argv,
                    stdin=subprocess.DEVNULL,
                    stdout=log_file,
                    stderr=subprocess.STDOUT,
                    cwd=REPO_ROOT,
                    env=env,
                    start_new_session=True,
                    preexec_fn=_die_with_parent if sys.platform == "linux" else None,
                )
            except OSError:
                log_file.close()
                raise
            self.children[node] = Child(node, list(argv), log_path, process, log_file)
            self._write_children()

    def _write_children(self) -> None:
        data = {
            node: {"pid": c.pid, "argv": c.argv, "log": str(c.log_path)}
            for node, c in self.children.items()
        }
        (self.run_dir / "children.json").write_text(json.dumps(data, indent=2) + "\n")

    def alive(self) -> list[Child]:
        return [c for c in self.children.values() if c.process.poll() is None]

    def stop_all(self) -> None:
        """SIGTERM every child's process group, SIGKILL what is left after the grace period."""
        for child in self.alive():
            self._signal(child, signal.SIGTERM)
        deadline = time.monotonic() + self.grace_s
        while self.alive() and time.monotonic() < deadline and self.signals < 2:
            time.sleep(0.05)
        for child in self.alive():
            self.notes.append(f"{child.node} did not exit after SIGTERM: killed")
            self._signal(child, signal.SIGKILL)
        for child in self.children.values():
            with contextlib.suppress(subprocess.TimeoutExpired):
                child.process.wait(timeout=5.0)
            child.log_file.close()

    @staticmethod
    def _signal(child: Child, signum: signal.Signals) -> None:
        with contextlib.suppress(ProcessLookupError, PermissionError):
            os.killpg(child.pid, signum)

    # -- the run

    def run(self, timeout_s: float) -> int | None:
        """Start, wait for the monitor (or a crash, timeout, signal), stop everything.

        Returns the monitor's exit code, or None when the run was cut short
        (``notes`` says why). Installs SIGINT/SIGTERM handlers for the duration.
        """
        previous = {
            signum: signal.signal(signum, self._on_signal)
            for signum in (signal.SIGINT, signal.SIGTERM)
        }
        try:
            self.start()
            return self._watch(timeout_s)
        finally:
            try:
                self.stop_all()
            finally:
                for signum, handler in previous.items():
                    signal.signal(signum, handler)

    def _watch(self, timeout_s: float) -> int | None:
        if self.interrupted:
            self.notes.append(f"interrupted by {signal.Signals(self.interrupted).name}")
            return None
        monitor = self.children[self.monitor]
        deadline = time.monotonic() + timeout_s
        crashed_at: float | None = None
        while True:
            code = monitor.process.poll()
            if code is not None:
                return code
            if self.interrupted:
                self.notes.append(f"interrupted by {signal.Signals(self.interrupted).name}")
                return None
            now = time.monotonic()
            if now > deadline:
                self.notes.append(f"timeout: the run did not end within {timeout_s:g} s")
                return None
            if crashed_at is None:
                for child in self.children.values():
                    rc = child.process.poll()
                    if child.node != self.monitor and rc is not None:
                        self.notes.append(f"{child.node} exited during the run with code {rc}")
                        crashed_at = now
            elif now - crashed_at > CRASH_WAIT_S:
                return None
            time.sleep(0.05)

    def failed_children(self, monitor_code: int | None) -> list[Child]:
        """Children whose log is worth showing: a non-zero exit, or the monitor of a failed run."""
        out = []
        for child in self.children.values():
            rc = child.process.returncode
            if child.node == self.monitor:
                if monitor_code != 0:
                    out.append(child)
            elif rc not in (0, None, -signal.SIGTERM):
                out.append(child)
        return out


# --------------------------------------------------------------------------- CLI


def configure(parser: argparse.ArgumentParser) -> None:
    """Options of ``crosspath up``."""
    parser.add_argument("scenario", type=Path, help="scenario file (TOML)")
    parser.add_argument("--mode", choices=[m.value for m in RunMode], default=RunMode.RSU.value)
    parser.add_argument("--policy", choices=[p.value for p in Policy], default=Policy.PAPER.value)
    parser.add_argument("--seed", type=int, default=0, help="seed of the start times")
    parser.add_argument("--speed", type=float, default=1.0, help="run seconds per wall second")
    parser.add_argument("--json", type=Path, default=None, help="write the run result here")
    parser.add_argument(
        "--timeout", type=float, default=None, help="wall s (default: max_sim_s / speed + 60)"
    )
    parser.add_argument("--max-sim-s", type=float, default=None, help="run time limit [s]")
    parser.add_argument(
        "--run-dir", type=Path, default=None, help="logs and result (default results/up/<time>)"
    )
    parser.add_argument("--start-delay", type=float, default=1.0, help="wall s before run time 0")
    parser.add_argument("--log-level", default="INFO", help="log level of the daemons")


def _fail(message: str) -> int:
    sys.stderr.write(f"crosspath up: {message}\n")
    return 2


def run(args: argparse.Namespace) -> int:
    """One run over Zenoh on loopback; 0 when it completed, 1 when it failed, 130/143 when
    interrupted, 2 on bad arguments."""
    from services.daemons.monitor import format_network
    from services.sim.results import format_summary

    try:
        scenario = load_scenario(args.scenario)
    except ScenarioError as exc:
        return _fail(str(exc))
    if not (args.speed > 0 and args.speed <= 1000):
        return _fail(f"--speed must be in (0, 1000], got {args.speed}")
    if args.seed < 0:
        return _fail(f"--seed must be >= 0, got {args.seed}")
    mode = RunMode(args.mode)
    stamp = time.strftime("%Y%m%d-%H%M%S")
    run_id = f"up-{stamp}-{secrets.token_hex(3)}"
    run_dir: Path = args.run_dir or Path("results") / "up" / f"{stamp}-{run_id[-6:]}"
    result_path = run_dir / "result.json"
    max_sim = args.max_sim_s if args.max_sim_s is not None else scenario.params.max_sim_s
    timeout = args.timeout if args.timeout is not None else max_sim / args.speed + 60.0
    nodes = node_order(scenario, mode)
    commands = actor_commands(
        args.scenario,
        mode,
        args.policy,
        args.seed,
        args.speed,
        loopback_endpoints(nodes),
        json_out=result_path,
        run_id=run_id,
        max_sim_s=args.max_sim_s,
        start_delay_s=args.start_delay,
        log_level=args.log_level,
        zenoh_options={"transport/link/tx/lease": LEASE_MS},
    )
    launcher = Launcher(commands, run_dir)
    print(f"crosspath up: run {run_id}, {len(nodes)} processes, logs in {run_dir}", flush=True)
    code = launcher.run(timeout)
    for note in launcher.notes:
        print(f"crosspath up: {note}", file=sys.stderr)
    result: dict[str, Any] | None = None
    if result_path.exists():
        with contextlib.suppress(OSError, ValueError):
            result = json.loads(result_path.read_text())
    if result is not None:
        print(format_summary(result))
        print(format_network(result.get("network", {})))
        if args.json is not None:
            args.json.parent.mkdir(parents=True, exist_ok=True)
            args.json.write_text(json.dumps(result, indent=2) + "\n")
        if result.get("error"):
            print(f"crosspath up: run failed: {result['error']}", file=sys.stderr)
    for child in launcher.failed_children(code):
        if child.node == launcher.monitor and result is not None:
            continue  # its result was printed above
        rc = child.process.returncode
        tail = tail_log(child.log_path)
        print(
            f"--- {child.node} (exit {rc}), last lines of {child.log_path}:\n{tail}",
            file=sys.stderr,
        )
    if launcher.interrupted:
        return 128 + launcher.interrupted
    if code == 0 and result is not None and not result.get("error"):
        return 0
    return 1
