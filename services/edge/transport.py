"""The daemons' pub/sub edge: Zenoh for real runs, an in-memory bus for tests.

This is the only module of crosspath that imports zenoh. Daemon shells talk to
a :class:`Transport`: ``publish(key, payload, qos)``, ``subscribe(keyexpr,
handler)``, liveliness tokens and watches. Handlers always run on the asyncio
event loop thread, never on a Zenoh thread: the Zenoh callback only copies the
key and the payload bytes and hands them over with ``loop.call_soon_threadsafe``
(it never blocks and never raises; if the loop is closed the datagram is
dropped and counted in ``dropped``).

The receive path must not share fate with the control loop (issue 13: a flood of
5000 future paths per second stalled the RSU's ticks for seconds and grew the cars
without bound). A subscription made with a :class:`ReceivePolicy` goes through an
:class:`Inbox`: an admission check of the key on the network thread (the shell
refuses senders that are not actors of the current run before the payload is even
copied), a per-lane token bucket, one bounded queue per lane (a lane is one key and
message kind, i.e. one sender: for V2X the latest message wins), bounds on lanes,
bytes and rate states (least recently used evicted), and a loop side that takes
the lanes round robin a few at a time (``batch``, ``budget_s``) and then yields, so
a timer due meanwhile (the next tick) runs within about one budget; a daemon's inboxes
also hold their datagrams back while its control tick is due and has not run
(``tick_due``, at most :data:`TICK_YIELD_S`), since the cars plan at the run times the
RSU ticks at and their paths arrive as its tick falls due. One wake-up of
the loop per batch instead of one per datagram. Without a policy every datagram is
handed to the loop as it comes (tests, tools).

QoS (DESIGN.md, key expressions): ``protocol.keys.QOS`` says per stream how it
is published; :func:`qos_for` (stream) and :func:`qos_for_key` (key) look it up.
V2X streams are best effort and dropped under congestion (future paths also
express: never batched), at priority DATA_HIGH; plumbing and statistics are
reliable, block under congestion, at priority DATA.

UDP for V2X, TCP for plumbing: Zenoh picks the *link* per message, not per
publisher. Verified against zenoh 1.10 (``io/zenoh-transport/src/unicast/
universal/tx.rs``, ``TransportUnicastUniversal::select``): among the links of
the transport to a remote node, a message goes on a link whose reliability
matches the message's (a UDP link is best effort, a TCP link reliable), else on
any link. So when two nodes hold both a UDP and a TCP link, best-effort V2X
datagrams travel over UDP and reliable plumbing over TCP. Two nodes hold more
than one link only when ``transport/unicast/max_links`` > 1 (Zenoh's default is
1: a single link, often TCP, carries everything) - hence
``ZenohSettings.max_links`` defaults to 2. We checked it on loopback by counting
the kernel's UDP datagrams and TCP segments (``/proc/net/snmp``) while two peers
exchanged 500 messages of each kind: best effort went as 501 UDP datagrams and
2 TCP segments, reliable as 0 UDP datagrams and 1000 TCP segments; with
``max_links`` 1 both went over TCP. Recommended setup (``deploy/zenoh/``): each
daemon is a peer listening on one ``udp/`` and one ``tcp/`` endpoint and
connecting to both endpoints of a rendezvous node (another peer or a router);
gossip scouting then opens direct UDP and TCP links between the peers. A
*client* holds a single link to its router (it connects to the first endpoint
that answers), so in client mode everything shares that link.
"""

from __future__ import annotations

import asyncio
import contextlib
import itertools
import json
import logging
import math
import re
import threading
import time
from collections import OrderedDict, deque
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import Any, Final, Protocol

import zenoh

from protocol.auth import DIGEST_TRAILER_LEN, SCHEME_ED25519, Form
from protocol.keys import DEFAULT_PREFIX, QOS, Qos, Stream, parse
from protocol.messages import Flags
from services.edge.settings import ZenohSettings, background_endpoint
from services.edge.stats import LatencyHistogram

__all__ = [
    "AWAITED_PROTOCOLS",
    "RELIABLE_QOS",
    "V2X_QOS",
    "EndpointError",
    "Handler",
    "Inbox",
    "LivelinessHandler",
    "MemoryBus",
    "MemoryTransport",
    "Qos",
    "ReceivePolicy",
    "ReceiveStats",
    "Subscription",
    "Transport",
    "TransportConfigError",
    "TransportError",
    "ZenohTransport",
    "connect_in_turn",
    "diagnose_open_error",
    "init_zenoh_logging",
    "keyexpr_matches",
    "qos_for",
    "qos_for_key",
    "validate_key",
    "zenoh_config",
    "zenoh_reason",
]

logger = logging.getLogger("crosspath.transport")

Handler = Callable[[str, bytes], None]
"""Receives (key, payload) on the event loop thread."""

LivelinessHandler = Callable[[str, bool], None]
"""Receives (token key, alive) on the event loop thread."""


class TransportError(RuntimeError):
    """The transport cannot do what was asked (not open, closed, Zenoh refused)."""


class TransportConfigError(TransportError):
    """The settings cannot work as given: an invalid Zenoh option or endpoint, an address
    in use or not on this host. Trying again with the same settings does not help."""


class EndpointError(TransportConfigError):
    """One endpoint cannot be opened: ``role`` (``listen`` or ``connect``), ``endpoint``
    (as configured) and Zenoh's ``reason``, without its source locations."""

    def __init__(self, role: str, endpoint: str, reason: str) -> None:
        verb = "listen on" if role == "listen" else "connect to"
        super().__init__(f"cannot {verb} {endpoint}: {reason}")
        self.role = role
        self.endpoint = endpoint
        self.reason = reason


V2X_QOS: Final = Qos(reliable=False, express=True, drop=True)
"""Best effort, express, dropped under congestion: the radio (future paths)."""

RELIABLE_QOS: Final = Qos(reliable=True, express=False, drop=False)
"""Reliable, batched, blocking under congestion: simulation plumbing and stats."""


def qos_for(stream: Stream | str) -> Qos:
    """The publication QoS of a protocol stream (``protocol.keys.QOS``); ValueError if unknown."""
    try:
        return QOS[Stream(stream)]
    except ValueError:
        raise ValueError(f"unknown stream {stream!r}") from None


def qos_for_key(key: str, prefix: str = DEFAULT_PREFIX) -> Qos:
    """The QoS of a concrete crosspath key; ``protocol.keys.BadKey`` if it is not one."""
    return QOS[parse(key, prefix=prefix).stream]


# --------------------------------------------------------------------------- key expressions

_FORBIDDEN = frozenset("#?$")


