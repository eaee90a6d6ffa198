"""Concurrent learners and operators, each a separate client process, against one server process."""

from __future__ import annotations

import hashlib
import multiprocessing as mp
from collections.abc import Iterator
from typing import Any

import pytest
from procs import ServerProcess, start_server
from zenoh_fixtures import learner_publish_worker, promote_worker, unique_name

from capevo.records import State
from capevo.registry.descriptor import parse_publish_spec

pytestmark = pytest.mark.zenoh

SPEC = parse_publish_spec("kind: code\ndescription: concurrency test\n")
N_PROCS = 4
PER_PROC = 6
SPAWN = mp.get_context("spawn")  # never fork a process that may hold a Zenoh session


@pytest.fixture(scope="module")
def server(tmp_path_factory: pytest.TempPathFactory) -> Iterator[ServerProcess]:
    srv = start_server(tmp_path_factory.mktemp("conc") / "registry")
    yield srv
    assert srv.stop() == 0, srv.log_text()


def _run_all(target: Any, arg_sets: list[tuple[Any, ...]]) -> list[Any]:
    """Start one spawned process per arg set, release them together, collect one result each."""
    ready, go, results = SPAWN.Queue(), SPAWN.Event(), SPAWN.Queue()
    procs = [SPAWN.Process(target=target, args=(*args, ready, go, results)) for args in arg_sets]
    for p in procs:
        p.start()
    try:
        for _ in procs:
            ready.get(timeout=60)  # every client is connected before anyone starts
        go.set()
        return [results.get(timeout=120) for _ in procs]
    finally:
        for p in procs:
            p.join(timeout=30)
            if p.is_alive():
                p.kill()


def test_concurrent_learners_get_unique_gap_free_versions(server: ServerProcess) -> None:
    name = unique_name("learners")
    outcomes = _run_all(
        learner_publish_worker,
        [(server.endpoint, server.namespace, name, PER_PROC, f"learner-{i}") for i in range(N_PROCS)],
    )
    assert [err for _, _, err in outcomes if err] == []
    versions = sorted(v for _, published, _ in outcomes for v, _ in published)
    assert versions == list(range(N_PROCS * PER_PROC))
    with server.client() as client:
        detail = client.get_ecm(name)
        assert [v.version for v in detail.versions] == versions
        by_version = {v.version: v for v in detail.versions}
        for tag, published, _ in outcomes:
            # Each learner's versions increase in the order it published them, with its own bytes.
            assert [v for v, _ in published] == sorted(v for v, _ in published)
            for i, (version, sha) in enumerate(published):
                expected = f"{tag}-{i}".encode() * 100
                assert by_version[version].created_by == tag
                assert sha == by_version[version].artifact.sha256 == hashlib.sha256(expected).hexdigest()
                assert client.get_artifact(name, version) == expected
        assert client.verify().ok


def test_concurrent_promotes_with_expected_active_exactly_one_wins(server: ServerProcess) -> None:
    name = unique_name("race")
    with server.client() as client:
        for i in range(N_PROCS + 1):
            client.publish(name, f"v{i}".encode(), SPEC)
        client.promote(name, 0)
    outcomes = _run_all(
        promote_worker, [(server.endpoint, server.namespace, name, v, 0) for v in range(1, N_PROCS + 1)]
    )
    winners = [o for o in outcomes if o[1] == "ok"]
    losers = [o for o in outcomes if o[1] != "ok"]
    assert len(winners) == 1, outcomes
    winner = winners[0][0]
    assert winners[0][2] == "active"
    for version, kind, code, message in losers:
        assert (kind, code) == ("error", "conflict"), (version, kind, code, message)
        assert message == f"cannot promote {name}: expected active v0, but the active version is v{winner}"
    with server.client() as client:
        assert client.get_version(name).version == winner
        states = {v.version: v.state for v in client.get_ecm(name).versions}
        assert states[0] is State.SUPERSEDED
        assert [v for v, s in states.items() if s is State.ACTIVE] == [winner]
        assert sum(1 for e in client.history(name) if e.action.value == "promote") == 2
