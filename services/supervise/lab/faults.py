"""Fault injection on the lab's air (V2X) only: packet loss, rate limit, crashes.

Loss is applied with nftables in the node's own namespace, in table
``netdev crosspath_lab`` whose chains are bound to the air interface (netdev
``ingress``/``egress`` hooks) and match only IPv4: the wire (simulation
plumbing) and ARP are never touched, and a dropped packet is invisible to the
sending application (no ``EPERM`` from ``sendto`` as an ``inet`` output-hook drop
would give). The ``egress`` hook needs Linux >= 5.16 and nftables >= 1.0.1
(Debian 12 has both); ingress loss works on any kernel with nftables.

What "loss R" means here (``R`` a fraction 0..1, as every probability in
crosspath; percent appears only in log lines). The default direction is
**ingress**: the rule sits on each *receiver's* air ingress, so a broadcast
future path reaches each receiver independently with probability ``1 - R``, as
on a radio channel where every receiver has its own reception.
``Direction.EGRESS`` puts the rule on the *sender's* air egress instead (before
its rate limit, so lost packets use no channel time): a lost broadcast is then
lost for every receiver at once (a transmitter fault, not a channel). Loss on a
node covers everything that node receives (ingress) or sends (egress) on the air.

Loss models (both per packet, draws from the kernel's ``numgen random``):

* independent (``burst=None``): each packet is dropped with probability R;
* bursty (``burst=b``): a two-state Gilbert model per *link*, the link being
  the peer address (sender for ingress, destination for egress). In the Bad
  state every packet is lost, in Good none. Per packet the state changes first
  and the packet's fate follows the new state: Good→Bad with probability
  ``p = R/(1-R) / b``, Bad→Good with ``r = 1/b``. The stationary loss
  is ``p/(p+r) = R`` and loss bursts are geometric with mean ``b`` packets.
  The Bad state is membership of the peer address in a dynamic nft set
  (``add @bad`` / ``delete @bad`` from the packet path). It needs ``b >=
  R/(1-R)`` (else ``p > 1``), e.g. ``b >= 1`` for R = 0.5.

Counters in the same table: ``air_seen`` (IPv4 packets that met the loss rule)
and ``air_dropped`` (those dropped). ``set_loss`` keeps them across calls;
``clear`` removes the table and with it the counters.

Rate limit: a ``tbf`` root qdisc on the node's air interface, i.e. on what the
node *transmits* (the DSRC channel of the paper is 6 Mbit/s). The default
bucket is 5 ms of the rate but at least two full frames (3028 B) and the queue
holds 50 ms; a sender faster than the rate is slowed by its socket buffer or
its datagrams are dropped in the qdisc (``rate_dropped`` in the counters).

Crash: SIGKILL of every process in a node's namespace (the launcher restarts
it with :meth:`Lab.exec` when it wants to).
"""

from __future__ import annotations

import contextlib
import json
import logging
import os
import signal
import subprocess
from collections.abc import Collection
from dataclasses import asdict, dataclass
from enum import StrEnum
from typing import Any, Final

from services.supervise.lab.netns import Lab, LabError, command, tool

LOG = logging.getLogger("crosspath.lab")

NFT_TABLE: Final = "crosspath_lab"
_SCALE: Final = 1_000_000
"""``numgen random mod _SCALE``: probabilities have a resolution of 1e-6."""
_FRAME_BYTES: Final = 1514
_MIN_BURST_BYTES: Final = 2 * _FRAME_BYTES
_BURST_SECONDS: Final = 0.005
_CHAINS: Final = frozenset({"ingress", "egress"})


class Direction(StrEnum):
    """Where a node's loss rule sits: what it receives, or what it sends."""

    INGRESS = "ingress"
    EGRESS = "egress"


