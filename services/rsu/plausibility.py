"""Is a car's path physically plausible? A pure check the RSU runs before planning (issue 13).

A certified car key proves who sent a path, not that the path is true (a stolen
key, a buggy car). The RSU therefore refuses, and counts, paths no car of the
scenario could drive:

- ``implausible_speed``: current speed, or declared top speed, above the
  scenario's fastest car by more than the tolerance;
- ``implausible_path_speed`` / ``implausible_path_accel``: the path's points,
  sampled at least :data:`SAMPLE_S` apart (so 1 cm / 1 ms quantisation stays
  small), imply a speed or an acceleration beyond the tolerance;
- ``implausible_path_start``: the first point far from the current position;
- ``implausible_jump``: the car moved farther since its previous path than its
  top speed allows;
- ``implausible_zone_stop``: a car that claims to approach (a non-empty path) while
  standing inside a conflict zone it has not moved in for :data:`ZONE_STAND_S` —
  the parked ghost of the issue's table. (The RSU plans a car in the zone as
  occupying it; one standing there for seconds is blocking, not crossing.)

Tolerances (decisions): speed ``v_max * 1.2 + 1 m/s``; acceleration
``max(accel, decel_emergency) * 1.5 + 1 m/s²``; jumps and path start 2 m plus the
distance at the tolerated speed. Everything in metres, seconds, m/s, m/s².
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Final

import numpy as np

from protocol import VehiclePath
from protocol.messages import FloatArray
from services.model.geometry import polygon_contains
from services.model.scenario import Scenario, limits_from_params

__all__ = ["SAMPLE_S", "ZONE_STAND_S", "Bounds", "Seen", "check_path"]

SAMPLE_S: Final = 0.25
"""Least time between the path points compared [s]."""

ZONE_STAND_S: Final = 3.0
"""A car standing in a conflict zone this long while claiming a path is implausible [s]."""

_STANDING_MPS: Final = 0.2
_SLACK_M: Final = 2.0


@dataclass(frozen=True, slots=True)
class Bounds:
    """The most any car of the scenario may do, with the tolerances applied."""

    v_max: float
    """Tolerated speed [m/s]."""
    a_max: float
    """Tolerated acceleration or deceleration [m/s²]."""
    zones: tuple[FloatArray, ...] = ()
    """Conflict zone polygons, (K, 2) each [m]."""

    @classmethod
    def from_scenario(cls, scenario: Scenario) -> Bounds:
        """Bounds of the fastest car of ``scenario`` (its defaults if it lists none)."""
        limits = [scenario.limits(v.id) for v in scenario.vehicles]
        limits.append(limits_from_params(scenario.params))
        v = max(lim.v_max for lim in limits)
        a = max(max(lim.accel, lim.decel_emergency) for lim in limits)
        zones = tuple(scenario.zone_polygon(i.id) for i in scenario.intersections)
        return cls(v_max=v * 1.2 + 1.0, a_max=a * 1.5 + 1.0, zones=zones)


@dataclass(frozen=True, slots=True)
class Seen:
    """What the RSU kept of a car's previous accepted path."""

    x: float
    y: float
    t: float
    standing_since: float | None = None
    """Run time since which the car stands inside a conflict zone, or None."""


def _in_zone(bounds: Bounds, x: float, y: float) -> bool:
    return any(polygon_contains(zone, x, y) for zone in bounds.zones)


def check_path(path: VehiclePath, previous: Seen | None, bounds: Bounds) -> tuple[str | None, Seen]:
    """Why ``path`` is implausible (a counter name) or None, and what to remember of it.

    ``previous`` is what the last call returned for the same car (None at first)."""
    t = path.header.time_s
    x, y = path.x, path.y
    standing = path.speed <= _STANDING_MPS and _in_zone(bounds, x, y)
    since = None
    if standing:
        since = (
            t if previous is None or previous.standing_since is None else previous.standing_since
        )
    seen = Seen(x, y, t, since)
    if path.speed > bounds.v_max or (path.limits is not None and path.limits.v_max > bounds.v_max):
        return "implausible_speed", seen
    if (
        previous is not None
        and t > previous.t
        and math.hypot(x - previous.x, y - previous.y) > bounds.v_max * (t - previous.t) + _SLACK_M
    ):
        return "implausible_jump", seen
    pts = path.points
    if len(pts):
        p0 = pts[0]
        if math.hypot(p0[0] - x, p0[1] - y) > bounds.v_max * abs(p0[2] - t) + _SLACK_M:
            return "implausible_path_start", seen
        why = _path_dynamics(pts, bounds)
        if why is not None:
            return why, seen
        if since is not None and t - since >= ZONE_STAND_S and _moves(pts):
            return "implausible_zone_stop", seen
    return None, seen


def _moves(pts: FloatArray) -> bool:
    return bool(math.hypot(pts[-1, 0] - pts[0, 0], pts[-1, 1] - pts[0, 1]) > _SLACK_M)


def _path_dynamics(pts: FloatArray, bounds: Bounds) -> str | None:
    """Speed and acceleration implied by points at least :data:`SAMPLE_S` apart."""
    t = pts[:, 2]
    picks: Sequence[int] = _sample(t)
    if len(picks) < 2:
        return None
    sub = pts[list(picks)]
    dt = np.diff(sub[:, 2])
    dist = np.hypot(np.diff(sub[:, 0]), np.diff(sub[:, 1]))
    v = dist / dt
    if float(v.max()) > bounds.v_max:
        return "implausible_path_speed"
    if len(v) >= 2:
        a = np.abs(np.diff(v)) / ((dt[:-1] + dt[1:]) / 2)
        if float(a.max()) > bounds.a_max:
            return "implausible_path_accel"
    return None


def _sample(t: FloatArray) -> list[int]:
    """Indices of points at least :data:`SAMPLE_S` apart, greedy from the first."""
    picks = [0]
    last = t[0]
    while True:
        k = int(np.searchsorted(t, last + SAMPLE_S, side="left"))
        if k >= len(t):
            return picks
        picks.append(k)
        last = t[k]
