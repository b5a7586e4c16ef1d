"""Network namespaces for the multi-host lab: one per car, RSU and monitor.

Every actor gets its own network namespace ``cpl-<lab>-<node>`` with two
interfaces, ``air0`` on the *air* (V2X over UDP, the radio: the only place
faults are injected) and ``wire0`` on the *wire* (simulation plumbing, TCP,
the wired link to the simulator in the paper). Each interface is one end of a
veth pair whose other end is a port of a bridge; both bridges live in a
dedicated namespace ``cpl-<lab>-hub``, so the lab adds nothing at all to the
root namespace (no link, no address, no route, no nft table). The addresses
(air ``10.231.1.0/24``, wire ``10.231.2.0/24``) therefore exist only inside our
own namespaces, and two labs with different names can run side by side with
the same addresses without seeing each other.

Names are prefixed (``cpl-``, ``cpla<i>``, ``cplw<i>``, ``cplair``, ``cplwire``)
so that clean-up only ever removes what the lab made: :meth:`Lab.down` removes
the namespaces ``cpl-<lab>-*`` (which takes their links, addresses, routes, nft
tables and qdiscs with them) after killing every process inside them, found
with ``ip netns pids`` so that it also works after the controlling process
crashed. A state file ``/run/crosspath-lab/<lab>.json`` records the plan, so a
later process (``crosspath lab down``, ``lab run`` after ``lab up``) knows the
addresses and names.

Decisions where the issue was silent:

* IPv6 is disabled on ``air0``/``wire0`` (not on ``lo``) so that interface
  counters show only our IPv4 traffic (no router solicitations, no MLD).
* Both bridges have multicast snooping off: a multicast or broadcast frame on
  the air reaches every node, like a radio. Learning stays on, so a unicast
  frame is not counted on uninvolved nodes' interfaces.
* Each node has a route for ``224.0.0.0/4`` on the air interface (configurable
  with ``LabPlan.build(..., multicast=Net.WIRE)``), so multicast (e.g. Zenoh
  scouting) works without naming an interface.
* ``exec`` starts processes in a new session by default: a Ctrl-C on the
  terminal reaches only the controller, which then shuts the lab down in order.
"""

from __future__ import annotations

import contextlib
import ipaddress
import json
import logging
import os
import re
import shutil
import signal
import subprocess
import time
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass
from enum import StrEnum
from pathlib import Path
from types import TracebackType
from typing import IO, Any, Final

LOG = logging.getLogger("crosspath.lab")

PREFIX: Final = "cpl-"
"""Every namespace the lab makes starts with this; nothing else is ever removed."""
AIR_NET: Final = ipaddress.IPv4Network("10.231.1.0/24")
WIRE_NET: Final = ipaddress.IPv4Network("10.231.2.0/24")
AIR_IF: Final = "air0"
WIRE_IF: Final = "wire0"
AIR_BRIDGE: Final = "cplair"
WIRE_BRIDGE: Final = "cplwire"
HUB_NODE: Final = "hub"
MAX_NODES: Final = 250
DEFAULT_STATE_DIR: Final = Path("/run/crosspath-lab")
STATE_VERSION: Final = 1

_LAB_RE: Final = re.compile(r"[a-z0-9]{1,12}")
_NODE_RE: Final = re.compile(r"[A-Za-z0-9_][A-Za-z0-9_-]{0,31}")
_PREFIX_RE: Final = re.compile(r"cpl-[A-Za-z0-9_-]*")
_IFNAMSIZ: Final = 15  # Linux interface names: at most 15 bytes
_CMD_TIMEOUT_S: Final = 30.0

Redirect = int | IO[Any] | None
"""What ``subprocess`` accepts for stdin/stdout/stderr."""


class LabError(RuntimeError):
    """A lab operation failed; carries the command and its stderr when one ran."""

    def __init__(
        self,
        message: str,
        *,
        argv: Sequence[str] = (),
        returncode: int | None = None,
        stderr: str = "",
    ) -> None:
        detail = message
        if argv:
            detail += f"\n  command: {' '.join(argv)}"
        if returncode is not None:
            detail += f"\n  exit status: {returncode}"
        if stderr.strip():
            detail += f"\n  stderr: {stderr.strip()}"
        super().__init__(detail)
        self.argv: tuple[str, ...] = tuple(argv)
        self.returncode = returncode
        self.stderr = stderr


