"""One daemon run in the network lab, with faults on the air, measured on the interfaces.

:func:`run_lab` builds a lab (one network namespace per car, RSU and the
monitor; ``services.supervise.lab.netns``), starts every daemon in its namespace
with the command lines of ``crosspath up`` (``launcher.actor_commands``), each
node listening on ``udp/<air address>:7447`` and ``tcp/<wire address>:7448`` and
connecting to both endpoints of every node started before it, injects the
faults, carries out the crash and restart schedule on the run clock, waits for
the monitor's run result and tears the lab down, also on an error, a timeout or
Ctrl-C / SIGTERM (:class:`LabInterrupted`).

What travels where (checked in every run, reported in ``lab.checks``): Zenoh
sends best-effort messages (all V2X) on a node pair's UDP link and reliable
ones (plumbing, stats) on its TCP link (``deploy/zenoh/README.md``), so V2X
crosses the air bridge and the plumbing the wire bridge. A packet counter table
``inet crosspath_meter`` in every node counts IP bytes per interface and
protocol; ``lab.checks`` sums TCP bytes on the air and UDP bytes on the wire
(both 0 in our runs).

Decisions where the issue was silent:

* **Zenoh link lease.** ``crosspath up`` uses a 2 s lease so a crash is
  noticed fast. In the lab that would defeat the faults: a UDP link that hears
  nothing for a lease is closed, and Zenoh then sends best-effort messages over
  any link left, the lossless TCP link on the wire (measured: at 100 % loss and a
  2 s lease every future path still arrived, over TCP). So lab daemons use
  :data:`LAB_LEASE_MS` (1 h): a silent UDP link stays up and its datagrams are
  lost, as on a radio. Crash detection does not rely on it: the runner watches
  its processes and ends the run when one exits unexpectedly (the monitor still
  sees a crash when the kernel closes the crashed daemon's sockets).
* **When faults start.** Loss on a UDP link that is not yet established would
  keep Zenoh from establishing it (its handshake is lost too) and V2X would go
  over TCP from the start. The runner therefore waits until every node pair
  holds its UDP link (``ss``: a connected UDP socket to every earlier node's air
  endpoint), then installs the faults before run time 0. ``lab.faults.applied_at_s``
  says when (negative: before the run's epoch).
* **Loss** is ingress loss on every car's and RSU's air interface (independent
  per receiver, as a radio; optional Gilbert bursts), ``R`` a fraction 0..1. The rate
  limit (tbf) is on every car's and RSU's air interface. The monitor is not a
  radio node: it sends and receives no V2X.
* **Crash and restart** (``NODE@T``, run seconds): SIGKILL of every process in
  the node's namespace at run time ``T``; a restart starts the same command
  line again in the namespace (its log continues in the same file). The monitor
  is told which nodes may crash (``--expect-crash``), so the run goes on. Only
  RSUs can be restarted: a car's body cannot resume where it stopped (a crashed
  car is recorded where it was last seen, so the run lasts until ``max_sim_s``).
  Counts a daemon made after its last stats report before the kill are lost, so
  after a crash a stream's ``delivery_ratio`` can exceed 1.
* **After a crash** a peer whose UDP link to the crashed daemon was opened by the
  other side (its end is the shared listening socket, which gets no ICMP "port
  unreachable" error) keeps that link, and sends V2X into it, until the long
  lease ends: this shows as extra on-air bytes of that car after a crash, not in
  the daemons' counters. Daemons that held such links may need the SIGKILL of
  ``Lab.down`` (after 2 s) to exit.
* **Names**: ``run_lab`` makes lab ``r<8 hex>`` unless given a name; a lab of
  the same name is removed first (``Lab.up``). Every daemon's command line
  carries the lab name (Zenoh ``metadata``), so ``pgrep -f <lab>`` finds them.
* **Counters** are read once when the faults are in place (before run time 0)
  and once after the monitor has exited; ``lab.air`` gives the differences and
  rates per *run* second (as the daemons' ``network`` section), beside each
  daemon's own V2X payload counters. Interface bytes include Ethernet, IP, UDP
  and Zenoh headers, keepalives, and every unicast copy: Zenoh peers send a
  future path once per receiver, where a radio would broadcast it once.
* **Timeline** (with crashes): ``fallback_s`` per car is from the kill to the
  first physics step at which the car reports AUTO, for every car that was in a
  coordinated mode at the kill; ``rebuild_s`` is from the moment the restarted
  RSU joined the run (``joined_s``) to the first moment its reservation table
  held every car within its coverage; ``rebuild_from_restart_s`` counts from
  the restart of the process instead (Python and Zenoh start-up included).
"""

from __future__ import annotations

import contextlib
import dataclasses
import json
import logging
import math
import secrets
import shlex
import signal
import subprocess
import threading
import time
from collections.abc import Callable, Iterator, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from types import FrameType
from typing import IO, Any, Final

from services.edge.tls import make_tls, tls_options
from services.model.results import ChannelParams, RunResult
from services.model.scenario import Scenario, load_scenario
from services.model.types import Policy, RunMode
from services.supervise.expand import expand_scenario
from services.supervise.hosts import default_cars_per_process, group_cars
from services.supervise.lab.faults import (
    AirCounters,
    Direction,
    Loss,
    Rate,
    air_counters,
    crash,
    set_loss,
    set_rate,
)
from services.supervise.lab.netns import Lab, LabError, LabPlan, Role, check_lab_name, tool
from services.supervise.launcher import (
    MONITOR,
    REPO_ROOT,
    Endpoints,
    actor_commands,
    daemon_env,
    make_run_authority,
    node_order,
    tail_log,
)

__all__ = [
    "DEFAULT_RUN_ROOT",
    "LAB_LEASE_MS",
    "TCP_PORT",
    "UDP_PORT",
    "LabInterrupted",
    "LabSession",
    "TimedAction",
    "approach_time",
    "crash_timeline",
    "lab_endpoints",
    "parse_timed",
    "rebuild_timeline",
    "run_lab",
    "shell_command",
]

