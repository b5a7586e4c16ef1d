"""Names shared by every layer: the run modes of the paper and the RSU's velocity policies."""

from __future__ import annotations

from enum import StrEnum

__all__ = ["Policy", "RunMode"]


class RunMode(StrEnum):
    """The paper's three scenarios."""

    STANDALONE = "standalone"  # no V2X
    FP_ONLY = "fp-only"  # future paths between cars, no RSU
    RSU = "rsu"  # future paths plus the RSU


class Policy(StrEnum):
    """Velocity manager policy: the paper's, or ours (see ``services.rsu.velocity``)."""

    PAPER = "paper"
    SLOT = "slot"
