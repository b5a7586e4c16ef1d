"""Longitudinal car dynamics along a route (the paper controls speed only).

A car's body state is its arc length ``s`` along its route (m, of the car's
centre), its speed ``v`` (m/s, never negative: cars do not reverse) and its actual
acceleration ``a`` (m/s²). The commanded acceleration reaches the wheels through a
first-order lag (time constant ``actuator_lag_s``), integrated exactly over a step,
so the result does not depend on the physics rate beyond the command's sampling.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from services.model.geometry import FloatArray, Polyline, footprint, vertex_curvature
from services.model.limits import SPEED_CAP_FACTOR, STANDING_MPS

__all__ = ["BodyState", "Limits", "TruthState", "curve_speed_cap", "step"]


@dataclass(frozen=True, slots=True)
class Limits:
    """Dynamic limits of one car: m/s, m/s², s. Decelerations are positive numbers;
    ``lat_accel`` is the lateral acceleration allowed in curves [m/s²]."""

    v_max: float
    accel: float
    decel_comfort: float
    decel_emergency: float
    actuator_lag_s: float
    lat_accel: float = 2.0

    def __post_init__(self) -> None:
        for name in ("v_max", "accel", "decel_comfort", "decel_emergency", "lat_accel"):
            val = getattr(self, name)
            if not (math.isfinite(val) and val > 0.0):
                raise ValueError(f"Limits.{name} must be finite and > 0, got {val!r}")
        if not (math.isfinite(self.actuator_lag_s) and self.actuator_lag_s >= 0.0):
            raise ValueError(f"Limits.actuator_lag_s must be >= 0, got {self.actuator_lag_s!r}")
        if self.decel_emergency < self.decel_comfort:
            raise ValueError("Limits.decel_emergency must be >= decel_comfort")


@dataclass(frozen=True, slots=True)
class BodyState:
    """Longitudinal state: arc length s (m, car centre), speed v (m/s >= 0), actual
    acceleration a (m/s²)."""

    s: float
    v: float
    a: float = 0.0


@dataclass(frozen=True, slots=True)
class TruthState:
    """Ground truth of one car at time ``t`` (s, run time base).

    ``x, y`` is the car's centre (m), ``heading`` radians CCW from east, ``speed``
    m/s, ``accel`` m/s², ``s`` arc length of the centre along its route (m),
    ``length``/``width`` its rectangle (m). Sensors and metrics consume this.
    """

    id: str
    t: float
    x: float
    y: float
    heading: float
    speed: float
    accel: float
    s: float
    length: float
    width: float

    def footprint(self) -> FloatArray:
        """Corners (4, 2) of the car's rectangle, see ``geometry.footprint``."""
        return footprint(self.x, self.y, self.heading, self.length, self.width)


def _advance(
    s: float, v: float, a: float, a_cmd: float, tau: float, dt: float
) -> tuple[float, float, float]:
    """Exact solution of s' = v, v' = a, a' = (a_cmd - a)/tau over ``dt`` (no v >= 0 clamp)."""
    if tau <= 0.0:
        return s + v * dt + 0.5 * a_cmd * dt * dt, v + a_cmd * dt, a_cmd
    e = math.exp(-dt / tau)
    da = a - a_cmd
    a1 = a_cmd + da * e
    v1 = v + a_cmd * dt + da * tau * (1.0 - e)
    s1 = s + v * dt + 0.5 * a_cmd * dt * dt + da * tau * (dt - tau * (1.0 - e))
    return s1, v1, a1


