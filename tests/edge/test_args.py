"""Argparse value types: what each accepts, and a one-phrase reason for what it refuses."""

from __future__ import annotations

import argparse
import os
from pathlib import Path

import pytest

from services.edge.args import (
    finite_float,
    float_at_least,
    fraction,
    non_negative_float,
    non_negative_int,
    output_dir,
    output_file,
    positive_float,
    positive_int,
    run_speed,
)


def refused(parse: object, text: str) -> str:
    assert callable(parse)
    with pytest.raises(argparse.ArgumentTypeError) as exc:
        parse(text)
    return str(exc.value)


def test_integers() -> None:
    assert non_negative_int("0") == 0 and non_negative_int(" 7 ") == 7
    assert positive_int("1") == 1
    assert refused(non_negative_int, "-1") == "must be >= 0, got -1"
    assert refused(positive_int, "0") == "must be >= 1, got 0"
    assert "integer" in refused(non_negative_int, "1.5")
    assert "integer" in refused(positive_int, "x")


def test_floats_refuse_nan_and_infinity() -> None:
    assert finite_float("-2.5") == -2.5
    for bad in ("nan", "inf", "-inf", "NaN"):
        assert "finite" in refused(finite_float, bad)
        assert "finite" in refused(non_negative_float, bad)
        assert "finite" in refused(positive_float, bad)
    assert "number" in refused(finite_float, "fast")


def test_float_bounds() -> None:
    assert non_negative_float("0") == 0.0
    assert refused(non_negative_float, "-0.5") == "must be >= 0, got -0.5"
    assert positive_float("1e-3") == 0.001
    assert refused(positive_float, "0") == "must be > 0, got 0"
    assert float_at_least(1.0)("1") == 1.0
    assert refused(float_at_least(1.0), "0.5") == "must be >= 1, got 0.5"
    assert run_speed("1000") == 1000.0
    assert "<= 1000" in refused(run_speed, "1000.5")
    assert "> 0" in refused(run_speed, "0")


def test_fraction_is_0_to_1_and_percent_only_with_its_sign() -> None:
    assert fraction("0") == 0.0 and fraction("0.3") == 0.3 and fraction("1") == 1.0
    assert fraction("30%") == pytest.approx(0.3) and fraction(" 100 % ".strip()) == 1.0
    assert refused(fraction, "30") == "must be a fraction within 0..1 (30 % is 0.3), got 30"
    assert refused(fraction, "1.5") == "must be a fraction within 0..1 (1.5 % is 0.015), got 1.5"
    assert refused(fraction, "-0.1") == "must be a fraction within 0..1, got -0.1"
    assert refused(fraction, "150%") == "must be within 0..100 %, got 150%"
    assert "finite" in refused(fraction, "nan")


def test_output_file(tmp_path: Path) -> None:
    assert output_file(str(tmp_path / "r.json")) == tmp_path / "r.json"
    assert output_file(str(tmp_path / "new" / "deeper" / "r.json")) == (
        tmp_path / "new" / "deeper" / "r.json"
    )
    assert not (tmp_path / "new").exists()  # checking creates nothing
    existing = tmp_path / "old.json"
    existing.write_text("{}")
    assert output_file(str(existing)) == existing
    assert refused(output_file, str(tmp_path)) == f"{tmp_path} is a directory, expected a file path"
    assert "not a directory" in refused(output_file, str(existing / "r.json"))
    assert "empty" in refused(output_file, "")


def test_output_dir(tmp_path: Path) -> None:
    assert output_dir(str(tmp_path)) == tmp_path
    assert output_dir(str(tmp_path / "a" / "b")) == tmp_path / "a" / "b"
    assert not (tmp_path / "a").exists()
    afile = tmp_path / "file"
    afile.write_text("keep")
    assert refused(output_dir, str(afile)) == f"{afile} exists and is not a directory"
    assert "not a directory" in refused(output_dir, str(afile / "sub"))
    assert afile.read_text() == "keep"


def test_unwritable_places_are_refused(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    existing = tmp_path / "old.json"
    existing.write_text("{}")
    # Root passes every permission check, so the check is faked: nothing is writable.
    monkeypatch.setattr(os, "access", lambda _path, _mode: False)
    assert refused(output_file, str(tmp_path / "r.json")) == f"cannot write in {tmp_path}"
    assert refused(output_file, str(existing)) == f"{existing} is not writable"
    assert refused(output_dir, str(tmp_path)) == f"cannot write in {tmp_path}"
    assert refused(output_dir, str(tmp_path / "a" / "b")) == f"cannot write in {tmp_path}"
