"""The shell code every crosspath daemon shares: transport, V2X edge, statistics, run control.

:class:`DaemonShell` is the one place where a daemon

- opens its :class:`~services.edge.transport.Transport` (Zenoh, or the
  in-memory bus in tests) and announces itself with a liveliness token on
  ``{prefix}/sim/alive/{node}`` (declared after its subscriptions, so a node
  seen alive is ready to receive);
- receives V2X datagrams (:meth:`DaemonShell.subscribe_v2x`): a payload larger
  than ``MAX_DATAGRAM`` (1460 B) is counted malformed without decoding; a key
  that is not a crosspath key, a payload that does not decode
  (``protocol.DecodeError``) or a message that does not match the key it came
  on (``protocol.keys.matches``: sender or target differ) is counted malformed
  and dropped, logged at debug level at most once per second per stream. A
  decoded message's one-way latency is ``clock.now() - header.time_s``;
  messages dated more than :data:`MAX_FUTURE_S` in the future or older than
  :data:`MAX_AGE_S` are counted ``dropped_stale`` and dropped;
- in a run, declares its scoped V2X subscriptions (:class:`ScopedSubscription`: the
  vehicle's and the RSU's) on the keys of the run's senders only, not on their
  wildcards (:meth:`DaemonShell.scope_v2x`, at most :data:`MAX_SCOPED_KEYS` keys each):
  Zenoh then routes nothing else to the daemon, so a flood from ids that are not in the
  run costs it no CPU at all (issue 13, 7 Dec: 5000 datagrams/s from 500 fake ids took
  each daemon from about 6 % to 40 % of a core on the wildcard, 7-9 % now);
- receives through bounded inboxes (``services.edge.transport.Inbox``, issue 13): a
  datagram whose key names a sender that is not a node of the current run (one that
  still arrives: on a wildcard, between runs or in a run with more senders than the
  scope's bound) is refused on the network thread (counted ``refused`` in the stats'
  ``receive`` section) before its payload is copied; V2X keeps the latest datagram per
  sender and kind, rate limited to :data:`V2X_RATE_HZ` per run second; plumbing is first
  in, first out (:data:`PLUMBING_DEPTH` per sender) and signed
  (``services.edge.plumbing.PlumbingAuth``) when the daemon has credentials;
- with credentials (``[security]``, issue 13) verifies every V2X datagram that
  passed those checks (``services.edge.trust.TrustStore``: certificate chain,
  role, sender, run tag, replay window, Ed25519) and refuses the rest, counted
  by reason in the stats' ``auth`` section; the handler finds the verified
  certificate in :attr:`DaemonShell.verified`. Without credentials it warns
  loudly at start and accepts unsigned datagrams;
- sends V2X messages (:meth:`DaemonShell.publish_v2x`) with the stream's QoS
  (best effort, UDP), signed when it has credentials, and counts them (bytes =
  the datagram's length, signature included);
- publishes its counters (:class:`~services.edge.plumbing.StatsReport`) on
  ``{prefix}/stats/{node}`` every ``stats_period_s`` and a final one per run, and
  serves the same counters as Prometheus metrics when ``metrics_port`` is set
  (``services.edge.metrics``).

Errors, split as h11 splits them (a peer's protocol error vs our own bug):

- what a peer sent wrong never raises out of a handler: it is checked at this
  boundary (above), or by the plumbing decoders (``PlumbingError``, counted in
  ``plumbing_malformed``), or by the pure cores, which count and drop it;
- anything else a handler raises is a bug of ours. It is logged once at ERROR
  with its traceback, counted (``internal_errors`` in the stats), the current
  run is ended (the RSU still sends its terminations) and the daemon exits with
  status 1, which systemd's ``Restart=on-failure`` restarts: after an exception
  half-way through a decision the core's state is not known to be consistent, and
  a restarted daemon rejoins a run in progress (``expect_crash``);
- an endpoint that cannot be opened (address in use or not on this host, an
  unknown protocol, a bad port) ends the daemon at startup with one line naming
  the endpoint and the reason, exit status 78 (``EXIT_CONFIG``, which the systemd
  units do not restart on); a Zenoh client that reaches none of its routers
  exits 1 (restarted: the router may come up later);
- a peer whose connect endpoints do not answer logs one WARNING naming them after
  :data:`UNREACHABLE_WARN_S` and keeps trying (Zenoh retries), and one INFO line
  once connected.

Clock-skew tolerance: :data:`MAX_FUTURE_S` and :data:`MAX_AGE_S` are in run
seconds. On one host there is no skew; across hosts, clocks must agree to well
under a second (NTP does) or the receiver drops everything as stale or from
the future. Skew up to the tolerance is accepted and shows as error in the
measured latency (see ``services.edge.clock``).

Latencies are recorded in *wall* seconds (run-time latency divided by the
run's speed), so the ``network`` section reports what the network did,
whatever ``--speed`` was.

:class:`DaemonBase` is the base of every daemon service (vehicle, RSU,
monitor): the config, the scenario, the shell, the startup and shutdown, and
the stop / internal-error handling around its ``work``. :class:`ActorDaemon`
(vehicle and RSU) follows the monitor's run control
(``services.edge.plumbing``): it waits for a
:class:`~services.edge.plumbing.StartRun` naming it, runs one *episode*
(subclass hook) on the run clock, and ends it on the matching
:class:`~services.edge.plumbing.StopRun`, when the monitor's liveliness
token disappears, when run time passes ``max_sim_s`` + :data:`END_MARGIN_S`, or
on SIGTERM/SIGINT; then it waits for the next start. Starts whose run id was
seen before, or that arrive while a run is active, are ignored.

:class:`DaemonCommand` is the command line of a daemon: its options, the
configuration layering (TOML ``--config``, ``CROSSPATH_*`` env, ``--set``, the
flags) and the exit statuses (2: configuration error).
"""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import logging
import os
import time
from collections import OrderedDict
from collections.abc import AsyncIterator, Callable, Collection, Coroutine, Mapping
from pathlib import Path
from typing import Any, Final, Generic, TypeVar

