"""``cosimulate``: one co-simulation of a SUMO network and its demand, in-process
(``services.sumo.cosim``) or with the RSUs as daemons (``services.sumo.daemons``)."""

from __future__ import annotations

from pathlib import Path

from services.edge.provenance import origin as find_origin
from services.model.results import RunResult
from services.sumo.cosim import CosimOptions, Cosimulation
from services.sumo.daemons import DaemonsCosimulation

__all__ = ["cosimulate"]


def cosimulate(
    net: str | Path,
    routes: str | Path,
    options: CosimOptions | None = None,
) -> RunResult:
    """One co-simulation of the SUMO network ``net`` and demand ``routes``
    (``services.sumo.cosim``); the run result with its ``sumo`` section (its provenance
    hashes the network file). ``ValueError`` for a missing file or a network crosspath
    cannot read (``SumoNetError``); ``SumoNotFound`` without SUMO. With
    ``options.daemons`` the RSUs are daemons over Zenoh (``DaemonsError`` when one
    fails)."""
    net_path, routes_path = Path(net), Path(routes)
    o = options or CosimOptions()
    kind: type[Cosimulation] = DaemonsCosimulation if o.daemons else Cosimulation
    return kind(net_path, routes_path, o, origin=find_origin(net_path)).run()
