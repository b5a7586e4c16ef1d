"""Mode management (paper §IV-C): the one transition table of the RSU.

Every car the RSU knows is in one of three modes: ``AUTO`` (drives its
autonomous plan), ``C_SLOW`` (coordinated, slowing), ``C_FAST`` (coordinated,
speeding up). The RSU turns what it learns about a car into one ``RsuEvent`` and
looks up ``TRANSITIONS[(mode, event)] -> (next mode, action)``; nothing else
changes a mode. Events, in the order the RSU tests them:

``SILENT``
    The car's reservation expired (no future path and no autonomous path for
    ``expiry_s``): it is dropped and its mode forgotten; nothing is sent.
``LEAVING``
    The car's current position has passed the conflict zone: outside the zone
    polygon and heading away from the zone's centre. A coordinated car gets a
    termination; an AUTO car needs nothing (and is never put into a coordinated
    mode once it is leaving).
``CONFLICT``
    The car's path conflicts, within ``T_collision`` of now, with another car's
    entry and this car is the one that must yield (see below).
``FREE_APPROACHING``
    No conflict within ``T_free`` and the car is approaching the intersection:
    in coverage, not yet in the zone, its path enters the zone within ``T_free``.
``NO_CONFLICT``
    No conflict within ``T_collision``, but not free or not approaching.

Which path is judged, and who yields (our reading of the paper, where it is silent):

* An ``AUTO`` car is judged on its broadcast future path. On a conflict the
  sender yields (paper: "the first vehicle that sent its future path
  accelerated": the path already in the table keeps its right of way).
* A ``C_SLOW`` car's future path is discarded (paper); its table entry is the
  last coordinated path the RSU sent it (what it has been told to do), and it
  is judged on each autonomous path it sends: free and approaching ->
  ``C_FAST``; no conflict within ``T_collision`` -> ``AUTO`` (termination);
  else it stays ``C_SLOW`` and is sent a new coordinated path.
* A ``C_FAST`` car is judged on the coordinated path the RSU computes from each
  autonomous path it sends (``V_max`` through the intersection). A committed
  ``C_FAST`` car has priority: whenever a ``C_FAST`` car and a car in another
  mode conflict within ``T_collision``, the other one gets ``CONFLICT`` (is put
  into ``C_SLOW``), whoever sent the path. Between two ``C_FAST`` cars the
  later arriver at the zone (larger zone entry time; tie: larger id) yields.
* Made safe (ours, issue 12; ``services.rsu.core``, "The invariant"): a ``C_FAST``
  car is judged on the plan it is sent, promoted only when that plan is clear over
  ``T_free``, and settles its conflicts within ``T_free``; a ``C_SLOW`` car's path is
  all it can give, so a car that conflicts with it yields, ``C_FAST`` too; of two
  committed cars, one that can still keep out of the zone yields, and of two that
  cannot, one whose stop stands clear of the other's way; a follower
  yields to the car ahead in its lane; a ``C_SLOW`` car is released (``NO_CONFLICT``
  -> ``AUTO``) only when its path is clear over ``T_free`` by the margins; after two
  mode changes, promotions and releases wait a dwell (bounded changes per crossing).
* Hysteresis (ours): conflicts are judged on sampled points, so a pair at the
  edge of ``D_margin`` / headway can appear and vanish as a path is re-sent
  with its points 0.1 s further on. To keep that from flipping modes 10 times
  a second, a car is judged ``FREE_APPROACHING``, and a ``C_SLOW`` car is
  released, only when its path is clear even with ``release_margin_m`` more
  room and ``release_margin_s`` more headway (defaults 0.6 m, 0.2 s: more
  than the resampling of a 120-point path at ``V_max`` can move a point).
* Commands are soft state: the RSU repeats a pending initiation or termination
  every ``command_repeat_s`` until the car's broadcast future path shows the
  commanded mode; until then, that car's future paths are not used for
  decisions (they do not reflect the command yet).

A (re)started RSU, and committed cars (ours, issue 16; the paper is silent):

* **Listening first.** A core commands nobody for ``listen_s`` (default one
  ``expiry_s``, 0.5 s) after its first input: every future path it hears is
  reserved as the car drives it, so when it starts deciding, its table holds
  every car in coverage and no car is judged against an empty table. While a
  car still shows a coordinated mode it cannot have from this core (given by
  the crashed incarnation; it falls back after its 0.3 s coordinated timeout)
  listening lasts on, by at most one more ``expiry_s``. At a cold start no car
  is near the zone yet, so this changes nothing there.
* **Committed cars keep their order.** A car is committed when it can no longer
  stop comfortably before the zone: it is in it, or its front is within
  ``v^2 / (2 decel_comfort) + stop_gap_m`` of the zone's edge along its path.
  A committed car never yields to one that is not (this comes before the
  ``C_FAST`` rules above), and a car is promoted to ``C_FAST`` only if the
  plan it would get keeps ``headway_s`` between its body's zone occupancy and
  that of every committed or ``C_FAST`` car; else the promotion is a
  ``CONFLICT`` (it waits its turn in ``C_SLOW``; ``order_kept`` in the core's
  counters). A committed car whose path ends at rest with this car's body
  just ahead of it (``HELD_REACH_M``) is not waited for: it waits for this
  car (its own planner senses the body), so waiting for it locks the box. The
  occupancy check is needed besides the table's point pairs: a slow car's body
  is in the zone far longer than its reference point is within ``D_margin`` of
  the crossing.
"""

