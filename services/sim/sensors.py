"""The car's own sensors: 360°, limited range, 2-D occlusion by buildings.

A car senses another when the other's centre is within ``sensor_range`` (m) of its
own centre and a sight line from its centre reaches the other's centre or any corner
of its footprint without crossing a building's interior. Sensed cars are reported as
ground truth (no noise): what the sensors limit is *which* cars are known, the
question the paper's blind corner asks.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np

from services.model.geometry import BoolArray, FloatArray, PolygonSet, footprints, visible_mask
from services.model.kinematics import TruthState

__all__ = ["perceive", "sight_points"]


def sight_points(others: Sequence[TruthState]) -> FloatArray:
    """Points a sight line may aim at, (5 * M, 2): each car's centre then its 4 corners."""
    if not others:
        return np.zeros((0, 2), dtype=np.float64)
    x = np.array([o.x for o in others], dtype=np.float64)
    y = np.array([o.y for o in others], dtype=np.float64)
    corners = footprints(
        x,
        y,
        [o.heading for o in others],
        [o.length for o in others],
        [o.width for o in others],
    )
    centres = np.stack((x, y), axis=1)[:, None, :]
    out: FloatArray = np.concatenate((centres, corners), axis=1).reshape(-1, 2)
    return out


def _within(other: TruthState, ego: TruthState, r2: float) -> bool:
    """Centre within sqrt(``r2``) of ``ego``'s. Products, not ``**``: a far-off value (a
    peer's ``x = 1e300``) gives inf, never an OverflowError, and NaN compares False."""
    dx = other.x - ego.x
    dy = other.y - ego.y
    return dx * dx + dy * dy <= r2 and _finite_shape(other)


def _finite_shape(other: TruthState) -> bool:
    return all(math.isfinite(v) for v in (other.heading, other.length, other.width))


def perceive(
    ego: TruthState,
    others: Sequence[TruthState],
    buildings: Sequence[FloatArray] | PolygonSet,
    sensor_range: float,
) -> list[TruthState]:
    """The cars ``ego`` can sense now, in the order given (``ego`` itself is skipped).

    ``buildings`` are convex polygons; pass ``Scenario.occluders`` (pre-packed) in hot
    loops. ``sensor_range`` is in metres and compared with centre-to-centre distance.
    Another car whose position or shape is not finite is never sensed (the daemons
    validate truth on reception, ``services.edge.plumbing.TRUTH_BOUNDS``; this is the
    second line); ValueError when ``ego``'s own position is not finite (our bug).
    """
    if not sensor_range >= 0.0:
        raise ValueError(f"sensor_range must be >= 0, got {sensor_range!r}")
    if not (math.isfinite(ego.x) and math.isfinite(ego.y)):
        raise ValueError(f"ego position must be finite, got ({ego.x!r}, {ego.y!r})")
    r2 = sensor_range * sensor_range
    near = [o for o in others if o.id != ego.id and _within(o, ego, r2)]
    if not near:
        return []
    vis = visible_mask((ego.x, ego.y), sight_points(near), buildings).reshape(len(near), 5)
    seen: BoolArray = np.any(vis, axis=1)
    return [o for k, o in enumerate(near) if seen[k]]
