from __future__ import annotations

import os
import socket

import pytest
from hypothesis import settings

# CI runs the property tests derandomized (`.ci/run` sets CAPEVO_HYPOTHESIS_PROFILE=ci): the same
# examples every run, so a landing never fails on an example no earlier run tried. Local runs keep
# hypothesis' random exploration, which is how new edge cases get found.
settings.register_profile("ci", derandomize=True, print_blob=True)
settings.load_profile(os.environ.get("CAPEVO_HYPOTHESIS_PROFILE", "default"))


def free_tcp_port() -> int:
    """A loopback TCP port that was free a moment ago (bind to 0, read, release)."""
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


@pytest.fixture
def free_port() -> int:
    return free_tcp_port()
