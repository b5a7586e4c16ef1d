"""``crosspath up SCENARIO --mode M``: one run with every actor in its own OS process, over Zenoh.

The launcher starts, on loopback, the monitor, the RSU(s) (``rsu`` mode only)
and the cars: one process per car, or with ``--cars-per-process N`` (by default for
more than 4 cars, ``services.supervise.hosts``) hosts of N cars, each car still its own
Zenoh node (``crosspath vehicle --ids``, ``services.daemons.host``); a scenario with
flows is first expanded for the seed into ``<run dir>/scenario.toml``
(``services.supervise.expand``). Each runs as ``python -m services.cli.main <command>``
(so it works without the console script on PATH), waits for the monitor's
result, prints the result table and a network table, and then terminates
every child: SIGTERM to its process group, SIGKILL after
:data:`GRACE_S` seconds. No process is left behind, also when a child crashes
(the launcher sees it exit, and the monitor sees its liveliness token go: the
run fails with a clear message and the last lines of the failed child's log),
on ``--timeout`` and when the launcher gets SIGINT (Ctrl-C) or SIGTERM; a second
signal skips the grace period. On Linux the children also get SIGTERM from the
kernel if the launcher itself dies, even by SIGKILL (``PR_SET_PDEATHSIG``; a child
whose launcher died before that was set exits at once).

No child outlives the launcher, restarted ones included: every daemon's command
line carries the run id (Zenoh ``metadata``, ``{"crosspath_run": RUN_ID}``), and
after stopping its own children the launcher sweeps ``/proc`` for any process
whose command line still carries it (e.g. an RSU restarted by hand from
``children.json`` after a crash, which is not the launcher's child): SIGTERM,
then SIGKILL after :data:`SWEEP_GRACE_S`. ``notes`` says what it swept. An actor
that exits during the run is reported in the result's ``crashes``
(``services.model.results.CrashEvent``, ``lost`` at the run time the launcher saw
it go) when the monitor did not list it itself, and ``notes`` say what followed.

Network: every daemon is a Zenoh peer with multicast scouting off, listening
on one UDP and one TCP port of 127.0.0.1 (free ports picked at start) and
connecting to both endpoints of every node started before it (monitor, RSUs,
cars in that order). So every pair of nodes holds a direct UDP link, which
carries the best-effort V2X traffic, and a direct TCP link, which carries the
reliable plumbing (``max_links`` 2; see ``deploy/zenoh/README.md``). A node's
open connects to the TCP endpoints one after another, then to the UDP ones in the
background (``ZenohSettings.connect_in_turn``: links of a pair opened at once lost
declarations for good), and fails when the nodes before it do not answer within
``connect_timeout_s`` (30 s).

Files: each child's stdout and stderr go to ``<run dir>/<node>.log``; the
monitor writes ``<run dir>/result.json``; ``<run dir>/children.json`` lists the
children's pids and command lines. The run dir is ``--run-dir``; without it,
``<OUT>-logs/`` beside ``--json OUT``, and only without both
``results/up/<timestamp>/`` under the working directory (git-ignored).

:func:`actor_commands` builds the same command lines for other addresses: the
network lab starts them inside network namespaces.

In Python: :func:`prepare_up` builds one run (nothing started) and
:meth:`UpRun.execute` runs it and returns an :class:`UpOutcome` with the typed
run result (``services.model.results.RunResult``); ``services.api.run_daemons``
and the ``up`` command both use them. ``--trace OUT`` asks the monitor for its
per-step record of every car's truth and writes it as the CSV of ``crosspath
sim --trace`` (``services.sim.harness.harness_trace``: ``accel`` is derived
from the speed and ``detail`` is empty, as the cars do not report them); the
``--json`` result then carries no trace.
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
import threading
import time
from collections.abc import Callable, Collection, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from types import FrameType
from typing import IO, Final, get_args

from services.edge.args import (
    add_mode_and_policy,
    int_at_least,
    non_negative_float,
    non_negative_int,
    output_dir,
    output_file,
    positive_float,
    run_speed,
)
from services.edge.progress import Ticker
from services.edge.settings import LogLevel, background_endpoint
from services.model.catalog import resolve_scenario
from services.model.results import CrashEvent, RunResult
from services.model.scenario import Scenario, load_scenario
from services.model.types import Policy, RunMode, parse_mode, parse_policy
from services.supervise.expand import expand_scenario
from services.supervise.hosts import bind_listen_port, default_cars_per_process, group_cars

__all__ = [
    "GRACE_S",
    "Child",
    "Endpoints",
    "Launcher",
    "UpOutcome",
    "UpRun",
    "actor_commands",
    "configure",
    "daemon_env",
    "free_ports",
    "loopback_endpoints",
    "node_order",
    "prepare_up",
    "run",
]

GRACE_S: Final = 5.0
"""Seconds a child has to exit after SIGTERM before it is killed."""

LEASE_MS: Final = 2000
"""Zenoh link lease of the daemons ``crosspath up`` starts [ms] (Zenoh's default is 10 s): a
crashed peer's UDP link, and with it its liveliness token, is gone after at most this."""

HOST_LEASE_MS: Final = 10000
"""The link lease when cars share host processes (``--cars-per-process`` > 1) [ms]: Zenoh's
default. A 40-car run holds thousands of links on two busy cores, and with
:data:`LEASE_MS` an idle car's links were seen to expire (its token lost: the run
failed); a crashed host is still seen within this."""

WAIT_ACTORS_PER_NODE_S: Final = 1.5
"""The monitor waits for the actors this long per node (at least 30 s) [wall s]: a 40-car
run on two loaded cores was seen to need more than 30 s to bring every node up."""

SWEEP_GRACE_S: Final = 2.0
"""Seconds a swept leftover process has to exit after SIGTERM before it is killed."""

CRASH_WAIT_S: Final = 4.0
"""After an actor exits during the run, how long the monitor gets to notice and fail."""

MONITOR: Final = "monitor"
"""Node id of the monitor."""

REPO_ROOT: Final = Path(__file__).resolve().parents[2]
"""The directory holding ``services``: the source tree, or site-packages when installed."""

FROM_SOURCE: Final = (REPO_ROOT / "pyproject.toml").is_file()
"""Whether ``services`` comes from a source tree rather than an installed package: only then
do the children need :data:`REPO_ROOT` on ``PYTHONPATH`` (an installed one is already on
``sys.executable``'s path, and putting site-packages first would shadow the stdlib)."""

TAIL_LINES: Final = 20
"""Lines of a failed child's log printed."""


@dataclass(frozen=True, slots=True)
class Endpoints:
    """A node's two Zenoh locators: ``udp/<addr>:<port>`` (V2X) and ``tcp/<addr>:<port>``
    (plumbing); it listens on both and the nodes after it connect to both."""

    udp: str
    tcp: str

    def __post_init__(self) -> None:
        # the network lab's TLS mode: ``quic/...?rel=0`` (datagrams) and ``tls/...``
        for protos, locator in ((("udp", "quic"), self.udp), (("tcp", "tls"), self.tcp)):
            head, sep, rest = locator.partition("/")
            if head not in protos or not sep or ":" not in rest:
                raise ValueError(f"expected {protos[0]}/<address>:<port>, got {locator!r}")

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
    trace: bool = False,
    keys_dir: Path | None = None,
    started_later: Collection[str] = (),
) -> dict[str, list[str]]:
    """Command lines (argv) of every daemon of one run, in start order (see :func:`node_order`).

    ``endpoints`` gives every node's locators (monitor included); node ``i``
    listens on its own and connects to those of nodes ``0..i-1``. Nothing is
    started and nothing but the scenario file is read. Start each with
    :func:`daemon_env` and :data:`REPO_ROOT` as working directory (as
    :class:`Launcher` does); ``zenoh_options`` are raw Zenoh settings for every
    daemon (``crosspath up`` shortens the link lease, :data:`LEASE_MS`); ``trace`` asks
    the monitor for the per-step trace in its result; ``keys_dir`` (an authority made by
    :func:`make_run_authority`) gives every daemon its key, certificate, the root and the
    revocation list (None: no credentials, unsigned V2X). Every node connects to the
    TCP endpoints before it one after another (``zenoh.connect_in_turn``), so each must be
    up within 30 s, except those of ``started_later`` (``crosspath lab up`` starts the
    monitor after the others), which it connects to in the background. Raises
    ``ValueError`` (``ScenarioError`` included) when the scenario is unusable or an
    endpoint is missing.
    """
    mode = RunMode(mode)
    policy = Policy(policy)
    scenario = load_scenario(scenario_path)
    order = node_order(scenario, mode, monitor)
    missing = [n for n in order if n not in endpoints]
    if missing:
        raise ValueError(f"no endpoints for {', '.join(missing)}")
    scenario_arg = str(resolve_scenario(scenario_path).resolve())  # a packaged name too
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
            # many cars open their Zenoh sessions one after another on a busy machine
            argv += ["--wait-actors", repr(max(30.0, WAIT_ACTORS_PER_NODE_S * len(order)))]
            if trace:
                argv += ["--trace"]
        elif node in rsus:
            argv += ["rsu", "--scenario", scenario_arg, "--id", node]
        else:
            argv += ["vehicle", "--scenario", scenario_arg, "--id", node]
        for locator in endpoints[node].locators:
            argv += ["--listen", locator]
        for earlier in order[:index]:
            for locator in endpoints[earlier].locators:
                if earlier in started_later:  # not awaited (connect_in_turn)
                    locator = background_endpoint(locator)
                argv += ["--connect", locator]
        # the nodes it connects to are up: their links are opened one after another
        argv += ["--set", "zenoh.connect_in_turn=true"]
        if zenoh_options:
            argv += ["--set", f"zenoh.options={json.dumps(dict(zenoh_options))}"]
        if log_level is not None:
            argv += ["--log-level", log_level]
        if prefix is not None:
            argv += ["--prefix", prefix]
        if keys_dir is not None:
            argv += security_args(keys_dir)
        commands[node] = argv
    return commands


