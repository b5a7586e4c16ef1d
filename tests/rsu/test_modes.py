"""The mode transition table: every pair, and that anything else raises."""

from __future__ import annotations

import pytest

from protocol.messages import Mode
from services.rsu.modes import TRANSITIONS, Action, InvalidTransition, RsuEvent, transition

A, S, F = Mode.AUTO, Mode.C_SLOW, Mode.C_FAST

EXPECTED = {
    (A, RsuEvent.CONFLICT): (S, Action.SEND_INITIATION_SLOW),
    (A, RsuEvent.FREE_APPROACHING): (F, Action.SEND_INITIATION_FAST),
    (A, RsuEvent.NO_CONFLICT): (A, Action.NONE),
    (A, RsuEvent.LEAVING): (A, Action.NONE),
    (A, RsuEvent.SILENT): (A, Action.FORGET),
    (S, RsuEvent.CONFLICT): (S, Action.NONE),
    (S, RsuEvent.FREE_APPROACHING): (F, Action.SEND_INITIATION_FAST),
    (S, RsuEvent.NO_CONFLICT): (A, Action.SEND_TERMINATION),
    (S, RsuEvent.LEAVING): (A, Action.SEND_TERMINATION),
    (S, RsuEvent.SILENT): (A, Action.FORGET),
    (F, RsuEvent.CONFLICT): (S, Action.SEND_INITIATION_SLOW),
    (F, RsuEvent.FREE_APPROACHING): (F, Action.NONE),
    (F, RsuEvent.NO_CONFLICT): (F, Action.NONE),
    (F, RsuEvent.LEAVING): (A, Action.SEND_TERMINATION),
    (F, RsuEvent.SILENT): (A, Action.FORGET),
}


@pytest.mark.parametrize(("pair", "result"), sorted(EXPECTED.items()))
def test_every_transition(pair: tuple[Mode, RsuEvent], result: tuple[Mode, Action]) -> None:
    assert transition(*pair) == result


def test_table_is_exactly_the_expected_one() -> None:
    assert TRANSITIONS == EXPECTED
    assert len(TRANSITIONS) == len(Mode) * len(RsuEvent)


def test_commands_match_the_mode_change() -> None:
    for (mode, _event), (after, action) in TRANSITIONS.items():
        if action == Action.SEND_INITIATION_SLOW:
            assert after == S and mode != S
        elif action == Action.SEND_INITIATION_FAST:
            assert after == F and mode != F
        elif action == Action.SEND_TERMINATION:
            assert after == A and mode != A
        elif action == Action.NONE:
            assert after == mode
        else:
            assert action == Action.FORGET and _event == RsuEvent.SILENT


@pytest.mark.parametrize(
    ("mode", "event"),
    [
        (0, 1),  # plain ints would match the IntEnum keys by hash; refused
        (A, 1),
        (0, RsuEvent.CONFLICT),
        (RsuEvent.CONFLICT, A),  # swapped
        ("AUTO", "CONFLICT"),
        (None, RsuEvent.SILENT),
    ],
)
def test_invalid_pairs_raise(mode: object, event: object) -> None:
    with pytest.raises(InvalidTransition):
        transition(mode, event)  # type: ignore[arg-type]


def test_pair_missing_from_the_table_raises(monkeypatch: pytest.MonkeyPatch) -> None:
    trimmed = dict(TRANSITIONS)
    del trimmed[(A, RsuEvent.LEAVING)]
    monkeypatch.setattr("services.rsu.modes.TRANSITIONS", trimmed)
    with pytest.raises(InvalidTransition, match="AUTO on LEAVING"):
        transition(A, RsuEvent.LEAVING)
    assert issubclass(InvalidTransition, ValueError)
