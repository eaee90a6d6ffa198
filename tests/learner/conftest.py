"""Fixtures shared by the learner tests."""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path

import pytest

from capevo.learner.skills import seed_registry
from capevo.registry.local import LocalRegistry


@pytest.fixture
def registry(tmp_path: Path) -> Iterator[LocalRegistry]:
    """A local registry holding the built-in code v0 of every ECM of ``pick`` (test_rl's own
    module fixture replaces it with a neural one)."""
    reg = LocalRegistry(tmp_path / "reg", actor="test")
    seed_registry(reg, "pick")
    yield reg
    reg.close()