def security_args(keys_dir: Path) -> list[str]:
    """``--set security.*`` for a daemon of a run whose authority is ``keys_dir``
    (``{node}`` in the key and certificate paths: the daemon's own id)."""
    d = keys_dir.resolve()
    out: list[str] = []
    for name, value in (
        ("key", d / "{node}.key"),
        ("certificate", d / "{node}.cert"),
        ("root", d / "root.pub"),
        ("revocation", d / "revoked.txt"),
    ):
        out += ["--set", f"security.{name}={value}"]
    return out


def make_run_authority(directory: Path, scenario: Scenario, monitor: str = MONITOR) -> Path:
    """A throw-away authority for one run in ``directory`` (issue 13): a root and a key
    and certificate for every car, RSU and the monitor of ``scenario``, valid one day."""
    from services.edge.trust import Authority, rsu_grants

    auth = Authority.init(directory, exist_ok=True)
    cars = [v.id for v in scenario.vehicles]
    auth.provision(cars, rsu_grants(scenario), [monitor], validity_s=86400)
    return directory


def free_ports(count: int, host: str = "127.0.0.1") -> list[tuple[int, int]]:
    """``count`` (udp port, tcp port) pairs free on ``host`` right now (all held open
    together while picking, so they are distinct), below the ephemeral range where
    there is room (:func:`~services.supervise.hosts.bind_listen_port`)."""
    held: list[socket.socket] = []
    pairs: list[tuple[int, int]] = []
    try:
        for _ in range(count):
            ports = []
            for kind in (socket.SOCK_DGRAM, socket.SOCK_STREAM):
                sock = socket.socket(socket.AF_INET, kind)
                held.append(sock)
                bind_listen_port(sock, host)  # below the ephemeral range (hosts.py)
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