def validate_key(key: str, *, wildcards: bool) -> str:
    """Check a key (``wildcards=False``) or key expression (chunks ``*`` and ``**`` allowed).

    crosspath uses a canonical subset of Zenoh key expressions: non-empty
    ``/``-separated chunks, no ``#``, ``?`` or ``$``, wildcards only as whole chunks.
    Raises ValueError.
    """
    if not key:
        raise ValueError("empty key expression")
    chunks = key.split("/")
    for chunk in chunks:
        if not chunk:
            raise ValueError(f"key expression {key!r} has an empty chunk")
        if chunk in ("*", "**"):
            if not wildcards:
                raise ValueError(f"key {key!r} must not contain wildcards")
            continue
        if "*" in chunk or _FORBIDDEN.intersection(chunk):
            raise ValueError(f"key expression {key!r}: invalid chunk {chunk!r}")
    for a, b in itertools.pairwise(chunks):
        if a == "**" and b in ("*", "**"):
            raise ValueError(f"key expression {key!r} is not canonical ({a}/{b})")
    return key


def keyexpr_matches(pattern: str, key: str) -> bool:
    """Whether the concrete ``key`` is in the set ``pattern`` names.

    ``*`` matches exactly one chunk, ``**`` zero or more chunks.
    """
    pat = pattern.split("/")
    chunks = key.split("/")
    # reachable[j]: pattern prefix consumed so far can match chunks[:j]
    reachable = [False] * (len(chunks) + 1)
    reachable[0] = True
    for part in pat:
        nxt = [False] * (len(chunks) + 1)
        if part == "**":
            seen = False
            for j in range(len(chunks) + 1):
                seen = seen or reachable[j]
                nxt[j] = seen
        else:
            for j in range(len(chunks)):
                if reachable[j] and (part == "*" or part == chunks[j]):
                    nxt[j + 1] = True
        reachable = nxt
    return reachable[len(chunks)]


# --------------------------------------------------------------------------- receive path


_COUNTERS: Final = (
    "offered",
    "refused",
    "duplicate",
    "rate_limited",
    "coalesced",
    "overflow",
    "delivered",
)


class ReceiveStats:
    """What the inboxes of one subscription did (thread-safe): datagrams ``offered`` by the
    network, ``refused`` by the admission check, ``duplicate`` (an exact copy of a recent
    datagram of its lane: a replay), ``rate_limited``, ``coalesced`` (replaced
    by a newer one of the same lane before the loop took it), ``overflow`` (no room) and
    ``delivered``; the wall-second latency from arrival to the end of the handler; the most
    lanes (senders) and bytes ever queued at once. Its snapshot has a fixed size."""

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self.counts: dict[str, int] = dict.fromkeys(_COUNTERS, 0)
        self.latency = LatencyHistogram()
        self.max_lanes = 0
        self.max_bytes = 0

    def count(self, name: str, n: int = 1) -> None:
        with self._lock:
            self.counts[name] += n

    def _queued(self, lanes: int, nbytes: int) -> None:
        with self._lock:
            self.counts["offered"] += 1
            self.max_lanes = max(self.max_lanes, lanes)
            self.max_bytes = max(self.max_bytes, nbytes)

    def _delivered(self, latency_s: float) -> None:
        with self._lock:
            self.counts["delivered"] += 1
            self.latency.add(max(0.0, latency_s))

    def reset(self) -> None:
        """Start counting afresh (a new run)."""
        with self._lock:
            self.counts = dict.fromkeys(_COUNTERS, 0)
            self.latency = LatencyHistogram()
            self.max_lanes = 0
            self.max_bytes = 0

    def snapshot(self) -> dict[str, Any]:
        """Counters, ``latency_ms_p50`` / ``_p99`` / ``_max`` (None before any delivery),
        ``max_lanes`` and ``max_bytes``: a few dozen bytes whatever the traffic."""
        with self._lock:
            hist = self.latency
            out: dict[str, Any] = dict(self.counts)
            p50, p99 = hist.percentile(0.5), hist.percentile(0.99)
            out["latency_ms_p50"] = None if p50 is None else round(p50 * 1e3, 3)
            out["latency_ms_p99"] = None if p99 is None else round(p99 * 1e3, 3)
            out["latency_ms_max"] = round(hist.max_s * 1e3, 3) if hist.count else None
            out["max_lanes"] = self.max_lanes
            out["max_bytes"] = self.max_bytes
            return out


def _digest_signed(payload: bytes) -> bool:
    """Whether a signed datagram names its signer by key id (the trailer is the last
    ``DIGEST_TRAILER_LEN`` bytes: scheme 1, length, form 0), not by its certificate."""
    n = len(payload)
    return (
        n >= DIGEST_TRAILER_LEN
        and payload[n - DIGEST_TRAILER_LEN] == SCHEME_ED25519
        and payload[n - DIGEST_TRAILER_LEN + 1] == DIGEST_TRAILER_LEN - 2
        and payload[n - DIGEST_TRAILER_LEN + 2] == Form.DIGEST
    )


def _carries_certificate(payload: bytes) -> bool:
    """Whether a datagram is signed with its signer's certificate attached (scheme 1,
    not the digest form): the only kind a receiver can learn a key from."""
    return len(payload) > 3 and bool(payload[3] & Flags.AUTH) and not _digest_signed(payload)


Admit = Callable[[str], bool]
"""Cheap check of a key on the network thread: False refuses the datagram (counted)."""