LOG = logging.getLogger("crosspath.lab")

UDP_PORT: Final = 7447
"""Every node's Zenoh UDP endpoint (V2X) on its air address (the ``k``-th car of a host
process: ``UDP_PORT + 2k``)."""
TCP_PORT: Final = 7448
"""Every node's Zenoh TCP endpoint (plumbing) on its wire address (``TCP_PORT + 2k``)."""
QUIC_DATAGRAMS: Final = "?rel=0"
"""Endpoint metadata of a QUIC link that carries best-effort messages as unreliable QUIC
datagrams (the TLS lab's air: V2X stays lossy datagrams, now under mutual TLS)."""
TLS_SETTLE_S: Final = 0.5
"""After every node pair exchanged QUIC packets on the air, how long to let the
handshakes finish before faults go in [wall s]."""
LAB_LEASE_MS: Final = 3_600_000
"""Zenoh link lease of lab daemons [ms]: long, so a lossy UDP link is never closed (see
the module docstring)."""
START_DELAY_S: Final = 2.0
"""Wall seconds from the monitor's start message to run time 0 (faults go in meanwhile)."""
LINK_WAIT_S: Final = 15.0
"""How long to wait for every node pair's UDP link before giving up [wall s]."""
START_WAIT_S: Final = 45.0
"""How long to wait for the monitor to start the run (all daemons up) [wall s]."""
DEFAULT_RUN_ROOT: Final = Path("results") / "lab"
METER_TABLE: Final = "crosspath_meter"
AIR_FROM_SET: Final = "air_from"
"""The meter's set of addresses a node received UDP from on the air."""
_METER_NETS: Final = ("air", "wire")
_METER_PROTOS: Final = ("udp", "tcp", "other")


class LabInterrupted(KeyboardInterrupt):
    """SIGINT or SIGTERM arrived during a lab run; the lab was torn down before this left."""

    def __init__(self, signum: int) -> None:
        super().__init__(signal.Signals(signum).name)
        self.signum = signum


@dataclass(frozen=True, slots=True)
class TimedAction:
    """``node`` at run time ``at_s`` [s] (a crash or a restart)."""

    node: str
    at_s: float

    def __post_init__(self) -> None:
        if not self.node:
            raise ValueError("empty node name")
        if not (math.isfinite(self.at_s) and self.at_s >= 0.0):
            raise ValueError(f"time must be a finite number >= 0, got {self.at_s}")

    def __str__(self) -> str:
        return f"{self.node}@{self.at_s:g}"


def parse_timed(text: str) -> TimedAction:
    """``"rsu1@15.2"`` → ``TimedAction("rsu1", 15.2)``; ``ValueError`` when malformed."""
    node, sep, at = text.rpartition("@")
    if not sep or not node:
        raise ValueError(f"expected NODE@SECONDS, got {text!r}")
    try:
        seconds = float(at)
    except ValueError:
        raise ValueError(f"expected NODE@SECONDS, got {text!r}") from None
    return TimedAction(node, seconds)


def lab_endpoints(
    lab: Lab,
    nodes: Sequence[str],
    *,
    tls: bool = False,
    netns_of: Mapping[str, tuple[str, int]] | None = None,
) -> dict[str, Endpoints]:
    """Every node's endpoints: UDP on its air address (V2X), TCP on its wire address; with
    ``tls``, QUIC datagrams (:data:`QUIC_DATAGRAMS`) on the air and TLS on the wire, both
    with mutual TLS. ``netns_of`` maps a node to (the node whose namespace it lives in,
    its index there): the ``k``-th car of a host process listens on ports ``+ 2k``."""
    out: dict[str, Endpoints] = {}
    for n in nodes:
        ns, k = (netns_of or {}).get(n, (n, 0))
        air, wire = (
            f"{lab.air_addr(ns)}:{UDP_PORT + 2 * k}",
            f"{lab.wire_addr(ns)}:{TCP_PORT + 2 * k}",
        )
        if tls:
            out[n] = Endpoints(f"quic/{air}{QUIC_DATAGRAMS}", f"tls/{wire}")
        else:
            out[n] = Endpoints(f"udp/{air}", f"tcp/{wire}")
    return out


# --------------------------------------------------------------------------- signals


