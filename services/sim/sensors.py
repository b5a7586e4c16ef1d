"""The car's own sensors: 360°, limited range, 2-D occlusion by buildings.

A car senses another when the other's centre is within ``sensor_range`` (m) of its
own centre and a sight line from its centre reaches the other's centre or any corner
of its footprint without crossing a building's interior. Sensed cars are reported as
ground truth (no noise): what the sensors limit is *which* cars are known, the
question the paper's blind corner asks.
"""

from __future__ import annotations

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


def perceive(
    ego: TruthState,
    others: Sequence[TruthState],
    buildings: Sequence[FloatArray] | PolygonSet,
    sensor_range: float,
) -> list[TruthState]:
    """The cars ``ego`` can sense now, in the order given (``ego`` itself is skipped).

    ``buildings`` are convex polygons; pass ``Scenario.occluders`` (pre-packed) in hot
    loops. ``sensor_range`` is in metres and compared with centre-to-centre distance.
    """
    if not sensor_range >= 0.0:
        raise ValueError(f"sensor_range must be >= 0, got {sensor_range!r}")
    r2 = sensor_range * sensor_range
    near = [o for o in others if o.id != ego.id and (o.x - ego.x) ** 2 + (o.y - ego.y) ** 2 <= r2]
    if not near:
        return []
    vis = visible_mask((ego.x, ego.y), sight_points(near), buildings).reshape(len(near), 5)
    seen: BoolArray = np.any(vis, axis=1)
    return [o for k, o in enumerate(near) if seen[k]]
