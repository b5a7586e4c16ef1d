"""Run SUMO on a network and demand; per-car delay measured as crosspath measures it.

crosspath's ``delay_s`` is a finished car's travel time beyond the free-flow travel time
of its route, plus its insertion wait (``services.model.results``). SUMO's tripinfo
gives ``timeLoss`` (time lost against driving at the ideal speed) and ``departDelay``
(the insertion wait). Both tools count the acceleration from rest differently from
their free-flow reference, so the SUMO delay of a car is

    delay = timeLoss + departDelay - free_timeLoss(route)

where ``free_timeLoss(route)`` is the ``timeLoss`` of one car driving the route alone on
the same geometry with an ``unregulated`` junction (:func:`free_time_loss`): travel
time beyond free flow plus the insertion wait, as crosspath's; clipped at 0.

A run goes through ``libsumo`` (in this process; one simulation at a time per
process) or, when it is missing, ``traci`` (SUMO as a child process). Step 0.1 s (the
planning step of crosspath), collisions checked on lanes and in the junction
(``collision.action warn``: the cars stay, each pair is counted once), teleporting off
(``time-to-teleport -1``: a jam shows as delay and unfinished cars, not as
vanished cars). The run stops when every car has arrived or at ``max_sim_s``.
"""

from __future__ import annotations

import importlib
import logging
import math
import time
import xml.etree.ElementTree as ET
from collections.abc import Mapping, Sequence
from dataclasses import asdict, dataclass, field
from pathlib import Path
from types import ModuleType
from typing import Any, Final

from services.sumo.netgen import (
    ROUTES,
    Control,
    SumoNotFound,
    VehicleTypeSpec,
    build_network,
    sumo_binary,
    write_routes,
)

__all__ = [
    "STEP_S",
    "SUMO_RUN_ARGS",
    "SumoRun",
    "free_time_loss",
    "run_sumo",
    "sumo_api",
]

log = logging.getLogger("crosspath.sumo")

STEP_S = 0.1
"""SUMO's step [s]."""


SUMO_RUN_ARGS: Final = (
    "--collision.action",
    "warn",
    "--collision.check-junctions",
    "true",
    "--time-to-teleport",
    "-1",
    "--no-step-log",
    "true",
    "--no-warnings",
    "true",
)
"""SUMO options of every run here (baseline and co-simulation): collisions counted, not
removed, on lanes and in junctions; no teleporting; quiet."""


def sumo_api() -> ModuleType:
    """``libsumo`` if installed, else ``traci``; :class:`SumoNotFound` if neither."""
    for name in ("libsumo", "traci"):
        try:
            return importlib.import_module(name)
        except ImportError:
            continue
    raise SumoNotFound("neither libsumo nor traci is installed: pip install 'crosspath[sumo]'")


@dataclass(frozen=True, slots=True)
class SumoRun:
    """One SUMO run's outcome.

    ``delays_s`` per finished car (see the module docstring) [s]; ``time_loss_s`` and
    ``depart_delay_s`` SUMO's own per finished car; ``loaded`` cars in the demand,
    ``inserted`` those SUMO inserted, ``finished`` those that arrived; ``collisions``
    distinct colliding pairs; ``sim_s`` the simulated time [s], ``wall_s`` the wall time.
    """

    control: str
    loaded: int
    inserted: int
    finished: int
    collisions: int
    sim_s: float
    wall_s: float
    delays_s: dict[str, float] = field(default_factory=dict)
    time_loss_s: dict[str, float] = field(default_factory=dict)
    depart_delay_s: dict[str, float] = field(default_factory=dict)

    @property
    def all_finished(self) -> bool:
        return self.finished == self.loaded

    @property
    def mean_delay_s(self) -> float | None:
        """Mean delay over the finished cars [s] (None if none finished)."""
        if not self.delays_s:
            return None
        return sum(self.delays_s.values()) / len(self.delays_s)

    def to_json(self) -> dict[str, Any]:
        doc = asdict(self)
        doc["all_finished"] = self.all_finished
        doc["mean_delay_s"] = self.mean_delay_s
        return doc


