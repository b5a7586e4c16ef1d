"""Key expressions: building, parsing, validation, QoS table."""

from __future__ import annotations

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from protocol import Kind, keys
from protocol.keys import QOS, STREAM_OF_KIND, BadKey, ParsedKey, Stream
from tests.protocol.vectors import VECTORS

ids = st.from_regex(r"[A-Za-z0-9_-]{1,32}", fullmatch=True)
prefixes = st.lists(st.from_regex(r"[A-Za-z0-9_-]{1,12}", fullmatch=True), min_size=1, max_size=3)


def test_default_keys() -> None:
    assert keys.future_path("car-a") == "crosspath/v2x/fp/car-a"
    assert keys.autonomous_path("rsu-1", "car-a") == "crosspath/v2x/rsu/rsu-1/ap/car-a"
    assert keys.rsu_command("rsu-1", "car-a") == "crosspath/v2x/rsu/rsu-1/cmd/car-a"
    assert keys.rsu_beacon("rsu-1") == "crosspath/v2x/rsu/rsu-1/beacon"
    assert keys.sim("truth") == "crosspath/sim/truth"
    assert keys.sim("control", "start") == "crosspath/sim/control/start"
    assert keys.stats("car-a") == "crosspath/stats/car-a"


def test_wildcard_subscriptions() -> None:
    assert keys.all_future_paths() == "crosspath/v2x/fp/*"
    assert keys.all_autonomous_paths("rsu-1") == "crosspath/v2x/rsu/rsu-1/ap/*"
    assert keys.all_autonomous_paths() == "crosspath/v2x/rsu/*/ap/*"
    assert keys.all_commands("car-a") == "crosspath/v2x/rsu/*/cmd/car-a"
    assert keys.all_commands() == "crosspath/v2x/rsu/*/cmd/*"
    assert keys.all_beacons() == "crosspath/v2x/rsu/*/beacon"
    assert keys.all_v2x() == "crosspath/v2x/**"
    assert keys.all_sim() == "crosspath/sim/**"
    assert keys.all_stats() == "crosspath/stats/*"


def test_prefix_with_several_segments() -> None:
    prefix = "lab1/crosspath"
    key = keys.rsu_command("rsu-1", "car-a", prefix=prefix)
    assert key == "lab1/crosspath/v2x/rsu/rsu-1/cmd/car-a"
    assert keys.parse(key, prefix=prefix) == ParsedKey(Stream.CMD, rsu="rsu-1", vehicle="car-a")
    assert keys.all_beacons(prefix=prefix) == "lab1/crosspath/v2x/rsu/*/beacon"
    with pytest.raises(BadKey, match="does not start with"):
        keys.parse(key)  # default prefix


@pytest.mark.parametrize(
    "prefix", ["", "*", "a/*", "**/a", "a//b", "/a", "a/", "a b", "a$", "a?b", "x" * 65, "a#b"]
)
def test_bad_prefixes(prefix: str) -> None:
    with pytest.raises(BadKey):
        keys.future_path("car-a", prefix=prefix)
    with pytest.raises(BadKey):
        keys.parse("crosspath/v2x/fp/car-a", prefix=prefix)


@pytest.mark.parametrize("bad", ["", "*", "**", "a/b", "a b", "v" * 33, "é", "$x", "a.b"])
def test_bad_ids(bad: str) -> None:
    with pytest.raises(BadKey, match="invalid vehicle id"):
        keys.future_path(bad)
    with pytest.raises(BadKey, match="invalid rsu id"):
        keys.rsu_beacon(bad)
    with pytest.raises(BadKey):
        keys.autonomous_path("rsu-1", bad)
    with pytest.raises(BadKey):
        keys.rsu_command(bad, "car-a")
    with pytest.raises(BadKey):
        keys.stats(bad)
    with pytest.raises(BadKey):
        keys.sim("truth", bad)
    with pytest.raises(BadKey):
        keys.all_commands(bad)
    with pytest.raises(BadKey):
        keys.validate_id(bad)
    assert not keys.is_valid_id(bad)


def test_validate_id() -> None:
    assert keys.validate_id("car_A-01") == "car_A-01"
    assert keys.validate_id("v" * 32) == "v" * 32
    assert not keys.is_valid_id(42)
    with pytest.raises(BadKey, match="invalid node id"):
        keys.validate_id("no way", "node id")


def test_bad_key_is_a_value_error_not_a_key_error() -> None:
    assert issubclass(BadKey, ValueError)
    assert not issubclass(BadKey, KeyError)


def test_sim_needs_a_segment() -> None:
    with pytest.raises(BadKey):
        keys.sim()


