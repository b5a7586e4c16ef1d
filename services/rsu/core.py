"""The RSU's pure core: reservation table, mode manager and velocity manager together.

Sans-IO: ``now`` (float seconds on the run's time base) and decoded messages
in; messages to send (``Outgoing``) and the next deadline out. No clock reads,
no asyncio, no Zenoh; the daemon shell and the in-process simulation both
drive this object.

Per received message (paper §IV-C; the rules are in ``services.rsu.modes``):

* ``FuturePath`` (broadcast): from a car in coverage. An ``AUTO`` car's path
  goes into the reservation table and is judged; a coordinated car's future
  path only proves it alive (and can show it has left the intersection): its
  entry is the coordinated path the RSU sent it. A future path also
  acknowledges a pending command when its ``mode`` shows the commanded mode;
  until then the car's future paths are not used for decisions.
* ``AutonomousPath`` (addressed to this RSU): from a coordinated car; judged,
  answered with a coordinated path (or a termination).
* Anything else, anything for another RSU, from a car the RSU does not
  coordinate, from outside coverage, out of order or malformed: ignored and
  counted in ``counters``.

Errors as h11 splits them: a path is validated once, where it comes in
(:func:`path_problem`: finite, within the wire's bounds, (N, 3) points, a
sender); an invalid one is counted in ``invalid`` and ``invalid_<reason>`` and
dropped, so nothing a peer sends raises out of ``on_message``. Past that check
the decision code trusts its input: an exception out of ``on_message`` or
``tick`` is a bug of ours and propagates (the daemon shell logs it with its
traceback and exits, see ``services.edge.shell``).

``tick(now)`` (10 Hz) expires silent cars, repeats pending commands every
``command_repeat_s`` and sends the beacon every ``beacon_period_s``.

The invariant (issue 12), what every RSU step keeps, tested as a hypothesis property in
``tests/rsu/test_invariant.py`` (N cars at a 4-way intersection with turns, both
policies, cars following their coordinated paths exactly) and cause by cause in
``tests/rsu/test_issue12_causes.py``:

1. After every step, no two paths the RSU has committed to (the coordinated paths it
   sent, the future paths of the cars it does not coordinate: its table) conflict
   within ``T_collision``, by the table's rule, which counts cars in the same lane (a
   follower a body length and a metre behind, ``services.rsu.reservation``). When a
   conflict appears, the car that must yield (``_yields``) gets a path that avoids it
   in the same step; a ``C_FAST`` car settles its conflicts within ``T_free``.
2. A car that follows its coordinated path never drives into the car ahead: a
   ``C_FAST`` plan is retimed behind every car ahead in its lane
   (``VelocityManager.behind_leaders``), a stop stops a follow distance behind where
   the car ahead ends its path, and a follower always yields to the car ahead.
3. No car is told ``C_FAST`` on a path that was not checked: the plan that is sent
   (not the car's own path) is checked against the table over ``T_free`` with the
   release margins, and against the crossing order of committed cars.
4. A car changes mode at a bounded rate: the first ``FREE_MODE_CHANGES`` freely, then
   promotions and releases at most every ``MODE_DWELL_S``, after ``MAX_MODE_CHANGES``
   every ``LATE_DWELL_S``; a ``C_SLOW`` car is released only when its own path is clear
   over ``T_free`` by the margins, and an ``AUTO`` car held back from promotion by the
   dwell alone, still beyond ``T_collision`` and with its own path clear, drives that
   path rather than being slowed for the wait (it was: C_SLOW -> AUTO -> C_SLOW every
   3-4 s). A rate, not a count: the property test's cars, which all start where they
   can stop, stay within ``MAX_MODE_CHANGES + 2``, but a car that waits a minute in a
   queue under heavy demand is promoted and demoted again by the cars crossing before
   it (``four-way-flows`` seed 0: up to 16 changes, the demand experiment at 600 veh/h:
   up to 20; see the README, "Delay against demand").
5. No car waits forever while its way is free: a ``C_SLOW`` car whose path is clear
   and which is approaching is promoted (dwell permitting).
6. Bodies in the zone keep a crossing order (``_zone_taken``, ``_order_clash``): a car
   whose front is in the zone is committed; no ``C_FAST`` plan puts a body in the zone
   within a headway of a committed car's, and no slot plan, release or unslowed ``AUTO``
   path does so where the two bodies' sweeps through the zone meet (``_bodies_meet``;
   the point rule's 2.8 m misses bodies that touch at a crawl).
7. Under ``slot``, no slot leaves a car that can still stop before the zone standing
   in it: a path that ends at rest with the body in the zone gets the paper's stop
   instead (``VelocityManager.rests_in_zone``, ``tests/rsu/test_box.py``).
8. Don't block the box (both policies, 6 Dec): no car that can still keep out of the
   zone braking hard keeps or gets ``C_FAST``, is released or left ``AUTO`` on a path that
   ends at rest with its body in the zone while another car stands in it
   (``_box_blocked``; cause 10 in ``tests/rsu/test_issue12_causes.py``, a property over
   where that car stands and how the other comes). Only a standing car counts: a car
   crossing in front stops a follower's own path in the box only for a moment, and
   holding every such path (tried for grants, see ``VelocityManager``) cost more than
   it saved.
9. A body this RSU holds standing (``C_SLOW`` on a stop, at rest) is an obstacle: a
   release or promotion may pass it by bodies, 0.1 m clear (``_passes_stuck``), though
   within the point rule's 2.8 m of it, and must pass it so even where the point rule
   sees nothing (``_touches_stuck``: a body held crosswise reaches 2.25 m from its
   centre); it moves only when this RSU releases it, judged
   against the passing car's new path. The one exception to 1 besides a car standing
   for the other (``_past_standing``); tested as a property (cause 10: no such release
   touches the held body) and by example (two held left turners, each in the other's
   way, locked for good without it).

Tried and dropped (3 Dec, c821a6a): first come, first served claims under ``slot``. A
``C_SLOW`` car with no slot took the earliest one that only later arrivals (first heard
after it, able to stop comfortably) stood in, and those were re-planned around it in
the same step. On the demand experiment's straight flows it helped (400 veh/h, seeds
0-4: 10.7 -> 9.2 s mean delay; 600 veh/h seed 4 finished every car instead of 18 of
35 by 180 s), but with turns it hurt: ``four-way-flows`` seed 0 13.4 -> 16.8 s,
``four-way-flows-40`` seed 0 13.1 -> 16.5 s with the min gap down from 0.21 to 0.07 m
(claiming only over cars not yet ``C_FAST``: 18.5 s). Demoting granted cars for a car
that starts from rest costs more than the wait it saves once turning bodies occupy
the zone longer.

Tried and dropped (4 Dec): two committed cars that neither can keep out of the zone, even
braking hard, are ordered by mode (whoever conflicts with a ``C_SLOW`` path yields), so a
``C_FAST`` car 0.4 m from the zone yielded to a ``C_SLOW`` one 0.5 m from it and stood 10 s
with its nose in the zone (demand experiment, slot, 600 veh/h, seed 0). Letting the later
to reach the zone yield fixed that case but led rsu/paper at 600 veh/h, seed 0, into a box
gridlock (8 cars never through): a car stopped 0.7 m into the zone and a crossing car
stopped by its own sensors in front of it, each waiting for the other. That needs a way
out of such a gridlock first. (The firm stop for a car that cannot stay out braking hard,
``VelocityManager.stop_limit``, tried with it, landed on its own: random search found a
conflict it fixes.)

Tried and dropped (5 Dec, late): a starvation gate. A car that had waited (at most 2 m/s)
``STARVED_S`` with the zone within 3 m ahead of its front held back every crossing car
(its way crossed, not the same or the opposite) that could still stop and had waited less:
no promotion, no release, no slot (a stop instead), and the starved car was exempt from the
dwell. Cause it aimed at (demand experiment, slot, 600 veh/h, seed 0): the E-W queue head
stood at its line 41-72 s, released to ``AUTO`` when its own path (held by the crossing cars
it senses) stayed at the line and slowed again by crossing cars granted ``C_FAST`` 100-130 m
out; once it went, its queue followed as a platoon, a car every 2.1-2.7 s. At 3 s the head
left at 56 s instead of 66 s but the mean over seeds 0-4 rose from 16.2 to 16.9 s (the
crossing queue's head waited instead); at 10 s the mean fell to 14.7 s only because seed 2
collided and locked (24 of 42 finished): a ``C_FAST`` car creeping behind its leader with its
plan ending 2 m into the zone was made to yield 3.8 m from the zone at 4.7 m/s to a car
promoted from rest, stopped with its nose 1.3 m in and was hit. Fairness at the head costs
more than it saves while granted cars keep their way.

Open, found the same evening by the demand experiment's turning mix (70/15/15 % straight,
left, right; the default grid is straight only), which at 600 veh/h stranded cars in 3 of 5
seeds under ``paper`` and 5 of 5 under ``slot`` (seeds 0-4), with one collision (paper,
seed 1); after the first fix below, 2 and 4 of 5, no collision (the README's table, "Delay
against demand"). Three mechanisms, each seen in a log of the RSU's mode changes:

* A committed car yields too late (fixed 6 Dec). ``paper``, seed 1: ns-4, ``C_FAST``
  3.75 m from the zone at 4.65 m/s, and sw-2, a left turner with its nose in the zone at
  2.2 m/s, both ``C_FAST`` behind leaders that had just gone (each one's reservation had
  ended at rest behind its leader, so neither saw the other until 80.25 s). Neither could
  stay out braking hard, so the later arriver, ns-4, yielded; its stop left its nose 0.55 m
  in, inside the turner's sweep; sw-2 was then demoted for ns-4's ``C_SLOW`` entry, stopped
  under it and they touched. Now of two committed cars that neither can stay out, the one
  whose stop stands clear of the other's way yields (``_stop_clears``: its stop, where it
  will stand with its reaction and its path's age, against the other's sweep, by bodies):
  sw-2 stops on its approach lane and ns-4 drives through. Earlier tries: letting a car
  whose centre is in the zone keep its way over one whose nose at most is kept sw-2
  ``C_FAST``, but its own planner's emergency stop still touched ns-4's nose; a slot search
  before a stop that cannot stay out (``paper``) found ns-4 no slot.
* The same start, then a lock (gone with the fix above: every car finishes). ``paper``,
  seed 9 (5 of 29 finished): sn-1 yields 4.75 m out at 5.2 m/s and stands with its nose
  1.05 m in; the left turner ne-0 stands in the box with 0.2 m of that nose in its exit;
  both ``AUTO``, each one's emergency stop waits for the other.
* Two standing turners (two cases fixed 6 Dec by rules 8 and 9 above, others open).
  ``slot``, 800 veh/h, seed 9 (open): opposing left turners, both ``C_SLOW`` and standing
  (one with its centre in the zone), each one's own path within the point rule's 2.8 m of
  the other's standing entry; neither is released (``_past_standing`` covers only a car
  standing straight ahead of it, ``_held_by``). Judging a car held standing by bodies
  instead of the point rule (tried) releases neither either: the one's turn truly runs
  through the other's body, so only preventing the pair from standing there helps.
  ``paper``, 600 veh/h, seed 0 (20 of 44 finished; fixed by rule 8): ne-1, turning left
  from the north with its centre in the zone, is rightly stopped there to let a straight
  car by; sw-2, ``C_FAST`` behind that car, is stopped by its own sensors (ne-1's body in
  its turn) with its nose 2.3 m into the zone, in ne-1's exit. sw-2's plan ended at rest
  where its own path did, 5.8 m from ne-1's standing reservation, so no rule saw it.
  ``slot``, 600 veh/h, seed 0 (27 of 44 finished; fixed by rule 9): sw-1 held with its
  nose 2.2 m in, ne-2 held at the edge; sw-1's turn passes ne-2's body 0.15-0.25 m clear,
  but within the point rule's 2.8 m, so neither was ever released. ``paper``, 600 veh/h,
  seed 0 again with rule 9 (27 of 44; 41 with rule 8 alone, open): ne-2 and sw-2, opposing
  left turners both ``C_FAST`` behind leaders, saw each other only when both were 1-2 m
  from the zone (each reservation ended at rest behind its leader); both stops ended in
  the zone; rule 9 then promoted sw-2 past ne-2's held body (more than 0.25 m clear), but
  sw-2's own planner still yielded to ne-2's broadcast future path (which would drive on
  into sw-2's turn), and once sw-2 stood ``C_FAST`` with its plan at rest, ne-2 was promoted
  too: both stand ``C_FAST``, each sensing the other. What both need is to see a crossing
  ``C_FAST`` car's way beyond where its reservation ends behind its leader.
* Two opposing left turners that each wait in the box's edge (open, 6 Dec). ``slot``,
  800 veh/h, seed 6 (50 of 67 finished): sw-0, ``C_FAST``, is stopped by its own planner
  with its nose 1.2 m into the zone, waiting for the opposing straight car ns-11; ne-1,
  ``C_FAST`` right behind ns-11, is a left turner too. Both reservations end at rest
  short of their turns (sw-0's for ns-11, ne-1's a follow distance behind ns-11), so the
  RSU first sees their crossing at 126.05 s, when sw-0's nose is in and ne-1 is 4.61 m
  out at 5.08 m/s, 0.14 m too close to keep out braking hard after its reaction. Rule 7's
  ``_stop_clears`` then weighs sw-0's stop against ne-1's *truncated* reservation, finds
  it clear and demotes sw-0; ne-1 enters 0.45 m, and each ends in the other's turn.
  Again the RSU lacks each car's way beyond where its path rests: a future path shows
  the planned trajectory, not the intended one (a maneuver-coordination message carries
  both), and without the intended turn no rule here can order the pair in time.

Tried and dropped (6 Dec): don't queue into the box. A car that could still keep out
was held short when its path rested with its body in the zone within ``HELD_REACH_M``
behind the rest of a car ahead whose reserved path rested (the same way, within
``SAME_WAY_RAD``), a queue through the box. It never fired for the pair above (sw-0
waits for a crossing car, not a queue: its leader rests 10.9 m ahead); without the
heading test it fired elsewhere and seed 6 went to 63 of 67 by chance, and with it the
turning runs moved within noise (600 veh/h, seeds 0-4: paper 29.4 -> 29.2 s, slot 31.0 ->
31.7 s, the same cars finished within one) while ``paper`` at 800 veh/h finished fewer.

Tried and dropped (6 Dec, later): no stop clears a path that ends at rest. For the lock
above, ``_stop_clears`` weighed sw-0's stop against ne-1's reservation, which ends at
rest short of ne-1's turn and so hides it; returning ``False`` whenever the other path
ends at rest brought back the collision rule 1 was made for (600 veh/h,
``paper``, seed 1: 26 of 44 finished, one collision), whose two reservations both ended
at rest behind their leaders.

Tried and dropped (6 Dec, night): a path whose centre stops short measured by its front.
``_front_gap`` is None when the centre's path never enters the zone, even when the path
ends at rest with the car's nose in it; measuring such a car by its front
(``_nose_gap``) made it committed, and so gave it the way. On the turning grids (60 s of
demand, 120 s to clear, finished of inserted): 600 veh/h seeds 0-4, paper 180 -> 187 of
201, slot 198 -> 199; 800 veh/h seeds 5-9, slot 196 -> 213, paper 218 -> 183 of 245; and
600 veh/h seeds 5-9, paper, every car -> 155 of 169. The losses were the opposing-left-
turner lock above (paper, 800, seed 8 at 56 s; 600, seed 9): cars with their noses in
the box kept the way and more of them entered it at once.

Fixed (8 Dec), at its source in the car: the opposing-left-turner lock above. Each
turner's autonomous path rested a stopping distance behind its straight leader (the
planner braked for the leader as if it might stop hard now), so its turn reached the table
only when the leader had gone. The autonomous path now follows the car ahead by that car's
future path (``services.vehicle.planner``, ``_follow_cap``), and a follower's turn is in the
table as soon as its leader's path runs through the box: turning 600 veh/h, seeds 0-4,
paper 180 -> 197 of 201 cars finished, slot 198 -> 198; turning 800 veh/h, seeds 5-9, paper
218 -> 240 and slot 196 -> 230 of 245; no lock and no collision in those runs (README,
"Turns at high demand"). No rule here changed.

Status: the property holds for both policies in the derandomized examples and for the two
cases random search once found under ``paper`` (``FOUND_BY_SEARCH``: the follow rule's lane
was measured across the asking car's heading only; ``FOUND_BY_SEARCH_TURN``: a stop that
could not stay out of the zone was a comfortable one through a turner's path). Open, found
by the same search (4 Dec): ``[("ns", 48.25, 0.0), ("en", 84.25158189414503, 0.0), ("sw",
75.25, 3.0), ("sw", 84.25, 0.0)]`` under ``paper``: c0, starting from rest 100 m out, is
promoted and demoted again within 0.3-0.5 s on its own paths (4.3 / 4.6 / 5.1 / 5.5 s), and
after ``MAX_MODE_CHANGES`` a promotion every ``LATE_DWELL_S`` can still be followed by a
safety demotion: 9 changes in its crossing against the test's bound of 8.

Limits, stated: a car that can no longer stop before the zone (committed) keeps its
way, so a conflict between two committed cars cannot be undone by the RSU, only
prevented; the property test starts every car where it can still stop. The one
exception: of two committed cars, one that can still keep its body out of the zone
braking at ``HARD_STOP_FACTOR`` times its comfortable deceleration, after
``REACTION_S`` at its speed (the command's way and the actuator's lag), yields to one
that cannot (``_stops_short``, ``tests/rsu/test_issue12_causes.py`` cause 9); a car
whose front is in the zone cannot, standing or not, and of two that cannot whose stops do
not settle it, the one whose centre is still outside yields (cause 11: a turner standing
mid-turn yielded to the car at the box's edge that waited for it, for good). A slot
takes a ``C_SLOW`` car into the zone as a ``C_FAST`` path does: of two cars neither of
which can keep out, the later arriver yields, slot or not (cause 9). A ``C_FAST`` car
whose new plan jumped earlier (the car ahead it was retimed behind has gone) and would
make it yield keeps the path it drives while that is still clear
(``_keeps_reservation``, cause 10): the earlier plan used to meet a crossing car
promoted into the gap, both committed, and lock the box.

Found 5 Dec by the demand experiment at 600 veh/h (rsu/slot) and fixed as above: seed 4,
a collision (a hard stop that fitted the gap exactly carried a car's nose 1 m into the
zone through its reaction (0.3 s actuator lag, up to 0.1 s until its next planning
step), and a crossing car, no longer able to stop, yielded
to it by the mode rule and hit it); seed 1, the box lock. A car standing with only its
nose over the zone's edge now counts as a body in the zone (``_body_in_zone``): its
centre is outside, and its centre 3 m from a crossing car's is beyond the point rule's
2.8 m.

Several RSUs (issue 12): each RSU coordinates a car only while it approaches that
RSU's zone (in coverage, its path entering the zone within ``T_free``) and terminates it
when it leaves the zone, so along a corridor a car is handed from one intersection's
RSU to the next as it passes each zone. The car sends its autonomous paths only to the
RSU whose command it took last (``services.vehicle.agent``), and a core ignores paths
addressed to another RSU (``foreign_rsu``). Where coverages overlap, the car belongs to
the RSU of the zone it reaches next on its route: the previous RSU has let it go on
leaving its zone. Not enforced yet: a second RSU that sees the car approaching its
zone while the first still coordinates it (zones closer than ``T_free`` at the car's
speed) can command it too; a future path carries no RSU id, so the core cannot tell
"coordinated by another RSU" from "coordinated by my forgotten self" (which it must
take back); the guard belongs on the car side (ignore another RSU's commands while
coordinated, until terminated).

A new core (a cold start or a restart after a crash) first listens for
``listen_s`` (default one ``expiry_s``) and keeps the crossing order of committed
cars (both in ``services.rsu.modes``).
"""