def _die_with_parent(parent: int) -> Callable[[], None]:
    """For the child before exec (Linux): SIGTERM when the launcher (pid ``parent``) dies,
    even by SIGKILL; exit at once if it already died before the request was made."""

    def preexec() -> None:
        import ctypes

        pr_set_pdeathsig = 1
        with contextlib.suppress(OSError, AttributeError):
            ctypes.CDLL(None, use_errno=True).prctl(pr_set_pdeathsig, int(signal.SIGTERM))
        if os.getppid() != parent:
            os._exit(1)

    return preexec


def processes_carrying(marker: str) -> list[int]:
    """Pids (ours excluded) whose command line contains ``marker``, from ``/proc`` (Linux;
    empty elsewhere). A process that ends while being read is skipped."""
    if not marker:
        raise ValueError("an empty marker would match every process")
    needle = marker.encode()
    own = os.getpid()
    found: list[int] = []
    with contextlib.suppress(OSError):
        entries = os.listdir("/proc")
        for entry in entries:
            if not entry.isdigit() or int(entry) == own:
                continue
            try:
                cmdline = Path("/proc", entry, "cmdline").read_bytes()
            except OSError:
                continue
            if needle in cmdline:
                found.append(int(entry))
    return sorted(found)


def sweep(marker: str, grace_s: float = SWEEP_GRACE_S) -> list[int]:
    """SIGTERM every process carrying ``marker`` (:func:`processes_carrying`), SIGKILL those
    left after ``grace_s``; the pids found."""
    found = processes_carrying(marker)
    for pid in found:
        with contextlib.suppress(ProcessLookupError, PermissionError):
            os.kill(pid, signal.SIGTERM)
    deadline = time.monotonic() + grace_s
    while time.monotonic() < deadline and set(processes_carrying(marker)) & set(found):
        time.sleep(0.05)
    for pid in set(processes_carrying(marker)) & set(found):
        with contextlib.suppress(ProcessLookupError, PermissionError):
            os.kill(pid, signal.SIGKILL)
    return found


