"""One owner for each shared limit: ``services.model.limits`` and the wire's in ``protocol``."""

from __future__ import annotations

import ast
import re
from pathlib import Path

import numpy as np
import pytest

from protocol import EncodeError, FuturePath, Header, Mode, decode, encode
from protocol.codec import MAX_COORD_M, MAX_STEP_M, MAX_STEP_S, MAX_TIME_US
from services.model import limits
from services.rsu.reservation import ReservationTable, within_wire_bounds

ROOT = Path(__file__).resolve().parents[2]
SOURCES = sorted((ROOT / "services").rglob("*.py")) + sorted((ROOT / "protocol").rglob("*.py"))


def _module_constants(path: Path) -> set[str]:
    """Names assigned at module level in ``path`` (plain and annotated assignments)."""
    names: set[str] = set()
    for node in ast.parse(path.read_text(encoding="utf-8")).body:
        targets = node.targets if isinstance(node, ast.Assign) else [getattr(node, "target", None)]
        if isinstance(node, ast.Assign | ast.AnnAssign):
            names.update(t.id for t in targets if isinstance(t, ast.Name))
    return names


def test_stopped_mps_is_gone_and_each_limit_has_one_owner() -> None:
    owner = ROOT / "services" / "model" / "limits.py"
    gone = {"STOPPED_MPS", "STOPPED_BELOW_MPS", "ARM_ABOVE_MPS", "ARMED_MPS", "V_HARD_CAP_FACTOR"}
    gone |= {"_MAX_ABS"}  # the RSU's own coordinate bound: the wire's MAX_COORD_M now
    assert SOURCES
    for path in SOURCES:
        text = path.read_text(encoding="utf-8")
        for name in sorted(gone):
            found = re.search(rf"\b{name}\b", text)
            assert found is None, f"{path.relative_to(ROOT)} still names {name}"
        if path != owner:
            twins = _module_constants(path) & set(limits.__all__)
            assert not twins, f"{path.relative_to(ROOT)} redefines {sorted(twins)}"
    assert set(limits.__all__) <= _module_constants(owner)


def test_the_values_did_not_change() -> None:
    """Renamed, not retuned: the physics, the metrics and the paper numbers stay identical."""
    assert limits.STANDING_MPS == 1e-9
    assert limits.STOP_COUNT_BELOW_MPS == 0.1
    assert limits.STOP_ARM_ABOVE_MPS == 1.0
    assert limits.SPEED_CAP_FACTOR == 1.05
    assert limits.RUN_END_BELOW_MPS == 0.05


def _path(points: list[tuple[float, float, float]]) -> FuturePath:
    pts = np.array(points, dtype=np.float64)
    return FuturePath(Header("A", 1, 0), 0.0, 0.0, 1.0, 0.0, 4.5, 1.8, Mode.AUTO, pts)


def test_the_codec_step_limits_are_the_ones_it_enforces() -> None:
    """MAX_STEP_M and MAX_STEP_S (read by the scenario loader) are exactly the codec's."""
    ok = _path([(0.0, 0.0, 0.0), (MAX_STEP_M, 0.0, MAX_STEP_S)])
    back = decode(encode(ok))
    assert isinstance(back, FuturePath)
    assert back.points[1, 0] == pytest.approx(MAX_STEP_M)
    with pytest.raises(EncodeError):
        encode(_path([(0.0, 0.0, 0.0), (MAX_STEP_M + 0.01, 0.0, 1.0)]))
    with pytest.raises(EncodeError):
        encode(_path([(0.0, 0.0, 0.0), (1.0, 0.0, MAX_STEP_S + 0.001)]))


def test_the_rsu_accepts_what_the_wire_carries_and_no_more() -> None:
    t_max = MAX_TIME_US / 1e6
    edge = np.array([[MAX_COORD_M, -MAX_COORD_M, t_max]])
    assert within_wire_bounds(edge)
    assert within_wire_bounds(np.zeros((0, 3)))
    for bad in ([[MAX_COORD_M * 1.01, 0.0, 0.0]], [[0.0, 0.0, t_max * 1.01]], [[0.0, np.nan, 0.0]]):
        assert not within_wire_bounds(np.array(bad))
        with pytest.raises(ValueError, match="1e\\+07 m"):
            ReservationTable(2.8, 1.0, 0.5).update("A", bad, 0.0)
