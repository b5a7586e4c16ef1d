"""A simulated car body: longitudinal kinematics along its route, and its ground truth.

Both harnesses use it: the in-process simulation steps every car's body; a
vehicle daemon steps its own body and publishes the ground truth for the
monitor and for the other cars' simulated sensors.

Insertion (in-process harness): a car that has arrived enters its route's start only
when the entry is clear (:func:`entry_clear`), else it waits outside the network; a car
standing at its goal (:func:`at_goal`) leaves the world.
"""

from __future__ import annotations

import math
from collections.abc import Iterable
from dataclasses import dataclass, field

from services.model.geometry import Polyline, convex_overlap
from services.model.kinematics import BodyState, Limits, TruthState, step
from services.model.limits import RUN_END_BELOW_MPS
from services.model.scenario import LANE_MATCH_HEADING_RAD, LANE_MATCH_LATERAL_M, Scenario

INSERT_GAP_M = 2.5
"""Bumper-to-bumper gap [m] an entering car (at rest) needs to a car in its lane; plus
``headway_s`` x that car's speed when it is ahead, plus its stopping distance at
``decel_comfort`` when it is behind and coming on."""


@dataclass(slots=True)
class CarBody:
    """One car's physical state; ``step`` at the physics rate."""

    vehicle_id: str
    route: Polyline
    limits: Limits
    length: float
    width: float
    start_time: float
    state: BodyState
    started: bool = field(default=False)

    @classmethod
    def from_scenario(cls, scenario: Scenario, vehicle_id: str, start_time: float) -> CarBody:
        spec = scenario.vehicle(vehicle_id)
        return cls(
            vehicle_id=vehicle_id,
            route=scenario.route(spec.route),
            limits=scenario.limits(vehicle_id),
            length=spec.length_m,
            width=spec.width_m,
            start_time=start_time,
            state=BodyState(s=spec.start_offset_m, v=0.0, a=0.0),
        )

    def step(self, now: float, dt: float, a_cmd: float) -> None:
        """Advance by ``dt`` [s]; a car not yet started stays at rest."""
        if not self.started:
            if now + 1e-9 < self.start_time:
                return
            self.started = True
        self.state = step(self.state, a_cmd, dt, self.limits)

    def truth(self, now: float) -> TruthState:
        s = min(self.state.s, self.route.length)
        x, y = self.route.point_at(s)
        return TruthState(
            id=self.vehicle_id,
            t=now,
            x=x,
            y=y,
            heading=self.route.heading_at(s),
            speed=self.state.v,
            accel=self.state.a,
            s=s,
            length=self.length,
            width=self.width,
        )


def all_at_goal(scenario: Scenario, truths: Iterable[TruthState]) -> bool:
    """Does every car stand at its goal? Ends a run, in either harness."""
    return all(at_goal(scenario, t) for t in truths)


def at_goal(scenario: Scenario, truth: TruthState) -> bool:
    """Does this car stand at its goal? It then leaves the world (in-process harness)."""
    tol = scenario.params.goal_tolerance_m
    return truth.s >= scenario.goal_m(truth.id) - tol and truth.speed <= RUN_END_BELOW_MPS


def entry_clear(
    entry: TruthState, present: Iterable[TruthState], headway_s: float, decel_mps2: float
) -> bool:
    """May a car enter at rest at ``entry`` (its pose at its route's start)?

    Cars in its lane (heading within 45°, centre within 2.5 m of the entry's centre
    line, as ``Scenario.lane_of`` matches lanes) must leave :data:`INSERT_GAP_M` plus a
    speed-dependent gap between bumpers: ``headway_s`` x speed for a car ahead, the
    headway plus its stopping distance at ``decel_mps2`` for one behind. Any other car
    only must not overlap the entry footprint (an opposing lane 3.5 m away does not
    block). Pure; units m, s, m/s.
    """
    ch, sh = math.cos(entry.heading), math.sin(entry.heading)
    fp = None
    # Footprints are rectangles centred on (x, y): two whose circumscribed circles are
    # apart cannot overlap, so the exact test runs only for cars close to the entry
    # (issue 14: the exact test on every pair was half of a 200-car run).
    reach = 0.5 * math.hypot(entry.length, entry.width) + 1e-6
    for o in present:
        ox, oy = o.x - entry.x, o.y - entry.y
        dx = ox * ch + oy * sh
        dy = -ox * sh + oy * ch
        same_lane = (
            abs(math.remainder(o.heading - entry.heading, math.tau)) <= LANE_MATCH_HEADING_RAD
            and abs(dy) <= LANE_MATCH_LATERAL_M
        )
        if not same_lane:
            if math.hypot(ox, oy) > reach + 0.5 * math.hypot(o.length, o.width):
                continue
            if fp is None:
                fp = entry.footprint()
            if convex_overlap(fp, o.footprint()):
                return False
            continue
        gap = abs(dx) - 0.5 * (entry.length + o.length)
        need = INSERT_GAP_M + headway_s * o.speed
        if dx < 0.0:
            need += o.speed * o.speed / (2.0 * decel_mps2)
        if gap < need:
            return False
    return True