def daemon_env(base: Mapping[str, str] | None = None) -> dict[str, str]:
    """The environment for a daemon started with :func:`actor_commands`' argv: ``base`` (or
    ours), from a source tree with that tree first on ``PYTHONPATH`` (:data:`FROM_SOURCE`),
    so ``-m services.cli.main`` works without an installed package; run it with
    :data:`REPO_ROOT` as working directory."""
    env = dict(os.environ if base is None else base)
    path = env.get("PYTHONPATH")
    if FROM_SOURCE:
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


def absent_actors(monitor_log: str) -> set[str]:
    """The actors a failed monitor's log names in its ``presence:`` lines (a run that never
    started: ``services.daemons.monitor``)."""
    found = set()
    for line in monitor_log.splitlines():
        _, sep, rest = line.partition(" presence: ")
        if sep:
            found.add(rest.partition(":")[0].strip())
    return found


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
    run_id: str | None = None
    """Carried by every child's command line: the final sweep finds leftovers by it."""
    exits: list[tuple[str, int, float]] = field(default_factory=list)
    """Actors (not the monitor) that exited during the run: node, exit code, wall time."""

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
                    preexec_fn=_die_with_parent(os.getpid()) if sys.platform == "linux" else None,
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
        if self.run_id:
            left = sweep(self.run_id, 0.0 if self.signals >= 2 else SWEEP_GRACE_S)
            if left:
                pids = ", ".join(str(pid) for pid in left)
                self.notes.append(f"swept {len(left)} leftover process(es) of the run: {pids}")

    @staticmethod
    def _signal(child: Child, signum: signal.Signals) -> None:
        with contextlib.suppress(ProcessLookupError, PermissionError):
            os.killpg(child.pid, signum)

    # -- the run

    def run(self, timeout_s: float) -> int | None:
        """Start, wait for the monitor (or a crash, timeout, signal), stop everything.

        Returns the monitor's exit code, or None when the run was cut short
        (``notes`` says why). Installs SIGINT/SIGTERM handlers for the duration when
        called from the main thread (Python allows them nowhere else).
        """
        previous = (
            {
                signum: signal.signal(signum, self._on_signal)
                for signum in (signal.SIGINT, signal.SIGTERM)
            }
            if threading.current_thread() is threading.main_thread()
            else {}
        )
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
            for child in self.children.values():
                rc = child.process.poll()
                seen = any(node == child.node for node, _, _ in self.exits)
                if child.node != self.monitor and rc is not None and not seen:
                    self.exits.append((child.node, rc, time.time()))
                    after = "" if crashed_at is None else " (after an earlier loss)"
                    self.notes.append(f"{child.node} exited during the run with code {rc}{after}")
                    if crashed_at is None:
                        crashed_at = now
            if crashed_at is not None and now - crashed_at > CRASH_WAIT_S:
                self.notes.append(
                    f"the monitor did not end the run within {CRASH_WAIT_S:g} s of the loss"
                )
                return None
            time.sleep(0.05)

    def failed_children(self, monitor_code: int | None) -> list[Child]:
        """Children whose log is worth showing: a non-zero exit, the monitor of a failed run,
        and the actors that monitor names as never present (its ``presence:`` lines)."""
        out = []
        absent: set[str] = set()
        for child in self.children.values():
            rc = child.process.returncode
            if child.node == self.monitor:
                if monitor_code != 0:
                    out.append(child)
                    absent = absent_actors(tail_log(child.log_path, 4 * TAIL_LINES))
            elif rc not in (0, None, -signal.SIGTERM):
                out.append(child)
        out += [c for c in self.children.values() if c.node in absent and c not in out]
        return out