from __future__ import annotations

import collections
import logging
import math
from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

from protocol.codec import MAX_COORD_M
from protocol.messages import (
    AutonomousPath,
    Command,
    CoordinatedPath,
    FuturePath,
    Header,
    Message,
    Mode,
    ModeCommand,
    RsuBeacon,
    VehiclePath,
)
from services.model.geometry import any_rects_overlap, footprint, footprints
from services.model.send_rule import ChangeRule
from services.model.types import Policy
from services.rsu import paths
from services.rsu.config import RsuConfig
from services.rsu.modes import Action, RsuEvent, transition
from services.rsu.reservation import (
    LANE_SLACK_M,
    SAME_WAY_RAD,
    Conflict,
    ReservationTable,
    oversize,
    path_headings,
    within_wire_bounds,
)
from services.rsu.velocity import HARD_STOP_FACTOR, REACTION_S, SpeedPlan, VelocityManager

__all__ = ["Outgoing", "Policy", "RsuConfig", "RsuCore", "path_problem"]

log = logging.getLogger("crosspath.rsu")

FloatArray = npt.NDArray[np.float64]

_DUE_SLACK_S = 1e-6  # a deadline this close counts as reached (float rounding)

BODY_CLEARANCE_M = 0.25
"""Two bodies whose sweeps through the zone come closer than twice this [m] cross or
merge there (``RsuCore._bodies_meet``): opposing lanes 3.5 m apart keep 1.7 m."""