from protocol import MAX_DATAGRAM, DecodeError, EncodeError, Message, decode, encode, keys
from protocol.auth import Certificate
from protocol.keys import ParsedKey, Stream
from services.edge.clock import RunClock
from services.edge.lifecycle import EXIT_CONFIG, EXIT_FAILED, Service, ServiceExit, run_service
from services.edge.logs import configure_logging
from services.edge.metrics import CoreView, DaemonMetrics, MetricsServer, zenoh_links
from services.edge.plumbing import (
    Control,
    PlumbingAuth,
    PlumbingError,
    StartRun,
    StatsReport,
    StopRun,
    TruthReport,
    alive_key,
    all_alive,
    control_key,
    decode_control,
    decode_truth,
    encode_stats,
    node_of_alive_key,
    truth_key,
)
from services.edge.settings import (
    CommonDaemonConfig,
    ConfigError,
    add_common_arguments,
    exit_on_config_error,
    load_config,
    overrides_from_args,
)
from services.edge.stats import LatencyHistogram, NodeStats
from services.edge.transport import (
    RELIABLE_QOS,
    Handler,
    LivelinessHandler,
    ReceivePolicy,
    Subscription,
    Transport,
    TransportConfigError,
    TransportError,
    ZenohTransport,
    init_zenoh_logging,
    qos_for,
)
from services.edge.trust import Refused, Signer, TrustStore, load_security
from services.model.scenario import Scenario, ScenarioError, load_scenario

__all__ = [
    "DECODE_MEMO",
    "DRAIN_S",
    "END_MARGIN_S",
    "MAX_AGE_S",
    "MAX_FUTURE_S",
    "PROFILE_ENV",
    "UNREACHABLE_WARN_S",
    "ActorDaemon",
    "DaemonBase",
    "DaemonCommand",
    "DaemonShell",
    "RateLimitedLog",
    "V2xHandler",
    "add_daemon_arguments",
    "decode_shared",
    "load_daemon_scenario",
    "open_transport",
    "run_daemon",
    "sleep_until",
    "wait_any",
    "wait_event",
]

MAX_FUTURE_S: Final = 1.0
"""A message dated more than this many run seconds after the receiver's now is dropped."""

MAX_AGE_S: Final = 2.0
"""A message older than this many run seconds at reception is dropped."""

END_MARGIN_S: Final = 30.0
"""An actor ends a run on its own this many run seconds after ``max_sim_s`` (monitor gone)."""

DRAIN_S: Final = 0.3
"""Wall seconds an actor keeps counting receptions after it stopped sending, before its
final stats report (datagrams in flight)."""

UNREACHABLE_WARN_S: Final = 5.0
"""Wall seconds after which a Zenoh session with connect endpoints but no link says so."""

V2X_RATE_HZ: Final = 50.0
"""Datagrams per run second one V2X lane (sender and kind) may deliver: five times a
future path's 10 Hz; scaled by the run's speed. Beyond it they are dropped and counted
(``rate_limited`` in the stats' ``receive`` section)."""

V2X_BURST: Final = 25.0
"""Datagrams a V2X lane may deliver back to back before its rate applies."""

V2X_DEDUPE: Final = 32
"""Datagrams a V2X lane remembers to drop exact copies (replays) before they cost a
token: 3.2 s of a 10 Hz sender, beyond the 2 s stale window. A replay flood of a
sender's genuine datagrams could otherwise spend its rate and starve it (issue 13)."""

PLUMBING_DEPTH: Final = 256
"""Plumbing messages queued per sender key (first in, first out; truth must not be
coalesced); more push out the oldest (counted ``coalesced``)."""

PLUMBING_LANES: Final = 256
"""Plumbing sender keys queued at once."""

PLUMBING_BYTES: Final = 16 * 1024 * 1024
"""Plumbing bytes queued at once (a stats report may be tens of kilobytes)."""

_V2X_LABELS: Final = frozenset(str(s) for s in (Stream.FP, Stream.AP, Stream.CMD, Stream.BEACON))

MAX_SCOPED_KEYS: Final = 64
"""Most keys a run-scoped V2X subscription (``subscribe_v2x(scope=...)``) declares in a
run; a run with more senders keeps the wildcard (and the network-thread refusal)."""

RunScope = Callable[[StartRun], Collection[str]]
"""The concrete keys a V2X subscription narrows to in a run (its senders' keys)."""

PROFILE_ENV: Final = "CROSSPATH_PROFILE"
"""Environment variable: a directory where each daemon writes its ``cProfile`` stats."""

V2xHandler = Callable[[ParsedKey, Message, float], None]
"""Receives (parsed key, decoded message, run time of reception) on the event loop."""


DECODE_MEMO: Final = 1024
"""Decoded V2X datagrams remembered per process (:func:`decode_shared`)."""

_DECODED: OrderedDict[bytes, Message] = OrderedDict()


def decode_shared(payload: bytes) -> Message:
    """``protocol.decode`` with a bounded per-process memo (issue 12: CPU per car): the cars
    of a multi-car host (``services.daemons.host``) each receive the very same datagram,
    which is decoded once. Messages are immutable; a payload that does not decode is not
    remembered (``DecodeError`` every time)."""
    message = _DECODED.get(payload)
    if message is None:
        message = decode(payload)
        _DECODED[payload] = message
        if len(_DECODED) > DECODE_MEMO:
            _DECODED.popitem(last=False)
    return message


class RateLimitedLog:
    """Logs one message per key at most every ``period_s`` wall seconds, counting the rest."""

    def __init__(
        self,
        logger: logging.Logger,
        period_s: float = 1.0,
        time_fn: Callable[[], float] = time.monotonic,
    ) -> None:
        self.logger = logger
        self.period_s = period_s
        self._time = time_fn
        self._last: dict[str, float] = {}
        self._suppressed: dict[str, int] = {}

    def log(self, level: int, key: str, msg: str, *args: object, exc: bool = False) -> None:
        now = self._time()
        last = self._last.get(key)
        if last is not None and now - last < self.period_s:
            self._suppressed[key] = self._suppressed.get(key, 0) + 1
            return
        self._last[key] = now
        suppressed = self._suppressed.pop(key, 0)
        if suppressed:
            msg += f" ({suppressed} similar suppressed)"
        self.logger.log(level, msg, *args, exc_info=exc)


async def open_transport(transport: Transport) -> None:
    """Open ``transport`` (Zenoh in a worker thread: connecting may take a while).

    Raises :class:`~services.edge.lifecycle.ServiceExit`: ``EXIT_CONFIG`` with one line
    naming the endpoint when the settings cannot work, ``EXIT_FAILED`` otherwise.
    """
    try:
        if isinstance(transport, ZenohTransport):
            await transport.open_async()
        else:
            transport.open()
    except TransportConfigError as exc:
        raise ServiceExit(str(exc), EXIT_CONFIG) from None
    except TransportError as exc:
        raise ServiceExit(str(exc), EXIT_FAILED) from None


