"""The car's side of the coordinated mode: one transition table, one file.

The RSU decides the mode (``services/rsu/modes.py``); the car follows:

=========  ==================  =========  ==========================================
mode       event               next       what the car does
=========  ==================  =========  ==========================================
AUTO       INITIATE_SLOW       C_SLOW     send autonomous paths 10 Hz to the RSU
AUTO       INITIATE_FAST       C_FAST     same, caution lifted
C_SLOW     INITIATE_FAST       C_FAST     (the RSU found room to speed up)
C_FAST     INITIATE_SLOW       C_SLOW     (a conflict appeared)
C_*        INITIATE_<same>     same       repeat of a command already taken
C_*        COORDINATED_PATH    same       follow its speeds
C_*        TERMINATE           AUTO       back to the autonomous planner
C_*        TIMEOUT             AUTO       no coordinated path for 0.3 s: fall back
AUTO       TERMINATE           AUTO       repeat of a termination already taken
AUTO       COORDINATED_PATH    AUTO       stale path after a termination: ignored
AUTO       TIMEOUT             AUTO       nothing to do
C_*        HANDOVER            AUTO       past the owner's zone, or out of its coverage
AUTO       HANDOVER            AUTO       nothing to do
=========  ==================  =========  ==========================================

Several RSUs (issue 12): **a car is coordinated by at most one RSU at a time, its
owner**, and along a corridor it is handed from one intersection's RSU to the next.
The rule (``owner_refusal``, ``owner_lapsed``; the agent applies it to every mode
command and coordinated path, ``services.vehicle.agent``):

1. *Who may take a car.* A car in ``AUTO`` takes an initiation (or a coordinated path,
   which implies one) only from the RSU of the **next intersection on its route** (the
   first crossing whose zone its centre has not left, ``authorize.approaching``), and
   only while it is **inside that RSU's coverage disc**. The RSU's intersection and
   disc are the scenario's ``[[rsus]]`` entry (centred on the intersection, as the RSU
   core's and the certificates'), else the RSU's last beacon; an RSU known from neither
   is refused. So where coverages overlap, the car belongs to the RSU of the zone it
   reaches next; the RSU of a zone it has left, or of one further down the road, is
   refused (``cmd_rsu_not_next``).
2. *While owned,* the car obeys its owner alone: every other RSU's initiation,
   termination and coordinated path is ignored and counted (``cmd_foreign_rsu``,
   ``cp_foreign_rsu``).
3. *Ownership ends*, and the car is back in ``AUTO`` under its own planner, when the
   owner terminates it; when no coordinated path from the owner has come for the
   coordinated timeout (the owner fell silent); or, the **handover**, as soon as the
   car's centre has left the owner's zone (where the RSU core terminates it as
   "leaving") or the car is outside the owner's coverage. From then on the next
   intersection's RSU may take it.
4. Before its first planning step the car knows no position, and takes no command.

Signed deployments check before this, in the daemon, that the RSU's certificate names
the intersection the car approaches or has just left and that the car is in the
certified coverage (``services.vehicle.authorize``); this rule then picks one owner
among the RSUs that pass.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from enum import Enum

from protocol.messages import Mode
from services.model.scenario import Crossing
from services.vehicle.authorize import approaching


class VehicleEvent(Enum):
    """What reaches the car's coordinated mode: an RSU's command or path, or a timeout
    (the RSU's own view of a car is ``services.rsu.modes.RsuEvent``)."""

    INITIATE_SLOW = "initiate_slow"
    INITIATE_FAST = "initiate_fast"
    COORDINATED_PATH = "coordinated_path"
    TERMINATE = "terminate"
    TIMEOUT = "timeout"
    HANDOVER = "handover"


TRANSITIONS: dict[tuple[Mode, VehicleEvent], Mode] = {
    (Mode.AUTO, VehicleEvent.INITIATE_SLOW): Mode.C_SLOW,
    (Mode.AUTO, VehicleEvent.INITIATE_FAST): Mode.C_FAST,
    (Mode.AUTO, VehicleEvent.TERMINATE): Mode.AUTO,
    (Mode.AUTO, VehicleEvent.COORDINATED_PATH): Mode.AUTO,
    (Mode.AUTO, VehicleEvent.TIMEOUT): Mode.AUTO,
    (Mode.C_SLOW, VehicleEvent.INITIATE_SLOW): Mode.C_SLOW,
    (Mode.C_SLOW, VehicleEvent.INITIATE_FAST): Mode.C_FAST,
    (Mode.C_SLOW, VehicleEvent.COORDINATED_PATH): Mode.C_SLOW,
    (Mode.C_SLOW, VehicleEvent.TERMINATE): Mode.AUTO,
    (Mode.C_SLOW, VehicleEvent.TIMEOUT): Mode.AUTO,
    (Mode.C_FAST, VehicleEvent.INITIATE_FAST): Mode.C_FAST,
    (Mode.C_FAST, VehicleEvent.INITIATE_SLOW): Mode.C_SLOW,
    (Mode.C_FAST, VehicleEvent.COORDINATED_PATH): Mode.C_FAST,
    (Mode.C_FAST, VehicleEvent.TERMINATE): Mode.AUTO,
    (Mode.C_FAST, VehicleEvent.TIMEOUT): Mode.AUTO,
    (Mode.AUTO, VehicleEvent.HANDOVER): Mode.AUTO,
    (Mode.C_SLOW, VehicleEvent.HANDOVER): Mode.AUTO,
    (Mode.C_FAST, VehicleEvent.HANDOVER): Mode.AUTO,
}


def next_mode(mode: Mode, event: VehicleEvent) -> Mode:
    """The mode after ``event``; every (mode, event) pair is in the table."""
    try:
        return TRANSITIONS[(mode, event)]
    except KeyError:
        raise ValueError(f"no transition from {mode.name} on {event.value}") from None


@dataclass(frozen=True, slots=True)
class RsuReach:
    """Where one RSU may coordinate: the intersection it serves and its coverage disc
    (centre (x, y) and radius [m])."""

    intersection: str
    x: float
    y: float
    radius: float

    def covers(self, x: float, y: float) -> bool:
        """Is (x, y) [m] inside the coverage disc?"""
        return math.hypot(x - self.x, y - self.y) <= self.radius


@dataclass(frozen=True, slots=True)
class Where:
    """The car's last known place: arc length ``s`` on its route and position [m]."""

    s: float
    x: float
    y: float


def owner_refusal(
    sender: str,
    owner: str | None,
    reach: RsuReach | None,
    crossings: Sequence[Crossing],
    where: Where | None,
    terminate: bool = False,
) -> str | None:
    """Why the car must not obey ``sender``'s mode command or coordinated path (rules 1,
    2 and 4 of the module docstring), as a counter suffix; None if it may. ``owner``: the
    RSU coordinating the car now (None in ``AUTO``); ``reach``: the sender's."""
    if owner is not None:
        return None if sender == owner else "foreign_rsu"
    if terminate:
        return None  # in AUTO a termination changes nothing: harmless from anyone
    if where is None:
        return "rsu_unplaced"
    if reach is None:
        return "rsu_unknown"
    if approaching(crossings, where.s) != reach.intersection:
        return "rsu_not_next"
    if not reach.covers(where.x, where.y):
        return "rsu_out_of_coverage"
    return None


def owner_zone_exit(crossings: Sequence[Crossing], intersection: str, s: float) -> float:
    """Arc length [m] at which a car at ``s`` on its route leaves ``intersection``'s zone
    (the first such crossing not yet left): where its owner hands it over; inf if none."""
    for c in crossings:
        if c.intersection == intersection and s < c.s_out:
            return c.s_out
    return math.inf


def owner_lapsed(reach: RsuReach, exit_s: float, where: Where) -> str | None:
    """Why the owner no longer coordinates the car (rule 3's handover): ``owner_zone_left``
    once its centre is past ``exit_s`` [m], ``owner_out_of_coverage`` outside the disc;
    None while it still does."""
    if where.s >= exit_s:
        return "owner_zone_left"
    if not reach.covers(where.x, where.y):
        return "owner_out_of_coverage"
    return None
