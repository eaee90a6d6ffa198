"""Fixtures shared by the runtime tests."""

from __future__ import annotations

import logging
from collections.abc import Iterator

import pytest


@pytest.fixture(scope="module")
def quiet() -> Iterator[None]:
    """robosuite's per-robot controller warnings off while a module builds environments."""
    logger = logging.getLogger("robosuite_logs")
    level = logger.level
    logger.setLevel(logging.ERROR)
    yield
    logger.setLevel(level)
