"""The RSU core's configuration: one frozen object per RSU (aioquic's ``QuicConfiguration``).

Built from a scenario by :func:`rsu_config`; the daemon and the in-process harness
both use it, so an RSU behaves the same in either.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

from protocol import Kind, max_points
from services.model.scenario import Scenario
from services.model.types import Policy
from services.rsu import paths

__all__ = ["RsuConfig", "rsu_config"]

FloatArray = npt.NDArray[np.float64]


@dataclass(frozen=True, slots=True, eq=False)
class RsuConfig:
    """One RSU: where it is, what it coordinates, and the paper's parameters.

    ``center`` is the centre of coverage [m] (the beacon's position);
    ``conflict_zone`` the convex intersection box (K, 2) [m] whose centroid is
    the intersection centre used for "leaving". Times [s], speeds [m/s],
    accelerations [m/s²]. The fields after ``beacon_period_s`` tune the
    ``slot`` policy and the stop holds (see ``services.rsu.velocity``).
    """

    rsu_id: str
    intersection: str
    center: tuple[float, float]
    conflict_zone: FloatArray
    coverage_m: float = 150.0
    d_margin_m: float = 2.8
    headway_s: float = 1.0
    t_collision_s: float = 5.0
    t_free_s: float = 10.0
    expiry_s: float = 0.5
    v_max_mps: float = 50 / 3.6
    accel_mps2: float = 1.5
    decel_comfort_mps2: float = 2.0
    policy: Policy = Policy.PAPER
    command_repeat_s: float = 0.1
    beacon_period_s: float = 1.0
    stop_gap_m: float = 2.0  # slot: front bumper to zone edge when it must stop and wait
    slot_step_s: float = 0.1  # slot: granularity of the entry-time search
    slot_min_speed_mps: float = 2.0  # slot: below this, stop and wait rather than crawl
    hold_step_s: float = 0.5  # spacing of the points holding a stop (< 2 * headway)
    release_margin_m: float = 0.6  # hysteresis: "free" and releases need this much more room
    release_margin_s: float = 0.2  # ... and this much more headway (see services.rsu.modes)
    max_points: int | None = None  # cap on coordinated path points (the codec's limit), or none

    def __post_init__(self) -> None:
        if not self.rsu_id or not self.intersection:
            raise ValueError("rsu_id and intersection must be non-empty")
        center = (float(self.center[0]), float(self.center[1]))
        if not all(math.isfinite(c) for c in center):
            raise ValueError("center must be finite")
        object.__setattr__(self, "center", center)
        object.__setattr__(self, "conflict_zone", paths.convex_polygon(self.conflict_zone))
        object.__setattr__(self, "policy", Policy(self.policy))
        for name in (
            "coverage_m",
            "d_margin_m",
            "headway_s",
            "t_collision_s",
            "t_free_s",
            "expiry_s",
            "v_max_mps",
            "accel_mps2",
            "decel_comfort_mps2",
            "command_repeat_s",
            "beacon_period_s",
            "slot_step_s",
            "slot_min_speed_mps",
            "hold_step_s",
        ):
            value = getattr(self, name)
            if not (isinstance(value, int | float) and math.isfinite(value) and value > 0):
                raise ValueError(f"RsuConfig.{name} must be positive and finite, got {value!r}")
        for name in ("stop_gap_m", "release_margin_m", "release_margin_s"):
            value = getattr(self, name)
            if not (isinstance(value, int | float) and math.isfinite(value) and value >= 0):
                raise ValueError(f"RsuConfig.{name} must be finite and >= 0, got {value!r}")
        if self.max_points is not None and self.max_points < 2:
            raise ValueError("RsuConfig.max_points must be at least 2")
        if self.t_collision_s > self.t_free_s:
            raise ValueError("t_collision_s must not exceed t_free_s")
        if self.slot_min_speed_mps >= self.v_max_mps:
            raise ValueError("slot_min_speed_mps must be below v_max_mps")


def rsu_config(scenario: Scenario, rsu_id: str, policy: Policy) -> RsuConfig:
    """The RSU core's configuration from the scenario (the daemon and the harness)."""
    p = scenario.params
    spec = scenario.rsu(rsu_id)
    inter = scenario.intersection(spec.intersection)
    return RsuConfig(
        rsu_id=spec.id,
        intersection=inter.id,
        center=(float(inter.center[0]), float(inter.center[1])),
        conflict_zone=np.array(scenario.zone_polygon(inter.id), dtype=np.float64),
        coverage_m=spec.coverage_m,
        d_margin_m=p.d_margin_m,
        headway_s=p.headway_s,
        t_collision_s=p.t_collision_s,
        t_free_s=p.t_free_s,
        expiry_s=p.reservation_expiry_s,
        v_max_mps=p.v_max_mps,
        accel_mps2=p.accel_mps2,
        decel_comfort_mps2=p.decel_comfort_mps2,
        policy=policy,
        # a coordinated path must fit one datagram: thin it to what the codec guarantees
        max_points=max_points(Kind.COORDINATED_PATH),
    )