@dataclass(frozen=True, slots=True)
class Loss:
    """A loss model for one node's air interface."""

    ratio: float
    """Long-run share of packets lost, a fraction 0..1."""
    burst: float | None = None
    """Mean loss-burst length in packets (Gilbert model); ``None``: independent losses."""
    direction: Direction = Direction.INGRESS

    def __post_init__(self) -> None:
        if not 0.0 <= self.ratio <= 1.0:
            raise ValueError(f"loss must be a fraction within 0..1, got {self.ratio}")
        if self.burst is not None:
            if not self.burst >= 1.0:
                raise ValueError(f"mean burst length must be >= 1 packet, got {self.burst}")
            if 0.0 < self.ratio < 1.0:
                least = self.ratio / (1.0 - self.ratio)
                if self.burst < least:
                    raise ValueError(
                        f"loss {self.ratio:g} needs a mean burst of at least {least:.3g} packets"
                    )
        Direction(self.direction)

    @property
    def p_enter(self) -> float:
        """Per-packet probability Good→Bad (bursty) or of a drop (independent)."""
        if self.burst is None or self.ratio in (0.0, 1.0):
            return self.ratio
        return self.ratio / (1.0 - self.ratio) / self.burst

    @property
    def p_leave(self) -> float:
        """Per-packet probability Bad→Good (bursty model only)."""
        return 0.0 if self.burst is None else 1.0 / self.burst


def _threshold(p: float) -> int:
    return round(p * _SCALE)


def loss_ruleset(air_if: str, loss: Loss, existing_chains: Collection[str] = ()) -> str:
    """The ``nft -f`` script that installs ``loss`` on ``air_if`` (pure).

    Keeps the counters; empties whichever of the ``ingress``/``egress`` chains
    already exist (``existing_chains``) and creates only the one it needs, so a
    kernel without the egress hook still takes ingress loss.
    """
    t = f"netdev {NFT_TABLE}"
    if loss.direction is Direction.INGRESS:
        chain, hook, peer = "ingress", "ingress", "ip saddr"
    else:
        chain, hook, peer = "egress", "egress", "ip daddr"
    lines = [
        f"add table {t}",
        f"add counter {t} air_seen",
        f"add counter {t} air_dropped",
        f"add set {t} bad {{ type ipv4_addr; flags dynamic; size 65536; }}",
        f'add chain {t} {chain} {{ type filter hook {hook} device "{air_if}" '
        "priority filter; policy accept; }",
    ]
    lines += [f"flush chain {t} {c}" for c in sorted({chain, *existing_chains} & _CHAINS)]
    lines.append(f"flush set {t} bad")
    rule = f"add rule {t} {chain} meta protocol ip"
    lines.append(f"{rule} counter name air_seen")
    drop = "counter name air_dropped drop"
    if loss.ratio >= 1.0:
        lines.append(f"{rule} {drop}")
    elif loss.ratio <= 0.0:
        pass
    elif loss.burst is None:
        lines.append(f"{rule} numgen random mod {_SCALE} < {_threshold(loss.p_enter)} {drop}")
    else:
        leave, enter = _threshold(loss.p_leave), _threshold(loss.p_enter)
        lines += [
            f"{rule} {peer} @bad numgen random mod {_SCALE} < {leave} "
            f"delete @bad {{ {peer} }} accept",
            f"{rule} {peer} @bad {drop}",
            f"{rule} numgen random mod {_SCALE} < {enter} add @bad {{ {peer} }} {drop}",
        ]
    return "\n".join(lines) + "\n"


def _nft_table(lab: Lab, node: str) -> list[dict[str, Any]] | None:
    """``nft -j list table`` of the loss table in ``node``; ``None`` when there is none."""
    argv = [
        tool("ip"),
        "netns",
        "exec",
        lab.netns(node),
        tool("nft"),
        "-j",
        "list",
        "table",
        "netdev",
        NFT_TABLE,
    ]
    done = command(argv, check=False)
    if done.returncode != 0:
        return None
    items = json.loads(done.stdout).get("nftables", [])
    return [dict(item) for item in items if isinstance(item, dict)]