class Role(StrEnum):
    """What runs in a namespace; decides the order of addresses (cars, RSUs, monitor)."""

    CAR = "car"
    RSU = "rsu"
    MONITOR = "monitor"


class Net(StrEnum):
    """The two lab networks."""

    AIR = "air"
    WIRE = "wire"


# --------------------------------------------------------------------------- tools


_INSTALL_HINT: Final = {
    "ip": "iproute2",
    "tc": "iproute2",
    "nft": "nftables",
}


def tool(name: str) -> str:
    """Absolute path of ``ip``, ``tc`` or ``nft``; looks in sbin even when PATH lacks it."""
    found = shutil.which(name)
    if found is None:
        for directory in ("/usr/sbin", "/sbin", "/usr/bin", "/bin"):
            candidate = Path(directory) / name
            if candidate.is_file() and os.access(candidate, os.X_OK):
                found = str(candidate)
                break
    if found is None:
        package = _INSTALL_HINT.get(name, name)
        raise LabError(
            f"{name!r} not found: install {package} (deploy/lab/install-sysdeps.sh does it)"
        )
    return found


def prerequisites() -> list[str]:
    """What is missing to build a lab on this machine (empty list: all there)."""
    missing: list[str] = []
    if os.geteuid() != 0:
        missing.append("root (network namespaces need euid 0)")
    for name, package in _INSTALL_HINT.items():
        try:
            tool(name)
        except LabError:
            missing.append(f"{name} ({package})")
    return missing


def command(
    argv: Sequence[str],
    *,
    input: str | None = None,
    check: bool = True,
    timeout: float = _CMD_TIMEOUT_S,
) -> subprocess.CompletedProcess[str]:
    """Run one system command; on failure raise :class:`LabError` with command and stderr."""
    LOG.debug("lab: %s", " ".join(argv))
    try:
        done = subprocess.run(
            list(argv),
            input=input,
            capture_output=True,
            text=True,
            timeout=timeout,
            check=False,
        )
    except FileNotFoundError as exc:
        raise LabError(f"cannot run {argv[0]!r}: {exc}", argv=argv) from exc
    except subprocess.TimeoutExpired as exc:
        raise LabError(f"command timed out after {timeout:g} s", argv=argv) from exc
    if check and done.returncode != 0:
        raise LabError("command failed", argv=argv, returncode=done.returncode, stderr=done.stderr)
    return done


def _ip_batch(netns: str, lines: Iterable[str]) -> None:
    """Run many ``ip`` commands inside one namespace in a single process."""
    script = "".join(f"{line}\n" for line in lines)
    if script:
        command([tool("ip"), "-n", netns, "-batch", "-"], input=script)


# --------------------------------------------------------------------------- plan


@dataclass(frozen=True, slots=True)
class NodePlan:
    """One actor's namespace, interfaces and addresses."""

    name: str
    role: Role
    index: int
    netns: str
    air_if: str
    """Air interface inside the node's namespace."""
    wire_if: str
    hub_air_if: str
    """Peer of ``air_if`` in the hub namespace (a port of the air bridge)."""
    hub_wire_if: str
    air_addr: str
    """IPv4 address on the air, without prefix length."""
    wire_addr: str


