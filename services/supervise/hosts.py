"""How ``crosspath up`` puts cars into OS processes: one per car, or several per host.

A car daemon is a Zenoh node whatever process it runs in; a host process
(``crosspath vehicle --ids A,B,C``, ``services.daemons.host``) runs several, each with
its own session and id, and shares the simulated world's truth among them. Decision
(README, "Many cars"; one process per car was not measured at 40 cars): up to
:data:`ONE_PER_PROCESS_UP_TO` cars keep one process each (the paper scenario's
behaviour); more cars are spread over about :data:`PROCESSES_PER_CPU` host processes
per CPU, so a 40-car run on 2 cores runs 4 hosts of 10 cars: 40 Python processes
would spend the machine on interpreters and context switches.
"""

from __future__ import annotations

import contextlib
import math
import os
import random
import socket
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Final

__all__ = [
    "EPHEMERAL_RANGE",
    "ONE_PER_PROCESS_UP_TO",
    "PROCESSES_PER_CPU",
    "bind_listen_port",
    "default_cars_per_process",
    "group_cars",
    "host_name",
]

ONE_PER_PROCESS_UP_TO: Final = 4
"""Scenarios with at most this many cars run one process per car by default."""

PROCESSES_PER_CPU: Final = 2
"""Host processes per CPU for larger scenarios (by default)."""


def default_cars_per_process(n_cars: int, cpus: int | None = None) -> int:
    """Cars per process when ``--cars-per-process`` is not given (module docstring)."""
    if n_cars <= ONE_PER_PROCESS_UP_TO:
        return 1
    n_cpu = max(1, cpus if cpus is not None else (os.cpu_count() or 1))
    return max(1, math.ceil(n_cars / (PROCESSES_PER_CPU * n_cpu)))


def host_name(index: int) -> str:
    """The launcher's name of host process ``index`` (its log is ``<name>.log``); the dot
    keeps it apart from every scenario id."""
    return f"host.{index}"


def _values(argv: Sequence[str], flag: str) -> list[str]:
    return [argv[i + 1] for i, arg in enumerate(argv[:-1]) if arg == flag]


def group_cars(
    commands: Mapping[str, list[str]], cars: Sequence[str], per_process: int
) -> dict[str, list[str]]:
    """The launcher's commands (node -> argv, in start order, one ``vehicle --id X`` per car)
    with the cars put ``per_process`` to a host: each group's command is its first car's,
    with ``--ids`` naming the group and the others' ``--listen`` endpoints added after
    its own (``services.daemons.host`` shares them out in that order). A group of one
    keeps the car's own command and name. Other nodes pass through unchanged."""
    if per_process < 1:
        raise ValueError(f"cars per process must be >= 1, got {per_process}")
    chunks = [list(cars[i : i + per_process]) for i in range(0, len(cars), per_process)]
    group_of = {car: k for k, chunk in enumerate(chunks) for car in chunk}
    out: dict[str, list[str]] = {}
    for node, argv in commands.items():
        k = group_of.get(node)
        if k is None or len(chunks[k]) == 1:
            out[node] = list(argv)
            continue
        chunk = chunks[k]
        if node != chunk[0]:
            continue
        host = list(argv)
        i = host.index("--id")
        host[i : i + 2] = ["--ids", ",".join(chunk)]
        last = max(j for j, arg in enumerate(host) if arg == "--listen") + 2
        extra: list[str] = []
        for other in chunk[1:]:
            for locator in _values(commands[other], "--listen"):
                extra += ["--listen", locator]
        host[last:last] = extra
        out[host_name(k)] = host
    return out


EPHEMERAL_RANGE: Final = Path("/proc/sys/net/ipv4/ip_local_port_range")
"""Linux's range of ephemeral ports (outgoing sockets are bound in it)."""

LISTEN_PORTS_FROM: Final = 10000
"""Lowest port :func:`bind_listen_port` picks below the ephemeral range."""


def bind_listen_port(sock: socket.socket, host: str, attempts: int = 200) -> None:
    """Bind ``sock`` to a free port of ``host`` outside the ephemeral range when there is
    room below it (Linux), else to any free port.

    Why: every Zenoh session connects to every earlier node, and each outgoing UDP link
    binds an ephemeral port; with 40 cars that is over a thousand of them, and a listen
    port picked from the same range before the daemons start was seen taken by one
    before its daemon could listen (``Address already in use``)."""
    low: int | None = None
    with contextlib.suppress(OSError, ValueError):
        low = int(EPHEMERAL_RANGE.read_text().split()[0])
    if low is not None and low > LISTEN_PORTS_FROM + attempts:
        rng = random.Random()
        for _ in range(attempts):
            try:
                sock.bind((host, rng.randrange(LISTEN_PORTS_FROM, low)))
            except OSError:
                continue
            return
    sock.bind((host, 0))
