"""Shared by the tests of the optional C kernels (``protocol/_speedups.c``,
``services/rsu/_scan.c``, ``services/model/_geometry.c``): each must give its numpy code's
answers, so each test runs the same call both ways."""

from __future__ import annotations

import os
from collections.abc import Callable
from typing import Any

import pytest


def require_kernel(built: bool, module: str) -> None:
    """At a test module's top: without the kernel, skip the module locally (no C
    compiler) but fail on CI (``CI`` set), where ``make test`` builds it."""
    if built:
        return
    if os.environ.get("CI"):
        pytest.fail(f"{module} was not built: make test builds it", pytrace=False)
    pytest.skip(f"{module} not built (no C compiler?)", allow_module_level=True)


def both_ways(
    switch: Callable[[bool], bool], fn: Callable[..., Any], *args: Any, **kwargs: Any
) -> tuple[Any, Any]:
    """``fn(*args, **kwargs)`` with the kernel, then on numpy (``switch`` turns the kernel
    on and off, as ``paths.use_kernel`` does); the kernel is left on."""
    switch(True)
    fast = fn(*args, **kwargs)
    switch(False)
    try:
        slow = fn(*args, **kwargs)
    finally:
        switch(True)
    return fast, slow