# --------------------------------------------------------------------------- one run


@dataclass(frozen=True, slots=True)
class UpOutcome:
    """What one run left: the monitor's result (None if it wrote none or it could not be
    read), the monitor's exit code (None when the run was cut short), the launcher's
    ``notes`` (why it was cut short, what it killed), the signal that interrupted it
    (0: none) and the children whose logs are worth showing."""

    run_id: str
    run_dir: Path
    result: RunResult | None
    monitor_code: int | None
    notes: tuple[str, ...]
    interrupted: int
    failed: tuple[Child, ...]

    @property
    def ok(self) -> bool:
        """The run completed: a result without ``error``, the monitor exited 0."""
        return (
            not self.interrupted
            and self.monitor_code == 0
            and self.result is not None
            and self.result.ok
        )

    def failure(self) -> str:
        """Why the run failed, with the last lines of the failed children's logs."""
        reasons = list(self.notes)
        if self.result is None:
            reasons.append("the monitor wrote no result")
        elif self.result.error is not None:
            reasons.append(self.result.error)
        elif self.monitor_code not in (0, None):
            reasons.append(f"the monitor exited with code {self.monitor_code}")
        text = "; ".join(reasons) or "the run failed"
        for child in self.failed:
            text += f"\n--- {child.node} (exit {child.process.returncode}), last lines of "
            text += f"{child.log_path}:\n{tail_log(child.log_path)}"
        return text


@dataclass(slots=True)
class UpRun:
    """One run prepared by :func:`prepare_up` (commands built, nothing started)."""

    run_id: str
    run_dir: Path
    launcher: Launcher
    timeout_s: float
    max_sim_s: float
    speed: float
    trace: bool

    @property
    def result_path(self) -> Path:
        """Where the monitor writes the run result."""
        return self.run_dir / "result.json"

    def execute(self) -> UpOutcome:
        """Start every daemon, wait for the run, stop them all; the outcome."""
        self.result_path.unlink(missing_ok=True)  # never mistake an earlier run's for ours
        code = self.launcher.run(self.timeout_s)
        notes = list(self.launcher.notes)
        result: RunResult | None = None
        if self.result_path.exists():
            try:
                result = RunResult.model_validate_json(self.result_path.read_bytes())
            except (OSError, ValueError) as exc:
                notes.append(f"unreadable result {self.result_path}: {str(exc).splitlines()[0]}")
        if result is not None and self.trace and result.trace_fields and result.trace:
            from services.sim.harness import TRACE_FIELDS, harness_trace

            result = result.updated(
                trace_fields=list(TRACE_FIELDS),
                trace=harness_trace(result.trace_fields, result.trace),
            )
        if result is not None:
            result = self._with_losses(result)
        failed = [
            c
            for c in self.launcher.failed_children(code)
            if not (c.node == self.launcher.monitor and result is not None)
        ]
        return UpOutcome(
            self.run_id,
            self.run_dir,
            result,
            code,
            tuple(notes),
            self.launcher.interrupted,
            tuple(failed),
        )

    def _with_losses(self, result: RunResult) -> RunResult:
        """``result`` with a ``lost`` crash event for every actor the launcher saw exit
        that the monitor did not list (an unexpected loss), at its run time [s]."""
        listed = {(c.node, c.event) for c in result.crashes or []}
        extra = [
            CrashEvent(
                node=node,
                event="lost",
                t_s=None
                if result.epoch_unix is None
                else round(max(0.0, (wall - result.epoch_unix) * self.speed), 3),
            )
            for node, _code, wall in self.launcher.exits
            if (node, "lost") not in listed
        ]
        if not extra:
            return result
        return result.updated(crashes=[*(result.crashes or []), *extra])


def _is_number(value: object) -> bool:
    """An int or float, not a bool (``True`` is not a speed)."""
    return isinstance(value, int | float) and not isinstance(value, bool)