async def watch_reachability(
    transport: ZenohTransport, log: logging.Logger, after_s: float = UNREACHABLE_WARN_S
) -> None:
    """Warn once when ``transport`` holds no link ``after_s`` after opening, naming its
    connect endpoints; say when it connects. Zenoh keeps retrying meanwhile."""
    endpoints = transport.connect_endpoints
    if not endpoints:
        return
    await asyncio.sleep(after_s)
    if transport.links():
        return
    log.warning(
        "no peer reachable after %g s: nothing answers at %s (daemon or router not running, "
        "wrong address, or a firewall?); still trying",
        after_s,
        ", ".join(endpoints),
    )
    while not transport.links():
        await asyncio.sleep(1.0)
    log.info("connected: %s", ", ".join(dst for _src, dst in transport.links()))


class ScopedSubscription:
    """A V2X subscription declared on its wildcard between runs and on the run's senders'
    keys in a run (:meth:`DaemonShell.scope_v2x`).

    Why: Zenoh routes a datagram only to sessions that declared a matching subscriber, so
    a datagram on a key the daemon did not declare never reaches it. A flood from ids
    that are not nodes of the run then costs the daemon nothing at all; on the wildcard
    each such datagram cost about 45 µs of CPU (Zenoh's receive path and the callback,
    measured 7 Dec) before the inbox refused it. Every key shares one receive policy
    (limits and counters) as the wildcard did, each with its own bounded inbox that holds
    only that sender's lanes (one per message kind); old keys are undeclared before new ones
    are declared, so no datagram is delivered twice (one may be missed in between: V2X
    is lossy, and a run's first datagrams come after its start delay).
    """

    __slots__ = ("_current", "_handler", "_policy", "_scope", "_shell", "keyexpr")

    def __init__(
        self,
        shell: DaemonShell,
        keyexpr: str,
        handler: Handler,
        policy: ReceivePolicy,
        scope: RunScope,
    ) -> None:
        self._shell = shell
        self.keyexpr = keyexpr
        self._handler = handler
        self._policy = policy
        self._scope = scope
        self._current: dict[str, Subscription] = {}

    @property
    def key(self) -> str:
        return self.keyexpr

    @property
    def keys(self) -> list[str]:
        """The key expressions declared now."""
        return sorted(self._current)

    def wanted(self, start: StartRun | None) -> list[str]:
        """The keys to declare for run ``start`` (None: between runs)."""
        if start is None:
            return [self.keyexpr]
        keys_ = sorted(set(self._scope(start)))
        return keys_ if len(keys_) <= MAX_SCOPED_KEYS else [self.keyexpr]

    def retarget(self, start: StartRun | None) -> None:
        """Declare the keys of run ``start``, undeclaring those no longer wanted first."""
        wanted = self.wanted(start)
        for key in [k for k in self._current if k not in wanted]:
            self._current.pop(key).close()
        for key in wanted:
            if key not in self._current:
                self._current[key] = self._shell.transport.subscribe(
                    key, self._handler, self._policy
                )

    def close(self) -> None:
        """Undeclare every key; the shell forgets this subscription."""
        self._shell._scoped.discard(self)
        while self._current:
            self._current.popitem()[1].close()


