"""Speed profiles along the route: the forward/backward pass and eq. (1) of the paper.

A speed profile is a grid of arc lengths ``s`` [m] (uniform step ``ds``) with a
speed ``v`` [m/s] at each grid point. Constraints are expressed as speed caps
on the grid; the passes make the profile feasible under the acceleration and
deceleration limits (v² changes by at most 2·a·ds per step).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

FloatArray = npt.NDArray[np.float64]


@dataclass(frozen=True, slots=True)
class SpeedProfile:
    """A planned speed along the route, with pass times by eq. (1)."""

    s: FloatArray  # arc length along the route [m], increasing, uniform step
    v: FloatArray  # planned speed [m/s]
    t: FloatArray  # pass time [s, run time base]; inf past a stop

    def speed_at(self, s: float) -> float:
        """Planned speed at arc length ``s`` (linear interpolation, clamped)."""
        return float(np.interp(s, self.s, self.v))

    def stop_s(self) -> float | None:
        """Arc length where the profile comes to rest, or None if it never does."""
        idx = np.flatnonzero(~np.isfinite(self.t))
        if idx.size == 0:
            return None
        return float(self.s[max(int(idx[0]) - 1, 0)])


def grid(s0: float, s_end: float, ds: float) -> FloatArray:
    """Uniform arc-length grid from ``s0`` to at least ``s_end`` (two points minimum)."""
    n = max(int(np.ceil((s_end - s0) / ds)) + 1, 2)
    return s0 + ds * np.arange(n, dtype=np.float64)


def stop_cap(s: FloatArray, s_stop: float, decel: float) -> FloatArray:
    """Speed cap for stopping at ``s_stop`` braking at ``decel`` [m/s²]: √(2·a·d), 0 past it."""
    return np.sqrt(2.0 * decel * np.maximum(s_stop - s, 0.0))


def backward_pass(cap: FloatArray, ds: float, decel: float) -> FloatArray:
    """Lower the caps so that every later cap is reachable braking at ``decel``."""
    # v_i <= sqrt(v_{i+1}^2 + 2 a ds): in v² space, a running minimum of cap²_j + 2a·ds·(j-i)
    v2 = cap * cap
    n = v2.shape[0]
    offs = 2.0 * decel * ds * np.arange(n, dtype=np.float64)
    # min over j >= i of (v2_j + offs_j) - offs_i
    rev = np.minimum.accumulate((v2 + offs)[::-1])[::-1]
    out: FloatArray = np.sqrt(np.maximum(rev - offs, 0.0))
    return np.minimum(out, cap)


def forward_pass(cap: FloatArray, v0: float, ds: float, accel: float) -> FloatArray:
    """Raise speed from ``v0`` no faster than ``accel`` allows, never above the caps."""
    v2 = cap * cap
    n = v2.shape[0]
    offs = 2.0 * accel * ds * np.arange(n, dtype=np.float64)
    # v2_i <= min(v0² + offs_i, min_{j<=i}(v2_j - offs_j) + offs_i)
    start = v0 * v0
    run = np.minimum.accumulate(np.concatenate(([start], v2 - offs))[1:])
    run = np.minimum(run, start)
    out: FloatArray = np.sqrt(np.maximum(run + offs, 0.0))
    return np.minimum(out, cap)


def track_envelope(
    target: FloatArray, v0: float, ds: float, accel: float, decel: float
) -> FloatArray:
    """Speeds that follow ``target`` from ``v0`` within the limits (used for coordinated speeds).

    Unlike a cap, a target that drops below the current speed is reached by
    braking at ``decel`` (the car decelerates smoothly, as the paper says of
    the C_SLOW mode), not instantly.
    """
    out = np.empty_like(target)
    v = v0
    up = 2.0 * accel * ds
    down = 2.0 * decel * ds
    for i in range(target.shape[0]):
        tv2 = target[i] * target[i]
        v2 = v * v
        v2 = min(tv2, v2 + up) if tv2 > v2 else max(tv2, v2 - down)
        v = float(np.sqrt(max(v2, 0.0)))
        out[i] = v
    return out


def pass_times(s: FloatArray, v: FloatArray, t0: float) -> FloatArray:
    """Eq. (1) of the paper: t_n = t_0 + Σ (x_k − x_{k−1}) / v_k.

    Each step uses the mean speed of its two ends (exact for constant
    acceleration); a step whose both ends are at rest is never passed, so
    times become infinite from the first stop on.
    """
    ds = np.diff(s)
    vm = 0.5 * (v[1:] + v[:-1])
    with np.errstate(divide="ignore"):
        dt = np.where(vm > 1e-3, ds / np.maximum(vm, 1e-9), np.inf)
    t = np.empty_like(s)
    t[0] = t0
    t[1:] = t0 + np.cumsum(dt)
    return t


def earliest_arrival(distance: float, v0: float, accel: float, v_max: float) -> float:
    """Time [s] to cover ``distance`` accelerating from ``v0`` at ``accel`` up to ``v_max``."""
    if distance <= 0.0:
        return 0.0
    v0 = min(max(v0, 0.0), v_max)
    d_acc = (v_max * v_max - v0 * v0) / (2.0 * accel)
    if distance <= d_acc:
        return float((-v0 + np.sqrt(v0 * v0 + 2.0 * accel * distance)) / accel)
    return (v_max - v0) / accel + (distance - d_acc) / v_max