@contextlib.contextmanager
def _on_signals(handler: Callable[[int, FrameType | None], None]) -> Iterator[None]:
    """``handler`` takes SIGINT and SIGTERM for the block (main thread only: elsewhere
    Python cannot install handlers, and the block runs unchanged)."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    previous = {s: signal.signal(s, handler) for s in (signal.SIGINT, signal.SIGTERM)}
    try:
        yield
    finally:
        for s, h in previous.items():
            signal.signal(s, h)


def _interruptible() -> contextlib.AbstractContextManager[None]:
    """SIGINT and SIGTERM raise :class:`LabInterrupted` (main thread only)."""

    def handler(signum: int, _frame: FrameType | None) -> None:
        raise LabInterrupted(signum)

    return _on_signals(handler)


@contextlib.contextmanager
def _shielded() -> Iterator[list[int]]:
    """Hold SIGINT/SIGTERM while cleaning up (so a second Ctrl-C cannot leave debris);
    yields the list of signals that arrived meanwhile."""
    arrived: list[int] = []
    with _on_signals(lambda signum, _frame: arrived.append(signum)):
        yield arrived


# --------------------------------------------------------------------------- meter


def meter_ruleset(air_if: str, wire_if: str) -> str:
    """The ``nft -f`` script of the per-interface, per-protocol byte counters (pure)."""
    t = f"inet {METER_TABLE}"
    lines = [f"add table {t}", f"add set {t} {AIR_FROM_SET} {{ type ipv4_addr; flags dynamic; }}"]
    for net in _METER_NETS:
        for proto in _METER_PROTOS:
            for way in ("in", "out"):
                lines.append(f"add counter {t} {net}_{proto}_{way}")
    for chain, hook, match in (("cin", "input", "iifname"), ("cout", "output", "oifname")):
        way = "in" if hook == "input" else "out"
        lines.append(
            f"add chain {t} {chain} {{ type filter hook {hook} priority -400; policy accept; }}"
        )
        if hook == "input":  # who sent us UDP on the air (the TLS lab's link check)
            lines.append(
                f'add rule {t} {chain} iifname "{air_if}" meta l4proto udp '
                f"add @{AIR_FROM_SET} {{ ip saddr }}"
            )
        for net, ifname in (("air", air_if), ("wire", wire_if)):
            rule = f'add rule {t} {chain} {match} "{ifname}"'
            lines.append(f"{rule} meta l4proto udp counter name {net}_udp_{way}")
            lines.append(f"{rule} meta l4proto tcp counter name {net}_tcp_{way}")
            lines.append(f"{rule} meta l4proto != {{ tcp, udp }} counter name {net}_other_{way}")
    return "\n".join(lines) + "\n"


def install_meter(lab: Lab, node: str) -> None:
    """Count IP bytes per interface and protocol in ``node`` (table ``inet crosspath_meter``)."""
    plan = lab.node(node)
    lab.nft(node, script=meter_ruleset(plan.air_if, plan.wire_if))


def read_meter(lab: Lab, node: str) -> dict[str, int]:
    """``{"air_udp_in_bytes": ..., "air_udp_in_packets": ..., ...}`` of ``node`` (IP bytes)."""
    out = lab.nft(node, ["-j", "list", "table", "inet", METER_TABLE])
    values: dict[str, int] = {}
    for item in json.loads(out).get("nftables", []):
        counter = item.get("counter") if isinstance(item, dict) else None
        if isinstance(counter, dict):
            name = str(counter.get("name"))
            values[f"{name}_bytes"] = int(counter.get("bytes", 0))
            values[f"{name}_packets"] = int(counter.get("packets", 0))
    return values


# --------------------------------------------------------------------------- links


def udp_peers(lab: Lab, node: str) -> set[str]:
    """``addr:port`` of every peer ``node`` holds a connected UDP socket to."""
    done = lab.run(node, [tool("ss"), "-Hnu", "state", "established"], timeout=10)
    peers: set[str] = set()
    for line in done.stdout.decode(errors="replace").splitlines():
        cols = line.split()
        if len(cols) >= 4:
            peers.add(cols[-1])
    return peers


def air_senders(lab: Lab, node: str) -> set[str]:
    """Addresses ``node`` has received UDP from on the air (the meter's set)."""
    out = lab.nft(node, ["-j", "list", "set", "inet", METER_TABLE, AIR_FROM_SET])
    found: set[str] = set()
    for item in json.loads(out).get("nftables", []):
        entry = item.get("set") if isinstance(item, dict) else None
        if isinstance(entry, dict):
            found.update(str(e) for e in entry.get("elem", []) if isinstance(e, str))
    return found


def wait_udp_links(
    lab: Lab,
    order: Sequence[str],
    timeout_s: float = LINK_WAIT_S,
    *,
    tls: bool = False,
    endpoints: Mapping[str, Endpoints] | None = None,
) -> dict[str, list[str]]:
    """Wait until every namespace node holds a UDP link to every node started before it
    (``order``: namespace nodes in start order).

    Plain UDP links are connected sockets (``ss``); with ``tls`` the QUIC endpoints'
    sockets are not connected, so a link counts once both namespaces received UDP from
    each other on the air (:func:`air_senders`), then :data:`TLS_SETTLE_S` lets the
    handshakes finish (QUIC retransmits a lost handshake packet, unlike Zenoh over UDP).
    ``endpoints`` (every node's, cars of hosts included) gives the ports to expect.
    Returns what is still missing per node (empty when all links are up).
    """
    air = {n: lab.air_addr(n) for n in order}
    wanted: dict[str, set[str]] = {}
    for j, node in enumerate(order):
        if j == 0:
            continue
        if tls:
            wanted[node] = {air[n] for n in order[:j]}
        elif endpoints is None:
            wanted[node] = {f"{air[n]}:{UDP_PORT}" for n in order[:j]}
        else:
            earlier = {air[n] for n in order[:j]}
            wanted[node] = {
                e.udp.split("/", 1)[1]
                for e in endpoints.values()
                if e.udp.split("/", 1)[1].rsplit(":", 1)[0] in earlier
            }
    deadline = time.monotonic() + timeout_s
    while True:
        missing: dict[str, list[str]] = {}
        if tls:
            heard = {n: air_senders(lab, n) for n in order}
            for j, node in enumerate(order):
                for other in order[:j]:
                    if air[other] not in heard[node] or air[node] not in heard[other]:
                        missing.setdefault(node, []).append(air[other])
        else:
            for node, want in wanted.items():
                absent = want - udp_peers(lab, node)
                if absent:
                    missing[node] = sorted(absent)
        if not missing or time.monotonic() > deadline:
            if tls and not missing:
                time.sleep(TLS_SETTLE_S)
            return missing
        time.sleep(0.1)


# --------------------------------------------------------------------------- crash points


def approach_time(
    scenario: Scenario | Path | str,
    seed: int = 0,
    *,
    mode: RunMode | str = RunMode.RSU,
    policy: Policy | str = Policy.PAPER,
    distance_m: float = 60.0,
) -> float:
    """Run time [s] at which the first car comes within ``distance_m`` of the centre of the
    (first RSU's) intersection, from an in-process run of the same seed: a good moment to
    crash the RSU, while the cars approach."""
    from services.sim.harness import SimOptions, Simulation

    sc = scenario if isinstance(scenario, Scenario) else load_scenario(Path(scenario))
    inter = sc.rsus[0].intersection if sc.rsus else sc.intersections[0].id
    cx, cy = (float(v) for v in sc.intersection(inter).center)
    sim = Simulation(
        sc, SimOptions(mode=RunMode(mode), policy=Policy(policy), seed=seed, trace=True)
    )
    sim.run()
    for row in sim.trace_rows:
        t, x, y = float(row[0]), float(row[3]), float(row[4])
        if math.hypot(x - cx, y - cy) <= distance_m:
            return t
    raise ValueError(f"no car comes within {distance_m:g} m of intersection {inter!r}")


# --------------------------------------------------------------------------- timelines


def _rows_by_car(
    trace: Sequence[Sequence[Any]], fields: Sequence[str]
) -> dict[str, list[Sequence[Any]]]:
    iv = list(fields).index("vehicle")
    it = list(fields).index("t")
    by: dict[str, list[Sequence[Any]]] = {}
    for row in trace:
        by.setdefault(str(row[iv]), []).append(row)
    for rows in by.values():
        rows.sort(key=lambda r: float(r[it]))
    return by


def crash_timeline(
    trace: Sequence[Sequence[Any]], fields: Sequence[str], crash_s: float
) -> dict[str, Any]:
    """Fallback after an RSU crash at run time ``crash_s`` (pure).

    ``coordinated``: cars whose last reported mode at or before ``crash_s`` was not
    AUTO; ``fallback_s``: per such car, time from the crash to its first step in
    AUTO (None if it never came); ``fallback_all_s``: the largest (None when a car
    never fell back or none was coordinated).
    """
    f = list(fields)
    it, im = f.index("t"), f.index("mode")
    coordinated: list[str] = []
    fallback: dict[str, float | None] = {}
    for car, rows in sorted(_rows_by_car(trace, fields).items()):
        before = [r for r in rows if float(r[it]) <= crash_s + 1e-9]
        if not before or str(before[-1][im]) == "AUTO":
            continue
        coordinated.append(car)
        back = next(
            (float(r[it]) for r in rows if float(r[it]) > crash_s and str(r[im]) == "AUTO"), None
        )
        fallback[car] = None if back is None else round(back - crash_s, 4)
    values = list(fallback.values())
    worst = (
        None
        if not values or any(v is None for v in values)
        else max(v for v in values if v is not None)
    )
    return {
        "crash_s": round(crash_s, 4),
        "coordinated": coordinated,
        "fallback_s": fallback,
        "fallback_all_s": worst,
    }


def rebuild_timeline(
    table_log: Sequence[Sequence[Any]],
    joined_s: float | None,
    restart_s: float,
    trace: Sequence[Sequence[Any]],
    fields: Sequence[str],
    centre: tuple[float, float],
    coverage_m: float,
) -> dict[str, Any]:
    """When a restarted RSU's reservation table held every car in its coverage again (pure).

    ``table_log`` is the RSU's ``[[t, [cars]], ...]``; a car is in coverage at ``t`` when
    its last reported position at or before ``t`` lies within ``coverage_m`` of
    ``centre``. ``table_full_at_s`` is the first logged moment the table held all of
    them; ``rebuild_s`` counts from ``joined_s``, ``rebuild_from_restart_s`` from
    ``restart_s``.
    """
    f = list(fields)
    it, ix, iy = f.index("t"), f.index("x"), f.index("y")
    by_car = _rows_by_car(trace, fields)

    def in_coverage(t: float) -> set[str]:
        cars: set[str] = set()
        for car, rows in by_car.items():
            last = None
            for r in rows:
                if float(r[it]) > t + 1e-9:
                    break
                last = r
            if (
                last is not None
                and math.hypot(float(last[ix]) - centre[0], float(last[iy]) - centre[1])
                <= coverage_m
            ):
                cars.add(car)
        return cars

    full_at: float | None = None
    needed: list[str] = []
    for entry in table_log:
        t, cars = float(entry[0]), {str(c) for c in entry[1]}
        if joined_s is not None and t < joined_s - 1e-9:
            continue
        want = in_coverage(t)
        if want and want <= cars:
            full_at, needed = t, sorted(want)
            break
    return {
        "restart_s": round(restart_s, 4),
        "joined_s": joined_s,
        "table_full_at_s": full_at,
        "cars": needed,
        "rebuild_s": None if full_at is None or joined_s is None else round(full_at - joined_s, 4),
        "rebuild_from_restart_s": None if full_at is None else round(full_at - restart_s, 4),
    }


# --------------------------------------------------------------------------- processes


@dataclass(slots=True)
class _Daemon:
    """One started daemon process (a restart makes a new one)."""

    node: str
    argv: list[str]
    process: subprocess.Popen[bytes]
    log: IO[bytes]
    started_wall: float


@dataclass(slots=True)
class LabSession:
    """A lab with its daemons: build, start, fault, measure, tear down (used by
    :func:`run_lab` and ``crosspath lab up``)."""

    scenario_path: Path
    mode: RunMode
    name: str
    log_dir: Path
    lease_ms: int = LAB_LEASE_MS
    tls: bool = True
    """Mutual TLS on every Zenoh link (QUIC datagrams on the air, TLS on the wire) with
    certificates from a throw-away ``crosspath keys`` authority; False: plain UDP and TCP
    (for comparison)."""
    seed: int = 0
    """The seed a scenario with flows is expanded for (``services.supervise.expand``)."""
    cars_per_process: int | None = None
    """Cars per daemon process (None: ``hosts.default_cars_per_process``); a host
    process's cars share its namespace (the first car's), each listening on its own ports."""
    lab: Lab = field(init=False)
    plan: LabPlan = field(init=False)
    order: list[str] = field(init=False)
    """Nodes in start order: the monitor, the RSUs (``rsu`` mode), the cars."""
    daemons: list[_Daemon] = field(init=False, default_factory=list)
    scenario: Scenario = field(init=False)
    groups: list[list[str]] = field(init=False)
    """The cars of each daemon process, in start order (one each without hosts)."""
    netns_of: dict[str, tuple[str, int]] = field(init=False)
    """Car -> (the namespace node of its process, its index in the process)."""
    expanded: bool = field(init=False)
    """The scenario had flows: ``scenario_path`` is its expansion for :attr:`seed`."""

    def __post_init__(self) -> None:
        check_lab_name(self.name)
        if self.cars_per_process is not None and self.cars_per_process < 1:
            raise ValueError(f"cars per process must be >= 1, got {self.cars_per_process}")
        self.scenario = load_scenario(self.scenario_path)
        self.expanded = bool(self.scenario.spec.flows)
        if self.expanded:  # every daemon loads the cars of this seed
            self.scenario_path = expand_scenario(
                self.scenario, self.seed, self.log_dir / "scenario.toml"
            )
            self.scenario = load_scenario(self.scenario_path)
        self.order = node_order(self.scenario, self.mode, MONITOR)
        cars = [v.id for v in self.scenario.vehicles]
        per = self.cars_per_process or default_cars_per_process(len(cars))
        self.groups = [cars[i : i + per] for i in range(0, len(cars), per)]
        self.netns_of = {car: (g[0], k) for g in self.groups for k, car in enumerate(g)}
        rsus = [r.id for r in self.scenario.rsus] if self.mode is RunMode.RSU else []
        self.plan = LabPlan.build(
            self.name, cars=[g[0] for g in self.groups], rsus=rsus, monitor=MONITOR
        )
        self.lab = Lab(self.name)

    @property
    def ns_order(self) -> list[str]:
        """Namespace nodes in start order (a host process's namespace is its first car's)."""
        return [n for n in self.order if self.netns_of.get(n, (n, 0))[1] == 0]

    def endpoints(self) -> dict[str, Endpoints]:
        """Every node's endpoints (:func:`lab_endpoints`, TLS or not)."""
        return lab_endpoints(self.lab, self.order, tls=self.tls, netns_of=self.netns_of)

    def netns_node(self, key: str) -> str:
        """The namespace node of a command key (a node id, or a host's ``host.<k>``)."""
        if key.startswith("host."):
            return self.groups[int(key.removeprefix("host."))][0]
        return self.netns_of.get(key, (key, 0))[0]

    @property
    def radio_nodes(self) -> list[str]:
        """Cars and RSUs: the nodes on the air (faults apply to them)."""
        return [n.name for n in self.plan.nodes if n.role is not Role.MONITOR]

    def up(self) -> None:
        """Build the namespaces (removing leftovers of the same name) and the meters."""
        self.lab.up(self.plan)
        for node in self.plan.names:
            install_meter(self.lab, node)

    def commands(
        self,
        policy: Policy,
        seed: int,
        speed: float,
        *,
        run_id: str | None = None,
        json_out: Path | None = None,
        max_sim_s: float | None = None,
        start_delay_s: float | None = START_DELAY_S,
        log_level: str | None = "INFO",
        monitor_last: bool = False,
    ) -> dict[str, list[str]]:
        """The daemons' command lines (``actor_commands``) on the lab's addresses;
        ``monitor_last``: the monitor starts after the others (``crosspath lab up``), so
        they connect to it in the background."""
        options: dict[str, object] = {
            "transport/link/tx/lease": self.lease_ms,
            # Marks every process with its lab (Zenoh shows it in the admin space; and
            # ``pgrep -f`` finds the lab's processes by name).
            "metadata": {"crosspath_lab": self.name},
        }
        if self.expanded and seed != self.seed:
            raise ValueError(f"the flows were drawn for seed {self.seed}, not {seed}")
        # issue 13: signed V2X with a throw-away authority beside the logs
        keys_dir = make_run_authority(self.log_dir / "keys", self.scenario, MONITOR)
        commands = actor_commands(
            self.scenario_path,
            self.mode,
            policy,
            seed,
            speed,
            self.endpoints(),
            monitor=MONITOR,
            json_out=json_out,
            run_id=run_id,
            max_sim_s=max_sim_s,
            start_delay_s=start_delay_s,
            log_level=log_level,
            zenoh_options=options,
            keys_dir=keys_dir,
            started_later=(MONITOR,) if monitor_last else (),
        )
        per = max(len(g) for g in self.groups) if self.groups else 1
        if per > 1:
            commands = group_cars(commands, [c for g in self.groups for c in g], per)
        if self.tls:  # issue 13: mutual TLS, one X.509 certificate per process
            # absolute: Zenoh opens the files from the daemon's own working directory
            tls_dir = keys_dir.resolve()
            make_tls(tls_dir, list(commands))
            commands = {
                key: _with_zenoh_options(argv, options | tls_options(tls_dir, key))
                for key, argv in commands.items()
            }
        return commands

    def start(self, node: str, argv: Sequence[str]) -> _Daemon:
        """Start ``argv`` (command key ``node``) in its namespace; output appended to
        ``<log_dir>/<node>.log``."""
        self.log_dir.mkdir(parents=True, exist_ok=True)
        log = (self.log_dir / f"{node}.log").open("ab")
        if any(d.node == node for d in self.daemons):
            log.write(f"\n--- restarted at {time.strftime('%H:%M:%S')} ---\n".encode())
            log.flush()
        try:
            process = self.lab.exec(
                self.netns_node(node),
                list(argv),
                env=daemon_env(),
                stdout=log,
                stderr=subprocess.STDOUT,
                cwd=REPO_ROOT,
            )
        except BaseException:
            log.close()
            raise
        daemon = _Daemon(node, list(argv), process, log, time.time())
        self.daemons.append(daemon)
        return daemon

    def current(self, node: str) -> _Daemon | None:
        """The latest process started for ``node``."""
        for d in reversed(self.daemons):
            if d.node == node:
                return d
        return None

    def pids(self) -> dict[str, list[int]]:
        out: dict[str, list[int]] = {}
        for d in self.daemons:
            out.setdefault(d.node, []).append(d.process.pid)
        return out

    def apply_faults(self, loss: float, burst: float | None, rate_mbit: float | None) -> list[str]:
        """Loss (ingress, a fraction 0..1) and rate limit on every radio node; what was done."""
        done: list[str] = []
        for node in self.radio_nodes:
            if loss > 0.0:
                set_loss(self.lab, node, loss, burst, direction=Direction.INGRESS)
            if rate_mbit is not None:
                set_rate(self.lab, node, rate_mbit)
        if loss > 0.0:
            done.append(f"loss {loss:g}" + (f" (bursts of {burst:g})" if burst else ""))
        if rate_mbit is not None:
            done.append(f"rate {rate_mbit:g} Mbit/s")
        return done

    def counters(self) -> dict[str, dict[str, int]]:
        """Interface, loss, rate and meter counters of every node now."""
        out: dict[str, dict[str, int]] = {}
        for node in self.plan.names:
            values: dict[str, int] = air_counters(self.lab, node).as_dict()
            values.update(read_meter(self.lab, node))
            out[node] = values
        return out

    def close_logs(self) -> None:
        for d in self.daemons:
            with contextlib.suppress(OSError):
                d.log.close()

    def down(self) -> None:
        """Remove the lab: every process, namespace, link, rule (``Lab.down``)."""
        try:
            self.lab.down()
        finally:
            self.close_logs()


def _with_zenoh_options(argv: Sequence[str], options: Mapping[str, object]) -> list[str]:
    """``argv`` with its ``--set zenoh.options=...`` replaced by ``options``."""
    out = list(argv)
    flag = "zenoh.options="
    for i, arg in enumerate(out):
        if arg.startswith(flag) and i > 0 and out[i - 1] == "--set":
            out[i] = flag + json.dumps(dict(options))
            return out
    return [*out, "--set", flag + json.dumps(dict(options))]


def _wait_start(path: Path, session: LabSession, timeout_s: float) -> dict[str, Any]:
    """Wait for the monitor's start file; ``LabError`` if a daemon dies or time runs out."""
    deadline = time.monotonic() + timeout_s
    while True:
        if path.exists():
            with contextlib.suppress(OSError, ValueError):
                data: dict[str, Any] = json.loads(path.read_text())
                return data
        for d in session.daemons:
            rc = d.process.poll()
            if rc is not None:
                raise LabError(
                    f"{d.node} exited with code {rc} before the run started; last lines of "
                    f"{session.log_dir / (d.node + '.log')}:\n"
                    + tail_log(session.log_dir / f"{d.node}.log", 15)
                )
        if time.monotonic() > deadline:
            raise LabError(f"the run did not start within {timeout_s:g} s (see {session.log_dir})")
        time.sleep(0.05)


# --------------------------------------------------------------------------- the run


def _validate_schedule(
    scenario: Scenario,
    mode: RunMode,
    crash_at: Sequence[TimedAction],
    restart_at: Sequence[TimedAction],
) -> None:
    cars = {v.id for v in scenario.vehicles}
    rsus = {r.id for r in scenario.rsus} if mode is RunMode.RSU else set()
    for action in crash_at:
        if action.node not in cars | rsus:
            raise ValueError(
                f"cannot crash {action.node!r}: not a car or RSU of this {mode} run "
                f"(nodes: {', '.join(sorted(cars | rsus))})"
            )
    for action in restart_at:
        if action.node not in rsus:
            raise ValueError(
                f"cannot restart {action.node!r}: only RSUs can be restarted "
                "(a car's body cannot resume where it stopped)"
            )
        earlier = [c for c in crash_at if c.node == action.node and c.at_s < action.at_s]
        if not earlier:
            raise ValueError(f"restart {action} needs a crash of {action.node} before it")


def _kbps(nbytes: int, seconds: float) -> float | None:
    return round(nbytes * 8 / 1000 / seconds, 3) if seconds > 0 else None


def _air_section(
    before: Mapping[str, Mapping[str, int]],
    after: Mapping[str, Mapping[str, int]],
    actors: Mapping[str, Any],
    sim_s: float,
) -> dict[str, dict[str, Any]]:
    """Per node: interface and meter deltas, rates per run second, the daemon's own totals."""
    section: dict[str, dict[str, Any]] = {}
    for node, end in after.items():
        start = before.get(node, {})
        delta = {k: v - start.get(k, 0) for k, v in end.items()}
        entry: dict[str, Any] = {
            f.name: delta.get(f.name, 0) for f in dataclasses.fields(AirCounters)
        }
        entry["tx_kbps"] = _kbps(delta.get("tx_bytes", 0), sim_s)
        entry["rx_kbps"] = _kbps(delta.get("rx_bytes", 0), sim_s)
        for net in _METER_NETS:
            for proto in _METER_PROTOS:
                for way in ("in", "out"):
                    key = f"{net}_{proto}_{way}_bytes"
                    entry[key] = delta.get(key, 0)
        v2x = actors.get(node, {}).get("v2x") if isinstance(actors.get(node), Mapping) else None
        if isinstance(v2x, Mapping):
            entry["daemon_tx_msgs"] = int(v2x.get("msgs_tx", 0))
            entry["daemon_tx_bytes"] = int(v2x.get("bytes_tx", 0))
            entry["daemon_rx_msgs"] = int(v2x.get("msgs_rx", 0))
            entry["daemon_rx_bytes"] = int(v2x.get("bytes_rx", 0))
            entry["daemon_tx_kbps"] = _kbps(entry["daemon_tx_bytes"], sim_s)
            entry["daemon_rx_kbps"] = _kbps(entry["daemon_rx_bytes"], sim_s)
        section[node] = entry
    return section


def _mode_summary(trace: Sequence[Sequence[Any]], fields: Sequence[str]) -> dict[str, Any]:
    """Per car: the modes it reported and run seconds spent coordinated (not AUTO)."""
    f = list(fields)
    it, im = f.index("t"), f.index("mode")
    out: dict[str, Any] = {}
    for car, rows in sorted(_rows_by_car(trace, fields).items()):
        modes = sorted({str(r[im]) for r in rows})
        dt = 0.0
        if len(rows) > 1:
            dt = (float(rows[-1][it]) - float(rows[0][it])) / (len(rows) - 1)
        coordinated = sum(1 for r in rows if str(r[im]) != "AUTO") * dt
        out[car] = {"modes": modes, "coordinated_s": round(coordinated, 3)}
    return out


def run_lab(
    scenario: Path | str,
    mode: RunMode | str = RunMode.RSU,
    policy: Policy | str = Policy.PAPER,
    seed: int = 0,
    loss: float = 0.0,
    *,
    burst: float | None = None,
    rate_mbit: float | None = None,
    speed: float = 1.0,
    crash_at: Sequence[TimedAction] = (),
    restart_at: Sequence[TimedAction] = (),
    name: str | None = None,
    run_dir: Path | None = None,
    json_out: Path | None = None,
    max_sim_s: float | None = None,
    timeout_s: float | None = None,
    trace: bool = False,
    log_level: str = "INFO",
    lease_ms: int = LAB_LEASE_MS,
    tls: bool = True,
    cars_per_process: int | None = None,
    say: Callable[[str], None] | None = None,
) -> RunResult:
    """One run in a fresh lab; returns the run result with ``network`` and ``lab`` (its
    provenance's channel says ``lab`` with the loss, burst and rate).

    ``loss`` a fraction 0..1 (ingress on every car and RSU), ``burst`` the mean loss
    burst in packets (Gilbert), ``rate_mbit`` a tbf limit on every car's and RSU's
    air; ``crash_at`` / ``restart_at`` the schedule (run seconds); ``trace`` keeps
    the per-step trace in the result. A run that fails (a daemon died, the monitor
    gave up, timeout) still returns a result, with ``error`` (one that recorded nothing
    when the monitor wrote none). Raises ``ValueError``
    for bad arguments, :class:`~services.supervise.lab.netns.LabError` when the lab
    cannot be built or the run cannot start, :class:`LabInterrupted` on
    SIGINT/SIGTERM. The lab is always torn down before this returns or raises.

    ``tls`` (the default) runs every Zenoh link under mutual TLS (:class:`LabSession`);
    a scenario with flows is expanded for ``seed``; ``cars_per_process`` as ``crosspath
    up --cars-per-process`` (a host process's cars share one namespace).
    """
    run_mode = RunMode(mode)
    run_policy = Policy(policy)
    if not (0.0 < speed <= 1000.0):
        raise ValueError(f"speed must be in (0, 1000], got {speed}")
    if seed < 0:
        raise ValueError(f"seed must be >= 0, got {seed}")
    loss_model = Loss(loss, burst) if loss > 0.0 else None
    if loss_model is None and not 0.0 <= loss <= 1.0:
        raise ValueError(f"loss must be a fraction within 0..1, got {loss}")
    if rate_mbit is not None:
        Rate.of(rate_mbit)
    name = name or f"r{secrets.token_hex(4)}"
    stamp = time.strftime("%Y%m%d-%H%M%S")
    run_id = f"lab-{name}-{secrets.token_hex(3)}"
    out_dir = run_dir or DEFAULT_RUN_ROOT / f"{stamp}-{name}"
    session = LabSession(
        Path(scenario),
        run_mode,
        name,
        out_dir,
        lease_ms,
        tls=tls,
        seed=seed,
        cars_per_process=cars_per_process,
    )
    sc = session.scenario
    _validate_schedule(sc, run_mode, crash_at, restart_at)
    for action in crash_at:
        if any(action.node in g and len(g) > 1 for g in session.groups):
            raise ValueError(f"cannot crash {action.node!r} alone: it shares a host process")
    max_sim = max_sim_s if max_sim_s is not None else sc.params.max_sim_s
    timeout = timeout_s if timeout_s is not None else max_sim / speed + 60.0
    report = say or (lambda _msg: None)
    result_path = out_dir / "result.json"
    start_path = out_dir / "start.json"
    out_dir.mkdir(parents=True, exist_ok=True)
    result_path.unlink(missing_ok=True)
    start_path.unlink(missing_ok=True)
    notes: list[str] = []
    lab_info: dict[str, Any] = {
        "name": name,
        "run_dir": str(out_dir),
        "lease_ms": lease_ms,
        "tls": tls,
        "processes": {},
        "endpoints": {},
        "nodes": {},
        "faults": {
            "loss": loss,
            "burst": burst,
            "direction": str(Direction.INGRESS),
            "rate_mbit": rate_mbit,
            "nodes": session.radio_nodes,
            "applied_at_s": None,
        },
        "schedule": [],
    }
    before: dict[str, dict[str, int]] = {}
    after: dict[str, dict[str, int]] = {}
    epoch: float | None = None
    crashed: set[str] = set()
    interrupted: LabInterrupted | None = None
    with _interruptible():
        try:
            report(f"lab {name}: building {len(session.plan.nodes)} namespaces")
            session.up()
            lab_info["nodes"] = {
                n.name: {
                    "role": str(n.role),
                    "netns": n.netns,
                    "air": n.air_addr,
                    "wire": n.wire_addr,
                }
                for n in session.plan.nodes
            }
            commands = session.commands(
                run_policy,
                seed,
                speed,
                run_id=run_id,
                json_out=result_path,
                max_sim_s=max_sim_s,
                log_level=log_level,
            )
            lab_info["endpoints"] = {n: e.locators for n, e in session.endpoints().items()}
            lab_info["processes"] = {k: session.netns_node(k) for k in commands}
            monitor_argv = commands[MONITOR] + [
                "--start-file",
                str(start_path.resolve()),
                "--trace",
            ]
            for node in sorted({a.node for a in crash_at}):
                monitor_argv += ["--expect-crash", node]
            commands[MONITOR] = monitor_argv
            for node, argv in commands.items():
                session.start(node, argv)
            report(f"lab {name}: {len(commands)} daemons started, logs in {out_dir}")
            start = _wait_start(start_path, session, START_WAIT_S)
            epoch = float(start["epoch_unix"])
            missing = wait_udp_links(
                session.lab, session.ns_order, tls=tls, endpoints=session.endpoints()
            )
            if missing:
                raise LabError(
                    "UDP links not established (faults would push V2X onto TCP): "
                    + "; ".join(f"{n} lacks {', '.join(m)}" for n, m in missing.items())
                )
            faults_done = session.apply_faults(loss, burst, rate_mbit)
            lab_info["faults"]["applied_at_s"] = round((time.time() - epoch) * speed, 4)
            before = session.counters()
            if faults_done:
                report(f"lab {name}: {', '.join(faults_done)} on {', '.join(session.radio_nodes)}")
            events = sorted(
                [("crash", a) for a in crash_at] + [("restart", a) for a in restart_at],
                key=lambda e: (e[1].at_s, e[0] != "crash"),
            )
            monitor = session.current(MONITOR)
            if monitor is None:
                raise LabError("the monitor was not started")
            deadline = time.monotonic() + timeout
            stopping: float | None = None
            while monitor.process.poll() is None:
                now_wall = time.time()
                while events and now_wall >= epoch + events[0][1].at_s / speed:
                    kind, action = events.pop(0)
                    if kind == "crash":
                        pids = crash(session.lab, action.node)
                        crashed.add(action.node)
                    else:
                        pids = [session.start(action.node, commands[action.node]).process.pid]
                        crashed.discard(action.node)
                    done_at = (time.time() - epoch) * speed
                    lab_info["schedule"].append(
                        {
                            "action": kind,
                            "node": action.node,
                            "at_s": action.at_s,
                            "done_at_s": round(done_at, 4),
                            "pids": pids,
                        }
                    )
                    report(f"lab {name}: {kind} {action.node} at run time {done_at:.2f} s")
                if stopping is None:
                    for d in session.daemons:
                        if d is monitor or d.node in crashed or d is not session.current(d.node):
                            continue
                        rc = d.process.poll()
                        if rc is not None:
                            notes.append(f"{d.node} exited during the run with code {rc}")
                            stopping = time.monotonic()
                    if time.monotonic() > deadline:
                        notes.append(f"timeout: the run did not end within {timeout:g} s")
                        stopping = time.monotonic()
                    if stopping is not None:
                        monitor.process.send_signal(signal.SIGTERM)
                elif time.monotonic() - stopping > 15.0:
                    monitor.process.kill()
                    break
                time.sleep(0.02)
            with contextlib.suppress(subprocess.TimeoutExpired):
                monitor.process.wait(timeout=5.0)
            try:
                after = session.counters()
            except LabError as exc:
                notes.append(f"could not read the counters after the run: {exc}")
        except LabInterrupted as exc:
            interrupted = exc
        finally:
            with _shielded() as arrived:
                session.down()
            if arrived and interrupted is None:
                interrupted = LabInterrupted(arrived[0])
    if interrupted is not None:
        raise interrupted
    result: RunResult
    try:
        result = RunResult.model_validate_json(result_path.read_bytes())
    except (OSError, ValueError):
        result = RunResult.failed(
            mode=run_mode,
            policy=run_policy if run_mode is RunMode.RSU else None,
            seed=seed,
            scenario=sc.name,
            harness="daemons",
            error="the monitor wrote no result",
        )
        mon_log = out_dir / f"{MONITOR}.log"
        notes.append(f"monitor log tail:\n{tail_log(mon_log, 15)}")
    if notes:
        prior = result.error
        result = result.updated(error="; ".join(notes) + (f" ({prior})" if prior else ""))
    fields = list(result.trace_fields or [])
    rows: list[Sequence[Any]] = list(result.trace or [])
    sim_s = result.sim_s
    actors: Mapping[str, Any] = result.actors or {}
    if after:
        lab_info["air"] = _air_section(before, after, actors, sim_s)
        lab_info["checks"] = {
            "air_tcp_bytes": sum(
                v.get("air_tcp_in_bytes", 0) + v.get("air_tcp_out_bytes", 0)
                for v in lab_info["air"].values()
            ),
            "wire_udp_bytes": sum(
                v.get("wire_udp_in_bytes", 0) + v.get("wire_udp_out_bytes", 0)
                for v in lab_info["air"].values()
            ),
        }
    if fields and rows:
        lab_info["modes"] = _mode_summary(rows, fields)
        timeline: dict[str, Any] = {}
        crashes = [s for s in lab_info["schedule"] if s["action"] == "crash"]
        restarts = [s for s in lab_info["schedule"] if s["action"] == "restart"]
        if crashes:
            timeline["crashes"] = [
                {"node": c["node"], **crash_timeline(rows, fields, float(c["done_at_s"]))}
                for c in crashes
            ]
        if restarts:
            timeline["restarts"] = []
            for r in restarts:
                node = str(r["node"])
                info = actors.get(node) if isinstance(actors.get(node), Mapping) else None
                spec = sc.rsu(node)
                centre = sc.intersection(spec.intersection).center
                table_log = list(info.get("table_log") or []) if info else []
                joined = info.get("joined_s") if info else None
                timeline["restarts"].append(
                    {
                        "node": node,
                        **rebuild_timeline(
                            table_log,
                            None if joined is None else float(joined),
                            float(r["done_at_s"]),
                            rows,
                            fields,
                            (float(centre[0]), float(centre[1])),
                            spec.coverage_m,
                        ),
                    }
                )
        if timeline:
            lab_info["timeline"] = timeline
    lab_info["pids"] = session.pids()
    channel = ChannelParams(kind="lab", loss=loss, burst=burst, rate_mbit=rate_mbit)
    prov = result.provenance
    result = result.updated(
        loss=loss,  # a probability, as in the in-process harness's result
        lab=lab_info,
        provenance=None if prov is None else prov.model_copy(update={"channel": channel}),
    )
    if not trace:
        result = result.without_trace()
    if json_out is not None:
        json_out.parent.mkdir(parents=True, exist_ok=True)
        json_out.write_text(result.to_json() + "\n")
    return result


def shell_command(argv: Sequence[str], netns: str) -> str:
    """How to run ``argv`` by hand inside ``netns`` (for ``crosspath lab up``)."""
    env = daemon_env({})
    return shlex.join(
        ["ip", "netns", "exec", netns, "env", f"PYTHONPATH={env['PYTHONPATH']}", *argv]
    )