@dataclass(frozen=True, slots=True)
class LabPlan:
    """Everything ``up`` will create, computed purely from node names (no I/O)."""

    lab: str
    nodes: tuple[NodePlan, ...]
    hub: str
    """Namespace holding the two bridges."""
    air_bridge: str
    wire_bridge: str
    air_net: str
    wire_net: str
    multicast: Net

    @classmethod
    def build(
        cls,
        lab: str,
        *,
        cars: Sequence[str] = (),
        rsus: Sequence[str] = (),
        monitor: str | None = "monitor",
        multicast: Net = Net.AIR,
    ) -> LabPlan:
        """Plan a lab: addresses in order cars, RSUs, monitor from ``.1`` upwards.

        Raises ``ValueError`` for a bad lab name, a bad or repeated node name, or
        more than :data:`MAX_NODES` nodes.
        """
        check_lab_name(lab)
        roles: list[tuple[str, Role]] = [(c, Role.CAR) for c in cars]
        roles += [(r, Role.RSU) for r in rsus]
        if monitor is not None:
            roles.append((monitor, Role.MONITOR))
        if not roles:
            raise ValueError("a lab needs at least one node")
        if len(roles) > MAX_NODES:
            raise ValueError(f"a lab holds at most {MAX_NODES} nodes, got {len(roles)}")
        seen: set[str] = set()
        nodes: list[NodePlan] = []
        for index, (name, role) in enumerate(roles):
            if not isinstance(name, str) or _NODE_RE.fullmatch(name) is None:
                raise ValueError(
                    f"bad node name {name!r}: use 1-32 of A-Z a-z 0-9 _ - (not starting with -)"
                )
            if name == HUB_NODE:
                raise ValueError(f"node name {HUB_NODE!r} is reserved for the bridges")
            if name in seen:
                raise ValueError(f"node name {name!r} appears twice")
            seen.add(name)
            hub_air, hub_wire = f"cpla{index}", f"cplw{index}"
            if max(len(hub_air), len(hub_wire), len(AIR_IF), len(WIRE_IF)) > _IFNAMSIZ:
                raise ValueError("interface name too long")  # cannot happen below MAX_NODES
            nodes.append(
                NodePlan(
                    name=name,
                    role=role,
                    index=index,
                    netns=f"{PREFIX}{lab}-{name}",
                    air_if=AIR_IF,
                    wire_if=WIRE_IF,
                    hub_air_if=hub_air,
                    hub_wire_if=hub_wire,
                    air_addr=str(AIR_NET[index + 1]),
                    wire_addr=str(WIRE_NET[index + 1]),
                )
            )
        return cls(
            lab=lab,
            nodes=tuple(nodes),
            hub=f"{PREFIX}{lab}-{HUB_NODE}",
            air_bridge=AIR_BRIDGE,
            wire_bridge=WIRE_BRIDGE,
            air_net=str(AIR_NET),
            wire_net=str(WIRE_NET),
            multicast=Net(multicast),
        )

    @property
    def names(self) -> tuple[str, ...]:
        """Node names in address order."""
        return tuple(n.name for n in self.nodes)

    @property
    def namespaces(self) -> tuple[str, ...]:
        """Every namespace of the lab, the hub first."""
        return (self.hub, *(n.netns for n in self.nodes))

    @property
    def ns_prefix(self) -> str:
        """Prefix shared by all this lab's namespaces and by no other lab's."""
        return lab_prefix(self.lab)

    @property
    def air_broadcast(self) -> str:
        """Directed broadcast address of the air (reaches every node's ``air0``)."""
        return str(AIR_NET.broadcast_address)

    def node(self, name: str) -> NodePlan:
        """The node called ``name``; ``KeyError`` names the known nodes."""
        for n in self.nodes:
            if n.name == name:
                return n
        raise KeyError(f"no node {name!r} in lab {self.lab!r} (nodes: {', '.join(self.names)})")

    def by_role(self, role: Role) -> tuple[NodePlan, ...]:
        return tuple(n for n in self.nodes if n.role is role)

    def to_json(self) -> dict[str, Any]:
        """Plain-JSON form for the state file (complete, for humans and for :meth:`from_json`)."""
        return {
            "version": STATE_VERSION,
            "lab": self.lab,
            "hub": self.hub,
            "air_bridge": self.air_bridge,
            "wire_bridge": self.wire_bridge,
            "air_net": self.air_net,
            "wire_net": self.wire_net,
            "multicast": str(self.multicast),
            "nodes": [
                {
                    "name": n.name,
                    "role": str(n.role),
                    "netns": n.netns,
                    "air_if": n.air_if,
                    "wire_if": n.wire_if,
                    "hub_air_if": n.hub_air_if,
                    "hub_wire_if": n.hub_wire_if,
                    "air_addr": n.air_addr,
                    "wire_addr": n.wire_addr,
                }
                for n in self.nodes
            ],
        }

    @classmethod
    def from_json(cls, data: Mapping[str, Any]) -> LabPlan:
        """Rebuild a plan from :meth:`to_json` output; ``ValueError`` if it does not fit."""
        try:
            if data["version"] != STATE_VERSION:
                raise ValueError(f"unknown lab state version {data['version']!r}")
            by_role: dict[Role, list[str]] = {r: [] for r in Role}
            for entry in data["nodes"]:
                by_role[Role(entry["role"])].append(str(entry["name"]))
            monitors = by_role[Role.MONITOR]
            if len(monitors) > 1:
                raise ValueError("more than one monitor")
            plan = cls.build(
                str(data["lab"]),
                cars=by_role[Role.CAR],
                rsus=by_role[Role.RSU],
                monitor=monitors[0] if monitors else None,
                multicast=Net(data.get("multicast", Net.AIR)),
            )
        except (KeyError, TypeError) as exc:
            raise ValueError(f"malformed lab state: {exc!r}") from exc
        if plan.to_json() != dict(data):
            raise ValueError("lab state does not match the plan rebuilt from its node names")
        return plan