def prepare_up(
    scenario_path: str | os.PathLike[str],
    mode: RunMode | str = RunMode.RSU,
    policy: Policy | str = Policy.PAPER,
    seed: int = 0,
    speed: float = 1.0,
    *,
    run_dir: Path | None = None,
    timeout_s: float | None = None,
    max_sim_s: float | None = None,
    start_delay_s: float = 1.0,
    log_level: str = "INFO",
    trace: bool = False,
    cars_per_process: int | None = None,
    insecure: bool = False,
) -> UpRun:
    """One ``crosspath up`` run over loopback, ready to :meth:`~UpRun.execute`.

    ``run_dir`` defaults to ``results/up/<time>-<id>``; ``timeout_s`` [wall s] to
    ``max_sim_s / speed + 60``. A scenario with flows is expanded for ``seed`` into
    ``<run dir>/scenario.toml`` (``services.supervise.expand``), which every daemon
    loads. Unless ``insecure``, a throw-away authority in ``<run dir>/keys`` signs every
    daemon's V2X (:func:`make_run_authority`). ``cars_per_process`` cars share one host
    process (``services.supervise.hosts``; None:
    :func:`~services.supervise.hosts.default_cars_per_process`). Raises
    ``ValueError`` (``ScenarioError`` included) for bad arguments, before anything starts.
    """
    run_mode, run_policy = parse_mode(mode), parse_policy(policy)
    if isinstance(seed, bool) or not isinstance(seed, int) or seed < 0:
        raise ValueError(f"seed must be an int >= 0, got {seed!r}")
    if not (_is_number(speed) and 0.0 < speed <= 1000.0):
        raise ValueError(f"speed must be in (0, 1000], got {speed!r}")
    if timeout_s is not None and not (_is_number(timeout_s) and 0.0 < timeout_s < float("inf")):
        raise ValueError(f"timeout must be a finite number > 0 [s], got {timeout_s!r}")
    if max_sim_s is not None and not 0.0 < max_sim_s < float("inf"):
        raise ValueError(f"max_sim_s must be a finite number > 0 [s], got {max_sim_s!r}")
    if not 0.0 <= start_delay_s <= 3600.0:
        raise ValueError(f"start delay must be within 0..3600 s, got {start_delay_s!r}")
    if cars_per_process is not None and (
        isinstance(cars_per_process, bool)
        or not isinstance(cars_per_process, int)
        or cars_per_process < 1
    ):
        raise ValueError(f"cars per process must be an int >= 1, got {cars_per_process!r}")
    scenario = load_scenario(Path(scenario_path))
    stamp = time.strftime("%Y%m%d-%H%M%S")
    run_id = f"up-{stamp}-{secrets.token_hex(3)}"
    out = run_dir if run_dir is not None else Path("results") / "up" / f"{stamp}-{run_id[-6:]}"
    if scenario.spec.flows:  # every daemon loads the cars of this seed (services.supervise.expand)
        scenario_path = expand_scenario(scenario, seed, out / "scenario.toml")
        scenario = load_scenario(scenario_path)
    cars = [v.id for v in scenario.vehicles]
    per_process = cars_per_process or default_cars_per_process(len(cars))
    max_sim = max_sim_s if max_sim_s is not None else scenario.params.max_sim_s
    timeout = timeout_s if timeout_s is not None else max_sim / speed + 60.0
    nodes = node_order(scenario, run_mode)
    keys_dir = None if insecure else make_run_authority(out / "keys", scenario)
    commands = actor_commands(
        Path(scenario_path),
        run_mode,
        run_policy,
        seed,
        speed,
        loopback_endpoints(nodes),
        json_out=out / "result.json",
        run_id=run_id,
        max_sim_s=max_sim_s,
        start_delay_s=start_delay_s,
        log_level=log_level,
        zenoh_options={
            "transport/link/tx/lease": LEASE_MS if per_process == 1 else HOST_LEASE_MS,
            # every child's command line carries the run id: the final sweep finds it
            "metadata": {"crosspath_run": run_id},
        },
        trace=trace,
        keys_dir=keys_dir,
    )
    if per_process > 1:
        commands = group_cars(commands, cars, per_process)
    # a host closes its cars' Zenoh sessions one by one (about 0.3 s each)
    grace = GRACE_S + 0.5 * (per_process - 1)
    launcher = Launcher(commands, out, run_id=run_id, grace_s=grace)
    return UpRun(run_id, out, launcher, timeout, max_sim, speed, trace)


# --------------------------------------------------------------------------- CLI


