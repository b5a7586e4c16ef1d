"""The simulated world as a car daemon sees it: other cars' ground truth, and who may enter.

The ground truth travels on the reliable plumbing (``{prefix}/sim/truth/{car}``), not
V2X: it stands for the world's physics and the cars' sensors. :class:`TruthBoard`
keeps each other car's latest report of a run; one board serves every car of a
process (``services.daemons.host`` subscribes the world once per process and shares
it, which saves the decoding of every report once per hosted car).

Insertion (issue 12, as the in-process harness ``services.sim.harness``): a car that
has arrived (its start time) enters at its route's start once the entry is clear
(``services.sim.car.entry_clear`` against the truth of the cars in the world, advanced
to now) and every car that arrived before it at the same entry has entered: cars
enter an entry in arrival order. Decision: the order rule replaces the harness's
one-loop insertion (where a car inserted in this very step is already in the list
the next one checks against); across processes, a car does not see another's
insertion before its first report arrives, so without it two cars arriving together
could both enter on the same spot.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field

from services.edge.plumbing import TruthReport
from services.model.kinematics import TruthState
from services.model.scenario import Scenario

__all__ = ["TruthBoard", "entry_predecessors"]

ENTRY_ROUND_M = 0.5
"""Entries closer than about this [m] (with the same heading) are the same entry."""


@dataclass(slots=True)
class TruthBoard:
    """Per car, its latest ``in`` report of the current run; who entered; who left."""

    run_id: str | None = None
    latest: dict[str, TruthReport] = field(default_factory=dict)
    entered: set[str] = field(default_factory=set)
    """Cars seen in the world (an ``in`` or ``left`` report) this run."""
    gone: set[str] = field(default_factory=set)
    """Cars that left the world at their goal this run (not sensed any more)."""
    _at: float | None = None
    _states: dict[str, TruthState] = field(default_factory=dict)

    def states_at(
        self, now: float, advance: Callable[[TruthState, float], TruthState]
    ) -> dict[str, TruthState]:
        """Every car's latest truth advanced to run time ``now`` by ``advance``, by car id:
        computed once per instant for all the cars of a host (they sense at the same run
        times), again when a report arrived since. Do not modify the result."""
        if self._at != now:
            self._states = {vid: advance(r.state, now) for vid, r in self.latest.items()}
            self._at = now
        return self._states

    def reset(self, run_id: str) -> None:
        """Forget an earlier run (a no-op when the board already follows ``run_id``: the
        cars of one process share it and each resets it at its episode's start)."""
        if self.run_id != run_id:
            self.run_id = run_id
            self.latest.clear()
            self.entered.clear()
            self.gone.clear()
            self._at = None

    def take(self, report: TruthReport) -> None:
        """One car's report of the current run (validated by the shell)."""
        if report.run_id != self.run_id:
            return
        vid = report.vehicle
        if report.presence == "waiting" or vid in self.gone:
            return
        self.entered.add(vid)
        self._at = None
        if report.presence == "left":
            self.gone.add(vid)
            self.latest.pop(vid, None)
            return
        prev = self.latest.get(vid)
        if prev is None or report.step > prev.step:
            self.latest[vid] = report


def entry_predecessors(
    scenario: Scenario, vehicle_id: str, start_times: Mapping[str, float]
) -> list[str]:
    """The cars that enter at ``vehicle_id``'s entry (its route's start, same place and
    heading) before it: earlier start time, or the same and earlier in the scenario."""
    order = {v.id: k for k, v in enumerate(scenario.vehicles)}

    def entry(vid: str) -> tuple[float, float, float]:
        spec = scenario.vehicle(vid)
        route = scenario.route(spec.route)
        x, y = route.point_at(spec.start_offset_m)
        h = route.heading_at(spec.start_offset_m)
        q = ENTRY_ROUND_M
        return (round(x / q) * q, round(y / q) * q, round(math.degrees(h) / 10.0) % 36)

    mine = entry(vehicle_id)
    key = (start_times[vehicle_id], order[vehicle_id])
    return [
        v.id
        for v in scenario.vehicles
        if v.id != vehicle_id
        and v.id in start_times
        and (start_times[v.id], order[v.id]) < key
        and entry(v.id) == mine
    ]
