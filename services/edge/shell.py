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
- sends V2X messages (:meth:`DaemonShell.publish_v2x`) with the stream's QoS
  (best effort, UDP) and counts them (bytes = encoded payload length);
- publishes its counters (:class:`~services.edge.plumbing.StatsReport`) on
  ``{prefix}/stats/{node}`` every ``stats_period_s`` and a final one per run.

Nothing a peer sends can raise out of a handler: every handler is wrapped, and
an unexpected exception in a core is logged (rate limited) and the datagram
dropped.

Clock-skew tolerance: :data:`MAX_FUTURE_S` and :data:`MAX_AGE_S` are in run
seconds. On one host there is no skew; across hosts, clocks must agree to well
under a second (NTP does) or the receiver drops everything as stale or from
the future. Skew up to the tolerance is accepted and shows as error in the
measured latency (see ``services.edge.clock``).

Latencies are recorded in *wall* seconds (run-time latency divided by the
run's speed), so the ``network`` section reports what the network did,
whatever ``--speed`` was.

:class:`ActorDaemon` is the base of the vehicle and RSU daemons: it follows the
monitor's run control (``services.edge.plumbing``): it waits for a
:class:`~services.edge.plumbing.StartRun` naming it, runs one *episode*
(subclass hook) on the run clock, and ends it on the matching
:class:`~services.edge.plumbing.StopRun`, when the monitor's liveliness
token disappears, when run time passes ``max_sim_s`` + :data:`END_MARGIN_S`, or
on SIGTERM/SIGINT; then it waits for the next start. Starts whose run id was
seen before, or that arrive while a run is active, are ignored.
"""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import logging
import os
import time
from collections.abc import Callable, Mapping
from pathlib import Path
from typing import Final, TypeVar

from protocol import MAX_DATAGRAM, DecodeError, EncodeError, Message, decode, encode, keys
from protocol.keys import ParsedKey, Stream
from services.edge.clock import RunClock
from services.edge.lifecycle import Service, run_service
from services.edge.logs import configure_logging
from services.edge.plumbing import (
    Control,
    PlumbingError,
    StartRun,
    StatsReport,
    StopRun,
    alive_key,
    all_alive,
    control_key,
    decode_control,
    encode_stats,
    node_of_alive_key,
)
from services.edge.settings import (
    CommonDaemonConfig,
    ConfigError,
    load_config,
    overrides_from_args,
)
from services.edge.stats import NodeStats
from services.edge.transport import (
    RELIABLE_QOS,
    Subscription,
    Transport,
    TransportError,
    ZenohTransport,
    init_zenoh_logging,
    qos_for,
)
from services.model.scenario import Scenario, ScenarioError, load_scenario

__all__ = [
    "DRAIN_S",
    "END_MARGIN_S",
    "MAX_AGE_S",
    "MAX_FUTURE_S",
    "ActorDaemon",
    "DaemonShell",
    "RateLimitedLog",
    "V2xHandler",
    "load_daemon_config",
    "load_daemon_scenario",
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

V2xHandler = Callable[[ParsedKey, Message, float], None]
"""Receives (parsed key, decoded message, run time of reception) on the event loop."""


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


class DaemonShell:
    """Transport, V2X edge, statistics and the current run clock of one daemon."""

    def __init__(
        self,
        config: CommonDaemonConfig,
        service: str,
        transport: Transport | None = None,
        *,
        time_fn: Callable[[], float] = time.time,
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
        self.ratelog = RateLimitedLog(self.log)
        self._token: Subscription | None = None
        self._stats_task: asyncio.Task[None] | None = None
        self._opened = False

    # ------------------------------------------------------------------ life

    async def open(self) -> None:
        """Open the transport (in a worker thread for Zenoh: connecting may take a while)."""
        if isinstance(self.transport, ZenohTransport):
            await self.transport.open_async()
        else:
            self.transport.open()
        self._opened = True

    def announce(self) -> None:
        """Declare the liveliness token; call after every subscription is declared."""
        if self._token is None:
            self._token = self.transport.declare_liveliness(
                alive_key(self.node, prefix=self.prefix)
            )

    def start_stats(self) -> None:
        """Publish a stats report every ``stats_period_s`` until :meth:`close`."""
        if self._stats_task is None:
            self._stats_task = asyncio.ensure_future(self._stats_loop())

    async def _stats_loop(self) -> None:
        period = self.config.stats_period_s
        while True:
            await asyncio.sleep(period)
            self.publish_stats(final=False)

    async def close(self) -> None:
        """Stop the stats task, undeclare everything and close the transport; idempotent."""
        task, self._stats_task = self._stats_task, None
        if task is not None:
            task.cancel()
            with contextlib.suppress(asyncio.CancelledError):
                await task
        token, self._token = self._token, None
        if token is not None:
            token.close()
        self._opened = False
        self.transport.close()

    # ------------------------------------------------------------------ runs

    def begin_run(self, run_id: str, epoch_unix: float, speed: float) -> RunClock:
        """Fresh counters and the run clock of a new run; acknowledges it with a stats report."""
        self.stats = NodeStats(self.node)
        self.run_id = run_id
        self.clock = RunClock(epoch_unix, speed, time_fn=self.time_fn)
        self.publish_stats(final=False)
        return self.clock

    async def end_run(self, drain_s: float = DRAIN_S) -> None:
        """Keep counting receptions for ``drain_s``, publish the final report, go idle."""
        if self.run_id is None:
            return
        if drain_s > 0:
            await asyncio.sleep(drain_s)
        self.publish_stats(final=True)
        self.run_id = None
        self.clock = None
        self.stats = NodeStats(self.node)

    def now(self) -> float | None:
        """Run time now, or None when no run is active."""
        return None if self.clock is None else self.clock.now()

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
    ) -> Subscription:
        """Receive V2X datagrams on ``keyexpr``; see the module docstring for the checks.

        ``stream`` names the counters of datagrams whose key cannot be parsed.
        Datagrams on a key of ``ignore_vehicle`` (this car's own future path, which
        Zenoh also delivers locally) are skipped without counting. Outside a run,
        valid messages are dropped uncounted (there is no clock to date them), but
        malformed ones are counted.
        """

        def on_datagram(key: str, payload: bytes) -> None:
            try:
                self._on_datagram(key, payload, stream, handler, ignore_vehicle)
            except Exception:
                self.ratelog.log(
                    logging.ERROR,
                    f"handler:{stream}",
                    "handling a datagram on %s failed",
                    key,
                    exc=True,
                )

        return self.transport.subscribe(keyexpr, on_datagram)

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
            message = decode(payload)
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
        self.stats.on_receive(name, len(payload), age / clock.speed)
        handler(parsed, message, now)

    def publish_v2x(self, key: str, message: Message) -> bool:
        """Encode and send one V2X message on ``key``; False (logged) if it could not be sent."""
        stream = keys.STREAM_OF_KIND[message.kind]
        try:
            payload = encode(message)
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

        A ``PlumbingError`` (or any exception) is counted in ``plumbing_malformed``
        and logged (rate limited); it never reaches the transport.
        """

        def on_payload(key: str, payload: bytes) -> None:
            try:
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
            except Exception:
                self.plumbing_malformed += 1
                self.ratelog.log(
                    logging.ERROR,
                    f"plumbing:{keyexpr}",
                    "handling plumbing message on %s failed",
                    key,
                    exc=True,
                )

        return self.transport.subscribe(keyexpr, on_payload)

    def publish_plumbing(self, key: str, payload: bytes) -> bool:
        """Send one reliable plumbing message; False (logged) if the transport refused."""
        try:
            self.transport.publish(key, payload, RELIABLE_QOS)
        except TransportError as exc:
            self.ratelog.log(logging.WARNING, f"publish:{key}", "send on %s failed: %s", key, exc)
            return False
        return True

    def stats_report(self, final: bool) -> StatsReport:
        """This node's counters now (run time ``time_s`` when a run is active)."""
        snapshot = self.stats.snapshot(self.now())
        snapshot["plumbing_malformed"] = self.plumbing_malformed
        return StatsReport(node=self.node, run_id=self.run_id, final=final, snapshot=snapshot)

    def publish_stats(self, final: bool) -> None:
        """Publish :meth:`stats_report` on ``{prefix}/stats/{node}`` (no-op before open)."""
        if not self._opened:
            return
        self.publish_plumbing(
            keys.stats(self.node, prefix=self.prefix), encode_stats(self.stats_report(final))
        )


async def wait_event(event: asyncio.Event, timeout: float) -> bool:
    """Wait for ``event`` at most ``timeout`` wall seconds; whether it is set."""
    if event.is_set():
        return True
    if timeout <= 0:
        return False
    with contextlib.suppress(TimeoutError):
        await asyncio.wait_for(event.wait(), timeout)
    return event.is_set()


async def wait_any(*events: asyncio.Event) -> None:
    """Return once any of ``events`` is set."""
    if any(event.is_set() for event in events):
        return
    waiters = [asyncio.ensure_future(event.wait()) for event in events]
    try:
        await asyncio.wait(waiters, return_when=asyncio.FIRST_COMPLETED)
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


class ActorDaemon:
    """A vehicle or RSU daemon: follows the monitor's runs (see the module docstring).

    Subclasses set ``service`` and implement :meth:`subscribe` (their V2X
    subscriptions), :meth:`takes_part` and :meth:`episode`; they may override
    :meth:`on_episode_end` (the RSU sends its terminations there).
    """

    service = "actor"

    def __init__(
        self,
        config: CommonDaemonConfig,
        scenario: Scenario,
        transport: Transport | None = None,
        *,
        time_fn: Callable[[], float] = time.time,
    ) -> None:
        self.config = config
        self.scenario = scenario
        self.shell = DaemonShell(config, self.service, transport, time_fn=time_fn)
        self.log = self.shell.log
        self.node = config.node_id
        self.prefix = config.key_prefix
        self.active: StartRun | None = None
        self.seen_runs: set[str] = set()
        self.alive: set[str] = set()
        self.runs_done = 0
        self._pending: StartRun | None = None
        self._wake = asyncio.Event()
        self._halt = asyncio.Event()
        self._halt_reason = ""

    # -- hooks

    def subscribe(self) -> None:
        """Declare the daemon's V2X subscriptions."""
        raise NotImplementedError

    def takes_part(self, start: StartRun) -> bool:
        """Whether this daemon is an actor of ``start``."""
        raise NotImplementedError

    async def episode(self, start: StartRun, clock: RunClock, halt: asyncio.Event) -> None:
        """Drive the pure core on ``clock`` until ``halt`` is set."""
        raise NotImplementedError

    async def on_episode_end(self, start: StartRun, clock: RunClock) -> None:
        """Called after the episode, before the final stats report (still on the run clock)."""

    # -- Service

    async def startup(self) -> None:
        await self.shell.open()
        self.shell.subscribe_plumbing(control_key(prefix=self.prefix), self._on_control)
        self.shell.transport.watch_liveliness(all_alive(prefix=self.prefix), self._on_liveliness)
        self.subscribe()
        self.shell.announce()
        self.shell.start_stats()
        self.log.info("%s %s ready, waiting for a run", self.service, self.node)

    async def run(self, stop: asyncio.Event) -> None:
        stopper = asyncio.ensure_future(self._forward_stop(stop))
        try:
            while not stop.is_set():
                self._wake.clear()
                start, self._pending = self._pending, None
                if start is None:
                    await wait_any(self._wake, stop)
                    continue
                await self._run_episode(start)
        finally:
            stopper.cancel()
            with contextlib.suppress(asyncio.CancelledError):
                await stopper

    async def _forward_stop(self, stop: asyncio.Event) -> None:
        await stop.wait()
        self._end("stopped by signal")
        self._wake.set()

    async def _run_episode(self, start: StartRun) -> None:
        self._halt.clear()
        self._halt_reason = ""
        self.active = start
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
                self.runs_done += 1

    async def shutdown(self) -> None:
        await self.shell.close()
        self.log.info("%s %s stopped", self.service, self.node)

    # -- control

    def _end(self, reason: str) -> None:
        if not self._halt.is_set():
            self._halt_reason = reason
            self._halt.set()

    def _on_control(self, key: str, payload: bytes) -> None:
        message: Control = decode_control(payload)
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

    def _on_liveliness(self, key: str, alive: bool) -> None:
        try:
            node = node_of_alive_key(key, prefix=self.prefix)
        except keys.BadKey:
            return
        if alive:
            self.alive.add(node)
            return
        self.alive.discard(node)
        if self.active is not None and node == self.active.monitor:
            self.log.warning("monitor %s is gone: ending run %s", node, self.active.run_id)
            self._end("monitor lost")


# --------------------------------------------------------------------------- CLI helpers

C = TypeVar("C", bound=CommonDaemonConfig)


def load_daemon_config(
    model: type[C], args: argparse.Namespace, extra: Mapping[str, object] | None = None
) -> C:
    """The daemon's config: TOML ``--config``, ``CROSSPATH_*`` env, ``--set`` and the common
    flags, then ``extra`` (the command's own flags, which win). Raises ``ConfigError``."""
    overrides = overrides_from_args(args)
    overrides.update(extra or {})
    path: Path | None = getattr(args, "config", None)
    return load_config(model, path, overrides, os.environ)


def load_daemon_scenario(path: Path) -> Scenario:
    """The scenario file; ``ConfigError`` on field ``scenario`` when it is unusable."""
    try:
        return load_scenario(path)
    except ScenarioError as exc:
        raise ConfigError([("scenario", str(exc))]) from None


def run_daemon(config: CommonDaemonConfig, service: Service) -> int:
    """Configure logging (stderr, node id on every line) and run ``service`` on uvloop.

    Zenoh's own logs are switched on only when ``RUST_LOG`` is set (they go to stdout).
    """
    configure_logging(config.log_level, config.node_id, config.log_json)
    if os.environ.get("RUST_LOG"):
        init_zenoh_logging()
    return run_service(service)
