"""Whether a car obeys a verified RSU message (issue 13, "Who may say what"). Pure.

The signature and the certificate chain are checked before this
(``services.edge.trust``); here the car asks whether *that* RSU may command
*it*, now:

- a mode command INITIATE or a coordinated path only from an RSU whose
  certificate names the intersection the car is approaching (the first
  crossing of its route it has not yet left) or has just left (the RSU holds a
  car until it releases it, a few metres past the zone), and only while the car
  is inside the certificate's coverage disc;
- a TERMINATE from any RSU certificate (decision: it only hands the car back to
  its own autonomous planner, which is always safe, and it must reach a car
  that has just left the coverage);
- beacons and other cars' paths are not commands: always accepted.
"""

from __future__ import annotations

from collections.abc import Sequence

from protocol import Command, CoordinatedPath, Message, ModeCommand
from protocol.auth import Certificate, Role
from services.model.scenario import Crossing

__all__ = ["approaching", "leaving", "refusal"]


def approaching(crossings: Sequence[Crossing], s: float) -> str | None:
    """The intersection a car at arc length ``s`` [m] on its route approaches or is in
    (the first crossing it has not left), None once past every one."""
    for c in crossings:
        if s < c.s_out:
            return c.intersection
    return None


def leaving(crossings: Sequence[Crossing], s: float) -> str | None:
    """The intersection a car at arc length ``s`` [m] left last, None before the first."""
    left = [c for c in crossings if c.s_out <= s]
    return left[-1].intersection if left else None


def refusal(
    message: Message,
    certificate: Certificate | None,
    crossings: Sequence[Crossing],
    s: float,
    x: float,
    y: float,
) -> str | None:
    """Why the car at (x, y) [m], arc length ``s`` [m], must not obey ``message`` signed
    under ``certificate``; None if it may. Reasons are counter names."""
    if not isinstance(message, ModeCommand | CoordinatedPath):
        return None
    if certificate is None or certificate.role is not Role.RSU:
        return "cmd_unauthorised"
    if isinstance(message, ModeCommand) and message.command is Command.TERMINATE:
        return None
    targets = {approaching(crossings, s), leaving(crossings, s)} - {None}
    if not targets & set(certificate.intersections):
        return "cmd_wrong_intersection"
    if certificate.coverage is None or not certificate.coverage.contains(x, y):
        return "cmd_out_of_coverage"
    return None
