"""The Python API (``services.api``): names or enums, refusals, provenance, and the same run
as the CLI's (its real daemon run: tests/experiments/test_paper_daemons.py)."""

from __future__ import annotations

import dataclasses
import hashlib
import math
import subprocess
import sys
from pathlib import Path
from typing import Any

import pytest

from services.api import run_daemons, simulate
from services.edge.provenance import package_version
from services.experiments.common import read_trace_csv
from services.model.results import RunResult
from services.model.scenario import ScenarioError, load_scenario
from services.model.types import Policy, RunMode
from services.rsu.config import RsuConfig
from services.sim.harness import TRACE_FIELDS

ROOT = Path(__file__).resolve().parents[1]
PAPER = ROOT / "scenarios" / "paper-blind-intersection.toml"
WALL_CLOCK = ("wall_s", "speedup_vs_real_time")


def _content(result: RunResult) -> dict[str, Any]:
    """The result's JSON without the fields that depend on the machine's speed."""
    data = result.to_dict()
    for key in WALL_CLOCK:
        data.pop(key)
    return data


def test_names_enums_paths_and_scenarios_are_the_same_run() -> None:
    by_name = simulate(PAPER, mode="rsu", policy="slot", seed=3)
    by_enum = simulate(str(PAPER), mode=RunMode.RSU, policy=Policy.SLOT, seed=3)
    loaded = simulate(load_scenario(PAPER), mode="rsu", policy=Policy.SLOT, seed=3)
    assert by_name.mode is RunMode.RSU and by_name.policy is Policy.SLOT
    assert _content(by_name) == _content(by_enum) == _content(loaded)
    packaged = simulate("paper-blind-intersection", mode="rsu", policy="slot", seed=3)
    assert packaged.vehicles == by_name.vehicles
    assert packaged.provenance is not None and by_name.provenance is not None
    assert packaged.provenance.scenario_sha256 == by_name.provenance.scenario_sha256


@pytest.mark.parametrize(
    ("kwargs", "message"),
    [
        ({"mode": "bogus"}, "unknown mode 'bogus': expected one of standalone, fp-only, rsu"),
        ({"mode": "fp_only"}, "expected one of standalone, fp-only, rsu"),
        ({"policy": "fastest"}, "unknown policy 'fastest': expected one of paper, slot"),
        ({"loss": 1.5}, "loss must be a finite number within 0..1"),
        ({"loss": 30}, "loss must be a finite number within 0..1"),
        ({"loss": math.nan}, "loss"),
        ({"latency_ms": -1.0}, "latency_ms"),
        ({"jitter_ms": math.nan}, "jitter_ms"),
        ({"jitter_ms": "1"}, "jitter_ms must be a number"),
        ({"seed": -1}, "seed must be an int >= 0"),
        ({"max_sim_s": 0.0}, "max_sim_s"),
        ({"start_times": {"A": 0.0, "B": math.inf}}, "start times"),
    ],
)
def test_simulate_refuses_what_it_cannot_run(kwargs: dict[str, Any], message: str) -> None:
    with pytest.raises(ValueError) as info:
        simulate(PAPER, **kwargs)
    assert message in str(info.value)


def test_simulate_refuses_bad_scenarios(tmp_path: Path) -> None:
    with pytest.raises(ScenarioError, match=r"missing\.toml"):
        simulate(tmp_path / "missing.toml")
    with pytest.raises(TypeError, match="scenario"):
        simulate(42)  # type: ignore[arg-type]
    with pytest.raises(TypeError, match="trace"):
        simulate(PAPER, trace=3)  # type: ignore[arg-type]


