"""Names shared by every layer: the run modes of the paper and the RSU's velocity policies."""

from __future__ import annotations

from enum import StrEnum
from typing import TypeVar

__all__ = ["Policy", "RunMode", "parse_mode", "parse_policy"]


class RunMode(StrEnum):
    """The paper's three scenarios."""

    STANDALONE = "standalone"  # no V2X
    FP_ONLY = "fp-only"  # future paths between cars, no RSU
    RSU = "rsu"  # future paths plus the RSU


class Policy(StrEnum):
    """Velocity manager policy: the paper's, or ours (see ``services.rsu.velocity``)."""

    PAPER = "paper"
    SLOT = "slot"


_E = TypeVar("_E", bound=StrEnum)


def _parse(kind: type[_E], value: object, what: str) -> _E:
    if isinstance(value, kind):
        return value
    if isinstance(value, str):
        for member in kind:
            if member.value == value:
                return member
    allowed = ", ".join(member.value for member in kind)
    raise ValueError(f"unknown {what} {value!r}: expected one of {allowed}")


def parse_mode(value: RunMode | str) -> RunMode:
    """``value`` (a :class:`RunMode` or its name) as a RunMode; ``ValueError`` naming the
    allowed values otherwise (so ``"rsu"`` is never mistaken for another mode)."""
    return _parse(RunMode, value, "mode")


def parse_policy(value: Policy | str) -> Policy:
    """``value`` (a :class:`Policy` or its name) as a Policy; ``ValueError`` naming the
    allowed values otherwise."""
    return _parse(Policy, value, "policy")
