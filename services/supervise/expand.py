"""One trial's plain scenario file: flows drawn for a seed, every start time fixed.

The daemons of a run must agree on its cars before any of them starts: a car's
node id is its vehicle id, and the monitor waits for every one of them. A scenario
with ``[[flows]]`` names its cars only per seed (``Scenario.for_seed``), so
``crosspath up`` writes, in the run dir, the scenario of the run's seed as a plain
file (no flows, every ``start_time_s`` a number: the flows' arrivals and the
``[[vehicles]]``' draws for that seed) and hands that file to every daemon.
Decision: the daemons load only plain files (``Scenario.require_no_flows``); the
expansion happens once, in the launcher, so every node reads the same cars. The
run's provenance digests the expanded file (what the daemons actually ran); its
description names the source file and the seed.

No TOML writer is a dependency: :func:`scenario_toml` emits the small subset the
scenario model needs (tables, arrays of tables, inline tables, numbers, strings,
booleans, arrays), and :func:`expand_scenario` checks that the file reads back as
the same scenario.
"""

from __future__ import annotations

import json
import math
from pathlib import Path
from typing import Any

from services.model.scenario import Scenario, parse_scenario

__all__ = ["expand_scenario", "plain_scenario", "scenario_toml"]


def plain_scenario(scenario: Scenario, seed: int) -> Scenario:
    """The scenario of one trial: flows drawn for ``seed`` (cars ``<flow>-<n>``) and every
    car's start time fixed to its draw for ``seed``; no flows, no ranges left."""
    expanded = scenario.for_seed(seed)
    starts = expanded.draw_start_times(seed)
    spec = expanded.spec
    cars = [v.model_copy(update={"start_time_s": starts[v.id]}) for v in spec.vehicles]
    info = spec.scenario.model_copy(
        update={
            "description": (
                f"{spec.scenario.description} [expanded for seed {seed} from {scenario.source}]"
            ).strip()
        }
    )
    return Scenario(
        spec.model_copy(update={"vehicles": cars, "flows": [], "scenario": info}), scenario.source
    )


def _value(value: Any) -> str:
    """One TOML value (inline)."""
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, int):
        return str(value)
    if isinstance(value, float):
        if math.isnan(value):
            return "nan"
        if math.isinf(value):
            return "inf" if value > 0 else "-inf"
        return repr(value)
    if isinstance(value, str):
        return json.dumps(value, ensure_ascii=False)  # a valid TOML basic string
    if isinstance(value, list | tuple):
        return "[" + ", ".join(_value(v) for v in value) + "]"
    if isinstance(value, dict):
        return "{" + ", ".join(f"{_key(k)} = {_value(v)}" for k, v in value.items()) + "}"
    raise TypeError(f"no TOML form for {type(value).__name__}: {value!r}")


def _key(key: str) -> str:
    bare = key.replace("_", "").replace("-", "").isalnum() and key.isascii()
    return key if bare else json.dumps(key)


def scenario_toml(scenario: Scenario) -> str:
    """The scenario's document as TOML text (every field, Nones left out)."""
    data = scenario.spec.model_dump(mode="python", exclude_none=True)
    lines: list[str] = []
    for name, body in data.items():
        if isinstance(body, dict):
            lines.append(f"[{_key(name)}]")
            lines += [f"{_key(k)} = {_value(v)}" for k, v in body.items()]
            lines.append("")
        elif isinstance(body, list) and body and all(isinstance(x, dict) for x in body):
            for item in body:
                lines.append(f"[[{_key(name)}]]")
                lines += [f"{_key(k)} = {_value(v)}" for k, v in item.items()]
                lines.append("")
        elif isinstance(body, list):
            continue  # an empty array of tables: the default
        else:
            raise TypeError(f"top-level {name!r} is neither a table nor an array of tables")
    return "\n".join(lines)


def expand_scenario(scenario: Scenario, seed: int, out: Path) -> Path:
    """Write :func:`plain_scenario` of ``scenario`` for ``seed`` to ``out`` (TOML); ``out``.
    Raises ``RuntimeError`` if the written file does not read back as the same scenario
    (a bug of :func:`scenario_toml`)."""
    plain = plain_scenario(scenario, seed)
    text = scenario_toml(plain)
    back = parse_scenario(text, str(out))
    if back.spec != plain.spec:
        raise RuntimeError(f"the expanded scenario {out} does not read back as written")
    out.parent.mkdir(parents=True, exist_ok=True)
    tmp = out.with_name(out.name + ".tmp")
    tmp.write_text(f"# {plain.spec.scenario.description}\n\n" + text, encoding="utf-8")
    tmp.replace(out)
    return out
