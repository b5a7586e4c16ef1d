"""``crosspath experiment paper`` (issue 6): artefacts, their consistency, reproducibility."""

from __future__ import annotations

import csv
import json
import re
import struct
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from services.cli.main import build_parser
from services.experiments.common import (
    Column,
    Trial,
    binned_mean,
    fmt_signed_pct,
    markdown_table,
    read_trace_csv,
    run_in_process,
    split_trace,
    strip_wall_clock,
    summarize,
    trials_for,
    write_trace_csv,
)
from services.experiments.paper import (
    COLUMNS,
    PAPER_REFERENCE,
    analyse_vehicle,
    run_paper_experiment,
)
from services.model.scenario import Crossing, load_scenario
from services.model.types import RunMode

ROOT = Path(__file__).resolve().parents[2]
PAPER = ROOT / "scenarios" / "paper-blind-intersection.toml"
TRIALS = 2
SEED = 5


@pytest.fixture(scope="module")
def first(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, dict[str, Any]]:
    out = tmp_path_factory.mktemp("paper-a")
    doc = run_paper_experiment(PAPER, TRIALS, SEED, out, jobs=2, progress=False)
    return out, doc


def _table(path: Path) -> tuple[list[str], dict[str, list[str]]]:
    """Header and label -> cells of the markdown table in ``path``."""
    lines = [ln for ln in path.read_text().splitlines() if ln.startswith("|")]
    split = [[c.strip() for c in ln.strip("|").split("|")] for ln in lines]
    header, rows = split[0], split[2:]
    return header, {r[0]: r[1:] for r in rows}


def _ours(header: list[str]) -> list[int]:
    """Cell indexes (after the label) of our columns, skipping the paper's."""
    return [i - 1 for i, h in enumerate(header) if i > 0 and h != "paper"]


def _number(cell: str) -> float:
    m = re.match(r"[−+±-]?\d+(\.\d+)?", cell)
    assert m is not None, cell
    return float(m.group(0).replace("−", "-").replace("±", ""))


# --------------------------------------------------------------------------- artefacts


def test_every_artefact_is_written(first: tuple[Path, dict[str, Any]]) -> None:
    out, doc = first
    names = ("results.json", "table.md", "REPORT.md", "runs.csv")
    for name in names:
        assert (out / name).stat().st_size > 0, name
    for fig in ("speed_profiles", "passing_times"):
        png = (out / f"{fig}.png").read_bytes()
        assert png[:8] == b"\x89PNG\r\n\x1a\n"
        # 300 dpi: the pHYs chunk holds pixels per metre (300 / 0.0254 = 11811)
        assert struct.unpack(">II", png[png.index(b"pHYs") + 4 :][:8]) == (11811, 11811)
        assert (out / f"{fig}.pdf").read_bytes()[:5] == b"%PDF-"
        assert b"<svg" in (out / f"{fig}.svg").read_bytes()[:2000]
    with (out / "runs.csv").open() as fh:
        csv_rows = list(csv.DictReader(fh))
    assert len(csv_rows) == len(COLUMNS) * TRIALS
    by_run = {(r["column"], int(r["seed"])): r for r in csv_rows}
    for col in COLUMNS:
        for run in doc["runs"][col.key]:
            row = by_run[(col.key, run["result"]["seed"])]
            assert int(row["collisions"]) == run["result"]["collisions"]
            assert row["mode"] == str(col.mode)
    on_disk = json.loads((out / "results.json").read_text())
    assert on_disk == json.loads(json.dumps(doc))
    report = (out / "REPORT.md").read_text()
    assert "(speed_profiles.png)" in report and "(passing_times.png)" in report
    for col in COLUMNS:
        assert f"### {col.title}" in report
    # the per-trial table of the report lists every run
    assert sum(report.count(f"| {c.key} | ") for c in COLUMNS) == len(COLUMNS) * TRIALS


def test_results_hold_every_trial_with_its_seed_and_draw(
    first: tuple[Path, dict[str, Any]],
) -> None:
    _, doc = first
    scenario = load_scenario(PAPER)
    assert [c["key"] for c in doc["columns"]] == [c.key for c in COLUMNS]
    assert doc["paper_reference"] == PAPER_REFERENCE
    for col in COLUMNS:
        runs = doc["runs"][col.key]
        assert [r["trial"] for r in runs] == list(range(TRIALS))
        for i, r in enumerate(runs):
            res = r["result"]
            assert res["seed"] == SEED + i
            assert res["mode"] == str(col.mode)
            assert res["policy"] == (str(col.policy) if col.mode is RunMode.RSU else None)
            draw = scenario.draw_start_times(SEED + i)
            assert res["start_times"] == pytest.approx(draw, abs=1e-4)
            assert set(r["behaviour"]) == set(doc["vehicles"])


