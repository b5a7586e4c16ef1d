"""The monitor's append-only step log: what a result can be rebuilt from if the monitor dies.

Why: a monitor killed mid-run (SIGKILL, OOM, a crashed host) never writes its
result, and the actors end their runs within a second of losing it. So the
monitor writes, as it goes, every input its result is made of to a JSON Lines
file beside ``--json OUT`` (``OUT``'s stem + ``.steps.jsonl``, e.g.
``result.steps.jsonl`` in a ``crosspath up`` run dir), line buffered, so
everything up to the kill is on disk:

- ``{"k": "start", ...}``: the run (id, scenario name and file, mode, policy,
  seed, start times, ``epoch_unix``, ``speed``, ``max_sim_s``, cars, RSUs,
  ``expect_crash``), once, when the run starts;
- ``{"k": "truth", "w": unix_s, "v": car, "n": step, "st": [...], "m": mode,
  "r": reason, "p": presence}``: every truth report the monitor's core kept, with its arrival
  (wall clock, Unix s) and the car's ``TruthState`` as the list
  :data:`STATE_FIELDS` (floats as JSON writes them: exact);
- ``{"k": "stats", "w": unix_s, "node", "final", "snapshot"}``: every stats
  report of the run that the monitor kept (V2X counters, ``late_ticks``);
- ``{"k": "end", "w": unix_s, "reason", "error", "steps"}``: once the result is
  built (``steps``: how many physics steps the monitor closed).

``services.daemons.monitor.rebuild_result`` replays it through the same pure
core (``services.sim.truth.TruthSteps``), so a rebuilt result's safety metrics
are computed exactly as the monitor's would have been for the steps it had
closed. This module only reads and writes the file.
"""

from __future__ import annotations

import json
import math
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import IO, Any, Final

from services.edge.plumbing import StartRun, StatsReport, TruthReport
from services.model.kinematics import TruthState

__all__ = [
    "STATE_FIELDS",
    "StepLog",
    "StepLogError",
    "StepLogRecord",
    "read_step_log",
    "step_log_path",
]

STATE_FIELDS: Final = ("t", "x", "y", "heading", "speed", "accel", "s", "length", "width")
"""The ``TruthState`` fields of a ``truth`` line's ``st`` list, in order."""

SUFFIX: Final = ".steps.jsonl"


class StepLogError(ValueError):
    """A step log that cannot be read (missing, no ``start`` line, a bad line)."""


def step_log_path(json_out: Path) -> Path:
    """Where the monitor writes the step log of a result written to ``json_out``."""
    return json_out.with_name(json_out.stem + SUFFIX)


class StepLog:
    """Appends lines to the step log (line buffered: a kill loses at most one line)."""

    def __init__(self, path: Path) -> None:
        self.path = path
        path.parent.mkdir(parents=True, exist_ok=True)
        self._fh: IO[str] | None = path.open("w", buffering=1, encoding="utf-8")

    def _write(self, data: dict[str, Any]) -> None:
        if self._fh is not None:
            self._fh.write(json.dumps(data, allow_nan=False, separators=(",", ":")) + "\n")

    def start(self, start: StartRun, scenario_file: str | None, expect_crash: list[str]) -> None:
        """The run's ``start`` line."""
        self._write(
            {
                "k": "start",
                "run_id": start.run_id,
                "scenario": start.scenario,
                "scenario_file": scenario_file,
                "mode": str(start.mode),
                "policy": str(start.policy),
                "seed": start.seed,
                "start_times": dict(start.start_times),
                "epoch_unix": start.epoch_unix,
                "speed": start.speed,
                "max_sim_s": start.max_sim_s,
                "vehicles": list(start.vehicles),
                "rsus": list(start.rsus),
                "expect_crash": expect_crash,
            }
        )

    def truth(self, wall: float, report: TruthReport) -> None:
        """One kept truth report, arrived at Unix time ``wall``."""
        st = report.state
        values = [float(getattr(st, name)) for name in STATE_FIELDS]
        if not all(math.isfinite(v) for v in values):
            return  # the plumbing decoder refuses these; never write what cannot be read
        self._write(
            {
                "k": "truth",
                "w": wall,
                "v": report.vehicle,
                "n": report.step,
                "st": values,
                "m": report.mode,
                "r": report.reason,
                "p": report.presence,
            }
        )

    def stats(self, wall: float, report: StatsReport) -> None:
        """One kept stats report."""
        self._write(
            {
                "k": "stats",
                "w": wall,
                "node": report.node,
                "final": report.final,
                "snapshot": report.snapshot,
            }
        )

    def end(self, wall: float, reason: str | None, error: str | None, steps: int) -> None:
        """The result was built: the run's end after ``steps`` closed steps."""
        self._write({"k": "end", "w": wall, "reason": reason, "error": error, "steps": steps})

    def close(self) -> None:
        """Close the file; idempotent."""
        fh, self._fh = self._fh, None
        if fh is not None:
            fh.close()


@dataclass(slots=True)
class StepLogRecord:
    """What a step log holds: the ``start`` line, and the other lines in order as
    (Unix time, truth report | stats report); ``end`` when the monitor finished;
    ``bad_lines`` lines that could not be read (a torn last line after a kill)."""

    start: dict[str, Any]
    events: list[tuple[float, TruthReport | StatsReport]] = field(default_factory=list)
    end: dict[str, Any] | None = None
    bad_lines: int = 0


def _lines(path: Path) -> Iterator[dict[str, Any]]:
    with path.open(encoding="utf-8") as fh:
        for line in fh:
            try:
                data = json.loads(line)
            except json.JSONDecodeError:
                yield {}
                continue
            yield data if isinstance(data, dict) else {}


def read_step_log(path: Path) -> StepLogRecord:
    """Read a step log; :class:`StepLogError` when it is missing or has no ``start``."""
    if not path.is_file():
        raise StepLogError(f"no step log at {path}")
    record: StepLogRecord | None = None
    bad = 0
    for data in _lines(path):
        kind = data.get("k")
        try:
            if kind == "start":
                if record is None:
                    record = StepLogRecord(start=data)
                continue
            if record is None:
                bad += 1
                continue
            if kind == "truth":
                state = TruthState(str(data["v"]), *(float(x) for x in data["st"]))
                report = TruthReport(
                    record.start["run_id"],
                    int(data["n"]),
                    state,
                    str(data["m"]),
                    str(data["r"]),
                    str(data.get("p", "in")),
                )
                record.events.append((float(data["w"]), report))
            elif kind == "stats":
                stats = StatsReport(
                    node=str(data["node"]),
                    run_id=record.start["run_id"],
                    final=bool(data["final"]),
                    snapshot=dict(data["snapshot"]),
                )
                record.events.append((float(data["w"]), stats))
            elif kind == "end":
                record.end = data
            else:
                bad += 1
        except (KeyError, TypeError, ValueError):
            bad += 1
    if record is None:
        raise StepLogError(f"{path}: no start line (the run never started?)")
    record.bad_lines = bad
    return record