def check_lab_name(lab: str) -> None:
    """Lab names are 1-12 of ``a-z0-9``: no ``-``, so ``cpl-<lab>-`` never prefixes another lab."""
    if not isinstance(lab, str) or _LAB_RE.fullmatch(lab) is None:
        raise ValueError(f"bad lab name {lab!r}: use 1-12 characters a-z 0-9")


def lab_prefix(lab: str) -> str:
    """Namespace prefix of lab ``lab``: ``cpl-<lab>-``."""
    check_lab_name(lab)
    return f"{PREFIX}{lab}-"


# --------------------------------------------------------------------------- system queries


def list_namespaces(prefix: str = PREFIX) -> list[str]:
    """Names of the existing network namespaces starting with ``prefix``."""
    out = command([tool("ip"), "netns", "list"]).stdout
    names = [line.split()[0] for line in out.splitlines() if line.strip()]
    return sorted(n for n in names if n.startswith(prefix))


def namespace_pids(netns: str) -> list[int]:
    """Processes whose network namespace is ``netns`` (never this process)."""
    done = command([tool("ip"), "netns", "pids", netns], check=False)
    if done.returncode != 0:
        return []  # namespace already gone
    me = os.getpid()
    return sorted({int(tok) for tok in done.stdout.split() if tok.isdigit()} - {me})


def _wait_entered(proc: subprocess.Popen[bytes], netns: str, timeout: float = 5.0) -> None:
    """Block until ``proc`` lives in ``netns`` (or has exited), at most ``timeout`` s.

    ``ip netns exec`` joins the namespace a moment after it starts; until it
    has, ``namespace_pids`` would not list it and a crash injected right away
    would miss it. Returning only once it has joined makes ``exec`` then
    ``crash`` deterministic.
    """
    try:
        target = os.stat(f"/run/netns/{netns}").st_ino
    except OSError:
        return  # namespace gone; the command fails on its own
    deadline = time.monotonic() + timeout
    while proc.poll() is None and time.monotonic() < deadline:
        try:
            if os.stat(f"/proc/{proc.pid}/ns/net").st_ino == target:
                return
        except OSError:
            return  # exited between poll and stat
        time.sleep(0.002)


def _signal_all(pids: Iterable[int], sig: signal.Signals) -> None:
    for pid in pids:
        with contextlib.suppress(ProcessLookupError, PermissionError):
            os.kill(pid, sig)