class DaemonShell:
    """Transport, V2X edge, statistics and the current run clock of one daemon."""

    def __init__(
        self,
        config: CommonDaemonConfig,
        service: str,
        transport: Transport | None = None,
        *,
        time_fn: Callable[[], float] = time.time,
        extras: Callable[[], Mapping[str, Any]] | None = None,
        core: Callable[[], CoreView | None] | None = None,
    ) -> None:
        self.config = config
        self.node = config.node_id
        self.prefix = config.key_prefix
        self.log = logging.getLogger(f"crosspath.{service}")
        self.transport: Transport = ZenohTransport(config.zenoh) if transport is None else transport
        self.time_fn = time_fn
        self.stats = NodeStats(self.node)
        self.run_id: str | None = None
        self.clock: RunClock | None = None
        self.plumbing_malformed = 0
        self.internal_errors = 0
        """Exceptions our own handlers raised (bugs); the first one stops the daemon."""
        self.late_ticks = 0
        """Ticks of this run that ran more than one tick period behind the run clock."""
        self.max_tick_lag_s = 0.0
        """Largest lag of a tick behind its due time in this run [run s]."""
        self.tick_lags = LatencyHistogram()
        """Every tick's lag in this run [run s]: the stats carry its p99 beside the max (one
        stall of the machine sets the max; the p99 says how late the loop usually runs)."""
        self.next_tick_s: float | None = None
        """Run time of the control tick the daemon sleeps towards (None: none, or it ran):
        the inboxes hold their datagrams back while it is due (``ReceivePolicy.tick_due``)."""
        self.fault: str | None = None
        """What failed first, once a handler raised."""
        self.faulted = asyncio.Event()
        self.ratelog = RateLimitedLog(self.log)
        self.actors: frozenset[str] | None = None
        """The nodes of the current run; when set, datagrams from any other sender are
        refused on the network thread (``services.edge.transport.Inbox``)."""
        self.receive: dict[str, ReceivePolicy] = {}
        """The receive policy (bounded inbox, counters) of each subscription, by label."""
        self.scope: StartRun | None = None
        """The run the scoped V2X subscriptions are declared for (None: their wildcards)."""
        self._scoped: set[ScopedSubscription] = set()
        self._extras = extras
        self.metrics: DaemonMetrics | None = None
        """Prometheus metrics (``services.edge.metrics``), when ``metrics_port`` is set."""
        if config.metrics_port is not None:
            links = zenoh_links(self.transport)
            self.metrics = DaemonMetrics(self.node, service, self, core, links)
        self._metrics_server: MetricsServer | None = None
        self._token: Subscription | None = None
        self._tasks: list[asyncio.Task[None]] = []
        self._stats_started = False
        self._opened = False
        security = load_security(config.security, self.node)
        self.signer: Signer | None = None if security is None else security[0]
        """Signs every V2X datagram sent (issue 13); None: unsigned (insecure)."""
        self.trust: TrustStore | None = None if security is None else security[1]
        """Verifies every V2X datagram received; None: accepts unsigned (insecure)."""
        self.verified: Certificate | None = None
        """The certificate of the datagram whose handler runs now (None when insecure)."""
        self.plumbing_auth: PlumbingAuth | None = (
            None if self.signer is None else PlumbingAuth(self.signer.credentials)
        )
        """Signs and verifies the plumbing (start, stop, truth, stats); None: insecure."""
        self.plumbing_subject: str | None = None
        """Who signed the plumbing message whose handler runs now (None when insecure)."""

    # ------------------------------------------------------------------ life

    async def open(self) -> None:
        """Serve the metrics (when configured), open the transport (:func:`open_transport`)
        and watch that it reaches a peer."""
        if self.signer is None:  # here, not in __init__: logging is configured by now
            self.log.warning(
                "INSECURE: %s — V2X is neither signed nor verified; any peer can command "
                "the cars (issue 13; give security.key/certificate/root)",
                "by choice (security.insecure)"
                if self.config.security.insecure
                else "no credentials",
            )
        if self.metrics is not None and self._metrics_server is None:
            port = self.config.metrics_port or 0
            self._metrics_server = await self.metrics.serve(self.config.metrics_host, port)
        await open_transport(self.transport)
        self._opened = True
        if isinstance(self.transport, ZenohTransport):
            self._spawn(watch_reachability(self.transport, self.log))

    def _spawn(self, coro: Coroutine[Any, Any, None]) -> None:
        self._tasks.append(asyncio.ensure_future(coro))

    def announce(self) -> None:
        """Declare the liveliness token; call after every subscription is declared."""
        if self._token is None:
            self._token = self.transport.declare_liveliness(
                alive_key(self.node, prefix=self.prefix)
            )

    def start_stats(self) -> None:
        """Publish a stats report at once (the signed "hello" the monitor needs to count
        this node present, issue 13) and every ``stats_period_s`` until :meth:`close`."""
        if not self._stats_started:
            self._stats_started = True
            self._spawn(self._stats_loop())

    async def _stats_loop(self) -> None:
        period = self.config.stats_period_s
        while True:
            self.publish_stats(final=False)
            await asyncio.sleep(period)

    async def close(self) -> None:
        """Stop the background tasks, undeclare everything, close the transport; idempotent."""
        tasks, self._tasks = self._tasks, []
        for task in tasks:
            task.cancel()
        for task in tasks:
            with contextlib.suppress(asyncio.CancelledError):
                await task
        token, self._token = self._token, None
        if token is not None:
            token.close()
        self._opened = False
        for scoped in self._scoped:  # the transport undeclares their keys
            scoped._current.clear()
        self._scoped.clear()  # and nothing declares them again
        self.transport.close()
        server, self._metrics_server = self._metrics_server, None
        if server is not None:
            await server.close()

    # ------------------------------------------------------------------ our own bugs

    def guard(self, what: str, call: Callable[[], None]) -> None:
        """Run a handler's ``call``; an exception out of it is a bug of ours (module doc)."""
        try:
            call()
        except Exception as exc:
            self.internal_errors += 1
            if self.fault is None:
                self.fault = f"{what} failed ({type(exc).__name__}: {exc})"
                self.log.error("%s failed: a bug, stopping", what, exc_info=exc)
                self.faulted.set()
            else:
                self.ratelog.log(logging.ERROR, "fault", "%s failed again: %r", what, exc)

    def raise_fault(self) -> None:
        """Raise ``ServiceExit`` (status 1) when a handler failed (traceback logged then)."""
        if self.fault is not None:
            raise ServiceExit(f"internal error: {self.fault}; traceback above", EXIT_FAILED)

    def watch_alive(self, handler: LivelinessHandler) -> Subscription:
        """Follow every node's liveliness token: ``handler(node, alive)`` under :meth:`guard`
        (a token on a key that names no node is ignored)."""

        def on_change(key: str, alive: bool) -> None:
            try:
                node = node_of_alive_key(key, prefix=self.prefix)
            except keys.BadKey:
                return
            self.guard(f"liveliness handler for {node}", lambda: handler(node, alive))

        return self.transport.watch_liveliness(all_alive(prefix=self.prefix), on_change)

    # ------------------------------------------------------------------ runs

    def begin_run(self, run_id: str, epoch_unix: float, speed: float) -> RunClock:
        """Fresh counters and the run clock of a new run; acknowledges it with a stats report."""
        if self.metrics is not None:
            self.metrics.observe()  # the counters between runs, before they are replaced
        self.stats = NodeStats(self.node)
        self.run_id = run_id
        self.late_ticks = 0
        self.max_tick_lag_s = 0.0
        self.tick_lags = LatencyHistogram()
        self.next_tick_s = None
        self.clock = RunClock(epoch_unix, speed, time_fn=self.time_fn)
        for label, policy in self.receive.items():
            policy.stats.reset()
            if label in _V2X_LABELS:
                self._v2x_limits(policy)
        if self.signer is not None and self.trust is not None:
            self.trust.begin_run(run_id)
            self.signer.begin_run(self.trust.run, speed)
            self.trust.counters.clear()
        self.publish_stats(final=False)
        return self.clock

    async def end_run(self, drain_s: float = DRAIN_S) -> None:
        """Keep counting receptions for ``drain_s``, publish the final report, go idle."""
        self.next_tick_s = None  # no more ticks: nothing to hold datagrams back for
        if self.run_id is None:
            return
        if drain_s > 0:
            await asyncio.sleep(drain_s)
        # One parsable line per run, kept in the node's log: what ``crosspath results
        # rebuild`` reads when the monitor died and never got the final stats report.
        self.log.info(
            "run %s ticks: late_ticks=%d max_tick_lag_s=%.3f",
            self.run_id,
            self.late_ticks,
            self.max_tick_lag_s,
        )
        self.publish_stats(final=True)
        self.run_id = None
        self.clock = None
        self.stats = NodeStats(self.node)
        for label, policy in self.receive.items():
            if label in _V2X_LABELS:
                self._v2x_limits(policy)

    def _v2x_limits(self, policy: ReceivePolicy) -> ReceivePolicy:
        """Set a V2X inbox's limits for now: :data:`V2X_RATE_HZ` per lane scaled by the
        run's speed (as at speed 1 between runs); between runs a verifying daemon uses V2X
        only to learn its peers' keys (``TrustStore.learn``), so it queues only datagrams
        that carry a certificate and a flood then costs no decoding."""
        speed = 1.0 if self.clock is None else self.clock.speed
        policy.rate_hz = V2X_RATE_HZ * speed
        policy.burst = max(V2X_BURST, V2X_RATE_HZ * speed / 2)
        policy.certificates_only = self.trust is not None and self.clock is None
        return policy

    def tick_due(self) -> float | None:
        """The run time of the control tick that is due and has not run yet, else None."""
        due, clock = self.next_tick_s, self.clock
        if due is None or clock is None:
            return None
        return due if clock.now() >= due else None

    def now(self) -> float | None:
        """Run time now, or None when no run is active."""
        return None if self.clock is None else self.clock.now()

    def on_tick(self, due_s: float, now_s: float, period_s: float) -> None:
        """A control-loop tick due at run time ``due_s`` ran at ``now_s`` [run s]; more
        than ``period_s`` behind counts in ``late_ticks``."""
        self.next_tick_s = None
        lag = now_s - due_s
        if lag > period_s:
            self.late_ticks += 1
        self.max_tick_lag_s = max(self.max_tick_lag_s, lag)
        self.tick_lags.add(lag)
        if self.metrics is not None:
            self.metrics.on_tick(lag, period_s)

    def run_truth(self, key: str, payload: bytes, start: StartRun | None) -> TruthReport | None:
        """A car's ground truth of run ``start``; None outside a run or for another run.

        Raises ``PlumbingError`` (counted by :meth:`subscribe_plumbing`) for a payload
        that does not decode, or that comes from a car not in the run or on another
        car's key.
        """
        if start is None:
            return None
        report = decode_truth(payload)
        if report.run_id != start.run_id:
            return None
        vid = report.vehicle
        if vid not in start.vehicles or key != truth_key(vid, prefix=self.prefix):
            raise PlumbingError(f"truth of {vid!r} on {key}: not a car of this run")
        return report

    # ------------------------------------------------------------------ V2X

    def _malformed(self, stream: str, key: str, why: str) -> None:
        self.stats.on_malformed(stream)
        self.ratelog.log(
            logging.DEBUG, f"malformed:{stream}", "dropped datagram on %s: %s", key, why
        )

    def subscribe_v2x(
        self,
        keyexpr: str,
        stream: Stream,
        handler: V2xHandler,
        *,
        ignore_vehicle: str | None = None,
        scope: RunScope | None = None,
    ) -> Subscription:
        """Receive V2X datagrams on ``keyexpr``; see the module docstring for the checks.

        With ``scope``, a :class:`ScopedSubscription`: in a run it is declared on
        ``scope(start)``, the keys of the run's senders (at most :data:`MAX_SCOPED_KEYS`,
        else the wildcard), so that nothing else reaches this daemon at all.

        ``stream`` names the counters of datagrams whose key cannot be parsed.
        Datagrams on a key of ``ignore_vehicle`` (this car's own future path, which
        Zenoh also delivers locally) are skipped without counting. Outside a run,
        valid messages are dropped uncounted (there is no clock to date them), but
        malformed ones are counted; a verifying daemon then queues only datagrams that
        carry a certificate (the rest ``refused`` in the ``receive`` section), whose keys
        it learns, and every lane is rate limited as at speed 1. ``handler`` runs under
        :meth:`guard`.
        """

        def on_datagram(key: str, payload: bytes) -> None:
            self.guard(
                f"handling a datagram on {key}",
                lambda: self._on_datagram(key, payload, stream, handler, ignore_vehicle),
            )

        policy = self.receive.setdefault(
            str(stream),
            self._v2x_limits(
                ReceivePolicy(admit=self._admits, dedupe=V2X_DEDUPE, tick_due=self.tick_due)
            ),
        )
        if scope is None:
            return self.transport.subscribe(keyexpr, on_datagram, policy)
        scoped = ScopedSubscription(self, keyexpr, on_datagram, policy, scope)
        scoped.retarget(self.scope)
        self._scoped.add(scoped)
        return scoped

    def scope_v2x(self, start: StartRun | None) -> None:
        """Declare every scoped V2X subscription for run ``start`` (None: between runs)."""
        self.scope = start
        for scoped in list(self._scoped):
            try:
                scoped.retarget(start)
            except TransportError as exc:  # the transport is closing or broken: it says so
                self.log.warning("cannot declare %s for the run: %s", scoped.keyexpr, exc)

    def _admits(self, key: str) -> bool:
        """Whether a datagram on ``key`` may be queued: always outside a run and for keys
        that name no sender (control, or not ours: counted malformed later), else only
        from a node of the run. Runs on the network thread: a key parse and a set lookup."""
        actors = self.actors
        if actors is None:
            return True
        try:
            parsed = keys.parse(key, prefix=self.prefix)
        except keys.BadKey:
            return True
        if parsed.stream in (Stream.CMD, Stream.BEACON):
            sender = parsed.rsu
        elif parsed.stream is Stream.STATS:
            sender = parsed.node
        elif parsed.stream is Stream.SIM:
            sender = parsed.parts[1] if len(parsed.parts) == 2 else None
        else:
            sender = parsed.vehicle
        return sender is None or sender in actors

    def _on_datagram(
        self,
        key: str,
        payload: bytes,
        stream: Stream,
        handler: V2xHandler,
        ignore_vehicle: str | None,
    ) -> None:
        try:
            parsed = keys.parse(key, prefix=self.prefix)
        except keys.BadKey as exc:
            self._malformed(str(stream), key, str(exc))
            return
        name = str(parsed.stream)
        if ignore_vehicle is not None and parsed.vehicle == ignore_vehicle:
            return
        if len(payload) > MAX_DATAGRAM:
            self._malformed(name, key, f"oversized ({len(payload)} B > {MAX_DATAGRAM} B)")
            return
        try:
            message = decode_shared(payload)
        except DecodeError as exc:
            self._malformed(name, key, str(exc))
            return
        if not keys.matches(parsed, message):
            self._malformed(
                name,
                key,
                f"{message.kind.name} from {message.header.sender!r} does not match its key",
            )
            return
        clock = self.clock
        if clock is None:
            if self.trust is not None:  # know the senders' certificates when the run starts
                self.trust.learn(payload, message)
            return
        now = clock.now()
        age = now - message.header.time_s
        if age > MAX_AGE_S or age < -MAX_FUTURE_S:
            self.stats.on_stale(name)
            self.ratelog.log(
                logging.DEBUG,
                f"stale:{name}",
                "dropped %s from %s dated %.3f s at %.3f s",
                message.kind.name,
                message.header.sender,
                message.header.time_s,
                now,
            )
            return
        trust = self.trust
        if trust is not None:
            try:
                self.verified = trust.verify_datagram(payload, message)
            except Refused as exc:
                self.ratelog.log(
                    logging.WARNING, f"refused:{name}", "refused datagram on %s: %s", key, exc
                )
                return
        try:
            self.stats.on_receive(name, len(payload), age / clock.speed)
            handler(parsed, message, now)
        finally:
            self.verified = None

    def publish_v2x(self, key: str, message: Message) -> bool:
        """Encode and send one V2X message on ``key``; False (logged) if it could not be sent."""
        stream = keys.STREAM_OF_KIND[message.kind]
        try:
            payload = encode(message)
            if self.signer is not None:
                payload = self.signer.seal(payload)
        except EncodeError as exc:
            self.ratelog.log(
                logging.ERROR, f"encode:{stream}", "cannot encode %s: %s", message.kind.name, exc
            )
            return False
        try:
            self.transport.publish(key, payload, qos_for(stream))
        except TransportError as exc:
            self.ratelog.log(
                logging.WARNING, f"publish:{stream}", "send on %s failed: %s", key, exc
            )
            return False
        self.stats.on_send(str(stream), len(payload))
        return True

    # ------------------------------------------------------------------ plumbing

    def subscribe_plumbing(
        self, keyexpr: str, handler: Callable[[str, bytes], None]
    ) -> Subscription:
        """Receive plumbing payloads; the handler raises ``PlumbingError`` for bad ones.

        A ``PlumbingError`` (a peer's bad payload) is counted in ``plumbing_malformed``
        and logged (rate limited); any other exception is a bug (:meth:`guard`).
        """

        def checked(key: str, payload: bytes) -> None:
            try:
                auth = self.plumbing_auth
                if auth is not None:
                    payload, self.plumbing_subject = auth.open(key, payload, prefix=self.prefix)
                handler(key, payload)
            except PlumbingError as exc:
                self.plumbing_malformed += 1
                self.ratelog.log(
                    logging.WARNING,
                    f"plumbing:{keyexpr}",
                    "dropped plumbing message on %s: %s",
                    key,
                    exc,
                )
            finally:
                self.plumbing_subject = None

        def on_payload(key: str, payload: bytes) -> None:
            self.guard(f"handling a plumbing message on {key}", lambda: checked(key, payload))

        label = keyexpr.removeprefix(f"{self.prefix}/")
        policy = self.receive.setdefault(
            label,
            ReceivePolicy(
                depth=PLUMBING_DEPTH,
                by_kind=False,
                max_lanes=PLUMBING_LANES,
                max_bytes=PLUMBING_BYTES,
                admit=self._admits,
                tick_due=self.tick_due,
            ),
        )
        return self.transport.subscribe(keyexpr, on_payload, policy)

    def publish_plumbing(self, key: str, payload: bytes) -> bool:
        """Send one reliable plumbing message (signed unless insecure); False (logged) if
        the transport refused."""
        if self.plumbing_auth is not None:
            payload = self.plumbing_auth.seal(payload)
        try:
            self.transport.publish(key, payload, RELIABLE_QOS)
        except TransportError as exc:
            self.ratelog.log(logging.WARNING, f"publish:{key}", "send on %s failed: %s", key, exc)
            return False
        return True

    def stats_report(self, final: bool) -> StatsReport:
        """This node's counters now (run time ``time_s`` when a run is active), with the
        daemon's ``extras``."""
        snapshot = self.stats.snapshot(self.now())
        snapshot["plumbing_malformed"] = self.plumbing_malformed
        snapshot["internal_errors"] = self.internal_errors
        if self.run_id is not None:
            snapshot["late_ticks"] = self.late_ticks
            snapshot["max_tick_lag_s"] = round(self.max_tick_lag_s, 4)
            p99 = self.tick_lags.percentile(0.99)
            if p99 is not None:
                snapshot["tick_lag_s_p99"] = round(p99, 4)
        snapshot["receive"] = {k: p.stats.snapshot() for k, p in sorted(self.receive.items())}
        if self.plumbing_auth is not None:
            snapshot["plumbing_refused"] = dict(sorted(self.plumbing_auth.refused.items()))
        if self.trust is not None:
            snapshot["auth"] = dict(sorted(self.trust.counters.items()))
        if self._extras is not None:
            snapshot.update(self._extras())
        return StatsReport(node=self.node, run_id=self.run_id, final=final, snapshot=snapshot)

    def publish_stats(self, final: bool) -> None:
        """Publish :meth:`stats_report` on ``{prefix}/stats/{node}`` (no-op before open)."""
        if self.metrics is not None:
            self.metrics.observe()  # before the shell replaces a run's counters
        if not self._opened:
            return
        self.publish_plumbing(
            keys.stats(self.node, prefix=self.prefix), encode_stats(self.stats_report(final))
        )


