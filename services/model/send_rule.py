"""When to send a path: the change-triggered rule (issue 14, bandwidth), for the car's
future path and autonomous path and the RSU's coordinated paths.

The paper broadcasts the future path every planning tick (10 Hz): about 411 bytes
x 10 = 33 kbps per car. Most of those paths say what the previous one said: a car
that follows its plan is where its last path put it. :class:`ChangeRule` sends a
path only when it tells a receiver something new:

- the new path deviates from the last one sent by more than ``change_m`` [m] at
  any time both cover (positions compared at the same times: the last path is
  interpolated at the new one's sample times). A time shift ``dt`` of a car moving
  at ``v`` is a deviation of ``v * dt``, so the one threshold bounds both space and
  time for a moving car; a crawling car's time error may be larger, but then its
  place is within ``change_m`` of where it said, far inside ``d_margin_m`` (2.8 m);
- the mode changes (an RSU's command is acknowledged by the next path, at once);
- the last path has no point at ``now`` any more (it ended: a car that stood at its
  goal, or the horizon ran out);
- and at least every ``refresh_s`` [s] whatever happens, so that receivers that
  missed a path, or joined late (an RSU that restarted), hear one soon.

The receivers hold a path for ``fp_refresh_s`` longer under this rule
(``services.model.scenario.Scenario.fp_hold_s``: the RSU's reservation expiry and a
car's ``fp_stale_s``, both derived from the scenario, so sender and receivers
agree). Chosen in the scenario's ``[vehicle_params]``: ``fp_rule = "change"``,
``fp_change_m`` (0.5 m), ``fp_refresh_s`` (1 s); the default ``"periodic"`` keeps
the paper's 10 Hz and every result made with it.

The autonomous path to the RSU (while coordinated) may follow the same rule with
its own refresh: ``ap_rule = "change"``, ``ap_refresh_s`` (0.2 s). The RSU answers
each one with a coordinated path, and the car leaves coordination after
``coordinated_timeout_s`` (0.3 s) without one, so that timeout grows by
``ap_refresh_s`` under this rule (``services.vehicle.agent``). The RSU's own streams
are unchanged: fewer autonomous paths in means fewer coordinated paths out. It is a
separate choice, off by default, because coordination then reacts up to 0.2 s later:
on the paper run it changes nothing, on the demand experiment one seed's delay moved
by +2.3 s and another's by -3.2 s (README, "Real daemons, bandwidth and latency").

The RSU's coordinated path to each car may follow it too: ``cp_rule = "change"``,
``cp_refresh_s`` (0.5 s). The RSU then sends a new coordinated path only when it
deviates from the last one it sent that car by more than ``fp_change_m``, on a mode
change, when the last one no longer covers ``now``, and at least every
``cp_refresh_s``; otherwise the last one stays the car's reservation (the car follows
it, so the table keeps what the car drives: ``services.rsu.core``). The car's
``coordinated_timeout_s`` grows by ``cp_refresh_s`` (``services.vehicle.agent``).

Pure: the caller passes ``now`` [s] and the path points (x, y, t) with absolute
times [s]; the rule remembers the last path it said to send.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from protocol.messages import Mode
from services.model.geometry import FloatArray
from services.model.scenario import VehicleParams

__all__ = ["ChangeRule", "change_rule", "deviation_m"]

_EPS_S = 1e-6
"""Clock slack [s]: a refresh due at exactly ``now`` is sent despite float noise."""


def deviation_m(last: FloatArray, new: FloatArray) -> float:
    """Largest distance [m] between two paths (x, y, t) at the new path's sample times
    that the last path covers; ``inf`` when the last path covers none of them."""
    if last.shape[0] == 0 or new.shape[0] == 0:
        return math.inf
    t_last = last[:, 2]
    t_new = new[:, 2]
    inside = (t_new >= t_last[0] - _EPS_S) & (t_new <= t_last[-1] + _EPS_S)
    if not inside.any():
        return math.inf
    t = t_new[inside]
    x = np.interp(t, t_last, last[:, 0])
    y = np.interp(t, t_last, last[:, 1])
    return float(np.hypot(x - new[inside, 0], y - new[inside, 1]).max())


@dataclass(slots=True)
class ChangeRule:
    """Send a future path when it changed by more than ``change_m`` [m], on a mode change
    or when the last one no longer covers ``now``, and at least every ``refresh_s`` [s]."""

    change_m: float
    refresh_s: float
    last_points: FloatArray | None = field(init=False, default=None)
    last_mode: Mode | None = field(init=False, default=None)
    last_sent_s: float = field(init=False, default=-math.inf)

    def __post_init__(self) -> None:
        for name in ("change_m", "refresh_s"):
            value = getattr(self, name)
            if not (isinstance(value, int | float) and math.isfinite(value) and value > 0):
                raise ValueError(f"ChangeRule.{name} must be positive and finite, got {value!r}")

    def why(self, now: float, points: FloatArray, mode: Mode) -> str | None:
        """Why this path must be sent ("first", "refresh", "mode", "uncovered", "change"),
        or None to skip it. Records it as the last one sent when it is to be sent."""
        reason = self._reason(now, points, mode)
        if reason is not None:
            self.last_points = points
            self.last_mode = mode
            self.last_sent_s = now
        return reason

    def _reason(self, now: float, points: FloatArray, mode: Mode) -> str | None:
        last = self.last_points
        if last is None:
            return "first"
        if now - self.last_sent_s >= self.refresh_s - _EPS_S:
            return "refresh"
        if mode is not self.last_mode:
            return "mode"
        if last.shape[0] == 0 or last[-1, 2] < now - _EPS_S:
            return "uncovered"
        if deviation_m(last, points) > self.change_m:
            return "change"
        return None


def change_rule(params: VehicleParams, *, stream: str = "fp") -> ChangeRule | None:
    """The rule of one stream from the scenario's ``[vehicle_params]``: ``"fp"`` the car's
    future path, ``"ap"`` its autonomous path to the RSU, ``"cp"`` the RSU's coordinated
    path to a car; None for the periodic rule (send every time)."""
    rules = {
        "fp": (params.fp_rule, params.fp_refresh_s),
        "ap": (params.ap_rule, params.ap_refresh_s),
        "cp": (params.cp_rule, params.cp_refresh_s),
    }
    if stream not in rules:
        raise ValueError(f"stream must be one of {sorted(rules)}, got {stream!r}")
    rule, refresh = rules[stream]
    if rule == "periodic":
        return None
    return ChangeRule(params.fp_change_m, refresh)
