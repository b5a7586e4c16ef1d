"""A simulated car body: longitudinal kinematics along its route, and its ground truth.

Both harnesses use it: the in-process simulation steps every car's body; a
vehicle daemon steps its own body and publishes the ground truth for the
monitor and for the other cars' simulated sensors.
"""

from __future__ import annotations

from collections.abc import Iterable
from dataclasses import dataclass, field

from services.model.geometry import Polyline
from services.model.kinematics import BodyState, Limits, TruthState, step
from services.model.limits import RUN_END_BELOW_MPS
from services.model.scenario import Scenario


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
    tol = scenario.params.goal_tolerance_m
    return all(t.s >= scenario.goal_m(t.id) - tol and t.speed <= RUN_END_BELOW_MPS for t in truths)