async def wait_event(event: asyncio.Event, timeout: float) -> bool:
    """Wait for ``event`` at most ``timeout`` wall seconds; whether it is set.

    The control loops' ticks sleep here, so a timeout must resume the caller in one loop
    turn: ``asyncio.wait`` does (its timer wakes the caller directly), while
    ``asyncio.wait_for`` first waits for the cancelled inner wait to finish, two more
    turns, and each turn may first run a slice of received datagrams (up to a few ms at
    the RSU: an RSU whose ticks fell due as the cars' paths arrived ran them 10-14 ms
    late on a 2-core machine). The waiter on ``event`` is cancelled, not awaited.
    """
    if event.is_set():
        return True
    if timeout <= 0:
        return False
    waiter = asyncio.ensure_future(event.wait())
    try:
        await asyncio.wait((waiter,), timeout=timeout)
    finally:
        waiter.cancel()
    return event.is_set()


async def wait_any(*events: asyncio.Event, timeout: float | None = None) -> None:
    """Return once any of ``events`` is set, or after ``timeout`` wall seconds."""
    if any(event.is_set() for event in events):
        return
    waiters = [asyncio.ensure_future(event.wait()) for event in events]
    try:
        await asyncio.wait(waiters, timeout=timeout, return_when=asyncio.FIRST_COMPLETED)
    finally:
        for waiter in waiters:
            waiter.cancel()