def test_table_averages_are_the_means_of_the_trials(first: tuple[Path, dict[str, Any]]) -> None:
    out, doc = first
    header, rows = _table(out / "table.md")
    idx = _ours(header)
    assert len(idx) == len(COLUMNS)
    for k, col in zip(idx, COLUMNS, strict=True):
        results = [r["result"] for r in doc["runs"][col.key]]
        every: list[float] = []
        for v in doc["vehicles"]:
            values = [res["vehicles"][v]["passing_time_s"] for res in results]
            assert None not in values
            every += values
            assert _number(rows[f"Car {v} passing time"][k]) == pytest.approx(
                float(np.mean(values)), abs=0.006
            )
            assert doc["aggregates"][col.key]["passing_time_s"][v]["mean"] == pytest.approx(
                float(np.mean(values)), abs=1e-4
            )
        assert _number(rows["Average passing time"][k]) == pytest.approx(
            float(np.mean(every)), abs=0.006
        )


def test_pass_first_counts_add_up_to_the_trials(first: tuple[Path, dict[str, Any]]) -> None:
    out, doc = first
    header, rows = _table(out / "table.md")
    for k, col in zip(_ours(header), COLUMNS, strict=True):
        cells = {v: rows[f"Car {v} passes first"][k].split(" / ") for v in doc["vehicles"]}
        assert all(int(n) == TRIALS for _, n in cells.values())  # "k / N trials"
        counts = {v: int(c[0]) for v, c in cells.items()}
        assert sum(counts.values()) == TRIALS
        for v, n in counts.items():
            assert n == sum(
                1 for r in doc["runs"][col.key] if r["result"]["vehicles"][v]["first_through"]
            )


def test_table_shows_the_papers_numbers_and_safety(first: tuple[Path, dict[str, Any]]) -> None:
    out, doc = first
    header, rows = _table(out / "table.md")
    paper_cells = [i - 1 for i, h in enumerate(header) if h == "paper"]
    assert len(paper_cells) == 3
    avg = [rows["Average passing time"][i] for i in paper_cells]
    assert avg == ["36.51 s", "37.17 s", "27.05 s"]
    assert [rows["Car A passes first"][i] for i in paper_cells] == ["10 / 10", "6 / 10", "6 / 10"]
    assert [rows["Car B passing time"][i] for i in paper_cells] == ["41.97 s", "36.32 s", "30.18 s"]
    assert rows["Change vs stand-alone"][paper_cells[2]] == "−25.9 %"
    for k, col in zip(_ours(header), COLUMNS, strict=True):
        agg = doc["aggregates"][col.key]
        total, trials_with = rows["Collisions (trials with one)"][k].split(" (")
        assert int(total) == agg["collisions"]
        assert trials_with == f"{agg['trials_with_collision']} / {TRIALS})"
        gaps = [r["result"]["min_gap_m"] for r in doc["runs"][col.key]]
        assert _number(rows["Min gap (worst trial)"][k]) == pytest.approx(min(gaps), abs=0.006)


def test_the_same_seed_reproduces_the_same_numbers(
    first: tuple[Path, dict[str, Any]], tmp_path: Path
) -> None:
    out_a, _ = first
    run_paper_experiment(PAPER, TRIALS, SEED, tmp_path, jobs=2, progress=False)
    a = strip_wall_clock(json.loads((out_a / "results.json").read_text()))
    b = strip_wall_clock(json.loads((tmp_path / "results.json").read_text()))
    assert "timing" not in a and "wall_s" not in a["runs"]["standalone"][0]["result"]
    assert a == b
    assert (out_a / "table.md").read_text() == (tmp_path / "table.md").read_text()


# --------------------------------------------------------------------------- pieces


def _trace(speeds: list[float], reasons: list[str], modes: list[str]) -> list[tuple[Any, ...]]:
    rows = []
    s = 0.0
    for i, (v, r, m) in enumerate(zip(speeds, reasons, modes, strict=True)):
        rows.append((i * 0.05, "B", s, 0.0, s, v, 0.0, r, "A" if r == "yield" else "", m))
        s += v * 0.05
    return rows


