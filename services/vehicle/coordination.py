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
=========  ==================  =========  ==========================================
"""

from __future__ import annotations

from enum import Enum

from protocol.messages import Mode


class VehicleEvent(Enum):
    """What reaches the car's coordinated mode: an RSU's command or path, or a timeout
    (the RSU's own view of a car is ``services.rsu.modes.RsuEvent``)."""

    INITIATE_SLOW = "initiate_slow"
    INITIATE_FAST = "initiate_fast"
    COORDINATED_PATH = "coordinated_path"
    TERMINATE = "terminate"
    TIMEOUT = "timeout"


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
}


def next_mode(mode: Mode, event: VehicleEvent) -> Mode:
    """The mode after ``event``; every (mode, event) pair is in the table."""
    try:
        return TRANSITIONS[(mode, event)]
    except KeyError:
        raise ValueError(f"no transition from {mode.name} on {event.value}") from None