async def sleep_until(clock: RunClock, run_t: float, halt: asyncio.Event) -> bool:
    """Sleep until run time ``run_t``; False as soon as ``halt`` is set."""
    while not halt.is_set():
        delay = clock.wall_delay(run_t - clock.now())
        if delay <= 0:
            return True
        await wait_event(halt, delay)
    return False


C = TypeVar("C", bound=CommonDaemonConfig)


class DaemonBase(Generic[C]):
    """A daemon service: config, scenario and :class:`DaemonShell` (see the module doc).

    Subclasses set ``service`` (the logger and command name) and ``role`` (what its
    ``node_id`` names in the scenario, for messages), and implement
    :meth:`node_ids` (None: any id), :meth:`setup` (their own state),
    :meth:`subscribe` and :meth:`work`; they may override :meth:`halt`,
    :meth:`stats_extras` and :attr:`periodic_stats`.
    """

    service = "daemon"
    role = "node"
    periodic_stats = True
    """Publish stats every ``stats_period_s`` (the monitor does not)."""

    def __init__(
        self,
        config: C,
        scenario: Scenario,
        transport: Transport | None = None,
        *,
        time_fn: Callable[[], float] = time.time,
    ) -> None:
        ids = self.node_ids(scenario)
        if ids is not None and config.node_id not in ids:
            problem = f"no {self.role} {config.node_id!r} in scenario {scenario.name!r}"
            raise ConfigError([("node_id", problem)])
        self.config = config
        self.scenario = scenario
        self.time_fn = time_fn
        self.shell = DaemonShell(
            config,
            self.service,
            transport,
            time_fn=time_fn,
            extras=self.stats_extras,
            core=self.core_view,
        )
        self.log = self.shell.log
        self.node = config.node_id
        self.prefix = config.key_prefix
        self.ready = False
        self._prepare()
        self.setup()

    # -- hooks

    def _prepare(self) -> None:
        """State of an intermediate base class (before :meth:`setup`)."""

    @classmethod
    def node_ids(cls, scenario: Scenario) -> Collection[str] | None:
        """The ids this daemon may have in ``scenario``; None: any."""
        return None

    def setup(self) -> None:
        """Initialise the subclass's own state (called at the end of ``__init__``)."""

    def subscribe(self) -> None:
        """Declare the daemon's subscriptions (before its liveliness token)."""

    async def work(self, halt: asyncio.Event) -> None:
        """Do the daemon's work until ``halt`` is set (or the work is done)."""
        raise NotImplementedError

    def halt(self, reason: str) -> None:
        """Called once when the daemon is to stop: a signal, or a bug in a handler."""

    def stats_extras(self) -> Mapping[str, Any]:
        """Extra fields of this daemon's stats reports."""
        return {}

    def core_view(self) -> CoreView | None:
        """The pure core's counters and state for the metrics; None: no core now."""
        return None

    def ready_message(self) -> str:
        """The INFO line logged once the daemon is ready."""
        return f"{self.service} {self.node} ready"

    # -- Service

    async def startup(self) -> None:
        await self.shell.open()
        self.subscribe()
        self.shell.announce()
        if self.periodic_stats:
            self.shell.start_stats()
        self.ready = True
        self.log.info("%s", self.ready_message())

    async def run(self, stop: asyncio.Event) -> None:
        """:meth:`work` until ``stop``; then raise ``ServiceExit`` if a handler failed."""
        halted = asyncio.Event()

        async def forward() -> None:
            await wait_any(stop, self.shell.faulted)
            halted.set()
            self.halt(
                "stopped by a signal" if self.shell.fault is None else "hit an internal error"
            )

        forwarder = asyncio.ensure_future(forward())
        try:
            await self.work(halted)
        finally:
            forwarder.cancel()
            with contextlib.suppress(asyncio.CancelledError):
                await forwarder
        self.shell.raise_fault()

    async def shutdown(self) -> None:
        await self.shell.close()
        if self.ready:
            self.log.info("%s %s stopped", self.service, self.node)