STUCK_PASS_M = 0.1
"""A path passes a stuck car's body (``RsuCore._passes_stuck``) when the two bodies, each
grown by half this [m] a side, do not touch: a car's own planner passes a standing body
at least ``PASS_MARGIN_M`` (0.05 m) clear at the creep speed."""

HELD_REACH_M = 3.0
"""A car whose reserved path ends at rest with another car's body within this [m]
straight ahead of its front waits for that car (``RsuCore._held_by``): a queue's gap
(follow gap plus the stop slack) with room to spare."""

MODE_DWELL_S = 0.5
"""A car is promoted or released no sooner than this after its last mode change [s]
(issue 12, cause 4: a follower flipped C_FAST <-> C_SLOW every 0.1 s)."""
FREE_MODE_CHANGES = 2
"""Mode changes per crossing made without any dwell."""
MAX_MODE_CHANGES = 6
"""Mode changes per crossing after which a car is promoted or released only every
``LATE_DWELL_S``: a car that cannot find its way in a few changes waits longer between
tries, rather than flip its mode every half second (it still gets through: a car whose
way is free is never held forever)."""
LATE_DWELL_S = 3.0
"""Dwell between promotions and releases after ``MAX_MODE_CHANGES`` [s]."""

KEEP_TRACK_M = 2.0
"""A ``C_FAST`` car keeps its last coordinated path (``RsuCore._keeps_reservation``) only
while it stands within this [m] of where that path puts it now: it drives that path."""

_SLOT_KINDS = frozenset({"slot"})
"""Coordinated paths (``SpeedPlan.kind``) that take a ``C_SLOW`` car into the zone."""
_STOP_KINDS = frozenset({"stop", "slot_fallback"})
"""Coordinated paths (``SpeedPlan.kind``) that stop a ``C_SLOW`` car."""


@dataclass(frozen=True, slots=True)
class Outgoing:
    """A message to send: to one car (its cmd stream) or, ``vehicle=None``, the beacon."""

    vehicle: str | None
    message: Message


@dataclass(slots=True)
class _Pending:
    """A command repeated until the car's future path shows ``mode``."""

    command: Command
    mode: Mode
    last_sent: float


@dataclass(slots=True)
class _Car:
    """What the RSU knows about one car."""

    vehicle: str
    mode: Mode = Mode.AUTO
    x: float = 0.0
    y: float = 0.0
    heading: float = 0.0
    speed: float = 0.0
    length: float = 4.5
    width: float = 1.8
    state_us: int = -(2**62)
    last_fp_us: int = -(2**62)
    last_ap_us: int = -(2**62)
    autonomous: VehiclePath | None = None  # latest path it would drive alone
    pending: _Pending | None = None
    claim: Mode = Mode.AUTO  # the mode its latest future path shows
    changes: int = 0  # mode changes the RSU made in this crossing
    changed_at: float = -math.inf  # when the last one was [s]
    held_short: bool = False  # its last coordinated path stops it short of the zone
    sent: ChangeRule | None = None  # under cp_rule: the last coordinated path sent it
    kind: str = ""  # how its last coordinated path was made (SpeedPlan.kind)
    last_cp: CoordinatedPath | None = None  # the last coordinated path sent it
    stop_since: float = -math.inf  # when it was first told the stop it is told now [s]

    @property
    def stopping(self) -> bool:
        """Its last coordinated path stops it (``C_SLOW`` on a stop, ``_STOP_KINDS``)."""
        return self.mode == Mode.C_SLOW and self.kind in _STOP_KINDS

    def observe(self, path: VehiclePath) -> None:
        if path.header.time_us >= self.state_us:
            self.state_us = path.header.time_us
            self.x, self.y = path.x, path.y
            self.heading, self.speed = path.heading, path.speed
            self.length, self.width = path.length, path.width

    @property
    def shape(self) -> tuple[float, float]:
        """Length, width [m]: what its conflict margin grows with."""
        return self.length, self.width


def _thinned(points: FloatArray, cap: int) -> npt.NDArray[np.int64]:
    """Indices of ``cap`` points spread evenly over ``points``, first and last kept."""
    idx: npt.NDArray[np.int64] = np.unique(
        np.round(np.linspace(0, points.shape[0] - 1, cap)).astype(np.int64)
    )
    return idx


def path_problem(path: VehiclePath) -> str | None:
    """Why a received path cannot be used (a short reason, the counter's suffix), or None.

    The decoder already refuses most of this; the check is here too because the core
    also takes messages that did not come through it (tests, other harnesses).
    """
    scalars = (path.x, path.y, path.speed, path.heading, path.length, path.width)
    if not all(isinstance(v, int | float) and math.isfinite(v) for v in scalars):
        return "not_finite"
    if path.speed < 0 or path.length < 0 or path.width < 0:
        return "negative"
    if not path.header.sender:
        return "no_sender"
    if abs(path.x) > MAX_COORD_M or abs(path.y) > MAX_COORD_M:
        return "out_of_bounds"
    pts = path.points
    if not isinstance(pts, np.ndarray) or pts.ndim != 2 or pts.shape[1] != 3:
        return "points_shape"
    if not within_wire_bounds(pts):
        return "points_out_of_bounds"
    return None


