"""The experiments' statistics: Student-t intervals, summaries, runs.csv."""

from __future__ import annotations

import csv
import math
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

from services.experiments.common import (
    fmt_ci,
    out_of,
    summarize,
    t_interval95,
    t_quantile_975,
    write_runs_csv,
)


@pytest.mark.parametrize(
    ("df", "expected"),
    [
        (1, 12.7062),
        (2, 4.3027),
        (9, 2.2622),
        (30, 2.0423),
        (40, 2.0211),
        (60, 2.0003),
        (120, 1.9799),
    ],
)
def test_t_quantiles_match_the_tables(df: int, expected: float) -> None:
    assert t_quantile_975(df) == pytest.approx(expected, abs=2e-4)


def test_t_quantile_refuses_no_degrees_of_freedom() -> None:
    with pytest.raises(ValueError, match="degrees of freedom"):
        t_quantile_975(0)


def test_interval_of_a_known_sample() -> None:
    # mean 2, sd 1, n 3: half width 4.3027 / sqrt(3)
    lo, hi = t_interval95([1.0, 2.0, 3.0]) or (math.nan, math.nan)
    assert (lo, hi) == pytest.approx((2.0 - 2.4841, 2.0 + 2.4841), abs=1e-3)
    assert t_interval95([5.0]) is None


@given(st.lists(st.floats(-1e6, 1e6), min_size=2, max_size=40))
def test_interval_holds_the_mean_and_narrows_with_more_data(values: list[float]) -> None:
    ci = t_interval95(values)
    assert ci is not None
    mean = float(np.mean(values))
    assert ci[0] <= mean + 1e-6 * (1 + abs(mean)) and mean - 1e-6 * (1 + abs(mean)) <= ci[1]
    doubled = t_interval95(values + values)
    assert doubled is not None
    assert doubled[1] - doubled[0] <= ci[1] - ci[0] + 1e-6 * (1 + abs(mean))


def test_summary_carries_the_interval_and_the_text_shows_it() -> None:
    s = summarize([1.0, None, 3.0])
    assert s["n"] == 2 and s["missing"] == 1
    assert s["ci95_low"] == pytest.approx(2.0 - 12.7062 * math.sqrt(2) / math.sqrt(2), abs=1e-3)
    assert fmt_ci(s, "s") == f"2.00 s [{s['ci95_low']:.2f}, {s['ci95_high']:.2f}]"
    assert fmt_ci(summarize([4.0]), "s") == "4.00 s"  # one value: no interval to show
    assert fmt_ci(summarize([None]), "s") == "–"
    assert out_of(1, 1) == "1 out of 1 trial" and out_of(2, 30) == "2 out of 30 trials"


def test_runs_csv_has_every_key_of_every_row(tmp_path: Path) -> None:
    path = tmp_path / "runs.csv"
    write_runs_csv(path, [{"a": 1, "b": None}, {"a": 2, "c": "x"}])
    with path.open() as fh:
        rows = list(csv.DictReader(fh))
    assert rows == [{"a": "1", "b": "", "c": ""}, {"a": "2", "b": "", "c": "x"}]