@pytest.mark.parametrize(
    ("key", "parsed"),
    [
        ("crosspath/v2x/fp/car-a", ParsedKey(Stream.FP, vehicle="car-a")),
        ("crosspath/v2x/rsu/r1/ap/car-a", ParsedKey(Stream.AP, rsu="r1", vehicle="car-a")),
        ("crosspath/v2x/rsu/r1/cmd/car-a", ParsedKey(Stream.CMD, rsu="r1", vehicle="car-a")),
        ("crosspath/v2x/rsu/r1/beacon", ParsedKey(Stream.BEACON, rsu="r1")),
        ("crosspath/sim/truth/car-a", ParsedKey(Stream.SIM, parts=("truth", "car-a"))),
        ("crosspath/stats/monitor", ParsedKey(Stream.STATS, node="monitor")),
    ],
)
def test_parse(key: str, parsed: ParsedKey) -> None:
    assert keys.parse(key) == parsed


@pytest.mark.parametrize(
    "key",
    [
        "",
        "crosspath",
        "crosspath/",
        "other/v2x/fp/car-a",
        "crosspathx/v2x/fp/car-a",
        "crosspath/v2x/fp",
        "crosspath/v2x/fp/*",
        "crosspath/v2x/fp/**",
        "crosspath/v2x/fp/car-a/extra",
        "crosspath/v2x/fp/car a",
        "crosspath/v2x/fp/",
        "crosspath/v2x/rsu/r1",
        "crosspath/v2x/rsu/*/beacon",
        "crosspath/v2x/rsu/r1/ap",
        "crosspath/v2x/rsu/r1/xx/car-a",
        "crosspath/v2x/rsu/r1/cmd/*",
        "crosspath/v2x/rsu/r1/beacon/x",
        "crosspath/v2x/xx/car-a",
        "crosspath/sim",
        "crosspath/sim/",
        "crosspath/sim/**",
        "crosspath/stats",
        "crosspath/stats/a/b",
        "crosspath/unknown/a",
        "crosspath/v2x/fp/" + "v" * 33,
    ],
)
def test_parse_rejects(key: str) -> None:
    with pytest.raises(BadKey):
        keys.parse(key)


def test_parse_rejects_non_strings() -> None:
    with pytest.raises(BadKey):
        keys.parse(b"crosspath/v2x/fp/car-a")  # type: ignore[arg-type]


@settings(max_examples=200, deadline=None)
@given(prefixes, ids, ids)
def test_build_then_parse(prefix_parts: list[str], rsu: str, vehicle: str) -> None:
    prefix = "/".join(prefix_parts)
    p = {"prefix": prefix}
    assert keys.parse(keys.future_path(vehicle, **p), **p) == ParsedKey(Stream.FP, vehicle=vehicle)
    assert keys.parse(keys.autonomous_path(rsu, vehicle, **p), **p) == ParsedKey(
        Stream.AP, rsu=rsu, vehicle=vehicle
    )
    assert keys.parse(keys.rsu_command(rsu, vehicle, **p), **p) == ParsedKey(
        Stream.CMD, rsu=rsu, vehicle=vehicle
    )
    assert keys.parse(keys.rsu_beacon(rsu, **p), **p) == ParsedKey(Stream.BEACON, rsu=rsu)
    assert keys.parse(keys.stats(rsu, **p), **p) == ParsedKey(Stream.STATS, node=rsu)
    assert keys.parse(keys.sim(rsu, vehicle, **p), **p) == ParsedKey(
        Stream.SIM, parts=(rsu, vehicle)
    )


def test_streams() -> None:
    assert [s.value for s in Stream] == ["fp", "ap", "cmd", "beacon", "sim", "stats"]
    assert set(QOS) == set(Stream)
    assert QOS[Stream.FP].express and QOS[Stream.FP].drop and not QOS[Stream.FP].reliable
    for s in (Stream.AP, Stream.CMD, Stream.BEACON):
        assert not QOS[s].reliable and QOS[s].drop
    for s in (Stream.SIM, Stream.STATS):
        assert QOS[s].reliable and not QOS[s].drop
    assert set(STREAM_OF_KIND) == set(Kind)


def test_message_keys_and_matching() -> None:
    for name, (message, _) in VECTORS.items():
        key = keys.message_key(message, rsu="rsu-1")
        parsed = keys.parse(key)
        assert parsed.stream is STREAM_OF_KIND[message.kind], name
        assert keys.matches(parsed, message), name
    fp_msg = VECTORS["fp-basic"][0]
    assert not keys.matches(keys.parse("crosspath/v2x/fp/car-z"), fp_msg)
    assert not keys.matches(keys.parse("crosspath/v2x/rsu/r/ap/car-a"), fp_msg)
    cmd = VECTORS["mc-initiate"][0]
    assert keys.matches(keys.parse("crosspath/v2x/rsu/rsu-1/cmd/car-a"), cmd)
    assert not keys.matches(keys.parse("crosspath/v2x/rsu/rsu-2/cmd/car-a"), cmd)
    assert not keys.matches(keys.parse("crosspath/v2x/rsu/rsu-1/cmd/car-b"), cmd)
    beacon = VECTORS["beacon"][0]
    assert not keys.matches(keys.parse("crosspath/v2x/rsu/rsu-9/beacon"), beacon)


def test_autonomous_path_key_needs_the_rsu() -> None:
    with pytest.raises(BadKey, match="destination rsu"):
        keys.message_key(VECTORS["ap-wide"][0])