def step(state: BodyState, a_cmd: float, dt: float, limits: Limits) -> BodyState:
    """Advance one physics step of ``dt`` seconds under commanded acceleration ``a_cmd``.

    The command is clipped to [-decel_emergency, accel] and filtered by the actuator
    lag. When the speed reaches zero while braking the car stops there and holds
    (speed 0, acceleration reset to 0); if the command is positive it pulls away again
    for the rest of the step. The speed is hard-capped at ``v_max * 1.05``.
    """
    if not (math.isfinite(dt) and dt > 0.0):
        raise ValueError(f"step: dt must be finite and > 0, got {dt!r}")
    if not math.isfinite(a_cmd):
        raise ValueError(f"step: a_cmd must be finite, got {a_cmd!r}")
    if not (math.isfinite(state.s) and math.isfinite(state.v) and math.isfinite(state.a)):
        raise ValueError(f"step: state must be finite, got {state!r}")
    cmd = min(max(a_cmd, -limits.decel_emergency), limits.accel)
    tau = limits.actuator_lag_s
    s, v, a = state.s, max(state.v, 0.0), state.a
    if v <= STANDING_MPS:
        v = 0.0
        a = max(a, 0.0)  # brakes hold a standing car: no negative acceleration at rest
        if cmd <= 0.0 and a <= 0.0:
            return BodyState(s, 0.0, 0.0)
    s1, v1, a1 = _advance(s, v, a, cmd, tau, dt)
    if v1 < 0.0:
        # Find when the speed crosses zero. With a monotone a(t) the crossing is unique.
        lo, hi = 0.0, dt
        for _ in range(60):
            mid = 0.5 * (lo + hi)
            if _advance(s, v, a, cmd, tau, mid)[1] > 0.0:
                lo = mid
            else:
                hi = mid
        t_stop = hi
        s_stop = max(s, _advance(s, v, a, cmd, tau, t_stop)[0])
        rest = dt - t_stop
        if cmd > 0.0 and rest > 0.0:
            s1, v1, a1 = _advance(s_stop, 0.0, 0.0, cmd, tau, rest)
            v1 = max(v1, 0.0)
        else:
            s1, v1, a1 = s_stop, 0.0, 0.0
    cap = limits.v_max * SPEED_CAP_FACTOR
    if v1 > cap:
        s1 = s + 0.5 * (v + cap) * dt
        v1 = cap
        a1 = min(a1, 0.0)
    return BodyState(s1, v1, a1)


def curve_speed_cap(
    line: Polyline, s: FloatArray, lat_accel: float, v_max: float, pad_m: float = 0.0
) -> FloatArray:
    """Speed cap [m/s] at arc lengths ``s`` [m] of ``line`` from its curvature:
    ``min(v_max, sqrt(lat_accel / kappa))``, i.e. lateral acceleration ≤ ``lat_accel``.

    Each vertex's curvature (``geometry.vertex_curvature``) holds over the span
    on either side of it (at most ``geometry.KINK_SPAN_M``), widened by
    ``pad_m`` on both sides: a sampled profile that interpolates between grid
    points ``pad_m`` apart then never exceeds the cap inside the curve. Pure; the
    vehicle planner and the RSU both use it, so a car's own plan and its
    coordinated path respect the same limit.
    """
    if not (math.isfinite(lat_accel) and lat_accel > 0.0):
        raise ValueError(f"curve_speed_cap: lat_accel must be finite and > 0, got {lat_accel!r}")
    if not (math.isfinite(v_max) and v_max > 0.0):
        raise ValueError(f"curve_speed_cap: v_max must be finite and > 0, got {v_max!r}")
    sa = np.asarray(s, dtype=np.float64)
    out: FloatArray = np.full(sa.shape, v_max, dtype=np.float64)
    sv, kappa, lo, hi = vertex_curvature(line)
    cap_v = np.sqrt(lat_accel / np.maximum(kappa, 1e-12))
    curved = np.flatnonzero(cap_v < v_max)
    if curved.size == 0 or sa.size == 0:
        return out
    s_lo = sv[curved] - lo[curved] - pad_m
    s_hi = sv[curved] + hi[curved] + pad_m
    # only vertices whose window meets the queried range
    near = (s_hi >= float(sa.min())) & (s_lo <= float(sa.max()))
    if not bool(np.any(near)):
        return out
    s_lo, s_hi, caps = s_lo[near], s_hi[near], cap_v[curved][near]
    inside = (sa.reshape(-1, 1) >= s_lo[None, :]) & (sa.reshape(-1, 1) <= s_hi[None, :])
    binding = np.where(inside, caps[None, :], np.inf).min(axis=1).reshape(sa.shape)
    out = np.minimum(out, binding)
    return out
