"""``crosspath router``: a Zenoh router for multi-host runs.

Daemons on different hosts (or network namespaces) that cannot discover each
other by multicast connect to a router; with gossip scouting they then also
open direct links to each other (see ``deploy/zenoh/README.md``). The router
listens on a UDP and a TCP endpoint (port 7447 on every IPv4 interface unless
``--listen`` says otherwise) with ``max_links`` 2, so best-effort V2X traffic
it forwards can take UDP and reliable plumbing TCP. It runs until SIGTERM or
SIGINT (a second signal forces the exit).

As every daemon (``services.edge.shell``): an endpoint it cannot open ends it
at once with one line naming the endpoint and the reason, exit status 78; when
it has ``--connect`` endpoints and none answers, it says so after a few seconds
and keeps trying.
"""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import logging
import sys
from pathlib import Path
from typing import Any

from services.edge.lifecycle import run_service
from services.edge.logs import configure_logging
from services.edge.metrics import DaemonMetrics, MetricsServer, zenoh_links
from services.edge.settings import ZenohSettings
from services.edge.shell import open_transport, watch_reachability
from services.edge.transport import ZenohTransport

logger = logging.getLogger("crosspath.router")

DEFAULT_LISTEN = ("udp/0.0.0.0:7447", "tcp/0.0.0.0:7447")


class RouterService:
    """A Zenoh session in router mode, open between startup and shutdown."""

    def __init__(
        self, settings: ZenohSettings, metrics_port: int | None = None, metrics_host: str = ""
    ) -> None:
        self.settings = settings
        self.transport: ZenohTransport | None = None
        self._watch: asyncio.Task[None] | None = None
        self.metrics_port = metrics_port
        self.metrics_host = metrics_host or "0.0.0.0"
        self.metrics: MetricsServer | None = None

    async def startup(self) -> None:
        transport = ZenohTransport(self.settings)
        if self.metrics_port is not None:  # Zenoh links, process (services.edge.metrics)
            metrics = DaemonMetrics("router", "router", links=zenoh_links(transport))
            self.metrics = await metrics.serve(self.metrics_host, self.metrics_port)
        await open_transport(transport)  # nothing to close when it fails
        self.transport = transport
        self._watch = asyncio.ensure_future(watch_reachability(transport, logger))
        sys.stdout.write(
            f"crosspath router: ready, zid {self.transport.zid()}, "
            f"listening on {', '.join(self.settings.listen) or '(from config file)'}\n"
        )
        sys.stdout.flush()

    async def run(self, stop: asyncio.Event) -> None:
        await stop.wait()

    async def shutdown(self) -> None:
        if self._watch is not None:
            self._watch.cancel()
            with contextlib.suppress(asyncio.CancelledError):
                await self._watch
        if self.transport is not None:
            self.transport.close()
            logger.info("router stopped")
        if self.metrics is not None:
            await self.metrics.close()


def configure(parser: argparse.ArgumentParser) -> None:
    """Options of ``crosspath router``."""
    parser.add_argument(
        "--listen",
        action="append",
        metavar="ENDPOINT",
        help=f"endpoint to listen on; repeatable (default: {' and '.join(DEFAULT_LISTEN)})",
    )
    parser.add_argument(
        "--connect",
        action="append",
        metavar="ENDPOINT",
        help="another router to connect to; repeatable",
    )
    parser.add_argument(
        "--zenoh-config",
        type=Path,
        metavar="FILE",
        help="Zenoh JSON5 configuration applied first (e.g. deploy/zenoh/router.json5)",
    )
    parser.add_argument(
        "--multicast-scouting",
        action="store_true",
        help="answer and send multicast scouting (off by default)",
    )
    parser.add_argument("--log-level", default="INFO", metavar="LEVEL", help="default INFO")
    parser.add_argument(
        "--metrics-port", type=int, metavar="PORT", help="serve Prometheus metrics on PORT"
    )
    parser.add_argument(
        "--metrics-host", default="0.0.0.0", metavar="ADDR", help="metrics address (0.0.0.0)"
    )


def settings_from_args(args: argparse.Namespace) -> ZenohSettings:
    """The router's Zenoh settings: only what the options give overrides the JSON5 file."""
    fields: dict[str, Any] = {"mode": "router"}
    if args.zenoh_config is not None:
        fields["config_file"] = args.zenoh_config
    if args.listen:
        fields["listen"] = list(args.listen)
    elif args.zenoh_config is None:
        fields["listen"] = list(DEFAULT_LISTEN)
    if args.connect:
        fields["connect"] = list(args.connect)
    if args.multicast_scouting:
        fields["multicast_scouting"] = True
    return ZenohSettings(**fields)


def run(args: argparse.Namespace) -> int:
    """Run the router until a signal; exit code 0 on a graceful stop."""
    try:
        configure_logging(args.log_level, "router")
        settings = settings_from_args(args)
    except ValueError as exc:
        sys.stderr.write(f"crosspath router: config error: {exc}\n")
        return 2
    return run_service(RouterService(settings, args.metrics_port, args.metrics_host))


def main(argv: list[str] | None = None) -> int:
    """``python -m services.daemons.router``: the same command without the full CLI."""
    parser = argparse.ArgumentParser(prog="crosspath router", description=__doc__)
    configure(parser)
    return run(parser.parse_args(argv))


if __name__ == "__main__":
    sys.exit(main())
