"""The C kernels' test helper (``tests/kernels.py``): a missing kernel fails on CI and
skips only locally; ``both_ways`` runs a call with the kernel and without, leaving it on."""

from __future__ import annotations

import pytest

from tests.kernels import both_ways, require_kernel


def test_a_missing_kernel_fails_on_ci_and_skips_locally(monkeypatch: pytest.MonkeyPatch) -> None:
    require_kernel(True, "built")  # nothing happens
    monkeypatch.setenv("CI", "true")
    with pytest.raises(pytest.fail.Exception, match="missing was not built"):
        require_kernel(False, "missing")
    monkeypatch.delenv("CI")
    with pytest.raises(pytest.skip.Exception, match="missing not built"):
        require_kernel(False, "missing")


def test_both_ways_runs_with_then_without_and_leaves_the_kernel_on() -> None:
    state = {"on": False}

    def switch(enabled: bool) -> bool:
        previous, state["on"] = state["on"], enabled
        return previous

    def call(x: int, *, y: int) -> tuple[bool, int]:
        return state["on"], x + y

    assert both_ways(switch, call, 1, y=2) == ((True, 3), (False, 3))
    assert state["on"] is True

    def boom(x: int) -> int:
        if not state["on"]:
            raise ValueError("numpy path failed")
        return x

    with pytest.raises(ValueError, match="numpy path failed"):
        both_ways(switch, boom, 1)
    assert state["on"] is True  # on again after a failure too
