"""Fixtures shared by the test modules (pytest loads this file before them)."""

from __future__ import annotations

from collections.abc import Iterator
from typing import Any

import pytest


@pytest.fixture(scope="module")
def ros() -> Iterator[Any]:
    """A private rclpy context per test module (independent of any other module's rclpy.init)."""
    import rclpy
    from rclpy.context import Context

    ctx = Context()
    rclpy.init(args=[], context=ctx)
    yield ctx
    rclpy.try_shutdown(context=ctx)