def _remove_namespaces(
    names: Sequence[str],
    *,
    grace: float,
    children: Sequence[subprocess.Popen[bytes]] = (),
) -> None:
    """Stop every process inside ``names`` (TERM, then KILL after ``grace`` s) and delete them."""
    for proc in children:
        if proc.poll() is None:
            with contextlib.suppress(ProcessLookupError):
                proc.send_signal(signal.SIGTERM)
    for ns in names:
        _signal_all(namespace_pids(ns), signal.SIGTERM)
    deadline = time.monotonic() + max(grace, 0.0)
    while True:
        alive = {ns: namespace_pids(ns) for ns in names}
        if not any(alive.values()) or time.monotonic() >= deadline:
            break
        time.sleep(0.05)
    for ns, pids in alive.items():
        if pids:
            LOG.warning("lab: killing %d process(es) left in %s", len(pids), ns)
            _signal_all(pids, signal.SIGKILL)
    for proc in children:
        if proc.poll() is None:
            with contextlib.suppress(ProcessLookupError):
                proc.kill()
        with contextlib.suppress(subprocess.TimeoutExpired):
            proc.wait(timeout=2.0)
    # Give SIGKILLed processes a moment to leave, so that the namespaces really go.
    deadline = time.monotonic() + 2.0
    while any(namespace_pids(ns) for ns in names) and time.monotonic() < deadline:
        time.sleep(0.02)
    errors: list[LabError] = []
    for ns in names:
        try:
            command([tool("ip"), "netns", "delete", ns])
        except LabError as exc:
            if ns in list_namespaces(PREFIX):
                errors.append(exc)
    if errors:
        raise LabError(f"could not delete {len(errors)} namespace(s): {errors[0]}")


def down_all(
    prefix: str = PREFIX,
    *,
    state_dir: Path | str = DEFAULT_STATE_DIR,
    grace: float = 2.0,
) -> list[str]:
    """Remove every lab leftover whose namespace starts with ``prefix`` (and nothing else).

    Kills the processes inside those namespaces, deletes the namespaces (their
    veths, addresses, nft tables and qdiscs go with them) and the matching state
    files. ``prefix`` must start with ``cpl-``. Returns the removed namespaces.
    """
    if _PREFIX_RE.fullmatch(prefix) is None:
        raise ValueError(f"prefix must start with {PREFIX!r} and hold only A-Z a-z 0-9 _ -")
    names = list_namespaces(prefix)
    _remove_namespaces(names, grace=grace)
    directory = Path(state_dir)
    if directory.is_dir():
        for path in directory.glob("*.json"):
            lab = path.stem
            if _LAB_RE.fullmatch(lab) and lab_prefix(lab).startswith(prefix):
                path.unlink(missing_ok=True)
    if names:
        LOG.info("lab: removed %s", ", ".join(names))
    return names


# --------------------------------------------------------------------------- the lab


