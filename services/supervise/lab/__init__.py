"""The multi-host network lab: one network namespace per actor, faults on the air.

:mod:`.netns` builds and removes the namespaces and runs commands in them;
:mod:`.faults` injects loss, rate limits and crashes on the air and reads counters.
See ``deploy/lab/README.md``.
"""

from services.supervise.lab.faults import (
    AirCounters,
    AirFaults,
    Direction,
    Loss,
    Rate,
    air_counters,
    clear,
    crash,
    set_loss,
    set_rate,
)
from services.supervise.lab.netns import (
    Lab,
    LabError,
    LabPlan,
    Net,
    NodePlan,
    Role,
    down_all,
    prerequisites,
)

__all__ = [
    "AirCounters",
    "AirFaults",
    "Direction",
    "Lab",
    "LabError",
    "LabPlan",
    "Loss",
    "Net",
    "NodePlan",
    "Rate",
    "Role",
    "air_counters",
    "clear",
    "crash",
    "down_all",
    "prerequisites",
    "set_loss",
    "set_rate",
]