@dataclass(slots=True)
class ReceivePolicy:
    """How a subscription's datagrams wait between the network thread and the event loop.

    A *lane* is the key (plus, with ``by_kind``, the V2X message kind, byte 2 of the
    payload: a mode command never replaces a coordinated path; and whether a signed
    datagram carries its signer's certificate, which a signer attaches about once a
    second and the receiver needs before it can verify the digest-signed ones), i.e.
    one sender and one kind of message. Each lane keeps at most ``depth`` datagrams
    (1: the latest wins)
    and is fed by a token bucket of ``rate_hz`` [datagrams per wall s] and ``burst``
    (``rate_hz`` 0: unlimited); at most ``max_lanes`` lanes and ``max_bytes`` queued
    bytes, else the datagram is dropped (``overflow``); at most ``max_buckets`` rate
    states, the least recently used evicted. With ``dedupe`` > 0, a lane remembers its last
    ``dedupe`` datagrams and drops an exact copy of one before it costs a token
    (``duplicate``): a replayer that repeats a sender's genuine (validly signed) datagrams
    cannot spend that sender's rate and starve it. With ``certificates_only`` only signed
    datagrams that carry their signer's certificate are queued, the rest ``refused``
    (between runs a verifying daemon uses nothing else: it learns keys). The loop takes
    the lanes round robin, at most ``batch`` datagrams or ``budget_s`` wall seconds per
    turn, then yields so that timers (the control loop's ticks) run on time. With
    ``tick_due`` (the daemon's control tick that is due and has not run yet, or None),
    the loop yields before a datagram while a tick is due, for at most
    :data:`TICK_YIELD_S` per tick: a tick that falls due as datagrams arrive runs before
    them instead of after a slice of them. Fields may be changed while subscribed (the
    shell scales the rates with the run's speed).
    """

    depth: int = 1
    by_kind: bool = True
    rate_hz: float = 0.0
    burst: float = 25.0
    max_lanes: int = 1024
    max_bytes: int = 4 * 1024 * 1024
    max_buckets: int = 4096
    dedupe: int = 0
    certificates_only: bool = False
    batch: int = 64
    budget_s: float = 0.002
    admit: Admit | None = None
    tick_due: Callable[[], float | None] | None = None
    stats: ReceiveStats = field(default_factory=ReceiveStats)

    def __post_init__(self) -> None:
        for name in ("depth", "max_lanes", "max_bytes", "max_buckets", "batch", "dedupe"):
            value = getattr(self, name)
            low = 0 if name == "dedupe" else 1
            if isinstance(value, bool) or not isinstance(value, int) or value < low:
                raise ValueError(f"{name} must be an int >= {low}, got {value!r}")
        for name in ("rate_hz", "burst", "budget_s"):
            value = getattr(self, name)
            if not (isinstance(value, int | float) and math.isfinite(value) and value >= 0):
                raise ValueError(f"{name} must be a finite number >= 0, got {value!r}")


TICK_YIELD_S: Final = 0.002
"""Longest an inbox holds its datagrams back for one due tick [wall s]: the tick's timer
may fire up to a millisecond after its time; a tick that still has not run by then (its
task waits for something else) must not stall the datagrams."""


class _Recent:
    """The hashes of a lane's last datagrams, oldest first (a dict keeps insertion order:
    a set and an order in one)."""

    __slots__ = ("digests",)

    def __init__(self) -> None:
        self.digests: dict[int, None] = {}

    def seen(self, digest: int, depth: int) -> bool:
        """True for a digest remembered; else remember it (forgetting beyond ``depth``)."""
        digests = self.digests
        if digest in digests:
            return True
        digests[digest] = None
        while len(digests) > depth:
            del digests[next(iter(digests))]
        return False


class Inbox:
    """The bounded queue of one subscription (see :class:`ReceivePolicy`).

    :meth:`admits` and :meth:`put` run on any thread and never block for long nor
    raise; the handler runs on ``loop``, a few datagrams per loop turn. Memory is
    bounded by the policy whatever arrives: this is what keeps a flood from stalling
    the control loop or growing the daemon.
    """

    def __init__(
        self,
        loop: asyncio.AbstractEventLoop,
        deliver: Handler,
        policy: ReceivePolicy,
        time_fn: Callable[[], float] = time.monotonic,
    ) -> None:
        self.loop = loop
        self.policy = policy
        self.active = True
        self._deliver = deliver
        self._time = time_fn
        self._lock = threading.Lock()
        self._lanes: OrderedDict[str, deque[tuple[str, bytes, float]]] = OrderedDict()
        self._buckets: OrderedDict[str, list[float]] = OrderedDict()
        self._recent: OrderedDict[str, _Recent] = OrderedDict()
        self._bytes = 0
        self._scheduled = False
        self._held_for: float | None = None
        """The due tick this inbox last held its datagrams back for, and since when."""
        self._held_since = 0.0

    @property
    def lanes(self) -> int:
        """Lanes (senders and kinds) with something queued now."""
        return len(self._lanes)

    @property
    def buckets(self) -> int:
        """Rate-limit states kept now."""
        return len(self._buckets)

    @property
    def remembered(self) -> int:
        """Lanes whose recent datagrams are remembered now (``dedupe``)."""
        return len(self._recent)

    @property
    def queued_bytes(self) -> int:
        return self._bytes

    def admits(self, key: str) -> bool:
        """The policy's admission check (counted when refused); True without one."""
        admit = self.policy.admit
        if admit is None:
            return True
        try:
            ok = admit(key)
        except Exception:
            logger.exception("admission check failed on %s", key)
            ok = False
        if not ok:
            self.policy.stats.count("refused")
        return ok

    def _token(self, lane: str, now: float) -> bool:
        policy = self.policy
        if policy.rate_hz <= 0:
            return True
        bucket = self._buckets.get(lane)
        if bucket is None:
            bucket = self._buckets[lane] = [policy.burst, now]
            if len(self._buckets) > policy.max_buckets:
                self._buckets.popitem(last=False)
        else:
            self._buckets.move_to_end(lane)
            bucket[0] = min(policy.burst, bucket[0] + (now - bucket[1]) * policy.rate_hz)
            bucket[1] = now
        if bucket[0] < 1.0:
            return False
        bucket[0] -= 1.0
        return True

    def _duplicate(self, lane: str, payload: bytes) -> bool:
        """Whether ``payload`` is an exact copy of one of the lane's last ``dedupe``
        datagrams (remembered by a keyed hash; at most ``max_buckets`` lanes, LRU)."""
        depth = self.policy.dedupe
        if depth <= 0:
            return False
        recent = self._recent.get(lane)
        if recent is None:
            recent = self._recent[lane] = _Recent()
            if len(self._recent) > self.policy.max_buckets:
                self._recent.popitem(last=False)
        else:
            self._recent.move_to_end(lane)
        return recent.seen(hash(payload), depth)

    def put(self, key: str, payload: bytes) -> None:
        """Queue one datagram (already admitted) and make sure the loop will take it."""
        policy = self.policy
        stats = policy.stats
        lane = key
        certified = _carries_certificate(payload)
        if policy.certificates_only and not certified:
            stats.count("refused")
            return
        if policy.by_kind and len(payload) > 3:
            lane = f"{key}#{payload[2]}"
            if certified:
                lane += "c"  # it carries its signer's certificate: never replaced by a digest
        now = self._time()
        with self._lock:
            if not self.active:
                return
            if self._duplicate(lane, payload):
                stats.count("duplicate")
                return
            if not self._token(lane, now):
                stats.count("rate_limited")
                return
            queue = self._lanes.get(lane)
            if queue is None:
                if len(self._lanes) >= policy.max_lanes:
                    stats.count("overflow")
                    return
                queue = self._lanes[lane] = deque()
            while len(queue) >= policy.depth:
                self._bytes -= len(queue.popleft()[1])
                stats.count("coalesced")
            if self._bytes + len(payload) > policy.max_bytes:
                if not queue:
                    del self._lanes[lane]
                stats.count("overflow")
                return
            queue.append((key, payload, now))
            self._bytes += len(payload)
            stats._queued(len(self._lanes), self._bytes)
            if self._scheduled:
                return
            self._scheduled = True
        self._wake()

    def _wake(self) -> None:
        try:
            try:
                running = asyncio.get_running_loop()
            except RuntimeError:
                running = None
            if running is self.loop:
                self.loop.call_soon(self._drain)
            else:
                self.loop.call_soon_threadsafe(self._drain)
        except RuntimeError:  # the loop is closed: nothing will take it
            with self._lock:
                self._scheduled = False
                self._lanes.clear()
                self._bytes = 0
            self.policy.stats.count("overflow")

    def close(self) -> None:
        """Drop what is queued; later datagrams are ignored."""
        with self._lock:
            self.active = False
            self._lanes.clear()
            self._buckets.clear()
            self._recent.clear()
            self._bytes = 0

    def _hold_for_tick(self, tick_due: Callable[[], float | None], now: float) -> bool:
        """Whether to let a due tick run before the next datagram (``tick_due``)."""
        try:
            due = tick_due()
        except Exception:
            logger.exception("tick_due failed")
            due = None
        if due is None:
            return False
        if due != self._held_for:
            self._held_for, self._held_since = due, now
        return now - self._held_since < TICK_YIELD_S

    def _drain(self) -> None:
        """One loop turn: deliver round robin until the batch or the budget is used up."""
        policy = self.policy
        start = self._time()
        done = 0
        while True:
            tick_due = policy.tick_due
            if tick_due is not None and self._hold_for_tick(tick_due, self._time()):
                self.loop.call_soon(self._drain)  # behind the tick's wake-up
                return
            with self._lock:
                if not self._lanes or not self.active:
                    self._scheduled = False
                    return
                lane, queue = next(iter(self._lanes.items()))
                key, payload, arrived = queue.popleft()
                self._bytes -= len(payload)
                if queue:
                    self._lanes.move_to_end(lane)
                else:
                    del self._lanes[lane]
            try:
                self._deliver(key, payload)
            except Exception:
                logger.exception("handler failed on a datagram from %s", key)
            end = self._time()
            policy.stats._delivered(end - arrived)
            done += 1
            if done >= policy.batch or end - start >= policy.budget_s:
                break
        with self._lock:
            if not self._lanes or not self.active:
                self._scheduled = False
                return
        self.loop.call_soon(self._drain)