def set_loss(
    lab: Lab,
    node: str,
    ratio: float,
    burst: float | None = None,
    *,
    direction: Direction = Direction.INGRESS,
) -> Loss:
    """Make ``node`` lose a share ``ratio`` (0..1) of its air packets (see the module doc).

    Replaces any earlier loss on the node atomically (one nft transaction).
    ``ValueError`` for an impossible model, ``LabError`` if nft fails.
    """
    loss = Loss(ratio, burst, Direction(direction))
    plan = lab.node(node)
    table = _nft_table(lab, node) or []
    chains = {str(item["chain"].get("name")) for item in table if "chain" in item}
    lab.nft(node, script=loss_ruleset(plan.air_if, loss, chains))
    LOG.info(
        "lab %s: %s loses %g %% on air (%s, burst %s)",
        lab.name,
        node,
        ratio * 100.0,
        loss.direction,
        burst,
    )
    return loss


def clear_loss(lab: Lab, node: str) -> None:
    """Remove the loss rules and counters of ``node`` (no-op when none)."""
    lab.nft(node, script=f"add table netdev {NFT_TABLE}\ndelete table netdev {NFT_TABLE}\n")


@dataclass(frozen=True, slots=True)
class Rate:
    """A token-bucket rate limit on what one node transmits on the air."""

    mbit: float
    """Rate in Mbit/s (10^6 bit/s)."""
    burst_bytes: int
    latency_ms: float

    @classmethod
    def of(cls, mbit: float, *, burst_bytes: int | None = None, latency_ms: float = 50.0) -> Rate:
        if not mbit > 0.0:
            raise ValueError(f"rate must be > 0 Mbit/s, got {mbit}")
        if not latency_ms > 0.0:
            raise ValueError(f"latency must be > 0 ms, got {latency_ms}")
        if burst_bytes is None:
            burst_bytes = max(_MIN_BURST_BYTES, round(mbit * 1e6 / 8 * _BURST_SECONDS))
        if burst_bytes < _FRAME_BYTES:
            raise ValueError(f"burst must hold one frame ({_FRAME_BYTES} B), got {burst_bytes}")
        return cls(mbit, burst_bytes, latency_ms)

    def tc_args(self, air_if: str) -> list[str]:
        kbit = max(1, round(self.mbit * 1000))
        return [
            "qdisc",
            "replace",
            "dev",
            air_if,
            "root",
            "tbf",
            "rate",
            f"{kbit}kbit",
            "burst",
            str(self.burst_bytes),
            "latency",
            f"{self.latency_ms:g}ms",
        ]


def set_rate(
    lab: Lab,
    node: str,
    mbit: float,
    *,
    burst_bytes: int | None = None,
    latency_ms: float = 50.0,
) -> Rate:
    """Limit what ``node`` transmits on the air to ``mbit`` Mbit/s (tbf, replaces earlier)."""
    rate = Rate.of(mbit, burst_bytes=burst_bytes, latency_ms=latency_ms)
    lab.tc(node, rate.tc_args(lab.node(node).air_if))
    LOG.info("lab %s: %s air rate %g Mbit/s", lab.name, node, mbit)
    return rate


def clear_rate(lab: Lab, node: str) -> None:
    """Remove the rate limit of ``node`` (no-op when none)."""
    plan = lab.node(node)
    if _tbf_stats(lab, node) is not None:
        lab.tc(node, ["qdisc", "del", "dev", plan.air_if, "root"])


def clear(lab: Lab, node: str) -> None:
    """Remove every fault on ``node``'s air: loss rules, their counters, rate limit."""
    clear_loss(lab, node)
    clear_rate(lab, node)


@dataclass(frozen=True, slots=True)
class AirFaults:
    """Faults for one node, as a launcher reads them from a scenario or the command line."""

    loss: Loss | None = None
    rate_mbit: float | None = None