def configure(parser: argparse.ArgumentParser) -> None:
    """Options of ``crosspath up``."""
    parser.add_argument("scenario", type=Path, help="TOML file or packaged name")
    add_mode_and_policy(parser)
    parser.add_argument("--seed", type=non_negative_int, default=0, help="seed of the start times")
    parser.add_argument(
        "--speed", type=run_speed, default=1.0, help="run seconds per wall second, up to 1000"
    )
    parser.add_argument(
        "--json", type=output_file, default=None, metavar="OUT", help="write the run result here"
    )
    parser.add_argument(
        "--trace",
        type=output_file,
        default=None,
        metavar="OUT",
        help="write the per-step CSV here (the columns of sim --trace)",
    )
    parser.add_argument(
        "--timeout",
        type=positive_float,
        default=None,
        help="wall s (default: max_sim_s / speed + 60)",
    )
    parser.add_argument(
        "--max-sim-s",
        type=positive_float,
        default=None,
        help="run time limit [s] (default: the scenario's)",
    )
    parser.add_argument(
        "--run-dir",
        type=output_dir,
        default=None,
        help="logs and result (default: <OUT>-logs beside --json OUT, else results/up/<time>)",
    )
    parser.add_argument(
        "--start-delay", type=non_negative_float, default=1.0, help="wall s before run time 0"
    )
    parser.add_argument(
        "--cars-per-process",
        type=int_at_least(1),
        default=None,
        metavar="N",
        help="cars per OS process, each still its own Zenoh node (default: 1 up to 4 cars, "
        "else about 2 processes per CPU)",
    )
    parser.add_argument(
        "--log-level",
        type=str.upper,
        choices=list(get_args(LogLevel)),
        default="INFO",
        help="log level of the daemons",
    )
    parser.add_argument(
        "--insecure",
        action="store_true",
        help="no keys: V2X unsigned and unverified (for comparison only; any peer can "
        "command the cars)",
    )


def _fail(message: str) -> int:
    sys.stderr.write(f"crosspath up: {message}\n")
    return 2


def run(args: argparse.Namespace) -> int:
    """One run over Zenoh on loopback; 0 when it completed, 1 when it failed, 130/143 when
    interrupted, 2 on bad arguments."""
    from services.daemons.monitor import format_degraded, format_network
    from services.sim.harness import write_trace_csv
    from services.sim.results import format_summary

    run_dir: Path | None = args.run_dir
    if run_dir is None and args.json is not None:  # beside the result asked for, not ./results
        run_dir = args.json.with_name(f"{args.json.stem}-logs")
    try:
        up = prepare_up(
            args.scenario,
            args.mode,
            args.policy,
            args.seed,
            args.speed,
            run_dir=run_dir,
            timeout_s=args.timeout,
            max_sim_s=args.max_sim_s,
            start_delay_s=args.start_delay,
            log_level=args.log_level,
            trace=args.trace is not None,
            cars_per_process=args.cars_per_process,
            insecure=args.insecure,
        )
    except ValueError as exc:  # ScenarioError included
        return _fail(str(exc))
    if args.insecure:
        print(
            "crosspath up: WARNING --insecure: V2X is neither signed nor verified, any peer "
            "on the network can command the cars (comparison runs only)",
            file=sys.stderr,
            flush=True,
        )
    launcher = up.launcher
    n_nodes = len(launcher.commands)
    print(f"crosspath up: run {up.run_id}, {n_nodes} processes, logs in {up.run_dir}", flush=True)

    def status() -> str:
        running = sum(1 for c in list(launcher.children.values()) if c.process.returncode is None)
        wall = up.max_sim_s / up.speed  # fits an 80-column terminal
        return (
            f"{running}/{n_nodes} running, run <= {wall:.0f} s wall, timeout {up.timeout_s:.0f} s"
        )

    with Ticker("crosspath up", status):
        outcome = up.execute()
    for note in outcome.notes:
        print(f"crosspath up: {note}", file=sys.stderr)
    result = outcome.result
    if result is not None:
        print(format_summary(result))
        print(format_network(result.network))
        if (degraded := format_degraded(result)) is not None:
            print(degraded)
        if args.trace is not None:
            write_trace_csv(args.trace, result.trace or [])
        if args.json is not None:
            args.json.parent.mkdir(parents=True, exist_ok=True)
            args.json.write_text(result.without_trace().to_json() + "\n")
        if result.error is not None:
            print(f"crosspath up: run failed: {result.error}", file=sys.stderr)
    for child in outcome.failed:
        rc = child.process.returncode
        tail = tail_log(child.log_path)
        print(
            f"--- {child.node} (exit {rc}), last lines of {child.log_path}:\n{tail}",
            file=sys.stderr,
        )
    if outcome.interrupted:
        return 128 + outcome.interrupted
    return 0 if outcome.ok else 1