# --------------------------------------------------------------------------- interface


class Subscription(Protocol):
    """A declared subscription, liveliness token or liveliness watch."""

    @property
    def key(self) -> str:
        """The key expression it was declared on."""

    def close(self) -> None:
        """Undeclare it; idempotent, a no-op once the transport is closed."""


class Transport(Protocol):
    """What a daemon shell needs from the network."""

    def open(self) -> None:
        """Connect; bind to the running event loop unless one was given."""

    def close(self) -> None:
        """Undeclare everything, then disconnect; idempotent."""

    def publish(self, key: str, payload: bytes, qos: Qos) -> None:
        """Send one datagram on ``key`` (never blocks for V2X QoS)."""

    def subscribe(
        self, keyexpr: str, handler: Handler, policy: ReceivePolicy | None = None
    ) -> Subscription:
        """Call ``handler(key, payload)`` on the loop for every datagram matching ``keyexpr``
        (through a bounded :class:`Inbox` when a ``policy`` is given)."""

    def declare_liveliness(self, key: str) -> Subscription:
        """Announce this node alive on ``key`` until closed (or the process dies); over
        Zenoh as generations ``key/<n>`` (``TOKEN_REFRESH_S``)."""

    def watch_liveliness(self, keyexpr: str, on_change: LivelinessHandler) -> Subscription:
        """Call ``on_change(key, alive)`` for tokens matching ``keyexpr``, present ones first
        (a key with several token generations counts once, ``TokenGenerations``)."""


def _bind_loop(loop: asyncio.AbstractEventLoop | None) -> asyncio.AbstractEventLoop:
    if loop is not None:
        return loop
    try:
        return asyncio.get_running_loop()
    except RuntimeError:
        raise TransportError(
            "open() needs a running event loop, or pass loop= to the constructor"
        ) from None


# --------------------------------------------------------------------------- Zenoh


def zenoh_config(settings: ZenohSettings) -> zenoh.Config:
    """Build a ``zenoh.Config``: the JSON5 file first, then the explicit settings.

    Without ``config_file`` every field of ``settings`` applies (defaults too);
    with one, only the fields set explicitly. ``options`` are applied last.
    Raises TransportError when Zenoh rejects the file or a value.
    """
    explicit = settings.model_fields_set
    try:
        if settings.config_file is not None:
            config = zenoh.Config.from_file(settings.config_file)
        else:
            config = zenoh.Config()

        def wanted(name: str) -> bool:
            return settings.config_file is None or name in explicit

        if wanted("mode"):
            config.insert_json5("mode", json.dumps(settings.mode))
        if wanted("listen"):
            config.insert_json5("listen/endpoints", json.dumps(settings.listen))
        if wanted("connect"):
            config.insert_json5("connect/endpoints", json.dumps(settings.connect))
        if wanted("multicast_scouting"):
            config.insert_json5(
                "scouting/multicast/enabled", json.dumps(settings.multicast_scouting)
            )
        if wanted("max_links"):
            config.insert_json5("transport/unicast/max_links", json.dumps(settings.max_links))
        if settings.connect_in_turn:
            endpoints = _configured_endpoints(config, "connect")
            if endpoints:  # a file's per-mode table of endpoints is left as it is
                config.insert_json5("connect/endpoints", json.dumps(connect_in_turn(endpoints)))
            config.insert_json5("connect/exit_on_failure", "true")
            timeout_ms = round(settings.connect_timeout_s * 1000)
            config.insert_json5("connect/timeout_ms", json.dumps(timeout_ms))
        for path, value in settings.options.items():
            config.insert_json5(path, json.dumps(value))
    except zenoh.ZError as exc:
        raise TransportConfigError(f"invalid Zenoh configuration: {zenoh_reason(exc)}") from None
    return config


AWAITED_PROTOCOLS: Final = frozenset({"tcp", "tls"})
"""Endpoint protocols that ``connect_in_turn`` waits for at open (the reliable plumbing
links); the others (``udp``, ``quic``: V2X) connect in the background."""