class ActorDaemon(DaemonBase[C]):
    """A vehicle or RSU daemon: follows the monitor's runs (see the module docstring).

    Subclasses set ``role`` (``"vehicle"`` or ``"RSU"``: which of the scenario's ids
    their ``node_id`` is), implement :meth:`takes_part` and :meth:`episode`, and
    declare their V2X subscriptions in :meth:`subscribe_v2x`; they may override
    :meth:`on_episode_end` (the RSU sends its terminations there).
    """

    @classmethod
    def node_ids(cls, scenario: Scenario) -> Collection[str]:
        if cls.role == "vehicle":
            return [v.id for v in scenario.vehicles]
        return [r.id for r in scenario.rsus]

    def _prepare(self) -> None:
        self.active: StartRun | None = None
        self.seen_runs: set[str] = set()
        self.alive: set[str] = set()
        self.runs_done = 0
        self._pending: StartRun | None = None
        self._wake = asyncio.Event()
        self._halt = asyncio.Event()
        self._halt_reason = ""

    # -- hooks

    def subscribe_v2x(self) -> None:
        """Declare the daemon's V2X (and other plumbing) subscriptions."""

    def takes_part(self, start: StartRun) -> bool:
        """Whether this daemon is an actor of ``start``."""
        raise NotImplementedError

    async def episode(self, start: StartRun, clock: RunClock, halt: asyncio.Event) -> None:
        """Drive the pure core on ``clock`` until ``halt`` is set."""
        raise NotImplementedError

    async def on_episode_end(self, start: StartRun, clock: RunClock) -> None:
        """Called after the episode, before the final stats report (still on the run clock)."""

    # -- DaemonBase

    def subscribe(self) -> None:
        self.shell.subscribe_plumbing(control_key(prefix=self.prefix), self._on_control)
        self.shell.watch_alive(self._on_alive)
        self.subscribe_v2x()

    def ready_message(self) -> str:
        return f"{self.service} {self.node} ready, waiting for a run"

    def halt(self, reason: str) -> None:
        self._end(reason)
        self._wake.set()

    async def work(self, halt: asyncio.Event) -> None:
        while not halt.is_set():
            self._wake.clear()
            start, self._pending = self._pending, None
            if start is None:
                await wait_any(self._wake, halt)
                continue
            await self._run_episode(start)

    async def ticks(
        self, start: StartRun, clock: RunClock, halt: asyncio.Event, hz: float, first: int = 0
    ) -> AsyncIterator[tuple[int, float]]:
        """Steps ``first, first + 1, ...`` at ``hz`` on the run clock: each (step, run time
        [s]) once that time has come. Ends when ``halt`` is set, or past ``max_sim_s`` +
        :data:`END_MARGIN_S` (the monitor is gone: the run is ended). A tick that runs
        more than one period behind its time counts in the shell's ``late_ticks``
        (published in the stats; the monitor marks the run ``degraded``): a loop that
        falls behind still runs every step, late, instead of skipping any."""
        dt = 1.0 / hz
        limit = start.max_sim_s + END_MARGIN_S
        step = first
        while True:
            now = step * dt
            self.shell.next_tick_s = now
            if not await sleep_until(clock, now, halt):
                return
            if now > limit:
                self._end(f"run time passed max_sim_s ({start.max_sim_s:g} s)")
                return
            self.shell.on_tick(now, clock.now(), dt)
            yield step, now
            step += 1

    async def _run_episode(self, start: StartRun) -> None:
        self._halt.clear()
        self._halt_reason = ""
        self.active = start
        self.shell.actors = frozenset((*start.vehicles, *start.rsus, start.monitor))
        self.shell.scope_v2x(start)
        clock = self.shell.begin_run(start.run_id, start.epoch_unix, start.speed)
        self.log.info(
            "run %s: %s mode, policy %s, epoch in %.2f s wall, speed %g",
            start.run_id,
            start.mode,
            start.policy,
            start.epoch_unix - self.shell.time_fn(),
            start.speed,
        )
        try:
            await self.episode(start, clock, self._halt)
        finally:
            self.log.info(
                "run %s ended at %.2f s: %s",
                start.run_id,
                clock.now(),
                self._halt_reason or "episode over",
            )
            try:
                await self.on_episode_end(start, clock)
            finally:
                self.active = None
                await self.shell.end_run(DRAIN_S)
                self.shell.actors = None
                self.shell.scope_v2x(None)
                self.runs_done += 1

    # -- control

    def _end(self, reason: str) -> None:
        if not self._halt.is_set():
            self._halt_reason = reason
            self._halt.set()

    def _on_control(self, key: str, payload: bytes) -> None:
        message: Control = decode_control(payload)
        auth = self.shell.plumbing_auth
        if auth is not None:
            runs = [r for r in (self.active, self._pending) if r is not None]
            run = next((r for r in runs if r.run_id == message.run_id), None)
            auth.check_control(self.shell.plumbing_subject, message, run)
        if isinstance(message, StopRun):
            if self.active is not None and message.run_id == self.active.run_id:
                self._end(f"stopped by the monitor ({message.reason})")
            elif self._pending is not None and message.run_id == self._pending.run_id:
                self._pending = None
            return
        start = message
        if start.run_id in self.seen_runs:
            return
        if not self.takes_part(start):
            self.seen_runs.add(start.run_id)
            self.log.debug("run %s does not include %s", start.run_id, self.node)
            return
        if start.scenario != self.scenario.name:
            self.seen_runs.add(start.run_id)
            self.log.error(
                "refusing run %s: scenario %r, but this daemon has %r",
                start.run_id,
                start.scenario,
                self.scenario.name,
            )
            return
        if self.active is not None or self._pending is not None:
            self.log.warning(
                "ignoring run %s: run %s is active",
                start.run_id,
                (self.active or self._pending or start).run_id,
            )
            return
        self.seen_runs.add(start.run_id)
        self._pending = start
        self._wake.set()

    def _on_alive(self, node: str, alive: bool) -> None:
        if alive:
            self.alive.add(node)
            return
        self.alive.discard(node)
        if self.active is not None and node == self.active.monitor:
            self.log.warning("monitor %s is gone: ending run %s", node, self.active.run_id)
            self._end("monitor lost")