def _simulate(
    net: Path,
    routes: Path,
    tripinfo: Path,
    max_sim_s: float,
    label: str,
) -> tuple[int, int, float]:
    """Run SUMO to the end; (inserted, colliding pairs, simulated time [s])."""
    api = sumo_api()
    cmd = [
        str(sumo_binary("sumo")),
        "-n",
        str(net),
        "-r",
        str(routes),
        "--step-length",
        str(STEP_S),
        "--tripinfo-output",
        str(tripinfo),
        *SUMO_RUN_ARGS,
        "--seed",
        "0",
    ]
    if api.__name__ == "traci":
        api.start(cmd, label=label)
    else:
        api.start(cmd)
    pairs: set[tuple[str, str]] = set()
    inserted = 0
    try:
        now = 0.0
        while now < max_sim_s - 1e-9 and api.simulation.getMinExpectedNumber() > 0:
            api.simulationStep()
            now = float(api.simulation.getTime())
            inserted += int(api.simulation.getDepartedNumber())
            for c in api.simulation.getCollisions():
                pair = (str(c.collider), str(c.victim))
                pairs.add((min(pair), max(pair)))
    finally:
        api.close()
    return inserted, len(pairs), now


def _tripinfo(path: Path) -> dict[str, tuple[str, float, float]]:
    """vehicle id -> (route id, timeLoss [s], departDelay [s]) of the arrived cars."""
    out: dict[str, tuple[str, float, float]] = {}
    for el in ET.parse(path).getroot().iter("tripinfo"):
        vid = el.get("id", "")
        route = vid.rsplit("-", 1)[0]
        out[vid] = (route, float(el.get("timeLoss", "nan")), float(el.get("departDelay", "nan")))
    return out


def free_time_loss(
    workdir: Path, vtype: VehicleTypeSpec | None = None, routes: Sequence[str] = tuple(ROUTES)
) -> dict[str, float]:
    """Per route, the ``timeLoss`` [s] of one car driving it alone: unregulated junction
    (cars from different approaches ignore each other there), the routes of one approach
    40 s apart (no car ever follows another)."""
    net = build_network(workdir, Control.UNREGULATED)
    per_side: dict[str, int] = {}
    departures: dict[str, list[float]] = {}
    for r in routes:
        k = per_side.get(r[0], 0)
        per_side[r[0]] = k + 1
        departures[r] = [40.0 * k]
    rou = workdir / "free.rou.xml"
    write_routes(rou, departures, vtype)
    trip = workdir / "free.tripinfo.xml"
    _simulate(net, rou, trip, 40.0 * max(per_side.values()) + 120.0, "free")
    info = _tripinfo(trip)
    missing = [r for r in routes if f"{r}-0" not in info]
    if missing:
        raise RuntimeError(f"SUMO free-flow reference: no trip for route(s) {missing}")
    return {r: info[f"{r}-0"][1] for r in routes}


def run_sumo(
    workdir: Path,
    control: Control,
    departures: Mapping[str, Sequence[float]],
    max_sim_s: float,
    free_loss: Mapping[str, float],
    vtype: VehicleTypeSpec | None = None,
    tag: str = "run",
) -> SumoRun:
    """One SUMO run of ``departures`` (route -> departure times [s]) with ``control``.

    ``free_loss`` comes from :func:`free_time_loss`; ``workdir`` gets the network, the
    routes and the tripinfo (``<tag>.*``).
    """
    if not (math.isfinite(max_sim_s) and max_sim_s > 0):
        raise ValueError(f"max_sim_s must be > 0, got {max_sim_s!r}")
    t0 = time.perf_counter()
    net = build_network(workdir, control)
    rou = workdir / f"{tag}.rou.xml"
    loaded = write_routes(rou, departures, vtype)
    trip = workdir / f"{tag}.tripinfo.xml"
    inserted, collisions, sim_s = _simulate(net, rou, trip, max_sim_s, tag)
    delays: dict[str, float] = {}
    losses: dict[str, float] = {}
    waits: dict[str, float] = {}
    for vid, (route, loss, wait) in _tripinfo(trip).items():
        losses[vid], waits[vid] = loss, wait
        delays[vid] = round(max(0.0, loss + wait - free_loss[route]), 3)
    return SumoRun(
        control=control.value,
        loaded=loaded,
        inserted=inserted,
        finished=len(delays),
        collisions=collisions,
        sim_s=round(sim_s, 3),
        wall_s=round(time.perf_counter() - t0, 3),
        delays_s=delays,
        time_loss_s=losses,
        depart_delay_s=waits,
    )