def connect_in_turn(endpoints: Sequence[str]) -> list[str]:
    """``endpoints`` as ``ZenohSettings.connect_in_turn`` hands them to Zenoh: the
    reliable ones (:data:`AWAITED_PROTOCOLS`) first, in their order, then the others,
    each marked ``exit_on_failure=false`` (its own Zenoh endpoint option).

    With ``connect/exit_on_failure`` true, Zenoh 1.10's open awaits each connect
    endpoint in turn instead of spawning all at once (``orchestrator.rs``,
    ``connect_peers_multiply_links``), except those marked, which it spawns in the
    background. Why: 40 peer processes started together, each listening on UDP and TCP
    and connecting to both endpoints of every node before it (the launcher's topology,
    ids ordered by start: the set-up that lost most), lost declarations between a pair
    for good (node 0 lacked another node's liveliness token and that node got none of
    node 0's data) in 10 of 28 runs whose pairs opened both links at once (2 of 8 as
    launched, 4 of 10 with TCP listed first, 4 of 10 with gossip autoconnect off), and in
    none of 30 whose pairs opened them one after another (awaiting every endpoint;
    awaiting TCP with UDP after it in the background, both links formed; one link per
    pair), 6 December. This order (all TCP, then all UDP) lost none of 30 on 7 December,
    when the unchanged set-up lost none of 20 either (the loss needs a busier machine
    than that day's). A dead UDP path (the lab's total-loss test) does not hold up the
    open. It also makes the mesh regular: 42 sessions opened in one process in the
    launcher's order each held exactly one UDP and one TCP link to node 0 and two of
    each to every other node (one it dialled, one gossip dialled back), opened in 5.0 s;
    all at once, the sessions held 42-74 UDP and 41-68 TCP links each, unevenly, and took
    20.8 s to open."""
    awaited = [e for e in endpoints if e.partition("/")[0] in AWAITED_PROTOCOLS]
    others = [e for e in endpoints if e.partition("/")[0] not in AWAITED_PROTOCOLS]
    return awaited + [background_endpoint(e) for e in others]


_RUST_LOCATION: Final = re.compile(r"\s+at \S+\.rs:\d+\.?")
_INNERMOST: Final = re.compile(r"\[([^\[\]]*)\]")
_ADDRESS_PREFIX: Final = re.compile(r"^\S+:\d+: ")


def zenoh_reason(error: BaseException) -> str:
    """Zenoh's error text as one short line: without its Rust source locations and, when
    it nests the OS error in brackets, that innermost error alone (``Address already in
    use (os error 98)`` rather than three lines about listeners)."""
    text = _RUST_LOCATION.sub("", str(error)).strip()
    inner = [part for part in _INNERMOST.findall(text) if "os error" in part]
    if inner:
        text = _ADDRESS_PREFIX.sub("", inner[-1].strip())
    return " ".join(text.split()).rstrip(".!") or type(error).__name__


def _configured_endpoints(config: zenoh.Config, role: str) -> list[str]:
    """The ``role`` endpoints of a built configuration (a plain list only)."""
    try:
        value = json.loads(config.get_json(f"{role}/endpoints"))
    except (zenoh.ZError, ValueError):
        return []
    return [e for e in value if isinstance(e, str)] if isinstance(value, list) else []


def _probe(role: str, endpoint: str) -> str | None:
    """Why Zenoh cannot open a session with just ``endpoint`` (as ``role``), or None.

    A peer session that only listens on (or only connects to) one endpoint, without
    scouting: it fails at once for an unknown protocol, a bad address or an address in
    use, and opens for an endpoint that merely does not answer yet.
    """
    config = zenoh.Config()
    config.insert_json5("mode", json.dumps("peer"))
    config.insert_json5("scouting/multicast/enabled", "false")
    config.insert_json5("listen/endpoints", json.dumps([endpoint] if role == "listen" else []))
    config.insert_json5("connect/endpoints", json.dumps([endpoint] if role == "connect" else []))
    try:
        session = zenoh.open(config)
    except zenoh.ZError as exc:
        return zenoh_reason(exc)
    closable: _Closable = session
    closable.close()
    return None


def diagnose_open_error(config: zenoh.Config, error: zenoh.ZError) -> TransportError:
    """The error to raise when ``zenoh.open(config)`` failed with ``error``.

    Zenoh's message often does not say which endpoint failed, so each configured
    endpoint is tried alone (:func:`_probe`): the first that fails on its own gives
    an :class:`EndpointError`. When none does (a client that reaches none of its
    routers, which may come up later), a plain :class:`TransportError`.
    """
    for role in ("listen", "connect"):
        for endpoint in _configured_endpoints(config, role):
            reason = _probe(role, endpoint)
            if reason is not None:
                return EndpointError(role, endpoint, reason)
    return TransportError(f"cannot open Zenoh session: {zenoh_reason(error)}")


def init_zenoh_logging(level: str = "warn") -> None:
    """Let Zenoh (Rust) log to stdout at ``level`` unless ``RUST_LOG`` says otherwise."""
    zenoh.init_log_from_env_or(level)


class _Undeclarable(Protocol):
    def undeclare(self) -> None: ...


class _Closable(Protocol):
    def close(self) -> None: ...


TOKEN_REFRESH_S: Final = (0.5, 1.0, 2.0, 4.0, 8.0)
"""Seconds between the generations of a liveliness token: five more, 15.5 s in all.

A token's declaration reaches a peer once, when declared or when a transport to the
peer opens, and was seen to be lost for good while many peers joined at once: with 40
peer processes starting together on this 2-core machine, each connecting to those
before it over UDP and TCP, node 0 lacked 1-2 of the others' tokens for 12 s although
every peer held a transport to it: in 1 of 6 runs with random ids and TCP endpoints
listed first, 0 of 11 with UDP first, and 6 of 17 with ids ordered by start and gossip
dialling only from the greater id (tried first, against zenoh#169's concurrent opens,
and dropped). That was first seen as a CI run's car whose token never reached the
monitor. Declaring a second token on the same key sends nothing (Zenoh aggregates a
session's tokens per key), but one on a new key arrived from every peer. So
``declare_liveliness(key)`` declares ``key/<generation>`` and, after each delay here,
the next generation before undeclaring the previous one; ``watch_liveliness`` reports
a key alive while any generation of it is (a bare ``key`` counts as one). With it, 10
of 10 such runs saw every token within 3 s. Subscriber declarations were lost the same
way (the nodes whose token node 0 lacked exchanged no data with it either); that loss
came from a pair's UDP and TCP links being opened at once and is avoided where nodes
start in order (:func:`connect_in_turn`).

The generations stop after the start-up burst, where declarations were lost:
continued every 8 s, they wrecked a 40-car ``crosspath up`` run (``four-way-flows-40``,
90 s: 13 cars through instead of 31-33, V2X delivery 0.37 instead of 0.72-0.78, 27
cars' truth reports missing for up to 38 s), so each new declaration costs every
peer far more than its few bytes."""

