"""The RSU core's configuration: one frozen object per RSU (aioquic's ``QuicConfiguration``).

Built from a scenario by :func:`rsu_config`; the daemon and the in-process harness
both use it, so an RSU behaves the same in either. Every knob comes from the
scenario file, validated there (pydantic: ``[params]``, ``[rsu_params]`` and the
RSU's own ``[rsus.params]``, see ``scenarios/README.md``); ``RsuConfig`` stays a
plain frozen object so that the core knows nothing of pydantic, and its own checks
only guard against a caller's bug (a ``ValueError``).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

from protocol import Kind, max_points
from services.model.scenario import Params, RsuParams, Scenario
from services.model.types import Policy
from services.rsu import paths

__all__ = ["RsuConfig", "rsu_config"]

FloatArray = npt.NDArray[np.float64]

_PAPER = Params()
_KNOBS = RsuParams()
# RsuConfig's defaults are the scenario's (one owner): a core built by hand in a test or
# a benchmark behaves as one built from a scenario that leaves the knobs out.


@dataclass(frozen=True, slots=True, eq=False)
class RsuConfig:
    """One RSU: where it is, what it coordinates, and the paper's parameters.

    ``center`` is the centre of coverage [m] (the beacon's position);
    ``conflict_zone`` the convex intersection box (K, 2) [m] whose centroid is
    the intersection centre used for "leaving". Times [s], speeds [m/s],
    accelerations [m/s²]. The speed and acceleration limits are the defaults for a
    car whose paths declare none (each car is planned with its own, see
    ``services.rsu.velocity``). The fields after ``beacon_period_s`` tune the
    ``slot`` policy and the stop holds (see ``services.rsu.velocity``).
    """

    rsu_id: str
    intersection: str
    center: tuple[float, float]
    conflict_zone: FloatArray
    coverage_m: float = 150.0
    d_margin_m: float = _PAPER.d_margin_m
    headway_s: float = _PAPER.headway_s
    t_collision_s: float = _PAPER.t_collision_s
    t_free_s: float = _PAPER.t_free_s
    expiry_s: float = _PAPER.reservation_expiry_s
    v_max_mps: float = _PAPER.v_max_mps
    accel_mps2: float = _PAPER.accel_mps2
    decel_comfort_mps2: float = _PAPER.decel_comfort_mps2
    lat_accel_mps2: float = _PAPER.lat_accel_mps2
    policy: Policy = Policy.PAPER
    # the knobs of [rsu_params] (services.model.scenario.RsuParams documents each)
    command_repeat_s: float = _KNOBS.command_repeat_s
    beacon_period_s: float = _KNOBS.beacon_period_s
    stop_gap_m: float = _KNOBS.stop_gap_m
    slot_step_s: float = _KNOBS.slot_step_s
    slot_min_speed_mps: float = _KNOBS.slot_min_speed_mps
    hold_step_s: float = _KNOBS.hold_step_s
    release_margin_m: float = _KNOBS.release_margin_m
    release_margin_s: float = _KNOBS.release_margin_s
    max_points: int | None = None  # cap on coordinated path points (the codec's limit), or none
    # the coordinated path's send rule (services.model.send_rule): None sends one in answer
    # to every autonomous path (the paper); else the deviation [m] below which the last
    # one sent stands, and the longest it stands [s]
    cp_change_m: float | None = None
    cp_refresh_s: float = 0.5

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
            "lat_accel_mps2",
            "command_repeat_s",
            "beacon_period_s",
            "slot_step_s",
            "slot_min_speed_mps",
            "hold_step_s",
            "cp_refresh_s",
        ):
            value = getattr(self, name)
            if not (isinstance(value, int | float) and math.isfinite(value) and value > 0):
                raise ValueError(f"RsuConfig.{name} must be positive and finite, got {value!r}")
        for name in ("stop_gap_m", "release_margin_m", "release_margin_s"):
            value = getattr(self, name)
            if not (isinstance(value, int | float) and math.isfinite(value) and value >= 0):
                raise ValueError(f"RsuConfig.{name} must be finite and >= 0, got {value!r}")
        if self.cp_change_m is not None and not (
            math.isfinite(self.cp_change_m) and self.cp_change_m > 0
        ):
            raise ValueError(f"RsuConfig.cp_change_m must be positive, got {self.cp_change_m!r}")
        if self.max_points is not None and self.max_points < 2:
            raise ValueError("RsuConfig.max_points must be at least 2")
        if self.t_collision_s > self.t_free_s:
            raise ValueError("t_collision_s must not exceed t_free_s")
        if self.slot_min_speed_mps >= self.v_max_mps:
            raise ValueError("slot_min_speed_mps must be below v_max_mps")


def rsu_config(scenario: Scenario, rsu_id: str, policy: Policy) -> RsuConfig:
    """The RSU core's configuration from the scenario (the daemon and the harness):
    ``[params]``, then ``[rsu_params]`` with the RSU's own overrides."""
    p = scenario.params
    spec = scenario.rsu(rsu_id)
    knobs = scenario.rsu_params(rsu_id)
    vp = scenario.spec.vehicle_params
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
        # held longer when cars send their future path on change only (fp_rule)
        expiry_s=scenario.fp_hold_s(p.reservation_expiry_s),
        v_max_mps=p.v_max_mps,
        accel_mps2=p.accel_mps2,
        decel_comfort_mps2=p.decel_comfort_mps2,
        lat_accel_mps2=p.lat_accel_mps2,
        policy=policy,
        command_repeat_s=knobs.command_repeat_s,
        beacon_period_s=knobs.beacon_period_s,
        stop_gap_m=knobs.stop_gap_m,
        slot_step_s=knobs.slot_step_s,
        slot_min_speed_mps=knobs.slot_min_speed_mps,
        hold_step_s=knobs.hold_step_s,
        release_margin_m=knobs.release_margin_m,
        release_margin_s=knobs.release_margin_s,
        # a coordinated path must fit one datagram: thin it to what the codec guarantees
        max_points=max_points(Kind.COORDINATED_PATH),
        cp_change_m=None if vp.cp_rule == "periodic" else vp.fp_change_m,
        cp_refresh_s=vp.cp_refresh_s,
    )