def apply(lab: Lab, node: str, faults: AirFaults) -> None:
    """Set ``node``'s air faults to exactly ``faults`` (clearing what is not given)."""
    if faults.loss is None:
        clear_loss(lab, node)
    else:
        set_loss(lab, node, faults.loss.ratio, faults.loss.burst, direction=faults.loss.direction)
    if faults.rate_mbit is None:
        clear_rate(lab, node)
    else:
        set_rate(lab, node, faults.rate_mbit)


# --------------------------------------------------------------------------- measurement


@dataclass(frozen=True, slots=True)
class AirCounters:
    """One node's air interface counters since ``up`` (bytes include Ethernet headers).

    ``rx_*`` count everything that reached the interface, also what the loss
    rule then dropped; ``loss_dropped`` is that share. ``tx_*`` is what the node
    put on the air after its rate limit.
    """

    tx_bytes: int
    tx_packets: int
    rx_bytes: int
    rx_packets: int
    tx_dropped: int
    rx_dropped: int
    loss_seen: int
    """IPv4 packets that met the loss rule (in its direction)."""
    loss_dropped: int
    """Packets dropped by the loss rule."""
    rate_dropped: int
    """Packets dropped by the tbf queue (rate limit)."""

    def as_dict(self) -> dict[str, int]:
        return asdict(self)


def _tbf_stats(lab: Lab, node: str) -> dict[str, Any] | None:
    air_if = lab.node(node).air_if
    out = lab.tc(node, ["-s", "-j", "qdisc", "show", "dev", air_if])
    for qdisc in json.loads(out or "[]"):
        if qdisc.get("kind") == "tbf" and qdisc.get("root"):
            return dict(qdisc)
    return None


def _nft_counters(lab: Lab, node: str) -> dict[str, int]:
    packets: dict[str, int] = {}
    for item in _nft_table(lab, node) or []:
        counter = item.get("counter")
        if isinstance(counter, dict):
            packets[str(counter.get("name"))] = int(counter.get("packets", 0))
    return packets


def air_counters(lab: Lab, node: str) -> AirCounters:
    """Read ``node``'s air interface, nft and tbf counters (``LabError`` if the lab is down)."""
    air_if = lab.node(node).air_if
    links = json.loads(lab.ip(node, ["-s", "-j", "link", "show", "dev", air_if]))
    try:
        stats = links[0]["stats64"]
        rx, tx = stats["rx"], stats["tx"]
    except (IndexError, KeyError, TypeError) as exc:
        raise LabError(f"no statistics for {air_if} in {node}") from exc
    nft = _nft_counters(lab, node)
    tbf = _tbf_stats(lab, node)
    return AirCounters(
        tx_bytes=int(tx["bytes"]),
        tx_packets=int(tx["packets"]),
        rx_bytes=int(rx["bytes"]),
        rx_packets=int(rx["packets"]),
        tx_dropped=int(tx.get("dropped", 0)),
        rx_dropped=int(rx.get("dropped", 0)),
        loss_seen=nft.get("air_seen", 0),
        loss_dropped=nft.get("air_dropped", 0),
        rate_dropped=int(tbf.get("drops", 0)) if tbf is not None else 0,
    )


# --------------------------------------------------------------------------- crashes


def crash(lab: Lab, node: str, sig: signal.Signals = signal.SIGKILL) -> list[int]:
    """Send ``sig`` (default SIGKILL) to every process in ``node``'s namespace; their pids."""
    pids = lab.pids(node)
    for pid in pids:
        with contextlib.suppress(ProcessLookupError):
            os.kill(pid, sig)
    LOG.info("lab %s: crashed %s (%s to %s)", lab.name, node, sig.name, pids)
    return pids


def kill(proc: subprocess.Popen[bytes], sig: signal.Signals = signal.SIGKILL) -> None:
    """Send ``sig`` to one process started with :meth:`Lab.exec`, if it still runs."""
    if proc.poll() is None:
        with contextlib.suppress(ProcessLookupError):
            proc.send_signal(sig)