MAX_TOKEN_GENERATIONS: Final = 4
"""Live generations a watch keeps per key (two in normal use); more are ignored."""

MAX_WATCHED_KEYS: Final = 4096
"""Keys a watch keeps alive state for; tokens on more keys are ignored. Without access
control any peer may declare tokens, on any key (Zenoh keeps them all in its own
tables too): the defence is the router's ACL (``deploy/zenoh``, a node may declare
only its own ``sim/alive/<node>`` and its generations); this bound only keeps a
watch's own state finite."""


class TokenGenerations:
    """Which keys matching a watch's ``keyexpr`` are alive, from the tokens seen
    (``TOKEN_REFRESH_S``): ``key/<generation>`` (a decimal last chunk) or ``key``
    itself; bounded by ``MAX_WATCHED_KEYS`` and ``MAX_TOKEN_GENERATIONS``."""

    __slots__ = ("_live", "ignored", "keyexpr")

    def __init__(self, keyexpr: str) -> None:
        self.keyexpr = keyexpr
        self._live: dict[str, set[str]] = {}
        self.ignored = 0
        """Tokens not tracked: on no matching key, or beyond a bound."""

    def update(self, token: str, alive: bool) -> str | None:
        """The key whose liveness ``token``'s appearance (``alive``) or disappearance
        changed, or None when it changed nothing (another generation lives on)."""
        head, _, last = token.rpartition("/")
        if head and last.isascii() and last.isdigit() and keyexpr_matches(self.keyexpr, head):
            key, generation = head, last
        elif keyexpr_matches(self.keyexpr, token):
            key, generation = token, ""
        else:
            self.ignored += 1
            return None
        live = self._live.get(key)
        if alive:
            if live is None:
                if len(self._live) >= MAX_WATCHED_KEYS:
                    self.ignored += 1
                    return None
                self._live[key] = {generation}
                return key
            if generation not in live:
                if len(live) >= MAX_TOKEN_GENERATIONS:
                    self.ignored += 1
                else:
                    live.add(generation)
            return None
        if live is None or generation not in live:
            return None
        live.discard(generation)
        if live:
            return None
        del self._live[key]
        return key


class _ZenohHandle:
    """One declared Zenoh entity (subscriber, liveliness token or watch)."""

    __slots__ = ("_entity", "_owner", "active", "inbox", "key", "refresh")

    def __init__(self, owner: ZenohTransport, key: str) -> None:
        self._owner = owner
        self.key = key
        self.active = True
        self.inbox: Inbox | None = None
        self._entity: _Undeclarable | None = None
        self.refresh: asyncio.TimerHandle | None = None
        """A token's next re-declaration (``TOKEN_REFRESH_S``), on the event loop."""

    def close(self) -> None:
        self._owner._release(self)

    def _undeclare(self) -> None:
        self.active = False
        if self.refresh is not None:
            self.refresh.cancel()
        if self.inbox is not None:
            self.inbox.close()
        entity, self._entity = self._entity, None
        if entity is not None:
            try:
                entity.undeclare()
            except zenoh.ZError as exc:
                logger.warning("undeclaring %s failed: %s", self.key, exc)


