"""Speed thresholds shared by several layers: one owner, one name per meaning.

Each constant here is read by more than one module (the physics, the metrics, the
paper experiment, the scenario loader). Before this module each reader kept its own
copy under one shared name that meant 1e-9, 0.1 or 0.5 m/s depending on the file;
now a name says what the threshold is *for*. Units are in the names: ``_MPS`` m/s.

The wire format's bounds (largest coordinate, speed, time, points per message) are
owned by ``protocol.codec`` (``MAX_COORD_M``, ``MAX_SPEED_MPS``, ``MAX_TIME_US``,
``max_points``...) and imported from there by whoever must respect them (the RSU,
the scenario loader): they are the limits of what can be sent, so they live with
the encoder.
"""

from __future__ import annotations

from typing import Final

__all__ = [
    "RUN_END_BELOW_MPS",
    "SPEED_CAP_FACTOR",
    "STANDING_MPS",
    "STOP_ARM_ABOVE_MPS",
    "STOP_COUNT_BELOW_MPS",
]

STANDING_MPS: Final = 1e-9
"""Physics (``services.model.kinematics.step``): at or below this speed a car is
standing, so its brakes hold it (no negative acceleration at rest) [m/s]. Only
float noise above zero: a car that is still rolling is not standing."""

STOP_COUNT_BELOW_MPS: Final = 0.1
"""Metrics and reports: a car whose speed falls below this has made a stop, for the
stop count (``services.sim.metrics``, ``services.experiments.paper``) [m/s]. Well above
the physics' ``STANDING_MPS`` so that a car crawling to a halt counts once, not after
a long float tail."""

STOP_ARM_ABOVE_MPS: Final = 1.0
"""Metrics and reports: after a stop, the next stop counts only once the car has
exceeded this speed again, so dithering around ``STOP_COUNT_BELOW_MPS`` is one stop
[m/s]."""

RUN_END_BELOW_MPS: Final = 0.05
"""Both harnesses (``services.sim.car.all_at_goal``): a run ends when every car is at
its goal and slower than this [m/s]; a car still braking to its final halt is not done."""

SPEED_CAP_FACTOR: Final = 1.05
"""Physics: the speed never exceeds ``v_max * SPEED_CAP_FACTOR`` whatever is commanded.
The scenario loader uses it too: the highest speed a car can report on the wire."""
