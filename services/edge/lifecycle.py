"""Run a daemon from start to exit, stopping gracefully on SIGTERM / SIGINT (as uvicorn does).

A daemon is a :class:`Service`: ``startup()`` opens what it needs (Zenoh session,
subscriptions), ``run(stop)`` does the work until ``stop`` is set, and
``shutdown()`` closes everything. :func:`serve` drives the three:

- the first SIGTERM or SIGINT sets ``stop``; ``run`` returns, ``shutdown`` runs,
  exit code 0;
- a second signal forces: the current step (``startup``, ``run`` or ``shutdown``)
  is cancelled, a best-effort ``shutdown`` gets ``force_timeout`` seconds (unless
  the forced step was ``shutdown`` itself), exit code 1;
- ``startup`` or ``run`` raising, or ``shutdown`` raising or overrunning
  ``shutdown_timeout``, also gives exit code 1, logged with its traceback (a bug
  of ours, or a failure we did not foresee);
- ``startup`` or ``run`` raising :class:`ServiceExit` ends the service with one
  log line (its message, no traceback) and its exit code: what the operator must
  fix is named, and :data:`EXIT_CONFIG` tells systemd not to restart (the units in
  ``deploy/systemd/`` list it in ``RestartPreventExitStatus``).

``run`` may also return on its own (the run is over): that is a normal exit, 0.

Once ``startup`` has returned, :func:`serve` tells systemd ``READY=1`` (units with
``Type=notify``, ``services.edge.notify``), and ``STOPPING=1`` before ``shutdown``.
"""

from __future__ import annotations

import asyncio
import contextlib
import gc
import logging
import signal
from collections.abc import Awaitable, Coroutine
from typing import Any, Protocol

from services.edge.notify import notify

logger = logging.getLogger("crosspath.lifecycle")

EXIT_OK = 0
EXIT_FAILED = 1
"""Any failure a restart may cure (systemd's ``Restart=on-failure`` restarts it)."""
EXIT_CONFIG = 78
"""``EX_CONFIG`` of sysexits.h: the configuration cannot work (an endpoint that cannot be
opened); restarting does not help, so the systemd units do not restart on it."""


class ServiceExit(Exception):
    """The service cannot go on, for the reason its one-line message gives.

    :func:`serve` logs the message at ERROR without a traceback and returns
    ``exit_code`` (the process's exit status).
    """

    def __init__(self, message: str, exit_code: int = EXIT_FAILED) -> None:
        super().__init__(message)
        self.exit_code = exit_code


STOP_SIGNALS = (signal.SIGTERM, signal.SIGINT)


class Service(Protocol):
    """What :func:`serve` runs."""

    async def startup(self) -> None:
        """Acquire resources; raise to abort (shutdown still runs, best effort)."""

    async def run(self, stop: asyncio.Event) -> None:
        """Work until ``stop`` is set (or the job is done), then return."""

    async def shutdown(self) -> None:
        """Release everything ``startup`` acquired; must tolerate a partial startup."""


class _Supervisor:
    """Signal bookkeeping of one :func:`serve` call."""

    def __init__(self, stop: asyncio.Event) -> None:
        self.stop = stop
        self.signals = 0
        self.forced = False
        self.current: asyncio.Task[Any] | None = None

    def on_signal(self, signum: int) -> None:
        self.signals += 1
        name = signal.Signals(signum).name
        if self.signals == 1:
            logger.info("%s received: stopping (send it again to force)", name)
            self.stop.set()
            return
        logger.warning("%s received again: forcing exit", name)
        self.stop.set()
        self.forced = True
        if self.current is not None and not self.current.done():
            self.current.cancel()

    async def step(self, coro: Coroutine[Any, Any, None]) -> None:
        """Run one step as a task the second signal can cancel."""
        task = asyncio.ensure_future(coro)
        self.current = task
        try:
            await task
        finally:
            self.current = None


def freeze_startup_objects() -> int:
    """Collect, then freeze what survives (:func:`gc.freeze`); the objects frozen.

    Why: a full collection walks every object the process holds, and after importing
    numpy, pydantic, Zenoh and cryptography (about 68 000 objects) it took 22-106 ms in
    our daemons on a 2-core test machine, at a moment the collector picks: a control tick
    due then is late by as much (issue 13's tick lateness). The modules, the configuration
    and the sessions live until the process ends anyway; frozen, no collection looks at
    them again, and a full collection costs what the run keeps alive (0.5-2 ms measured).
    """
    gc.collect()
    gc.freeze()
    return gc.get_freeze_count()


async def _bounded(awaitable: Awaitable[None], timeout: float) -> None:
    await asyncio.wait_for(awaitable, timeout)


async def serve(
    service: Service,
    *,
    install_signals: bool = True,
    stop: asyncio.Event | None = None,
    shutdown_timeout: float = 10.0,
    force_timeout: float = 2.0,
    freeze_gc: bool = False,
) -> int:
    """Run ``service`` through startup, run and shutdown; return the exit code.

    ``stop`` may be given to stop the service from elsewhere (e.g. a launcher
    running several services in one loop); signal handlers are installed only
    when ``install_signals`` (main thread, Unix) and removed on return. ``freeze_gc``
    (a process of its own: :func:`run_service`) moves everything alive after startup
    out of the cyclic collector's reach (:func:`freeze_startup_objects`).
    """
    supervisor = _Supervisor(asyncio.Event() if stop is None else stop)
    loop = asyncio.get_running_loop()
    installed: list[signal.Signals] = []
    if install_signals:
        for signum in STOP_SIGNALS:
            loop.add_signal_handler(signum, supervisor.on_signal, signum)
            installed.append(signum)
    code = EXIT_OK
    try:
        try:
            await supervisor.step(service.startup())
            if freeze_gc:
                freeze_startup_objects()
            notify("READY=1\nSTATUS=running")  # systemd Type=notify: the unit is started
            await supervisor.step(service.run(supervisor.stop))
        except asyncio.CancelledError:
            if not supervisor.forced:
                raise
            code = EXIT_FAILED
        except ServiceExit as exc:
            logger.error("%s", exc)
            code = exc.exit_code
        except Exception:
            logger.exception("service failed")
            code = EXIT_FAILED
        timeout = force_timeout if supervisor.forced else shutdown_timeout
        notify("STOPPING=1")
        try:
            await supervisor.step(_bounded(service.shutdown(), timeout))
        except asyncio.CancelledError:
            if not supervisor.forced:
                raise
            logger.warning("shutdown cancelled")
            code = EXIT_FAILED
        except TimeoutError:
            logger.error("shutdown did not finish within %.1f s", timeout)
            code = EXIT_FAILED
        except Exception:
            logger.exception("shutdown failed")
            code = EXIT_FAILED
        if supervisor.forced:
            code = EXIT_FAILED
    finally:
        for signum in installed:
            with contextlib.suppress(Exception):
                loop.remove_signal_handler(signum)
    return code


def run_service(service: Service, use_uvloop: bool = True) -> int:
    """Run ``service`` in a fresh event loop (uvloop when available and asked for)."""
    if use_uvloop:
        try:
            import uvloop
        except ImportError:  # pragma: no cover - uvloop is a dependency
            logger.debug("uvloop not available, using asyncio's loop")
        else:
            result: int = uvloop.run(serve(service, freeze_gc=True))
            return result
    return asyncio.run(serve(service, freeze_gc=True))