class ZenohTransport:
    """A :class:`Transport` over one Zenoh session; safe to call from any thread."""

    def __init__(
        self,
        settings: ZenohSettings,
        loop: asyncio.AbstractEventLoop | None = None,
        token_refresh_s: tuple[float, ...] = TOKEN_REFRESH_S,
    ) -> None:
        if not token_refresh_s or min(token_refresh_s) <= 0:
            raise ValueError(f"token refresh delays must be > 0 s, got {token_refresh_s}")
        self.settings = settings
        self._loop = loop
        self._token_refresh_s = token_refresh_s
        self.tokens_refreshed = 0
        """Liveliness tokens declared again (``TOKEN_REFRESH_S``)."""
        self._lock = threading.RLock()
        self._session: zenoh.Session | None = None
        self._closed = False
        self._publishers: dict[tuple[str, Qos], zenoh.Publisher] = {}
        self._handles: list[_ZenohHandle] = []
        self.dropped = 0
        """Datagrams received but not delivered (event loop closed, copy failed)."""
        self.connect_endpoints: list[str] = []
        """The endpoints this session connects to (settings and config file), once open."""

    # -- life

    def open(self) -> None:
        with self._lock:
            if self._closed:
                raise TransportError("transport is closed; make a new one")
            if self._session is not None:
                return
            self._loop = _bind_loop(self._loop)
            config = zenoh_config(self.settings)
            self.connect_endpoints = _configured_endpoints(config, "connect")
            try:
                self._session = zenoh.open(config)
            except zenoh.ZError as exc:
                error = diagnose_open_error(config, exc)
                if self.settings.connect_in_turn and not isinstance(error, TransportConfigError):
                    error = TransportError(
                        f"{error} (connect_in_turn: every tcp/tls connect endpoint must "
                        f"answer within {self.settings.connect_timeout_s:g} s)"
                    )
                raise error from None
            logger.info(
                "zenoh session %s open (mode %s, listen %s, connect %s)",
                self._session.zid(),
                self.settings.mode,
                self.settings.listen,
                self.settings.connect,
            )

    async def open_async(self) -> None:
        """:meth:`open` in a worker thread, so scouting and connecting do not stall the loop."""
        if self._loop is None:
            self._loop = asyncio.get_running_loop()
        await asyncio.to_thread(self.open)

    def close(self) -> None:
        with self._lock:
            if self._closed:
                return
            self._closed = True
            handles, self._handles = self._handles, []
            publishers, self._publishers = self._publishers, {}
            session, self._session = self._session, None
        for handle in handles:
            handle._undeclare()
        for (key, _), publisher in publishers.items():
            entity: _Undeclarable = publisher  # zenoh's stub leaves undeclare() untyped
            try:
                entity.undeclare()
            except zenoh.ZError as exc:
                logger.warning("undeclaring publisher %s failed: %s", key, exc)
        if session is not None:
            closable: _Closable = session
            try:
                closable.close()
            except zenoh.ZError as exc:
                logger.warning("closing zenoh session failed: %s", exc)
            logger.info("zenoh session closed")

    @property
    def is_open(self) -> bool:
        """Open and not yet closed."""
        return self._session is not None

    def zid(self) -> str:
        """This session's Zenoh id (hex)."""
        return str(self._require_session().zid())

    def links(self) -> list[tuple[str, str]]:
        """(local, remote) locators of the session's current links, e.g. for diagnostics."""
        return [(link.src, link.dst) for link in self._require_session().info.links()]

    def _require_session(self) -> zenoh.Session:
        session = self._session
        if session is None:
            raise TransportError("transport is closed" if self._closed else "transport not open")
        return session

    def __enter__(self) -> ZenohTransport:
        self.open()
        return self

    def __exit__(self, *_exc: object) -> None:
        self.close()

    # -- publishing

    def publish(self, key: str, payload: bytes, qos: Qos) -> None:
        """Send ``payload`` on ``key``; one Zenoh publisher per (key, QoS) is kept.

        With reliable QoS this may block while the link's queue is full.
        """
        publisher = self._publishers.get((key, qos))
        if publisher is None:
            publisher = self._declare_publisher(key, qos)
        try:
            publisher.put(payload)
        except zenoh.ZError as exc:
            raise TransportError(f"publish on {key} failed: {exc}") from None

    def _declare_publisher(self, key: str, qos: Qos) -> zenoh.Publisher:
        validate_key(key, wildcards=False)
        with self._lock:
            session = self._require_session()
            publisher = self._publishers.get((key, qos))
            if publisher is None:
                try:
                    publisher = session.declare_publisher(
                        key,
                        congestion_control=(
                            zenoh.CongestionControl.DROP
                            if qos.drop
                            else zenoh.CongestionControl.BLOCK
                        ),
                        priority=_zenoh_priority(qos),
                        express=qos.express,
                        reliability=(
                            zenoh.Reliability.RELIABLE
                            if qos.reliable
                            else zenoh.Reliability.BEST_EFFORT
                        ),
                    )
                except zenoh.ZError as exc:
                    raise TransportError(f"cannot declare publisher on {key}: {exc}") from None
                self._publishers[(key, qos)] = publisher
            return publisher

    # -- subscribing

    def subscribe(
        self, keyexpr: str, handler: Handler, policy: ReceivePolicy | None = None
    ) -> Subscription:
        validate_key(keyexpr, wildcards=True)
        with self._lock:
            session = self._require_session()
            loop = self._loop
            if loop is None:  # cannot happen once open
                raise TransportError("transport not open")
            handle = _ZenohHandle(self, keyexpr)
            deliver = self._deliverer(handle, handler)
            inbox = None if policy is None else Inbox(loop, deliver, policy)
            handle.inbox = inbox

            def on_sample(sample: zenoh.Sample) -> None:
                # Runs on a Zenoh thread: check the key, copy, hand over, never raise.
                try:
                    if sample.kind != zenoh.SampleKind.PUT:
                        return
                    key = str(sample.key_expr)
                    if inbox is None:
                        loop.call_soon_threadsafe(deliver, key, sample.payload.to_bytes())
                    elif inbox.admits(key):
                        inbox.put(key, sample.payload.to_bytes())
                except Exception:
                    self.dropped += 1

            try:
                handle._entity = session.declare_subscriber(keyexpr, on_sample)
            except zenoh.ZError as exc:
                raise TransportError(f"cannot subscribe to {keyexpr}: {exc}") from None
            self._handles.append(handle)
            return handle

    def _deliverer(self, handle: _ZenohHandle, handler: Handler) -> Handler:
        def deliver(key: str, data: bytes) -> None:
            if not handle.active:
                return
            try:
                handler(key, data)
            except Exception:
                logger.exception("handler for %s failed on a datagram from %s", handle.key, key)

        return deliver

    # -- liveliness

    def declare_liveliness(self, key: str) -> Subscription:
        validate_key(key, wildcards=False)
        with self._lock:
            session = self._require_session()
            loop = self._loop
            if loop is None:
                raise TransportError("transport not open")
            handle = _ZenohHandle(self, key)
            try:
                handle._entity = session.liveliness().declare_token(f"{key}/0")
            except zenoh.ZError as exc:
                raise TransportError(f"cannot declare liveliness token {key}: {exc}") from None
            self._handles.append(handle)
        with contextlib.suppress(RuntimeError):  # the loop closed: nothing left to repair
            loop.call_soon_threadsafe(self._schedule_refresh, handle, 0)
        return handle

    def _schedule_refresh(self, handle: _ZenohHandle, step: int) -> None:
        """On the loop: re-declare ``handle``'s token after the ``step``-th delay."""
        if not handle.active or self._loop is None:
            return
        delays = self._token_refresh_s
        if step < len(delays):
            handle.refresh = self._loop.call_later(
                delays[step], self._refresh_token, handle, step + 1
            )
        else:
            handle.refresh = None

    def _refresh_token(self, handle: _ZenohHandle, step: int) -> None:
        """Declare the next generation of ``handle``'s token, then undeclare the previous
        one (``TOKEN_REFRESH_S``); ``step`` numbers the generation."""
        with self._lock:
            session = self._session
            if session is None or not handle.active:
                return
            try:
                fresh = session.liveliness().declare_token(f"{handle.key}/{step}")
            except zenoh.ZError as exc:
                logger.warning("declaring liveliness token %s again failed: %s", handle.key, exc)
                fresh = None
            if fresh is not None:
                old, handle._entity = handle._entity, fresh
                self.tokens_refreshed += 1
                if old is not None:
                    try:
                        old.undeclare()
                    except zenoh.ZError as exc:
                        logger.warning("undeclaring %s failed: %s", handle.key, exc)
        self._schedule_refresh(handle, step)

    def watch_liveliness(self, keyexpr: str, on_change: LivelinessHandler) -> Subscription:
        validate_key(keyexpr, wildcards=True)
        with self._lock:
            session = self._require_session()
            loop = self._loop
            if loop is None:
                raise TransportError("transport not open")
            handle = _ZenohHandle(self, keyexpr)
            generations = TokenGenerations(keyexpr)

            def deliver(token: str, alive: bool) -> None:
                if not handle.active:
                    return
                key = generations.update(token, alive)
                if key is None:
                    return
                try:
                    on_change(key, alive)
                except Exception:
                    logger.exception("liveliness handler for %s failed", keyexpr)

            def on_sample(sample: zenoh.Sample) -> None:
                try:
                    alive = sample.kind == zenoh.SampleKind.PUT
                    loop.call_soon_threadsafe(deliver, str(sample.key_expr), alive)
                except Exception:
                    self.dropped += 1

            try:
                handle._entity = session.liveliness().declare_subscriber(
                    keyexpr if keyexpr.endswith("**") else f"{keyexpr}/**",
                    on_sample,
                    history=True,
                )
            except zenoh.ZError as exc:
                raise TransportError(f"cannot watch liveliness {keyexpr}: {exc}") from None
            self._handles.append(handle)
            return handle

    def _release(self, handle: _ZenohHandle) -> None:
        with self._lock:
            if handle not in self._handles:
                handle.active = False
                return
            self._handles.remove(handle)
        handle._undeclare()


