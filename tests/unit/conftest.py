"""Fixtures of the unit tests."""

from __future__ import annotations

from collections.abc import Iterator

import pytest

from tests.fleet_helpers import FleetThreads


@pytest.fixture
def fleet_threads() -> Iterator[FleetThreads]:
    """Start agents' fleet loops and bridges (on a ``FakeSession``) on threads; all stopped at the end."""
    threads = FleetThreads()
    try:
        yield threads
    finally:
        threads.close()
