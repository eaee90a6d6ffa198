from __future__ import annotations

from pathlib import Path

import pytest

from capevo.records import Action, State
from capevo.registry.local import LocalRegistry
from capevo.registry.roundtrip import DEMO_ECM, run_round_trip


@pytest.mark.zenoh
def test_round_trip_over_zenoh_leaves_first_version_active_and_full_history(tmp_path: Path, free_port: int) -> None:
    result = run_round_trip(tmp_path, port=free_port)

    assert result.endpoint == f"tcp/127.0.0.1:{free_port}"
    assert result.active_version == 0
    assert [(e.action, e.version) for e in result.history] == [
        (Action.PUBLISH, 0),
        (Action.PROMOTE, 0),
        (Action.PUBLISH, 1),
        (Action.PROMOTE, 1),
        (Action.ROLLBACK, 0),
    ]
    assert all(e.actor == "demo" for e in result.history)
    # What the client saw is what the registry made durable on disk.
    with LocalRegistry(tmp_path) as local:
        assert local.get_version(DEMO_ECM).version == 0
        assert local.get_version(DEMO_ECM, 1).state is State.SUPERSEDED
        assert local.verify().ok
