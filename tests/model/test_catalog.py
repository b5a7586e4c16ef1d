"""Packaged scenarios: found by name from any directory; a path is still a path."""

from __future__ import annotations

from pathlib import Path

import pytest

from services.model.catalog import (
    DEFAULT_SCENARIO_NAME,
    default_scenario,
    packaged_names,
    packaged_scenario,
    resolve_scenario,
)
from services.model.scenario import ScenarioError, load_scenario

ROOT = Path(__file__).resolve().parents[2]


def test_the_default_is_packaged_and_is_the_file_in_scenarios() -> None:
    assert DEFAULT_SCENARIO_NAME in packaged_names()
    assert (
        default_scenario().read_bytes()
        == (ROOT / "scenarios" / f"{DEFAULT_SCENARIO_NAME}.toml").read_bytes()
    )
    assert set(packaged_names()) == {p.stem for p in (ROOT / "scenarios").glob("*.toml")}


@pytest.mark.parametrize("ref", [DEFAULT_SCENARIO_NAME, f"{DEFAULT_SCENARIO_NAME}.toml"])
def test_a_bare_name_loads_the_packaged_scenario_from_any_directory(
    ref: str, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.chdir(tmp_path)
    assert resolve_scenario(ref) == default_scenario()
    assert load_scenario(ref).name == DEFAULT_SCENARIO_NAME
    assert load_scenario(Path(ref)).name == DEFAULT_SCENARIO_NAME


def test_a_file_in_the_working_directory_wins_over_a_packaged_name(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.chdir(tmp_path)
    mine = tmp_path / f"{DEFAULT_SCENARIO_NAME}.toml"
    mine.write_text(default_scenario().read_text().replace(DEFAULT_SCENARIO_NAME, "mine", 1))
    assert load_scenario(mine.name).name == "mine"


def test_an_unknown_name_says_which_are_packaged(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.chdir(tmp_path)
    with pytest.raises(ScenarioError) as err:
        load_scenario("no-such-scenario")
    assert "no packaged scenario 'no-such-scenario'" in str(err.value)
    assert DEFAULT_SCENARIO_NAME in str(err.value)
    with pytest.raises(LookupError, match=DEFAULT_SCENARIO_NAME):
        packaged_scenario("no-such-scenario")


def test_a_path_with_a_directory_is_never_taken_for_a_name(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.chdir(tmp_path)
    ref = f"elsewhere/{DEFAULT_SCENARIO_NAME}.toml"
    assert resolve_scenario(ref) == Path(ref)
    with pytest.raises(ScenarioError, match="No such file"):
        load_scenario(ref)