# --------------------------------------------------------------------------- CLI

D = TypeVar("D", bound=Service)


def add_daemon_arguments(
    parser: argparse.ArgumentParser, title: str, id_metavar: str | None = None
) -> argparse._ArgumentGroup:
    """The common daemon options, and a group ``title`` with ``--scenario`` (and ``--id``
    when ``id_metavar`` names what the node id is); the group, for the command's own."""
    add_common_arguments(parser)
    group = parser.add_argument_group(title)
    group.add_argument("--scenario", type=Path, metavar="FILE", help="TOML file or packaged name")
    if id_metavar is not None:
        group.add_argument("--id", dest="node_id", metavar=id_metavar, help="its id (node_id)")
    return group


def load_daemon_scenario(path: str | Path) -> Scenario:
    """The scenario (a file, or a packaged name); ``ConfigError`` on field ``scenario``
    when it is unusable."""
    try:
        scenario = load_scenario(path)
        scenario.require_no_flows("a daemon")
    except ScenarioError as exc:
        raise ConfigError([("scenario", str(exc))]) from None
    return scenario


class DaemonCommand(Generic[C, D]):
    """A daemon's command line: ``model`` its config, ``build`` its service, ``flags`` which
    command-line options set which config fields (dotted paths)."""

    def __init__(
        self,
        command: str,
        model: type[C],
        build: Callable[[C, Scenario], D],
        flags: Mapping[str, str],
    ) -> None:
        self.command = command
        self.model = model
        self.build = build
        self.flags = dict(flags)

    def load(self, args: argparse.Namespace) -> tuple[C, Scenario]:
        """Config and scenario: TOML ``--config``, ``CROSSPATH_*`` env, ``--set`` and the
        common flags, then this command's flags (which win). Raises ``ConfigError``."""
        overrides = overrides_from_args(args)
        for flag, name in self.flags.items():
            value = getattr(args, flag, None)
            if value is not None:
                overrides[name] = str(value) if isinstance(value, Path) else value
        path: Path | None = getattr(args, "config", None)
        config = load_config(self.model, path, overrides, os.environ)
        scenario: str | Path | None = getattr(config, "scenario", None)
        if scenario is None:
            raise ConfigError([("scenario", "a daemon needs a scenario")])
        return config, load_daemon_scenario(scenario)

    def serve(self, args: argparse.Namespace) -> tuple[int, D | None]:
        """Load, build and run the daemon until it stops; its exit status and service
        (None after a configuration error, reported in one line per problem: status 2)."""
        try:
            config, scenario = self.load(args)
            service = self.build(config, scenario)
        except ConfigError as exc:
            return exit_on_config_error(self.command, exc), None
        return run_daemon(config, service), service

    def run(self, args: argparse.Namespace) -> int:
        """:meth:`serve`'s exit status."""
        return self.serve(args)[0]

    def main(
        self, configure: Callable[[argparse.ArgumentParser], None], argv: list[str] | None = None
    ) -> int:
        """The command on its own (``python -m``), its options from ``configure``."""
        parser = argparse.ArgumentParser(prog=f"crosspath {self.command}")
        configure(parser)
        return self.run(parser.parse_args(argv))


def run_daemon(config: CommonDaemonConfig, service: Service) -> int:
    """Configure logging (stderr, node id on every line) and run ``service`` on uvloop.

    Zenoh's own logs are switched on only when ``RUST_LOG`` is set (they go to stdout).
    With :data:`PROFILE_ENV` set to a directory, the daemon runs under ``cProfile`` (timed
    by the event loop thread's CPU time) and writes ``<dir>/<node>.prof`` when it exits
    (``python -m pstats`` reads it): how the daemons' CPU per car was profiled (issue 12).
    """
    configure_logging(config.log_level, config.node_id, config.log_json)
    if os.environ.get("RUST_LOG"):
        init_zenoh_logging()
    target = os.environ.get(PROFILE_ENV)
    if not target:
        return run_service(service)
    import cProfile

    profiler = cProfile.Profile(time.thread_time)  # CPU of the loop's thread, not wall time
    profiler.enable()
    try:
        return run_service(service)
    finally:
        profiler.disable()
        out = Path(target)
        out.mkdir(parents=True, exist_ok=True)
        profiler.dump_stats(out / f"{config.node_id}.prof")
