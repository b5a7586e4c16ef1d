"""``crosspath vehicle --ids A,B,C``: several cars in one OS process, each its own Zenoh node.

A run with many cars does not need one Python process per car: a host runs one
:class:`~services.daemons.vehicle.VehicleDaemon` per car in one asyncio loop. Each
car keeps everything that makes it a node of its own: its own Zenoh session (own
listen endpoints, own links, own liveliness token ``sim/alive/{car}``), its own
V2X subscriptions and publications, its own stats and final report, its own run
clock ticks. What the cars of a host share is the simulated world only (not V2X):
the ground-truth plumbing (``sim/truth/*``) is subscribed once per process, by the
host's first car, into one :class:`~services.daemons.world.TruthBoard` that every
car of the host reads, so each report is received and decoded once per process
instead of once per car.

Endpoints (the convention of ``crosspath up``, :func:`host_configs`): the host's
``--listen`` endpoints are split evenly among its cars in order (``crosspath up``
gives two per car, one UDP and one TCP); every car connects to the host's
``--connect`` endpoints and to the endpoints of the cars before it in the host, so
the nodes keep the full mesh of ``crosspath up`` (node ``i`` connects to nodes
``0..i-1``). With ``metrics_port`` P, car ``k`` of the host serves its Prometheus
metrics on port P + k (``services.edge.metrics``).

Failure: a bug in one car's handler stops the whole host (exit 1, as a single car
daemon would): the host's cars are one process to the supervisor. The host logs to
one stream, every line naming the host (``<first car>+<n>``); each car's own lines
name it in the text. Decision: a crash of the host loses all its cars at once,
which the monitor sees as that many lost liveliness tokens.
"""

from __future__ import annotations

import argparse
import asyncio
import contextlib
from collections.abc import Callable, Sequence
from typing import Protocol, TypeVar

from protocol import keys
from services.daemons.world import TruthBoard
from services.edge.settings import CommonDaemonConfig, ConfigError, exit_on_config_error
from services.edge.shell import DaemonShell, run_daemon, wait_any
from services.model.scenario import Scenario

__all__ = ["CarHost", "HostedCar", "host_configs", "parse_ids", "serve_cars"]

C = TypeVar("C", bound=CommonDaemonConfig)


class HostedCar(Protocol):
    """What a host needs of a car daemon (``VehicleDaemon``)."""

    world: TruthBoard
    world_owner: bool
    shell: DaemonShell

    async def startup(self) -> None: ...

    async def run(self, stop: asyncio.Event) -> None: ...

    async def shutdown(self) -> None: ...


def parse_ids(text: str) -> list[str]:
    """``A,B,C`` as distinct node ids; ``ValueError`` naming the problem."""
    ids = [part.strip() for part in text.split(",") if part.strip()]
    if not ids:
        raise ValueError("--ids needs at least one vehicle id")
    for vid in ids:
        keys.validate_id(vid, "vehicle id")
    if len(set(ids)) != len(ids):
        raise ValueError(f"--ids names a car twice: {text}")
    return ids


def host_configs(config: C, ids: Sequence[str]) -> list[C]:
    """One config per car of a host from the host's ``config`` (see the module docstring
    for how the endpoints are shared out). Raises ``ConfigError`` when the listen
    endpoints do not split evenly among the cars."""
    listen = list(config.zenoh.listen)
    if len(listen) % len(ids):
        problem = f"{len(listen)} listen endpoints do not split evenly among {len(ids)} cars"
        raise ConfigError([("zenoh.listen", problem)])
    per = len(listen) // len(ids)
    out: list[C] = []
    for k, vid in enumerate(ids):
        own = listen[k * per : (k + 1) * per]
        connect = list(config.zenoh.connect) + listen[: k * per]
        zenoh = config.zenoh.model_copy(update={"listen": own, "connect": connect})
        # each car its own metrics endpoint: metrics_port + k (0 stays 0: any free port)
        port = config.metrics_port
        metrics = port + k if port else port
        update = {"node_id": vid, "zenoh": zenoh, "metrics_port": metrics}
        out.append(config.model_copy(update=update))
    return out


class CarHost:
    """The cars of one process as one service (``services.edge.lifecycle``)."""

    def __init__(self, cars: Sequence[HostedCar]) -> None:
        if not cars:
            raise ValueError("a host needs at least one car")
        self.cars = list(cars)
        self.world = TruthBoard()
        for k, car in enumerate(self.cars):
            car.world = self.world
            car.world_owner = k == 0
        # One cache of checked certificates per host (same root): a car inserted late
        # verifies the others' digest-signed datagrams at once, instead of refusing them
        # as ``unknown_key`` until each sender's next certificate (about 1 s).
        stores = [car.shell.trust for car in self.cars if car.shell.trust is not None]
        for store in stores[1:]:
            if store.root == stores[0].root:
                store.share_certificates(stores[0])

    async def startup(self) -> None:
        """Open the cars' sessions one after another, in order: car ``k`` connects to cars
        ``0..k-1``, which then listen already (opened all at once, a token was seen
        never to reach the monitor of a 40-car run)."""
        for car in self.cars:
            await car.startup()

    async def run(self, stop: asyncio.Event) -> None:
        """Run every car until ``stop`` or until one car's handler failed (then all stop
        and that car's ``ServiceExit`` ends the host)."""
        halt = asyncio.Event()

        async def watch() -> None:
            await wait_any(stop, *(car.shell.faulted for car in self.cars))
            halt.set()

        watcher = asyncio.ensure_future(watch())
        try:
            results = await asyncio.gather(
                *(car.run(halt) for car in self.cars), return_exceptions=True
            )
        finally:
            watcher.cancel()
            with contextlib.suppress(asyncio.CancelledError):
                await watcher
        for result in results:
            if isinstance(result, BaseException):
                raise result

    async def shutdown(self) -> None:
        """Close every car, one after another (each tolerates a partial startup; a Zenoh
        session takes about 0.3 s to close: ``crosspath up`` gives a host a longer grace
        period after SIGTERM)."""
        for car in self.cars:
            await car.shutdown()


def serve_cars(
    command: str,
    load: Callable[[argparse.Namespace], tuple[C, Scenario]],
    build: Callable[[C, Scenario], HostedCar],
    args: argparse.Namespace,
) -> int:
    """Run the cars ``args.ids`` names in this process (``crosspath vehicle --ids``); the
    exit status (2 on a configuration error)."""
    try:
        try:
            ids = parse_ids(str(args.ids))
        except ValueError as exc:
            raise ConfigError([("ids", str(exc))]) from None
        args.node_id = ids[0]
        config, scenario = load(args)
        cars = [build(cfg, scenario) for cfg in host_configs(config, ids)]
    except ConfigError as exc:
        return exit_on_config_error(command, exc)
    label = ids[0] if len(ids) == 1 else f"{ids[0]}+{len(ids) - 1}"
    return run_daemon(config.model_copy(update={"node_id": label}), CarHost(cars))
