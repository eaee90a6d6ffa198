from __future__ import annotations

import os

import pytest
from hypothesis import settings
from procs import free_tcp_port

# CI runs the property tests derandomized (`.ci/run` sets CAPEVO_HYPOTHESIS_PROFILE=ci): the same
# examples every run, so a landing never fails on an example no earlier run tried. Local runs keep
# hypothesis' random exploration, which is how new edge cases get found.
settings.register_profile("ci", derandomize=True, print_blob=True)
settings.load_profile(os.environ.get("CAPEVO_HYPOTHESIS_PROFILE", "default"))


@pytest.fixture
def free_port() -> int:
    return free_tcp_port()