def test_analysis_finds_the_stop_the_first_yield_and_mode_changes() -> None:
    # drive 10 m/s for 2 s, yield and stop for 1 s, then go, coordinated at the end
    speeds = [10.0] * 40 + [5.0] * 10 + [0.0] * 20 + [3.0] * 30
    reasons = ["cruise"] * 40 + ["yield"] * 30 + ["coordinated"] * 30
    modes = ["AUTO"] * 70 + ["C_FAST"] * 30
    tr = split_trace(_trace(speeds, reasons, modes))["B"]
    crossing = Crossing("X1", s_in=26.0, s_out=33.0, s_stop=18.0, center_s=29.5)
    a = analyse_vehicle(tr, crossing, goal_s=200.0, goal_tolerance_m=1.0)
    assert len(a["stops"]) == 1
    stop = a["stops"][0]
    assert stop["t_s"] == pytest.approx(2.5)
    assert stop["distance_m"] == pytest.approx(29.5 - 22.5)
    assert stop["behind_stop_line_m"] == pytest.approx(18.0 - 22.5)
    assert stop["duration_s"] == pytest.approx(1.0)
    assert a["first_yield"]["t_s"] == pytest.approx(2.0)
    assert a["first_yield"]["to"] == "A"
    assert a["first_yield"]["distance_m"] == pytest.approx(9.5)
    assert [(c["from"], c["to"]) for c in a["mode_changes"]] == [("AUTO", "C_FAST")]
    assert a["first_c_slow"] is None
    shares = a["reason_share"]
    assert sum(shares.values()) == pytest.approx(1.0, abs=1e-3)
    assert shares["yield"] > 0 and shares["emergency"] == 0.0
    assert a["mode_sequence"] == "AUTO→C_FAST"


def test_trace_csv_round_trip(tmp_path: Path) -> None:
    rows = _trace([1.0, 2.0], ["cruise", "yield"], ["AUTO", "C_SLOW"])
    write_trace_csv(tmp_path / "t.csv", rows)
    assert read_trace_csv(tmp_path / "t.csv") == tuple(rows)


def test_summaries_tables_and_formatting() -> None:
    s = summarize([1.0, None, 3.0])
    assert (s["n"], s["missing"], s["mean"], s["min"], s["max"]) == (2, 1, 2.0, 1.0, 3.0)
    assert s["std"] == pytest.approx(np.sqrt(2.0), abs=1e-4)
    assert summarize([None])["mean"] is None
    table = markdown_table(["", "x"], [["a", "1|2"]])
    assert table.splitlines() == ["|  | x |", "| :-- | --: |", "| a | 1\\|2 |"]
    with pytest.raises(ValueError):
        markdown_table(["a", "b"], [["only one"]])
    assert fmt_signed_pct(-25.91) == "−25.9 %" and fmt_signed_pct(1.81) == "+1.8 %"
    assert fmt_signed_pct(None) == "–"
    got = strip_wall_clock({"wall_s": 1, "a": [{"speedup_vs_real_time": 2, "b": 3}]})
    assert got == {"a": [{"b": 3}]}
    edges = np.array([0.0, 1.0, 2.0, 3.0])
    mean = binned_mean(np.array([0.2, 0.8, 2.5]), np.array([1.0, 3.0, 5.0]), edges)
    assert mean[0] == 2.0 and np.isnan(mean[1]) and mean[2] == 5.0


def test_trials_use_base_seed_plus_index_and_failures_are_reported(tmp_path: Path) -> None:
    col = Column("x", "X", RunMode.STANDALONE)
    plan = trials_for([col], PAPER, 3, 7)
    assert [t.seed for t in plan] == [7, 8, 9]
    with pytest.raises(ValueError):
        trials_for([col, col], PAPER, 1, 0)
    outcome = run_in_process(Trial(col, 0, 0, str(tmp_path / "missing.toml")))
    assert outcome.result is None and outcome.error is not None


def test_cli_refuses_bad_arguments(capsys: pytest.CaptureFixture[str], tmp_path: Path) -> None:
    parser = build_parser()
    with pytest.raises(SystemExit) as exc:  # refused while parsing, before any trial
        parser.parse_args(["experiment", "paper", "--trials", "0", "--out", str(tmp_path)])
    assert exc.value.code == 2
    assert "--trials: must be >= 1" in capsys.readouterr().err
    args = parser.parse_args(
        ["experiment", "paper", "--scenario", str(tmp_path / "nope.toml"), "--out", str(tmp_path)]
    )
    assert args._run(args) == 2
    assert "nope.toml" in capsys.readouterr().err
    assert not (tmp_path / "results.json").exists()
