"""Golden vectors: SPEC.md, tests/protocol/vectors.py and the codec agree byte for byte.

``reference_decode`` is a second decoder written from SPEC.md alone (plain
``struct``, a loop per point), so the document is checked against the code.
"""

from __future__ import annotations

import re
import struct
from pathlib import Path
from typing import Any

import pytest

import protocol
from protocol import decode, encode
from tests.protocol.vectors import VECTORS, assert_same

SPEC = Path(protocol.__file__).with_name("SPEC.md")
_VECTOR_RE = re.compile(r"#### Vector `([a-z0-9-]+)`.*?```hex\n(.*?)```", re.DOTALL)


def spec_vectors() -> dict[str, str]:
    text = SPEC.read_text(encoding="utf-8")
    return {name: "".join(body.split()) for name, body in _VECTOR_RE.findall(text)}


def test_spec_lists_every_vector_exactly() -> None:
    from_spec = spec_vectors()
    assert set(from_spec) == set(VECTORS)
    for name, (_, hex_) in VECTORS.items():
        assert from_spec[name] == hex_, name


def test_spec_has_a_vector_per_kind() -> None:
    kinds = {message.kind for message, _ in VECTORS.values()}
    assert kinds == set(protocol.Kind)


@pytest.mark.parametrize("name", sorted(VECTORS))
def test_encode_gives_the_vector(name: str) -> None:
    message, hex_ = VECTORS[name]
    assert encode(message) == bytes.fromhex(hex_)


@pytest.mark.parametrize("name", sorted(VECTORS))
def test_decode_gives_the_message(name: str) -> None:
    message, hex_ = VECTORS[name]
    assert_same(message, decode(bytes.fromhex(hex_)))


def test_worked_example_matches_its_vector() -> None:
    text = SPEC.read_text(encoding="utf-8")
    block = text.split("### 7.1 Worked example", 1)[1].split("```", 2)[1]
    data = "".join(line.split("  ")[0].replace(" ", "") for line in block.strip().splitlines())
    assert data == VECTORS["fp-basic"][1]


# ---------------------------------------------------------------- reference decoder


class _Reader:
    def __init__(self, data: bytes) -> None:
        self.data = data
        self.off = 0

    def take(self, fmt: str) -> Any:
        (value,) = struct.unpack_from("<" + fmt, self.data, self.off)
        self.off += struct.calcsize("<" + fmt)
        return value

    def ident(self) -> str:
        n = self.take("B")
        raw = self.data[self.off : self.off + n]
        self.off += n
        return raw.decode("ascii")


def _ref_points(r: _Reader, time_us: int, ncols: int) -> tuple[list[list[float]], list[float]]:
    n = r.take("H")
    widths = r.take("B")
    if n == 0:
        return [], []
    first = [r.take("i"), r.take("i"), r.take("i")] + ([r.take("H")] if ncols == 4 else [])
    rows = [first]
    columns: list[list[int]] = []
    for c in range(ncols):
        code = (widths >> (2 * c)) & 3
        fmt = {0: "", 1: "b", 2: "h"}[code]
        if c == 2 and fmt:
            fmt = fmt.upper()  # the t column is unsigned
        columns.append([r.take(fmt) if fmt else 0 for _ in range(n - 1)])
    for k in range(n - 1):
        rows.append([rows[-1][c] + columns[c][k] for c in range(ncols)])
    base_ms = time_us // 1000  # T counts whole ms from floor(time_us / 1000)
    points = [[row[0] / 100, row[1] / 100, (base_ms + row[2]) / 1000] for row in rows]
    speeds = [row[3] / 100 for row in rows] if ncols == 4 else []
    return points, speeds


def reference_decode(data: bytes) -> dict[str, Any]:
    """Decode from SPEC.md's tables; no validation beyond what parsing needs."""
    r = _Reader(data)
    out: dict[str, Any] = {}
    assert r.take("B") == 0xCB
    assert r.take("B") == 3
    kind = r.take("B")
    flags = r.take("B")
    out["seq"] = r.take("I")
    out["time_us"] = time_us = r.take("q")
    out["sender"] = r.ident()
    out["kind"] = kind
    if kind in (1, 2):
        for name, fmt in [
            ("x", "i"),
            ("y", "i"),
            ("speed", "H"),
            ("heading", "h"),
            ("length", "H"),
            ("width", "H"),
            ("v_max", "H"),
            ("accel", "B"),
            ("decel", "B"),
            ("lat_accel", "B"),
            ("mode", "B"),
        ]:
            out[name] = r.take(fmt)
        out["points"], _ = _ref_points(r, time_us, 3)
    elif kind == 3:
        out["vehicle"] = r.ident()
        out["mode"] = r.take("B")
        out["points"], out["speeds"] = _ref_points(r, time_us, 4)
    elif kind == 4:
        out["vehicle"] = r.ident()
        out["command"] = r.take("B")
        out["mode"] = r.take("B")
    elif kind == 5:
        out["intersection"] = r.ident()
        out["x"], out["y"], out["radius"] = r.take("i"), r.take("i"), r.take("I")
    if flags & 1:
        scheme = r.take("B")
        length = r.take("B")
        out["auth"] = bytes([scheme]) + data[r.off : r.off + length]
        r.off += length
    assert r.off == len(data)
    return out


@pytest.mark.parametrize("name", sorted(VECTORS))
def test_reference_decoder_agrees(name: str) -> None:
    message, hex_ = VECTORS[name]
    ref = reference_decode(bytes.fromhex(hex_))
    h = message.header
    assert (ref["kind"], ref["sender"], ref["seq"], ref["time_us"]) == (
        message.kind,
        h.sender,
        h.seq,
        h.time_us,
    )
    assert ref.get("auth", b"") == h.auth
    if isinstance(message, protocol.VehiclePath):
        assert ref["x"] / 100 == message.x and ref["y"] / 100 == message.y
        assert ref["speed"] / 100 == message.speed and ref["heading"] / 1e4 == message.heading
        assert ref["length"] / 100 == message.length and ref["width"] / 100 == message.width
        assert ref["mode"] == message.mode
        limits = message.limits
        declared = (ref["v_max"], ref["accel"], ref["decel"], ref["lat_accel"])
        if limits is None:
            assert declared == (0, 0, 0, 0)
        else:
            assert (declared[0] / 100, *(v / 10 for v in declared[1:])) == (
                limits.v_max,
                limits.accel,
                limits.decel,
                limits.lat_accel,
            )
        assert ref["points"] == message.points.tolist()
    elif isinstance(message, protocol.CoordinatedPath):
        assert ref["vehicle"] == message.vehicle and ref["mode"] == message.mode
        assert ref["points"] == message.points.tolist()
        assert ref["speeds"] == message.speeds.tolist()
    elif isinstance(message, protocol.ModeCommand):
        assert (ref["vehicle"], ref["command"], ref["mode"]) == (
            message.vehicle,
            message.command,
            message.mode,
        )
    else:
        assert isinstance(message, protocol.RsuBeacon)
        assert ref["intersection"] == message.intersection
        assert (ref["x"] / 100, ref["y"] / 100, ref["radius"] / 100) == (
            message.x,
            message.y,
            message.radius,
        )


def test_reference_decoder_agrees_on_a_long_path() -> None:
    from services.bench.codec import sample_messages

    for message in sample_messages(120).values():
        data = encode(message)
        ref = reference_decode(data)
        decoded = decode(data)
        if isinstance(decoded, protocol.VehiclePath | protocol.CoordinatedPath):
            assert ref["points"] == decoded.points.tolist()