class Lab:
    """Builds, runs commands in, and removes one named lab.

    ``Lab(name)`` is cheap and does no I/O; a fresh object finds the plan of a
    lab brought up by another process in the state file, so ``Lab(name).down()``
    always cleans up, also after a crash.
    """

    def __init__(self, name: str, *, state_dir: Path | str = DEFAULT_STATE_DIR) -> None:
        check_lab_name(name)
        self._name = name
        self._state_dir = Path(state_dir)
        self._plan: LabPlan | None = None
        self._children: list[subprocess.Popen[bytes]] = []

    # ---- identity and plan

    @property
    def name(self) -> str:
        return self._name

    @property
    def state_path(self) -> Path:
        """Where the plan is recorded while the lab is up."""
        return self._state_dir / f"{self._name}.json"

    @property
    def plan(self) -> LabPlan:
        """The plan of the running lab (from memory or the state file); ``LabError`` if down."""
        if self._plan is None:
            self._plan = self._load_state()
        return self._plan

    def is_up(self) -> bool:
        """True when the state file exists and all planned namespaces are present."""
        try:
            plan = self.plan
        except LabError:
            return False
        return set(plan.namespaces) <= set(list_namespaces(plan.ns_prefix))

    def _load_state(self) -> LabPlan:
        path = self.state_path
        try:
            data = json.loads(path.read_text(encoding="utf-8"))
        except FileNotFoundError:
            raise LabError(f"lab {self._name!r} is not up (no state file {path})") from None
        except (OSError, json.JSONDecodeError) as exc:
            raise LabError(f"cannot read lab state {path}: {exc}") from exc
        try:
            plan = LabPlan.from_json(data)
        except ValueError as exc:
            raise LabError(f"bad lab state {path}: {exc}") from exc
        if plan.lab != self._name:
            raise LabError(f"state file {path} belongs to lab {plan.lab!r}")
        return plan

    def _write_state(self, plan: LabPlan) -> None:
        self._state_dir.mkdir(mode=0o755, parents=True, exist_ok=True)
        tmp = self.state_path.with_suffix(".json.tmp")
        tmp.write_text(json.dumps(plan.to_json(), indent=2) + "\n", encoding="utf-8")
        os.replace(tmp, self.state_path)

    # ---- life cycle

    def up(self, plan: LabPlan) -> None:
        """Create the lab; first removes anything left by an earlier lab of the same name.

        The state file is written before anything is created, so an interrupted
        ``up`` is cleaned by ``down``. On any failure (also Ctrl-C) ``up`` removes
        what it made and re-raises.
        """
        if plan.lab != self._name:
            raise ValueError(f"plan is for lab {plan.lab!r}, this is lab {self._name!r}")
        missing = prerequisites()
        if missing:
            raise LabError("cannot build the lab, missing: " + ", ".join(missing))
        self.down()
        self._write_state(plan)
        self._plan = plan
        try:
            self._build(plan)
        except BaseException:
            with contextlib.suppress(LabError):
                self.down()
            raise
        LOG.info(
            "lab %s up: %d nodes, air %s, wire %s",
            plan.lab,
            len(plan.nodes),
            plan.air_net,
            plan.wire_net,
        )

    def _build(self, plan: LabPlan) -> None:
        ip = tool("ip")
        for ns in plan.namespaces:
            command([ip, "netns", "add", ns])
        sysctl = shutil.which("sysctl") or "/usr/sbin/sysctl"
        for node in plan.nodes:
            # New devices in this namespace start without IPv6 (lo keeps it).
            done = command(
                [
                    ip,
                    "netns",
                    "exec",
                    node.netns,
                    sysctl,
                    "-q",
                    "-w",
                    "net.ipv6.conf.default.disable_ipv6=1",
                ],
                check=False,
            )
            if done.returncode != 0:
                LOG.debug("lab: IPv6 left on in %s: %s", node.netns, done.stderr.strip())
        hub: list[str] = ["link set lo up"]
        for bridge in (plan.air_bridge, plan.wire_bridge):
            hub += [
                f"link add {bridge} type bridge stp_state 0 mcast_snooping 0",
                f"link set {bridge} up",
            ]
        for node in plan.nodes:
            for hub_if, node_if, bridge in (
                (node.hub_air_if, node.air_if, plan.air_bridge),
                (node.hub_wire_if, node.wire_if, plan.wire_bridge),
            ):
                hub += [
                    f"link add {hub_if} type veth peer name {node_if} netns {node.netns}",
                    f"link set {hub_if} master {bridge}",
                    f"link set {hub_if} up",
                ]
        _ip_batch(plan.hub, hub)
        air_len = ipaddress.IPv4Network(plan.air_net).prefixlen
        wire_len = ipaddress.IPv4Network(plan.wire_net).prefixlen
        for node in plan.nodes:
            mcast_if = node.air_if if plan.multicast is Net.AIR else node.wire_if
            _ip_batch(
                node.netns,
                [
                    "link set lo up",
                    f"addr add {node.air_addr}/{air_len} dev {node.air_if}",
                    f"addr add {node.wire_addr}/{wire_len} dev {node.wire_if}",
                    f"link set {node.air_if} up",
                    f"link set {node.wire_if} up",
                    f"route add 224.0.0.0/4 dev {mcast_if}",
                ],
            )

    def down(self, *, grace: float = 2.0) -> None:
        """Remove everything of this lab: processes (TERM, KILL after ``grace`` s), namespaces
        with their links, nft tables and qdiscs, and the state file. Safe to call repeatedly,
        from another process, and after a crash or a half-made ``up``."""
        # Every namespace of this lab, planned or left half-made, carries the prefix.
        names = list_namespaces(lab_prefix(self._name))
        _remove_namespaces(names, grace=grace, children=self._children)
        self._children = []
        self.state_path.unlink(missing_ok=True)
        self._plan = None
        if names:
            LOG.info("lab %s down: removed %d namespace(s)", self._name, len(names))

    def __enter__(self) -> Lab:
        return self

    def __exit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        self.down()

    # ---- nodes

    def node(self, node: str) -> NodePlan:
        """Plan entry of ``node``; ``LabError`` if the lab has no such node."""
        try:
            return self.plan.node(node)
        except KeyError as exc:
            raise LabError(str(exc.args[0])) from None

    def netns(self, node: str) -> str:
        return self.node(node).netns

    def air_addr(self, node: str) -> str:
        """IPv4 address of ``node`` on the air (V2X, UDP; faults apply here)."""
        return self.node(node).air_addr

    def wire_addr(self, node: str) -> str:
        """IPv4 address of ``node`` on the wire (simulation plumbing; never faulted)."""
        return self.node(node).wire_addr

    def pids(self, node: str) -> list[int]:
        """Every process currently inside ``node``'s namespace."""
        return namespace_pids(self.netns(node))

    def exec(
        self,
        node: str,
        argv: Sequence[str],
        *,
        env: Mapping[str, str] | None = None,
        stdin: Redirect = subprocess.DEVNULL,
        stdout: Redirect = None,
        stderr: Redirect = None,
        cwd: Path | str | None = None,
        new_session: bool = True,
    ) -> subprocess.Popen[bytes]:
        """Start ``argv`` inside ``node``'s namespace and return at once.

        ``env`` is *added to* this process's environment. ``ip netns exec``
        replaces itself with ``argv``, so the returned ``Popen``'s pid is the
        command's own: signal it directly. ``down`` stops it in any case.
        """
        ns = self.netns(node)
        if not argv:
            raise ValueError("empty argv")
        full_env = None if env is None else {**os.environ, **env}
        cmd = [tool("ip"), "netns", "exec", ns, *argv]
        LOG.debug("lab exec %s: %s", node, " ".join(argv))
        proc = subprocess.Popen(
            cmd,
            env=full_env,
            stdin=stdin,
            stdout=stdout,
            stderr=stderr,
            cwd=cwd,
            start_new_session=new_session,
        )
        self._children = [p for p in self._children if p.poll() is None]
        self._children.append(proc)
        _wait_entered(proc, ns)
        return proc

    def run(
        self,
        node: str,
        argv: Sequence[str],
        *,
        timeout: float,
        input: bytes | None = None,
        env: Mapping[str, str] | None = None,
        check: bool = True,
    ) -> subprocess.CompletedProcess[bytes]:
        """Run ``argv`` inside ``node``'s namespace to completion, output captured.

        ``LabError`` on timeout (the command is killed) and, with ``check``, on a
        non-zero exit status.
        """
        ns = self.netns(node)
        if not argv:
            raise ValueError("empty argv")
        full_env = None if env is None else {**os.environ, **env}
        cmd = [tool("ip"), "netns", "exec", ns, *argv]
        try:
            done = subprocess.run(
                cmd,
                input=input,
                capture_output=True,
                timeout=timeout,
                env=full_env,
                check=False,
            )
        except subprocess.TimeoutExpired as exc:
            raise LabError(f"timed out after {timeout:g} s in {node}", argv=cmd) from exc
        if check and done.returncode != 0:
            raise LabError(
                f"command failed in {node}",
                argv=cmd,
                returncode=done.returncode,
                stderr=done.stderr.decode(errors="replace"),
            )
        return done

    def nft(self, node: str, args: Sequence[str] = (), *, script: str | None = None) -> str:
        """Run ``nft args`` inside ``node``'s namespace; a ``script`` is fed to ``nft -f -``."""
        argv = [tool("ip"), "netns", "exec", self.netns(node), tool("nft"), *args]
        if script is not None:
            argv += ["-f", "-"]
        return command(argv, input=script).stdout

    def tc(self, node: str, args: Sequence[str], *, check: bool = True) -> str:
        """Run ``tc -n <netns> args`` for ``node``."""
        return command([tool("tc"), "-n", self.netns(node), *args], check=check).stdout

    def ip(self, node: str, args: Sequence[str]) -> str:
        """Run ``ip -n <netns> args`` for ``node``."""
        return command([tool("ip"), "-n", self.netns(node), *args]).stdout