def _zenoh_priority(qos: Qos) -> zenoh.Priority:
    """V2X (dropping) traffic goes ahead of plumbing when both share a link."""
    return zenoh.Priority.DATA_HIGH if qos.drop else zenoh.Priority.DATA


# --------------------------------------------------------------------------- in memory


class MemoryBus:
    """The shared medium of :class:`MemoryTransport` instances in one process."""

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self._subscriptions: list[_MemoryHandle] = []
        self._tokens: list[_MemoryHandle] = []
        self._watches: list[_MemoryHandle] = []
        self.published = 0
        """Datagrams published on the bus so far."""

    def _deliver(self, key: str, payload: bytes) -> None:
        with self._lock:
            self.published += 1
            targets = [h for h in self._subscriptions if keyexpr_matches(h.key, key)]
        for handle in targets:
            handle.post(key, payload)

    def _add_token(self, token: _MemoryHandle) -> None:
        with self._lock:
            self._tokens.append(token)
            watches = [w for w in self._watches if keyexpr_matches(w.key, token.key)]
        for watch in watches:
            watch.post(token.key, True)

    def _remove(self, handle: _MemoryHandle) -> None:
        with self._lock:
            was_token = handle in self._tokens
            for registry in (self._subscriptions, self._tokens, self._watches):
                if handle in registry:
                    registry.remove(handle)
            watches = (
                [w for w in self._watches if keyexpr_matches(w.key, handle.key)]
                if was_token
                else []
            )
        for watch in watches:
            watch.post(handle.key, False)

    def _add_watch(self, watch: _MemoryHandle) -> None:
        with self._lock:
            self._watches.append(watch)
            present = [t.key for t in self._tokens if keyexpr_matches(watch.key, t.key)]
        for key in present:
            watch.post(key, True)


class _MemoryHandle:
    """A subscription, token or watch on a :class:`MemoryBus`."""

    __slots__ = ("active", "callback", "inbox", "key", "owner")

    def __init__(
        self,
        owner: MemoryTransport,
        key: str,
        callback: Callable[[str, Any], None] | None,
    ) -> None:
        self.owner = owner
        self.key = key
        self.callback = callback
        self.active = True
        self.inbox: Inbox | None = None

    def post(self, key: str, value: bytes | bool) -> None:
        loop = self.owner._loop
        if loop is None or loop.is_closed():
            self.owner.dropped += 1
            return
        inbox = self.inbox
        if inbox is not None and isinstance(value, bytes):
            if inbox.admits(key):
                inbox.put(key, value)
            return
        try:
            running = asyncio.get_running_loop()
        except RuntimeError:
            running = None
        if running is loop:
            loop.call_soon(self._run, key, value)
        else:
            loop.call_soon_threadsafe(self._run, key, value)

    def _run(self, key: str, value: bytes | bool) -> None:
        if not self.active or self.callback is None:
            return
        try:
            self.callback(key, value)
        except Exception:
            logger.exception("handler for %s failed on %s", self.key, key)

    def close(self) -> None:
        if self.inbox is not None:
            self.inbox.close()
        self.owner._release(self)


class MemoryTransport:
    """A :class:`Transport` on an in-process :class:`MemoryBus`: lossless, no Zenoh.

    Delivery is asynchronous like Zenoh's (``loop.call_soon``), in publish order,
    to every subscription whose key expression matches (``*``, ``**``). QoS is
    accepted and ignored.
    """

    def __init__(
        self, bus: MemoryBus | None = None, loop: asyncio.AbstractEventLoop | None = None
    ) -> None:
        self.bus = MemoryBus() if bus is None else bus
        self._loop = loop
        self._lock = threading.Lock()
        self._open = False
        self._closed = False
        self._handles: list[_MemoryHandle] = []
        self.dropped = 0
        """Datagrams not delivered because this transport's loop was closed."""

    def open(self) -> None:
        with self._lock:
            if self._closed:
                raise TransportError("transport is closed; make a new one")
            self._loop = _bind_loop(self._loop)
            self._open = True

    def close(self) -> None:
        with self._lock:
            if self._closed:
                return
            self._closed = True
            self._open = False
            handles, self._handles = self._handles, []
        for handle in handles:
            handle.active = False
            self.bus._remove(handle)

    @property
    def is_open(self) -> bool:
        """Open and not yet closed."""
        return self._open

    def __enter__(self) -> MemoryTransport:
        self.open()
        return self

    def __exit__(self, *_exc: object) -> None:
        self.close()

    def _require_open(self) -> None:
        if not self._open:
            raise TransportError("transport is closed" if self._closed else "transport not open")

    def publish(self, key: str, payload: bytes, qos: Qos) -> None:
        validate_key(key, wildcards=False)
        self._require_open()
        self.bus._deliver(key, bytes(payload))

    def _track(self, handle: _MemoryHandle) -> None:
        with self._lock:
            self._require_open()
            self._handles.append(handle)

    def subscribe(
        self, keyexpr: str, handler: Handler, policy: ReceivePolicy | None = None
    ) -> Subscription:
        validate_key(keyexpr, wildcards=True)
        handle = _MemoryHandle(self, keyexpr, handler)
        self._track(handle)
        if policy is not None:
            loop = self._loop
            if loop is None:  # cannot happen once open
                raise TransportError("transport not open")
            handle.inbox = Inbox(loop, handle._run, policy)
        with self.bus._lock:
            self.bus._subscriptions.append(handle)
        return handle

    def declare_liveliness(self, key: str) -> Subscription:
        validate_key(key, wildcards=False)
        handle = _MemoryHandle(self, key, None)
        self._track(handle)
        self.bus._add_token(handle)
        return handle

    def watch_liveliness(self, keyexpr: str, on_change: LivelinessHandler) -> Subscription:
        validate_key(keyexpr, wildcards=True)
        handle = _MemoryHandle(self, keyexpr, on_change)
        self._track(handle)
        self.bus._add_watch(handle)
        return handle

    def _release(self, handle: _MemoryHandle) -> None:
        with self._lock:
            if handle in self._handles:
                self._handles.remove(handle)
        handle.active = False
        self.bus._remove(handle)