class RsuCore:
    """One roadside unit's decision logic (pure; see module docstring)."""

    def __init__(self, config: RsuConfig, *, listen_s: float | None = None) -> None:
        """``listen_s`` [s, >= 0]: how long the core only listens after its first input
        (default one reservation expiry, see ``services.rsu.modes``)."""
        listen = config.expiry_s if listen_s is None else listen_s
        if not (isinstance(listen, int | float) and math.isfinite(listen) and listen >= 0):
            raise ValueError(f"listen_s must be finite and >= 0 [s], got {listen_s!r}")
        self.config = config
        self.listen_s = float(listen)
        self._listen_from: float | None = None
        self._listened = False
        self.table = ReservationTable(config.d_margin_m, config.headway_s, config.expiry_s)
        self.velocity = VelocityManager(config)
        self.counters: collections.Counter[str] = collections.Counter()
        self._cars: dict[str, _Car] = {}
        self._seq = 0
        self._stamp_us = -(2**53)
        """Generation time of the last header [µs] (:meth:`_header`)."""
        self._next_beacon: float | None = None
        self._zone = paths.ConvexZone.of(config.conflict_zone)
        self._margins = (config.release_margin_m, config.release_margin_s)
        # zone occupancy of each table entry, by the entry's points object (an entry's
        # points are replaced, never changed): the crossing order checks every entry
        self._occupancies: dict[
            str, tuple[FloatArray, tuple[float, bool], tuple[float, float] | None]
        ] = {}

    # -- queries --------------------------------------------------------------------------

    def mode_of(self, vehicle: str) -> Mode:
        """The car's mode; AUTO for a car the RSU does not know."""
        car = self._cars.get(vehicle)
        return Mode.AUTO if car is None else car.mode

    def modes(self) -> dict[str, Mode]:
        """Every known car's mode."""
        return {v: car.mode for v, car in self._cars.items()}

    def pending(self, vehicle: str) -> tuple[Command, Mode] | None:
        """The command being repeated to the car until it shows the mode, if any."""
        car = self._cars.get(vehicle)
        if car is None or car.pending is None:
            return None
        return car.pending.command, car.pending.mode

    def next_deadline(self) -> float:
        """When ``tick`` next has work [s]: a beacon, a repeat, or an expiry."""
        deadline = 0.0 if self._next_beacon is None else self._next_beacon
        repeat = self.config.command_repeat_s
        for car in self._cars.values():
            if car.pending is not None:
                deadline = min(deadline, car.pending.last_sent + repeat)
        return min(deadline, self.table.next_expiry())

    def termination(self, now: float, vehicle: str) -> ModeCommand:
        """A ``TERMINATE`` for ``vehicle`` outside any decision (the run's end: the daemon
        hands every coordinated car back to its own planner), in this core's header
        sequence, so that the cars' replay windows take it after everything sent before."""
        return ModeCommand(self._header(now), vehicle, Command.TERMINATE, Mode.AUTO)

    def forget(self, vehicle: str) -> bool:
        """Drop a car entirely (table entry, mode, pending command)."""
        known = self._cars.pop(vehicle, None) is not None
        self._occupancies.pop(vehicle, None)
        return self.table.remove(vehicle) or known

    def listening(self, now: float) -> bool:
        """Still in the listening period (nothing commanded yet): ``listen_s`` from the first
        input, longer (by at most one ``expiry_s``, and only when ``listen_s`` > 0) while a
        car still claims a coordinated mode, which it cannot have from us. Once over, over.
        """
        if self._listened:
            return False
        if self._listen_from is None:
            self._listen_from = now
        end = self._listen_from + self.listen_s
        if now + _DUE_SLACK_S < end:
            return True
        if (
            self.listen_s > 0
            and now + _DUE_SLACK_S < end + self.config.expiry_s
            and any(car.claim != Mode.AUTO for car in self._cars.values())
        ):
            return True
        self._listened = True
        return False

    # -- inputs ---------------------------------------------------------------------------

    def on_message(
        self, now: float, message: Message, rsu_key: str | None = None
    ) -> list[Outgoing]:
        """Handle one received message; return what to send.

        A peer's bad message is counted and dropped; an exception is a bug of ours.
        """
        if isinstance(message, FuturePath):
            return self._on_future_path(now, message)
        if isinstance(message, AutonomousPath):
            return self._on_autonomous_path(now, message, rsu_key)
        self.counters["ignored_kind"] += 1
        return []

    def _invalid(self, path: VehiclePath) -> bool:
        """Count and log (debug) a path that fails :func:`path_problem`."""
        problem = path_problem(path)
        if problem is None:
            if oversize(path.length, path.width):
                self.counters["oversize"] += 1  # kept, its margin grows only to the cap
            return False
        self.counters["invalid"] += 1
        self.counters[f"invalid_{problem}"] += 1
        log.debug(
            "rsu %s: dropped %s from %r: %s",
            self.config.rsu_id,
            type(path).__name__,
            path.header.sender,
            problem,
        )
        return True

    def tick(self, now: float) -> list[Outgoing]:
        """Periodic work (10 Hz): expiry of silent cars, command repeats, the beacon."""
        self.listening(now)  # the listening period starts with the first input
        out: list[Outgoing] = []
        for vehicle in self.table.expire(now):
            self._apply_silent(vehicle)
        for vehicle in [v for v in self._cars if v not in self.table]:
            self._apply_silent(vehicle)
        for vehicle in [v for v in self._occupancies if v not in self.table]:
            del self._occupancies[vehicle]
        repeat = self.config.command_repeat_s
        for car in self._cars.values():
            pending = car.pending
            if pending is not None and now + _DUE_SLACK_S >= pending.last_sent + repeat:
                pending.last_sent = now
                message = ModeCommand(self._header(now), car.vehicle, pending.command, pending.mode)
                out.append(Outgoing(car.vehicle, message))
                self.counters["repeats"] += 1
        if self._next_beacon is None or now + _DUE_SLACK_S >= self._next_beacon:
            cfg = self.config
            beacon = RsuBeacon(
                self._header(now), cfg.intersection, cfg.center[0], cfg.center[1], cfg.coverage_m
            )
            out.append(Outgoing(None, beacon))
            self.counters["beacons"] += 1
            base = now if self._next_beacon is None else self._next_beacon
            following = base + cfg.beacon_period_s
            self._next_beacon = following if following > now else now + cfg.beacon_period_s
        return out

    # -- messages -------------------------------------------------------------------------

    def _header(self, now: float) -> Header:
        """The next header: sequence and generation time both increase from one message
        to the next. A daemon calls :meth:`tick` with the step's scheduled time, which a
        late tick has passed already, and :meth:`on_message` with the time of reception:
        without the max, a late tick's beacon or command repeat carried a higher sequence
        but an older time than a message already sent, and receivers' replay windows
        refused it as from before a counter restart (seen in daemon runs, 1-2 beacons each).
        """
        self._seq += 1
        self._stamp_us = max(self._stamp_us, round(now * 1e6))
        return Header(sender=self.config.rsu_id, seq=self._seq, time_us=self._stamp_us)

    def _on_future_path(self, now: float, fp: FuturePath) -> list[Outgoing]:
        self.counters["fp_rx"] += 1
        if self._invalid(fp):
            return []
        vehicle = fp.header.sender
        car = self._cars.get(vehicle)
        if car is not None:
            if fp.header.time_us < car.last_fp_us:
                self.counters["stale"] += 1
                return []
            car.last_fp_us = fp.header.time_us
            if car.pending is not None and car.pending.mode == fp.mode:
                car.pending = None
                self.counters["acks"] += 1
        cfg = self.config
        if math.hypot(fp.x - cfg.center[0], fp.y - cfg.center[1]) > cfg.coverage_m:
            self.counters["out_of_coverage"] += 1
            return []
        if car is None:
            car = _Car(vehicle, last_fp_us=fp.header.time_us)
            self._cars[vehicle] = car
            self.counters["vehicles_seen"] += 1
        car.observe(fp)
        car.claim = fp.mode
        if self.listening(now):
            # A (re)started RSU first learns every car's path and mode claim: each path is
            # reserved as the car drives it, and nobody is commanded yet.
            car.autonomous = fp
            self._reserve(now, car, fp.points)
            self.counters["fp_listened"] += 1
            return []
        coordinated = car.mode != Mode.AUTO
        if coordinated and self._leaving(car):
            return self._apply(now, car, RsuEvent.LEAVING, fp, None)
        if car.pending is not None and vehicle in self.table:
            # It has not taken our last command yet: this path does not reflect it.
            self.table.touch(vehicle, now)
            self.counters["fp_unacknowledged"] += 1
            return []
        if coordinated:
            # The future path is discarded (paper), except that it shows where the car is
            # and that it is alive; its table entry stays the coordinated path it was sent.
            self.table.touch(vehicle, now)
            if fp.mode != car.mode:
                # Soft state: the car has fallen back to its own planner (no coordinated path
                # reached it for 0.3 s, e.g. under packet loss). Take it back.
                self.counters["reinitiations"] += 1
                car.sent = None  # a re-initiation always comes with its coordinated path
                out = [self._command(now, car, Command.INITIATE, car.mode)]
                sent = self._coordinate(now, car, fp, None)
                if sent is not None:
                    out.append(sent)
                return out
            return []
        car.autonomous = fp
        return self._decide(now, car, fp)

    def _on_autonomous_path(
        self, now: float, ap: AutonomousPath, rsu_key: str | None
    ) -> list[Outgoing]:
        self.counters["ap_rx"] += 1
        if rsu_key is not None and rsu_key != self.config.rsu_id:
            self.counters["foreign_rsu"] += 1
            return []
        if self._invalid(ap):
            return []
        car = self._cars.get(ap.header.sender)
        if car is None:
            self.counters["unknown_vehicle"] += 1
            return []
        if car.mode == Mode.AUTO:
            self.counters["ap_not_coordinated"] += 1
            return []
        if ap.header.time_us < car.last_ap_us:
            self.counters["stale"] += 1
            return []
        car.last_ap_us = ap.header.time_us
        car.observe(ap)
        car.autonomous = ap
        return self._decide(now, car, ap)

    # -- decisions ------------------------------------------------------------------------

    def _leaving(self, car: _Car) -> bool:
        return paths.is_leaving(car.x, car.y, car.heading, self._zone)

    def _approaching(self, car: _Car, path: VehiclePath, now: float) -> bool:
        cfg = self.config
        return paths.is_approaching(
            car.x,
            car.y,
            path.points,
            self._zone,
            cfg.center,
            cfg.coverage_m,
            now,
            cfg.t_free_s,
        )

    def _clear(self, car: _Car, query: FloatArray, now: float) -> bool:
        """No conflict within ``T_free`` even with the release margins (hysteresis)."""
        if car.mode != Mode.AUTO:
            return True  # C_SLOW was already judged with the margins; C_FAST stays anyway
        cfg = self.config
        found = self.table.conflicts(
            car.vehicle, query, now, cfg.t_free_s, (), *self._margins, shape=car.shape
        )
        return not found

    def _stands_for(self, other: _Car, points: FloatArray, car: _Car) -> bool:
        """``other`` stands still, its path ``points`` never moves, and it waits for
        ``car``'s body (:meth:`_held_by`): a lock unless ``car`` passes it."""
        return (
            other.speed <= paths.AT_REST_MPS
            and paths.stands(points)
            and self._held_by(other, points, car)
        )

    def _past_standing(
        self, car: _Car, query: FloatArray, now: float, found: list[Conflict]
    ) -> list[Conflict]:
        """The release conflicts ``found`` (with the release margins) less those with a
        stuck car ``query`` passes clear (:meth:`_passes_stuck`) and with a
        car standing for this one (:meth:`_stands_for`) that ``query`` passes without
        the margins: the margins are hysteresis against paths that jitter, and a
        standing car's does not. Found in the demand experiment (600 veh/h, paper,
        seed 0): a car held in the zone passed a standing car's centre at 3.3 m, inside
        2.8 m plus the release margin, and was never released; the standing car waited
        for it to move, for good (its own planner then creeps past, ``PASS_MARGIN_M``)."""
        found = self._past_stuck(car, query, found)
        standing: set[str] = set()
        for c in found:
            other, entry = self._cars.get(c.vehicle), self.table.get(c.vehicle)
            if (
                other is not None
                and entry is not None
                and self._stands_for(other, entry.points, car)
            ):
                standing.add(c.vehicle)
        if not standing:
            return found
        bare = self.table.conflicts(
            car.vehicle, query, now, self.config.t_free_s, (), shape=car.shape
        )
        hit = {c.vehicle for c in bare}
        return [c for c in found if c.vehicle not in standing or c.vehicle in hit]

    def _past_stuck(self, car: _Car, points: FloatArray, found: list[Conflict]) -> list[Conflict]:
        """``found`` less the conflicts with stuck cars ``points`` passes clear
        (:meth:`_passes_stuck`)."""
        out = []
        for c in found:
            other, entry = self._cars.get(c.vehicle), self.table.get(c.vehicle)
            if (
                other is None
                or entry is None
                or not self._passes_stuck(car, points, other, entry.points)
            ):
                out.append(c)
        return out

    def _touches_stuck(self, car: _Car, points: FloatArray) -> bool:
        """``points`` (a release or promotion of ``car``) does not pass some body this RSU
        holds standing clear by ``STUCK_PASS_M`` (:meth:`_passes_stuck`), whether or not
        the point rule sees the two: a car held crosswise reaches 2.25 m beyond its centre,
        and a slow path ending just short of its corner kept 4.2 m from its centre, beyond
        the rule's 2.8 m, while 0.06 m from its body (cause 10's property, 7 December:
        held at (-1, -4) facing east, the other north from (1.75, -12) at 0.5 m/s)."""
        for other in self._cars.values():
            if other is car or not other.stopping or other.speed > paths.AT_REST_MPS:
                continue
            entry = self.table.get(other.vehicle)
            if entry is not None and not self._passes_stuck(car, points, other, entry.points):
                return True
        return False

    def _passes_stuck(self, car: _Car, points: FloatArray, other: _Car, entry: FloatArray) -> bool:
        """``other`` is held standing by this RSU (``C_SLOW`` on a stop, at rest, its table
        entry never moving: it moves only when this RSU releases it, which it judges against
        ``car``'s new path) and ``car``'s path ``points`` passes its body clear by
        ``STUCK_PASS_M``: such a body is an obstacle, judged by bodies, not by the point
        rule's 2.8 m or a crossing order. Found in the demand experiment's turning mix
        (slot, 600 veh/h, seed 0): two opposing left turners, one with its nose 2.2 m into
        the zone and one held at its edge; the first one's turn passes the second's body
        by 0.15-0.25 m, the second's runs through the first's nose, and the point rule held
        both for good (17 of 44 cars not through by the run's end). A car standing on its own
        (``AUTO``, ``C_FAST``) may move at any time, so it keeps the point rule and the
        crossing order (cause 7)."""
        if not other.stopping or other.speed > paths.AT_REST_MPS or not paths.stands(entry):
            return False
        if points.shape[0] == 0:
            return True
        reach = 0.5 * (math.hypot(car.length, car.width) + math.hypot(other.length, other.width))
        near = np.hypot(points[:, 0] - other.x, points[:, 1] - other.y) <= reach + 1.0
        if not near.any():
            return True
        grow = STUCK_PASS_M
        mine = self._bodies_at(points, near, car, grow)
        theirs = footprint(other.x, other.y, other.heading, other.length + grow, other.width + grow)
        return not any_rects_overlap(mine, theirs[np.newaxis])

    def _entry_occupancy(self, car: _Car, points: FloatArray) -> tuple[float, float] | None:
        """:meth:`_occupancy` of a table entry, computed once per entry (and nose)."""
        nose = self._nose_in_zone(car)
        hit = self._occupancies.get(car.vehicle)
        if hit is not None and hit[0] is points and hit[1] == (car.length, nose):
            return hit[2]
        occupancy = self._occupancy(points, car)
        self._occupancies[car.vehicle] = (points, (car.length, nose), occupancy)
        return occupancy

    def _nose_in_zone(self, car: _Car) -> bool:
        """The front of ``car``'s body, as it stands now, is in the zone."""
        half = 0.5 * car.length
        return self._zone.contains_point(
            car.x + half * math.cos(car.heading), car.y + half * math.sin(car.heading)
        )

    def _body_in_zone(self, points: FloatArray, car: _Car) -> npt.NDArray[np.bool_] | None:
        """Which points of ``points`` (``car``'s path) hold its body in the zone: its centre
        within half a length of the stretch of the path inside the zone (sampled points:
        an approximation by a point spacing), or, for a path that never takes the centre
        in, within half a length of where the car is while its nose is in the zone now (a
        car held with its nose over the edge blocks the crossing; neither the centre
        rule nor the point rule's 2.8 m sees it). None when the body never reaches it."""
        if points.shape[0] == 0:
            return None
        inside = np.flatnonzero(self._zone.contains(points[:, :2]))
        if inside.size == 0 and not self._nose_in_zone(car):
            return None
        s = paths.arc_length(points)
        half = 0.5 * car.length
        if inside.size == 0:
            xy = points[:, :2]
            here = int(np.argmin(np.hypot(xy[:, 0] - car.x, xy[:, 1] - car.y)))
            near: npt.NDArray[np.bool_] = np.abs(s - s[here]) <= half
            return near
        body: npt.NDArray[np.bool_] = (s >= s[inside[0]] - half) & (s <= s[inside[-1]] + half)
        return body

    def _occupancy(self, points: FloatArray, car: _Car) -> tuple[float, float] | None:
        """When ``car``'s body overlaps the conflict zone on this path: (first, last) [s]
        (:meth:`_body_in_zone`); None when it does not."""
        body = self._body_in_zone(points, car)
        if body is None:
            return None
        times = points[body, 2]
        return float(times.min()), float(times.max())

    def _committed(self, car: _Car, points: FloatArray | None = None) -> bool:
        """The car cannot comfortably stop before the zone any more: it is in the zone, or
        its front is within its comfortable braking distance (plus ``stop_gap_m``) of the
        zone's edge along ``points`` (default: its table entry). A car whose front is
        already in the zone is committed too, wherever its path ends: it blocks the
        crossing until it has driven on (found in ``four-way-flows``, slot, seed 0)."""
        return self._committed_at(car, self._front_gap(car, points))

    def _committed_at(self, car: _Car, gap: float | None) -> bool:
        """:meth:`_committed` of a car whose front is ``gap`` from the zone (:meth:`_front_gap`)."""
        if gap is None:
            return False
        braking = car.speed * car.speed / (2.0 * self._decel(car))
        return gap <= braking + self.config.stop_gap_m

    def _stops_short(self, car: _Car, points: FloatArray | None = None) -> bool:
        """The car can still keep its body out of the zone: a ``C_SLOW`` car whose stop
        does (``held_short``), or one whose front can stop before the zone braking at
        ``HARD_STOP_FACTOR`` times its comfortable deceleration after ``REACTION_S`` at its
        speed (as a stop would, ``VelocityManager.stop_limit``)."""
        gap = None if car.mode == Mode.C_SLOW else self._front_gap(car, points)
        return self._short_at(car, gap)

    def _short_at(self, car: _Car, gap: float | None) -> bool:
        """:meth:`_stops_short` of a car whose front is ``gap`` from the zone."""
        if car.mode == Mode.C_SLOW:
            return car.held_short
        if gap is None:
            return True
        if gap <= 0.0:
            # its front is in the zone already: standing still does not keep it out (a
            # turner at rest mid-turn counted as "stops short" and yielded to the car at
            # the box's edge that waited for it, for good: demand experiment, turning,
            # slot, 800 veh/h, seed 8, with a front-gap rule since dropped; see the
            # module docstring)
            return False
        room = gap - car.speed * REACTION_S  # it drives on this long before it brakes
        return car.speed * car.speed <= 2.0 * HARD_STOP_FACTOR * self._decel(car) * room

    def _front_gap(self, car: _Car, points: FloatArray | None = None) -> float | None:
        """How far the car's front is from the zone along ``points`` (default: its table
        entry) [m]: 0 when its centre or front is in the zone, None when the path does not
        reach the zone."""
        if self._zone.contains_point(car.x, car.y) or self._nose_in_zone(car):
            return 0.0
        half = 0.5 * car.length
        if points is None:
            entry = self.table.get(car.vehicle)
            if entry is None:
                return None
            points = entry.points
        span = paths.zone_span(points, self._zone)
        if span is None:
            return None
        s = paths.arc_length(points)
        # from the point of the path nearest the car now (an entry may be older than now)
        xy = points[: span[0] + 1, :2]
        here = int(np.argmin(np.hypot(xy[:, 0] - car.x, xy[:, 1] - car.y)))
        return max(float(s[span[0]] - s[here]) - half, 0.0)

    def _decel(self, car: _Car) -> float:
        """The car's own comfortable deceleration [m/s²] (its path's limits, else ours)."""
        path = car.autonomous
        return (
            self.velocity.default_limits.decel
            if path is None
            else self.velocity.limits_of(path).decel
        )

    def _swept(self, points: FloatArray, car: _Car) -> FloatArray:
        """Footprints (M, 4, 2) of ``car``'s body along ``points`` while it overlaps the
        zone (:meth:`_body_in_zone`), each side grown by ``BODY_CLEARANCE_M``;
        (0, 4, 2) when it does not."""
        body = self._body_in_zone(points, car)
        if body is None:
            return np.empty((0, 4, 2))
        return self._bodies_at(points, body, car)

    def _bodies_at(
        self,
        points: FloatArray,
        which: npt.NDArray[np.bool_],
        car: _Car,
        grow: float = 2.0 * BODY_CLEARANCE_M,
    ) -> FloatArray:
        """Footprints (M, 4, 2) of ``car``'s body at ``points[which]``, heading along the
        path (else as it heads now), length and width grown by ``grow`` [m]
        (``BODY_CLEARANCE_M`` a side)."""
        pts = points[which]
        unit = path_headings(points)[which]
        heading = np.where(np.isnan(unit[:, 0]), car.heading, np.arctan2(unit[:, 1], unit[:, 0]))
        return footprints(pts[:, 0], pts[:, 1], heading, car.length + grow, car.width + grow)

    def _stop_clears(self, now: float, car: _Car, other: _Car, other_points: FloatArray) -> bool:
        """Told to stop now (the paper's stop, ``VelocityManager.stop``; the one it has if it
        is stopping already), ``car`` stays clear of ``other``'s path ``other_points``
        through the zone: its body, wherever it goes until it stands (where it will
        stand, its reaction and its path's age included), never touches ``other``'s sweep
        there (both grown by ``BODY_CLEARANCE_M``). Space only, so a stop that clears is
        safe at any time."""
        entry = self.table.get(car.vehicle)
        if car.stopping and entry is not None:
            points = entry.points
        elif car.autonomous is not None:
            # planned from its last path, which is up to a period old: it drove on since
            age = max(now - car.autonomous.header.time_s, 0.0)
            plan = self.velocity.stop(
                car.vehicle, car.autonomous, now, self.table, reaction_s=REACTION_S + age
            )
            points = plan.points if plan.reserved is None else plan.reserved
        else:
            return False
        theirs = self._swept(other_points, other)
        if theirs.shape[0] == 0:
            return True
        cx, cy = self._zone.centroid
        reach = self._zone.radius + 0.5 * math.hypot(car.length, car.width) + BODY_CLEARANCE_M
        near = np.hypot(points[:, 0] - cx, points[:, 1] - cy) <= reach
        if not near.any():
            return True
        return not any_rects_overlap(self._bodies_at(points, near, car), theirs)

    def _bodies_meet(
        self, car: _Car, points: FloatArray, mine: FloatArray, other: _Car, entry: FloatArray
    ) -> bool:
        """``car`` (its path ``points``, swept bodies ``mine``) and ``other`` (its table
        entry ``entry``) cross or merge in the zone: their bodies' sweeps there overlap,
        and neither is ahead of the other in its lane (a follower is the follow rule's)."""
        if self._ahead_in_lane(other, car, points) or self._ahead_in_lane(car, other, entry):
            return False
        return any_rects_overlap(mine, self._swept(entry, other))

    def _order_clash(
        self,
        car: _Car,
        points: FloatArray,
        now: float,
        *,
        moving_only: bool = False,
        horizon_s: float = math.inf,
        crossing_only: bool = False,
    ) -> str | None:
        """The first committed car (in ``C_FAST`` or :meth:`_committed`) whose zone occupancy
        ``points`` would come within ``headway_s`` of, or None.

        The table's point-pair check compares reference points within ``D_margin``; a
        slow car's body occupies the zone far longer than that, so a crossing order is
        checked on the zone occupancy of whole bodies too. ``moving_only``: count only
        committed cars that are not told to stop (``C_SLOW``); ``horizon_s``: only
        occupancies that overlap within this of ``now`` [s]; ``crossing_only``: only cars
        whose bodies cross or merge with this one's in the zone (:meth:`_bodies_meet`:
        opposing traffic and followers pass), else any body in the zone.
        """
        mine = self._occupancy(points, car)
        if mine is None:
            return None
        swept: FloatArray | None = None
        headway = self.config.headway_s
        for vehicle in self.table:
            other = self._cars.get(vehicle)
            entry = self.table.get(vehicle)
            if vehicle == car.vehicle or other is None or entry is None:
                continue
            theirs = self._entry_occupancy(other, entry.points)
            if theirs is None or theirs[1] < now or (moving_only and other.mode == Mode.C_SLOW):
                continue
            overlaps = mine[0] < theirs[1] + headway and theirs[0] < mine[1] + headway
            soon = max(mine[0], theirs[0]) <= now + horizon_s  # the later entry
            if not (overlaps and soon):
                continue
            if not (other.mode == Mode.C_FAST or self._committed(other)):
                continue
            if self._held_by(other, entry.points, car):
                continue  # it waits for this car's body: waiting for it locks the box
            if self._passes_stuck(car, points, other, entry.points):
                continue  # a stuck body is an obstacle: this path passes it clear
            if crossing_only:
                if swept is None:
                    swept = self._swept(points, car)
                if not self._bodies_meet(car, points, swept, other, entry.points):
                    continue
            return vehicle
        return None

    def _held_by(self, other: _Car, points: FloatArray, car: _Car) -> bool:
        """``other``'s reserved path ``points`` ends at rest with ``car``'s body (as it
        stands now) within ``HELD_REACH_M`` straight ahead of ``other``'s front: ``other``
        (its own planner, which senses bodies) waits for ``car`` to move, so ``car`` must
        not wait for ``other`` in the crossing order. Found in ``four-way-flows``, paper,
        seed 3, all send rules ``change``: a committed ``C_FAST`` car held short of a car
        standing in the box kept that car waiting for it, forever."""
        if not paths.ends_at_rest(points):
            return False
        rest = float(points[-1, 0]), float(points[-1, 1])
        heading = paths.heading_of(points, points.shape[0] - 1)
        h = other.heading if heading is None else heading
        # the body at rest and the reach ahead of its front, as one rectangle
        ahead = 0.5 * HELD_REACH_M
        probe = footprints(
            rest[0] + ahead * math.cos(h),
            rest[1] + ahead * math.sin(h),
            h,
            other.length + HELD_REACH_M,
            other.width,
        )
        body = footprints(car.x, car.y, car.heading, car.length, car.width)
        return any_rects_overlap(probe, body)

    def _zone_taken(self, car: _Car, points: FloatArray, now: float) -> bool:
        """Left to its own path ``points``, ``car`` (``AUTO``, or ``C_SLOW`` about to be
        released) would be in the zone within a headway of a committed car's body
        (:meth:`_order_clash`). The point rule's 2.8 m between centres misses bodies
        that touch at a crawl (a 4.5 m car reaches 3.15 m from its centre at a corner;
        found in ``four-way-flows``, slot, seed 0). A car that is committed itself
        waits only for one that is moving (not ``C_SLOW``): two committed cars told to
        stop never wait for each other, the first judged goes on. Within ``T_collision``
        for an ``AUTO`` car (the paper's rule for slowing it), ``T_free`` for a release."""
        committed = self._committed(car, points)
        cfg = self.config
        horizon = cfg.t_collision_s if car.mode == Mode.AUTO else cfg.t_free_s
        clash = self._order_clash(
            car, points, now, moving_only=committed, horizon_s=horizon, crossing_only=True
        )
        if clash is None:
            return False
        self.counters["zone_taken"] += 1
        return True

    def _box_blocked(self, car: _Car, points: FloatArray) -> bool:
        """Don't block the box: ``points`` (``car``'s plan or own path) end at rest with its
        body in the zone, while another car stands there (at rest, its body in the zone
        now) and ``car``'s front can still stop before it braking hard, reaction and all
        (:meth:`_short_at` on :meth:`_nose_gap`). A body that
        stands in the box is stuck until its way clears, and a car that rests in the box
        behind or beside it may be what keeps that way shut (demand experiment, turning
        mix, paper, 600 veh/h, seed 0: a left turner stood mid-turn for a straight car,
        the next left turner from across stopped by its own sensors with its nose 2.3 m
        in, in the first one's exit, and neither could ever move). A stop at the edge
        costs the one car a wait; only a standing car counts, as a car crossing in front
        makes a follower's own path rest in the box only for a moment."""
        if not paths.ends_at_rest(points):
            return False
        zone = self._zone
        if not paths.body_in_zone(points, zone, car.length, car.width, car.heading):
            return False
        if self._body_now_in_zone(car) or not self._short_at(car, self._nose_gap(car, points)):
            return False
        for other in self._cars.values():
            if other is car or other.speed > paths.AT_REST_MPS:
                continue
            if not self._body_now_in_zone(other):
                continue
            entry = self.table.get(other.vehicle)
            if entry is not None and self._held_by(other, entry.points, car):
                continue  # it waits for this car: holding this one back locks them
            self.counters["box_blocked"] += 1
            return True
        return False

    def _nose_gap(self, car: _Car, points: FloatArray) -> float | None:
        """How far [m] ``car``'s front is from the zone along ``points``, continued straight
        past their end (a path whose centre stops short may still take the front in, where
        :meth:`_front_gap` sees no zone); None when the front never reaches it."""
        half = 0.5 * car.length
        s = paths.arc_length(points)
        s_zone = paths.zone_entry_s(points[:, :2], s, self._zone, half)
        if s_zone is None:
            return None
        xy = points[:, :2]
        here = int(np.argmin(np.hypot(xy[:, 0] - car.x, xy[:, 1] - car.y)))
        return max(s_zone - half - float(s[here]), 0.0)

    def _body_now_in_zone(self, car: _Car) -> bool:
        """``car``'s body, as it stands now, overlaps the zone."""
        return paths.pose_in_zone(car.x, car.y, car.heading, car.length, car.width, self._zone)

    def _yields(self, now: float, car: _Car, car_points: FloatArray, other: _Car) -> bool:
        """Must ``car`` (whose path is ``car_points``) give way to ``other``?

        A follower yields to the car ahead of it in its lane, and never the other way.
        A car that can no longer stop before the zone never yields to one that can; of two
        that cannot, one that still can braking hard (:meth:`_stops_short`) yields to one
        that cannot even so, and of two that cannot even so, one whose stop stands clear
        of the other's way (:meth:`_stop_clears`) yields to one whose stop does not, and
        else one whose centre is still outside the zone to one whose centre is in it. Then
        (issue 12, cause 3): a ``C_SLOW`` car's entry is already its stop (or slot) path,
        the most it can give, so whoever conflicts with it yields, ``C_FAST`` too; a
        ``C_FAST`` car has priority over an ``AUTO`` one; between two ``C_FAST`` cars
        the later arriver at the zone yields.
        """
        if self._ahead_in_lane(other, car, car_points):
            return True  # a follower never has the way over the car ahead of it
        other_entry = self.table.get(other.vehicle)
        if other_entry is not None and self._ahead_in_lane(car, other, other_entry.points):
            return False
        car_gap, other_gap = self._front_gap(car, car_points), self._front_gap(other)
        car_committed = self._committed_at(car, car_gap)
        other_committed = self._committed_at(other, other_gap)
        if car_committed != other_committed:
            return other_committed
        if car_committed:
            # Two committed cars: only one that can still keep out of the zone braking
            # hard yields (its stop does); demoting one that cannot leaves it standing in
            # the crossing, where the other drives into it (demand experiment, paper,
            # 400 veh/h, seed 0, with the final stop: both demoted in turn, and collided).
            car_short = self._short_at(car, car_gap)
            other_short = self._short_at(other, other_gap)
            if car_short != other_short:
                return car_short
            if not car_short and other_entry is not None:
                # Neither can: the one whose stop stands clear of the other's way yields
                # (demand experiment, turning mix, paper, 600 veh/h, seed 1: a straight car
                # 3.75 m out at 4.65 m/s, the later arriver, stopped 0.55 m into the zone,
                # in the sweep of a left turner that had just entered it, and they touched;
                # the turner, still on its approach lane, could stop clear of it)
                car_clear = self._stop_clears(now, car, other, other_entry.points)
                if car_clear != self._stop_clears(now, other, car, car_points):
                    return car_clear
            if not car_short:
                # Neither can, and neither's stop settles it: the car whose centre is in
                # the zone goes first, as the one at its edge cannot pass it (that run: a
                # left turner standing mid-turn yielded to a C_SLOW left turner from
                # across with only its nose in, which waited for it; the RSU re-stopped
                # it every time it moved off, for 60 s)
                car_in = self._zone.contains_point(car.x, car.y)
                if car_in != self._zone.contains_point(other.x, other.y):
                    return not car_in
        fast, slow = Mode.C_FAST, Mode.C_SLOW
        if other.mode == slow:
            if other.kind in _SLOT_KINDS and not self._short_at(car, car_gap):
                # a slot enters the zone as a C_FAST path does: of two that can no longer
                # keep out of it, the later arriver yields (demand experiment, slot,
                # 600 veh/h, seed 4: a car that could not stop yielded to a slot that
                # then took the zone after it)
                return self._later_arriver(car, car_points, other)
            return True
        if car.mode == fast and other.mode == Mode.AUTO:
            return False
        if other.mode == fast and car.mode != fast:
            return True
        if car.mode == fast and other.mode == fast:
            return self._later_arriver(car, car_points, other)
        return True  # neither committed: the path already in the table keeps its way

    def _later_arriver(self, car: _Car, car_points: FloatArray, other: _Car) -> bool:
        """``car`` (on ``car_points``) enters the zone after ``other`` (on its table entry);
        ties go by vehicle id."""
        entry = self.table.get(other.vehicle)
        zone = self._zone
        mine = paths.zone_entry_time(car_points, zone)
        theirs = math.inf if entry is None else paths.zone_entry_time(entry.points, zone)
        return (mine, car.vehicle) > (theirs, other.vehicle)

    def _ahead_in_lane(self, lead: _Car, car: _Car, car_points: FloatArray) -> bool:
        """``lead`` is ahead of ``car`` in its lane: it stands on ``car``'s path (within
        half their widths plus ``LANE_SLACK_M`` of it), further on than ``car``, heading
        the same way (within ``SAME_WAY_RAD``)."""
        if car_points.shape[0] < 2:
            return False
        reach = 0.5 * (car.width + lead.width) + LANE_SLACK_M
        if paths.farther_than(car_points, lead.x, lead.y, reach):
            return False  # nowhere near the path (issue 14: the projections cost)
        where = np.array([[lead.x, lead.y], [car.x, car.y]])
        s, off, i = paths.project_many(car_points, where)
        if float(off[0]) > reach or float(s[0]) <= float(s[1]):
            return False
        heading = paths.heading_of(car_points, int(i[0]))
        return heading is not None and math.cos(lead.heading - heading) >= math.cos(SAME_WAY_RAD)

    def _fast_plan(self, now: float, car: _Car, path: VehiclePath) -> SpeedPlan | None:
        """The ``C_FAST`` plan ``car`` would get, if it may have it: the plan itself (not
        the car's own path, issue 12 cause 2) is clear of the table over ``T_free`` with
        the release margins, and keeps the crossing order of committed cars."""
        cfg = self.config
        plan = self.velocity.plan(car.vehicle, path, Mode.C_FAST, now, self.table)
        found = self.table.conflicts(
            car.vehicle, plan.points, now, cfg.t_free_s, (), *self._margins, shape=car.shape
        )
        found = self._past_stuck(car, plan.points, found)
        if found or self._touches_stuck(car, plan.points):
            self.counters["fast_plan_unclear"] += 1
            return None
        if self._order_clash(car, plan.points, now) is not None:
            self.counters["order_kept"] += 1
            return None
        if self._box_blocked(car, plan.points):
            return None
        return plan

    def _may_change(self, car: _Car, now: float) -> bool:
        """Hysteresis in time (issue 12, cause 4): a car is promoted or released only
        ``MODE_DWELL_S`` after its last mode change (from its ``FREE_MODE_CHANGES``-th
        on: AUTO -> C_SLOW -> C_FAST, the usual crossing, is never held), ``LATE_DWELL_S``
        once it has changed mode ``MAX_MODE_CHANGES`` times in this crossing. Demotions
        for safety and the termination of a leaving car are never held back."""
        if car.changes < FREE_MODE_CHANGES:
            return True
        dwell = MODE_DWELL_S if car.changes < MAX_MODE_CHANGES else LATE_DWELL_S
        return now - car.changed_at >= dwell - _DUE_SLACK_S

    def _decide(self, now: float, car: _Car, path: VehiclePath) -> list[Outgoing]:
        """Judge a car on its autonomous path (see ``services.rsu.modes``) and act."""
        cfg = self.config
        plan: SpeedPlan | None = None
        near: list[Conflict] = []
        if self._leaving(car):
            event = RsuEvent.LEAVING
        else:
            if car.mode == Mode.C_FAST:
                # judged on the plan it is sent (cause 2), its own path's speeds aside
                plan = self.velocity.plan(car.vehicle, path, Mode.C_FAST, now, self.table)
                query = plan.points
            else:
                query = path.points
            # A slowing car is released only when it is clear by a margin (hysteresis).
            margins = self._margins if car.mode == Mode.C_SLOW else (0.0, 0.0)
            found = self.table.conflicts(
                car.vehicle, query, now, cfg.t_free_s, (), *margins, shape=car.shape
            )
            if found and car.mode == Mode.C_SLOW:
                found = self._past_standing(car, query, now, found)
            # A C_FAST car settles every conflict within T_free, not only within
            # T_collision: two cars promoted while far apart first meet beyond
            # T_collision, and by T_collision the one that must yield may no longer be
            # able to stop (issue 12, found by the invariant's property test).
            horizon = now + (cfg.t_free_s if car.mode == Mode.C_FAST else cfg.t_collision_s)
            near = [c for c in found if c.time <= horizon]
            if found:
                self.counters["conflicts"] += 1
            yields = False
            for conflict in near:
                other = self._cars.get(conflict.vehicle)
                if other is not None and self._yields(now, car, query, other):
                    yields = True
                    break
            if yields and plan is not None:
                kept = self._keeps_reservation(now, car, plan)
                if kept is not None:
                    return [kept]
            if yields:
                event = RsuEvent.CONFLICT
            elif car.mode == Mode.C_FAST:
                # it keeps its way (the others yield below), unless that rests it in a box
                # another car stands in
                blocked = self._box_blocked(car, query)
                event = RsuEvent.CONFLICT if blocked else RsuEvent.NO_CONFLICT
            elif not found and self._approaching(car, path, now) and self._clear(car, query, now):
                event = RsuEvent.FREE_APPROACHING
                may = self._may_change(car, now)
                plan = self._fast_plan(now, car, path) if may else None
                if plan is None:
                    # it waits its turn: a C_SLOW car stays (new path), an AUTO car slows,
                    # except an AUTO car held only by the dwell while still beyond
                    # T_collision: its own path is clear over T_free, so it drives it
                    # (slowing it for the dwell alone made a queued follower cycle
                    # C_SLOW -> AUTO -> C_SLOW every 3-4 s; four-way-flows, seed 0)
                    entry = paths.zone_entry_time(path.points, self._zone)
                    far = entry > now + cfg.t_collision_s
                    held = not may and far and car.mode == Mode.AUTO
                    if (
                        held
                        and not self._zone_taken(car, query, now)
                        and not self._box_blocked(car, query)
                    ):
                        event = RsuEvent.NO_CONFLICT
                    else:
                        event = RsuEvent.CONFLICT
            elif car.mode == Mode.C_SLOW and (found or not self._may_change(car, now)):
                # stays C_SLOW (a new path): released only when its own path is clear
                # over T_free by the margins (hysteresis: T_collision to slow it, T_free
                # to let it go; issue 12, cause 4), and not within the dwell
                event = RsuEvent.CONFLICT
            elif self._zone_taken(car, query, now) or self._box_blocked(car, query):
                event = RsuEvent.CONFLICT  # left alone, it would drive into a committed body
            elif car.mode == Mode.C_SLOW and self._touches_stuck(car, query):
                event = RsuEvent.CONFLICT  # released, it would touch a body held standing
            else:
                event = RsuEvent.NO_CONFLICT
        out = self._apply(now, car, event, path, plan)
        if car.mode == Mode.C_FAST:
            reuse = near if plan is not None and event != RsuEvent.CONFLICT else None
            out.extend(self._give_way_to(now, car, reuse))
        return out

    def _keeps_reservation(self, now: float, car: _Car, plan: SpeedPlan) -> Outgoing | None:
        """A ``C_FAST`` car whose new plan would make it yield keeps the coordinated path
        it was last sent (resent, as its table entry) when the new plan only jumped
        earlier than that path (the car ahead it was retimed behind has gone) and that
        path still covers ``T_collision`` clear of the table over ``T_free`` and of the
        crossing order. Without this, the earlier plan met a crossing car promoted into
        the gap the old one left, both committed, and the box locked (demand experiment,
        slot, 600 veh/h, seed 1). A car that is not where that path puts it now
        (``KEEP_TRACK_M``) does not drive it and keeps nothing. None when it does not
        keep it."""
        cfg = self.config
        last, entry = car.last_cp, self.table.get(car.vehicle)
        if last is None or entry is None or entry.points is not last.points:
            return None
        if last.mode != car.mode:
            return None
        pts = last.points
        if float(pts[-1, 2]) < now + cfg.t_collision_s:
            return None
        t = pts[:, 2]
        if not float(t[0]) <= now:
            return None
        where = float(np.interp(now, t, pts[:, 0])), float(np.interp(now, t, pts[:, 1]))
        if math.hypot(where[0] - car.x, where[1] - car.y) > KEEP_TRACK_M:
            return None  # it is not where that path puts it now: it does not drive it
        old_entry = paths.zone_entry_time(pts, self._zone)
        new_entry = paths.zone_entry_time(plan.points, self._zone)
        if not (now < old_entry < math.inf and new_entry < old_entry - cfg.headway_s):
            return None  # not a crossing whose plan jumped earlier
        if self.table.conflicts(car.vehicle, pts, now, cfg.t_free_s, (), shape=car.shape):
            return None
        if self._order_clash(car, pts, now, crossing_only=True) is not None:
            return None
        self.table.touch(car.vehicle, now)
        self.counters["reservation_kept"] += 1
        message = CoordinatedPath(self._header(now), car.vehicle, car.mode, pts, last.speeds)
        return Outgoing(car.vehicle, message)

    def _apply(
        self, now: float, car: _Car, event: RsuEvent, path: VehiclePath, plan: SpeedPlan | None
    ) -> list[Outgoing]:
        """One transition of the table for ``car``, and what it sends."""
        self.counters[f"event_{event.name.lower()}"] += 1
        mode, action = transition(car.mode, event)
        if mode != car.mode:
            car.changes += 1
            car.changed_at = now
            self.counters["mode_changes"] += 1
        car.mode = mode
        out: list[Outgoing] = []
        vehicle = car.vehicle
        if action == Action.SEND_TERMINATION:
            car.held_short = False
            out.append(self._command(now, car, Command.TERMINATE, Mode.AUTO))
            self.counters["terminations"] += 1
            self._reserve(now, car, path.points)
        elif action in (Action.SEND_INITIATION_SLOW, Action.SEND_INITIATION_FAST):
            out.append(self._command(now, car, Command.INITIATE, mode))
            self.counters["initiations"] += 1
            car.sent = None  # a new initiation always comes with its coordinated path
            sent = self._coordinate(now, car, path, plan if mode == Mode.C_FAST else None)
            if sent is not None:
                out.append(sent)
        elif action == Action.FORGET:
            self.forget(vehicle)
        elif mode == Mode.AUTO:
            self._reserve(now, car, path.points)
        elif isinstance(path, AutonomousPath):
            sent = self._coordinate(now, car, path, plan)
            if sent is not None:
                out.append(sent)
        else:
            self.table.touch(vehicle, now)
        return out

    def _apply_silent(self, vehicle: str) -> None:
        car = self._cars.get(vehicle)
        self.counters["expired"] += 1
        if car is None:
            self.table.remove(vehicle)
            return
        _, action = transition(car.mode, RsuEvent.SILENT)
        if action == Action.FORGET:
            self.forget(vehicle)

    def _give_way_to(self, now: float, car: _Car, near: list[Conflict] | None) -> list[Outgoing]:
        """A ``C_FAST`` car has priority: every car its path conflicts with (within
        ``T_free``) must yield, unless ``_yields`` says the C_FAST car is the one to."""
        if near is None:
            entry = self.table.get(car.vehicle)
            if entry is None:
                return []
            near = self.table.conflicts(
                car.vehicle, entry.points, now, self.config.t_free_s, shape=car.shape
            )
        out: list[Outgoing] = []
        for conflict in near:
            other = self._cars.get(conflict.vehicle)
            if other is None or other.autonomous is None or other.mode == Mode.C_SLOW:
                continue  # unknown, or already slowing
            other_entry = self.table.get(other.vehicle)
            other_points = other.autonomous.points if other_entry is None else other_entry.points
            if not self._yields(now, other, other_points, car):
                continue
            event = RsuEvent.LEAVING if self._leaving(other) else RsuEvent.CONFLICT
            self.counters["given_way"] += 1
            out.extend(self._apply(now, other, event, other.autonomous, None))
        return out

    def _unchanged(self, now: float, car: _Car, points: FloatArray) -> bool:
        """Under the coordinated path's change rule (``services.model.send_rule``): True
        when the last coordinated path sent to ``car`` stands instead of ``points`` (it is
        still the car's reservation in the table, in the same mode, covers now, was sent
        less than ``cp_refresh_s`` ago and deviates by at most ``cp_change_m``). Then the
        table keeps it, refreshed: the car drives it, so the table holds what it drives."""
        cfg = self.config
        if cfg.cp_change_m is None:
            return False
        rule = car.sent
        entry = self.table.get(car.vehicle)
        if rule is None or entry is None or entry.points is not rule.last_points:
            rule = car.sent = ChangeRule(cfg.cp_change_m, cfg.cp_refresh_s)
        if rule.why(now, points, car.mode) is not None:
            return False
        self.table.touch(car.vehicle, now)
        self.counters["cp_unchanged"] += 1
        return True

    def _command(self, now: float, car: _Car, command: Command, mode: Mode) -> Outgoing:
        car.pending = _Pending(command, mode, now)
        return Outgoing(car.vehicle, ModeCommand(self._header(now), car.vehicle, command, mode))

    def _reserve(self, now: float, car: _Car, points: FloatArray) -> None:
        self.table.update(car.vehicle, points, now, (car.length, car.width))

    def _coordinate(
        self, now: float, car: _Car, path: VehiclePath, plan: SpeedPlan | None
    ) -> Outgoing | None:
        """Compute (unless given), reserve and send the car's coordinated path; None when
        the send rule keeps the last one sent (``cp_change_m``: :meth:`_unchanged`)."""
        if plan is None:
            firm = car.held_short and car.mode == Mode.C_SLOW
            # a car committed itself waits only for moving bodies (as in _zone_taken): two
            # committed cars told to stop must not each wait for the other's hold
            moving_only = self._committed(car, path.points)

            def in_order(points: FloatArray) -> bool:
                # a slot enters the zone: it keeps the crossing order as a C_FAST plan does
                clash = self._order_clash(
                    car, points, now, moving_only=moving_only, crossing_only=True
                )
                return clash is None

            # a stop is news to a car not already told to stop: it reacts (REACTION_S)
            reaction = REACTION_S - (now - car.stop_since) if car.stopping else REACTION_S
            plan = self.velocity.plan(
                car.vehicle,
                path,
                car.mode,
                now,
                self.table,
                firm=firm,
                reaction_s=reaction,
                admissible=in_order,
            )
        points, speeds, reserved = plan.points, plan.speeds, plan.reserved
        cap = self.config.max_points
        if cap is not None and points.shape[0] > cap:
            # evenly thinned, first and last kept: same path, fewer points (fits a datagram)
            keep = _thinned(points, cap)
            points, speeds = points[keep], speeds[keep]
            self.counters["thinned_paths"] += 1
        if cap is not None and reserved is not None and reserved.shape[0] > cap:
            reserved = reserved[_thinned(reserved, cap)]
        points = np.array(points, dtype=np.float64)
        points.flags.writeable = False  # shared by the table, the message and the rule
        if self.config.cp_change_m is not None and self._unchanged(now, car, points):
            return None
        car.held_short = plan.short
        if plan.kind in _STOP_KINDS and not car.stopping:
            car.stop_since = now
        car.kind = plan.kind
        # where it will be (SpeedPlan.reserved), if further on than where it is told to stop
        self._reserve(now, car, points if reserved is None else reserved)
        self.counters["coordinated_paths"] += 1
        self.counters[f"plan_{plan.kind}"] += 1
        message = CoordinatedPath(self._header(now), car.vehicle, car.mode, points, speeds)
        car.last_cp = message
        return Outgoing(car.vehicle, message)
