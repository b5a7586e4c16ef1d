"""Per-process memos of a multi-car host (issue 12, CPU per car): a datagram that every car
of a host receives is decoded and its signature verified once; each car's own checks stay."""

from __future__ import annotations

from pathlib import Path
from unittest import mock

import pytest

from protocol import Command, DecodeError, Header, Mode, ModeCommand, decode, encode
from protocol import auth as auth_mod
from protocol.auth import Coverage
from services.edge import shell, trust
from services.edge.trust import Authority, Refused, Signer, TrustStore, run_tag


def _command(seq: int) -> ModeCommand:
    return ModeCommand(Header("rsu1", seq, 1_000_000), "car-a", Command.INITIATE, Mode.C_FAST)


def test_decode_memo_returns_the_same_message_and_never_remembers_garbage() -> None:
    payload = encode(_command(7))
    first = shell.decode_shared(payload)
    assert first == decode(payload)
    assert shell.decode_shared(bytes(payload)) is first  # an equal copy: no second decode
    with pytest.raises(DecodeError):
        shell.decode_shared(b"\x00garbage")
    assert b"\x00garbage" not in shell._DECODED


def test_signature_memo_verifies_once_per_process_and_keeps_replay_per_car(
    tmp_path: Path,
) -> None:
    auth = Authority.init(tmp_path / "pki")
    auth.issue_rsu("rsu1", ["x0"], Coverage(0.0, 0.0, 150.0))
    stores = [TrustStore(auth.root_public) for _ in range(3)]
    for store in stores:
        store.begin_run("run-1")
    signer = Signer(auth.credentials("rsu1"), run=run_tag("run-1"))
    data = signer.seal(encode(_command(1)))
    message = decode(data)
    with mock.patch.object(trust, "signature_ok", wraps=auth_mod.signature_ok) as real:
        for store in stores:  # three cars of one host
            assert store.verify_datagram(data, message).subject == "rsu1"
        assert real.call_count == 1
        with pytest.raises(Refused, match="replay"):
            stores[0].verify_datagram(data, message)
        tampered = bytearray(data)
        tampered[12] ^= 0xFF  # a byte the signature covers, same signature
        fresh = TrustStore(auth.root_public)
        fresh.begin_run("run-1")
        with pytest.raises(Refused):
            fresh.verify_datagram(bytes(tampered), decode(bytes(tampered)))
        assert real.call_count == 2


def test_truth_board_advances_once_per_instant_until_a_report_arrives() -> None:
    from services.daemons.vehicle import advance
    from services.daemons.world import TruthBoard
    from services.edge.plumbing import TruthReport
    from services.model.kinematics import TruthState

    board = TruthBoard()
    board.reset("run-1")
    calls: list[str] = []

    def counted(state: TruthState, now: float) -> TruthState:
        calls.append(state.id)
        return advance(state, now)

    a = TruthState("a", 1.0, 0.0, 0.0, 0.0, 10.0, 0.0, 0.0, 4.5, 1.8)
    board.take(TruthReport("run-1", 20, a))
    first = board.states_at(1.1, counted)
    assert board.states_at(1.1, counted) is first and calls == ["a"]  # the host's next car
    assert first["a"].x == pytest.approx(1.0)
    board.take(TruthReport("run-1", 21, a.__class__("b", 1.05, 5, 5, 0, 0, 0, 0, 4.5, 1.8)))
    assert set(board.states_at(1.1, counted)) == {"a", "b"} and len(calls) == 3
