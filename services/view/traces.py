"""What ``crosspath view --replay`` reads: the traces runs already write.

- the per-step CSV of ``crosspath sim --trace OUT`` and ``crosspath up --trace OUT``
  (``services.sim.harness.TRACE_FIELDS``: run time, car, position, speed, planner
  reason, mode); it names no scenario, so the map comes from ``--scenario``;
- the monitor's step log (``services.daemons.steplog``, ``result.steps.jsonl``),
  which every ``crosspath up`` run dir holds, or the run dir itself: ground truth
  with heading and size, and the scenario file named in its ``start`` line.

Neither carries V2X messages, so a replay shows positions, modes, speeds and the
map but no future or coordinated paths; those are drawn live only (decision: no
second recorder of the radio traffic).
"""

from __future__ import annotations

import csv
from dataclasses import dataclass
from pathlib import Path

from services.daemons.steplog import SUFFIX, StepLogError, read_step_log
from services.edge.plumbing import TruthReport
from services.view.state import TraceRow, rows_from_trace_csv

__all__ = ["LoadedTrace", "TraceError", "load_trace"]


class TraceError(ValueError):
    """A file or directory that is not a trace the view can replay."""


@dataclass(frozen=True, slots=True)
class LoadedTrace:
    """The rows of a trace, and the scenario (file or name) it names, if any."""

    rows: list[TraceRow]
    scenario: str | None
    kind: str  # "csv" or "steplog"


def _from_step_log(path: Path) -> LoadedTrace:
    try:
        record = read_step_log(path)
    except StepLogError as exc:
        raise TraceError(str(exc)) from None
    rows: list[TraceRow] = []
    for _, event in record.events:
        if isinstance(event, TruthReport):
            st = event.state
            rows.append(
                TraceRow(
                    st.t,
                    st.id,
                    st.x,
                    st.y,
                    st.speed,
                    event.mode,
                    event.reason,
                    st.heading,
                    st.length,
                    st.width,
                )
            )
    start = record.start
    scenario = start.get("scenario_file") or start.get("scenario")
    return LoadedTrace(rows, str(scenario) if scenario else None, "steplog")


def load_trace(path: Path) -> LoadedTrace:
    """Read a trace CSV, a step log or a run dir (see the module docstring);
    :class:`TraceError` with the reason when it is none of them or has no rows."""
    if path.is_dir():
        logs = sorted(path.glob(f"*{SUFFIX}"))
        if not logs:
            raise TraceError(f"{path}: no step log (*{SUFFIX}) in this directory")
        path = logs[0]
    if not path.is_file():
        raise TraceError(f"{path}: no such file")
    if path.name.endswith(SUFFIX) or path.suffix == ".jsonl":
        loaded = _from_step_log(path)
    else:
        try:
            with path.open(newline="", encoding="utf-8") as fh:
                rows = rows_from_trace_csv(csv.DictReader(fh))
        except (OSError, UnicodeDecodeError, csv.Error, ValueError) as exc:
            raise TraceError(f"{path}: {exc}") from None
        loaded = LoadedTrace(rows, None, "csv")
    if not loaded.rows:
        raise TraceError(f"{path}: the trace has no rows")
    return loaded