def test_the_result_carries_its_provenance() -> None:
    r = simulate(PAPER, mode="standalone", seed=1, loss=0.25, latency_ms=5.0, jitter_ms=0.5)
    prov = r.provenance
    assert prov is not None
    assert prov.scenario == "paper-blind-intersection" == r.scenario
    assert prov.scenario_file == str(PAPER)
    assert prov.scenario_sha256 == hashlib.sha256(PAPER.read_bytes()).hexdigest()
    assert prov.version == package_version() and prov.version
    if (ROOT / ".git").exists():
        head = subprocess.run(
            ["git", "-C", str(ROOT), "rev-parse", "HEAD"], capture_output=True, text=True
        ).stdout.strip()
        assert prov.commit == head
    channel = prov.channel
    assert (channel.kind, channel.loss) == ("memory", 0.25) and r.loss == 0.25
    assert channel.latency_s == pytest.approx(0.005) and channel.jitter_s == pytest.approx(0.0005)
    assert prov.policy is None and prov.policy_params == {}  # no RSU ran
    rsu = simulate(PAPER, mode="rsu", policy="slot", seed=1).provenance
    assert rsu is not None and rsu.policy is Policy.SLOT
    knobs = rsu.policy_params["rsu1"]
    scalar = {f.name for f in dataclasses.fields(RsuConfig)} - {"rsu_id", "center", "conflict_zone"}
    assert set(knobs) == scalar  # every knob of the RSU core
    assert knobs["policy"] == "slot" and knobs["max_points"] is not None


def test_simulate_equals_the_clis_json(tmp_path: Path) -> None:
    out = tmp_path / "r.json"
    proc = subprocess.run(
        [sys.executable, "-m", "services.cli.main", "sim", str(PAPER), "--mode", "rsu",
         "--policy", "slot", "--seed", "5", "--loss", "0.1", "--json", str(out)],
        capture_output=True, text=True, cwd=ROOT, timeout=120,
    )  # fmt: skip
    assert proc.returncode == 0, proc.stderr
    from_cli = RunResult.model_validate_json(out.read_text())
    mine = simulate(PAPER, mode="rsu", policy="slot", seed=5, loss=0.1)
    assert _content(mine) == _content(from_cli)
    assert mine.vehicles == from_cli.vehicles


def test_trace_in_the_result_or_in_a_csv(tmp_path: Path) -> None:
    kept = simulate(PAPER, mode="fp-only", seed=1, trace=True)
    assert kept.trace_fields == list(TRACE_FIELDS)
    assert kept.trace is not None and {row[1] for row in kept.trace} == {"A", "B"}
    for car in ("A", "B"):  # every physics step (20 Hz) while the car is in the world
        ts = [float(row[0]) for row in kept.trace if row[1] == car]
        assert len(ts) == round((ts[-1] - ts[0]) * 20) + 1 and ts[-1] - ts[0] > 30.0
    assert max(float(row[0]) for row in kept.trace) == pytest.approx(kept.sim_s)
    csv_path = tmp_path / "t.csv"
    written = simulate(PAPER, mode="fp-only", seed=1, trace=csv_path)
    assert written.trace is None and "trace" not in written.to_dict()
    assert read_trace_csv(csv_path) == tuple(kept.trace)
    assert simulate(PAPER, mode="fp-only", seed=1).trace is None


def test_run_daemons_refuses_before_starting_anything(tmp_path: Path) -> None:
    run_dir = tmp_path / "run"
    for kwargs, message in (
        ({"mode": "bogus"}, "unknown mode 'bogus'"),
        ({"policy": "x"}, "unknown policy 'x'"),
        ({"speed": 0.0}, "speed"),
        ({"speed": 5000.0}, "speed"),
        ({"timeout": 0.0}, "timeout"),
        ({"seed": -2}, "seed"),
    ):
        with pytest.raises(ValueError, match=message):
            run_daemons(PAPER, run_dir=run_dir, **kwargs)
    assert not run_dir.exists()


# The API's real daemon run (``run_daemons``, trace on) is checked where a run of it
# already happens: ``experiment paper --daemons`` calls it for every trial
# (tests/experiments/test_paper_daemons.py), one daemon run fewer in CI (about 28 s).