from __future__ import annotations

from enum import IntEnum

from protocol.messages import Mode


class RsuEvent(IntEnum):
    """What the RSU learned about one car (see module docstring)."""

    CONFLICT = 1
    FREE_APPROACHING = 2
    NO_CONFLICT = 3
    LEAVING = 4
    SILENT = 5


class Action(IntEnum):
    """What the RSU sends the car as part of a transition."""

    NONE = 0
    SEND_INITIATION_SLOW = 1
    SEND_INITIATION_FAST = 2
    SEND_TERMINATION = 3
    FORGET = 4  # drop the car: no message, mode and pending commands forgotten


class InvalidTransition(ValueError):
    """A (mode, event) pair that is not in the transition table."""


_A, _S, _F = Mode.AUTO, Mode.C_SLOW, Mode.C_FAST

TRANSITIONS: dict[tuple[Mode, RsuEvent], tuple[Mode, Action]] = {
    # AUTO: initiate on conflict (slow) or on a free approach (fast).
    (_A, RsuEvent.CONFLICT): (_S, Action.SEND_INITIATION_SLOW),
    (_A, RsuEvent.FREE_APPROACHING): (_F, Action.SEND_INITIATION_FAST),
    (_A, RsuEvent.NO_CONFLICT): (_A, Action.NONE),
    (_A, RsuEvent.LEAVING): (_A, Action.NONE),
    (_A, RsuEvent.SILENT): (_A, Action.FORGET),
    # C_SLOW: judged on its autonomous path; released to C_FAST or AUTO.
    (_S, RsuEvent.CONFLICT): (_S, Action.NONE),
    (_S, RsuEvent.FREE_APPROACHING): (_F, Action.SEND_INITIATION_FAST),
    (_S, RsuEvent.NO_CONFLICT): (_A, Action.SEND_TERMINATION),
    (_S, RsuEvent.LEAVING): (_A, Action.SEND_TERMINATION),
    (_S, RsuEvent.SILENT): (_A, Action.FORGET),
    # C_FAST: keeps V_max through the intersection until it leaves or loses priority.
    (_F, RsuEvent.CONFLICT): (_S, Action.SEND_INITIATION_SLOW),
    (_F, RsuEvent.FREE_APPROACHING): (_F, Action.NONE),
    (_F, RsuEvent.NO_CONFLICT): (_F, Action.NONE),
    (_F, RsuEvent.LEAVING): (_A, Action.SEND_TERMINATION),
    (_F, RsuEvent.SILENT): (_A, Action.FORGET),
}


def transition(mode: Mode, event: RsuEvent) -> tuple[Mode, Action]:
    """Look up the next mode and the action; raise InvalidTransition for anything else.

    Plain ints are refused (an IntEnum hashes like its value, so ``(0, 1)``
    would otherwise silently match a pair of the table).
    """
    if not isinstance(mode, Mode) or not isinstance(event, RsuEvent):
        raise InvalidTransition(f"not a (Mode, RsuEvent) pair: ({mode!r}, {event!r})")
    try:
        return TRANSITIONS[(mode, event)]
    except KeyError:
        raise InvalidTransition(f"no transition for {mode.name} on {event.name}") from None
