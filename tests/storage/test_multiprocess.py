"""Several real processes sharing one registry root (multiprocessing 'spawn').

Checks invariants 1 and 5 of :mod:`capevo.storage.sqlite` across processes: versions
stay unique and gap-free, and of racing compare-and-swap promotes exactly one wins.
"""

from __future__ import annotations

import multiprocessing as mp
from pathlib import Path
from typing import Any

from capevo.errors import CapevoError
from capevo.records.audit import chain_problems
from capevo.registry.descriptor import parse_publish_spec
from capevo.registry.local import LocalRegistry

N_PROCS = 4
N_PUBLISH = 25
N_ROUNDS = 3
SPEC_YAML = "kind: code\ndescription: concurrency probe\n"


def _publisher(root: str, worker: int, start: Any, out: Any) -> None:
    spec = parse_publish_spec(SPEC_YAML)
    with LocalRegistry(root, actor=f"worker-{worker}") as reg:
        start.wait()
        got = []
        for i in range(N_PUBLISH):
            payload = f"worker {worker} item {i}".encode()
            got.append((reg.publish("shared", payload, spec).version, payload))
    out.put((worker, got))


def _promoter(root: str, worker: int, barrier: Any, out: Any) -> None:
    with LocalRegistry(root, actor=f"worker-{worker}") as reg:
        for rnd in range(N_ROUNDS):
            seen = reg.get_version("race").version  # everyone reads before anyone moves
            barrier.wait()
            target = 1 + rnd * N_PROCS + worker
            try:
                reg.promote("race", target, expected_active=seen)
                out.put((rnd, worker, "won", seen, target))
            except CapevoError as exc:
                out.put((rnd, worker, exc.code.value, seen, exc.message))
            barrier.wait()  # nobody reads the next round's pointer before this round ends


def _run(target: Any, root: Path, sync: Any, ctx: Any, n_results: int) -> list[Any]:
    """Start one process per worker, release ``sync`` if it is an Event, collect results."""
    out = ctx.Queue()
    procs = [ctx.Process(target=target, args=(str(root), w, sync, out)) for w in range(N_PROCS)]
    for p in procs:
        p.start()
    if hasattr(sync, "set"):
        sync.set()
    results = [out.get(timeout=60) for _ in range(n_results)]
    for p in procs:
        p.join(timeout=30)
        assert p.exitcode == 0
    return results


def test_concurrent_publishers_get_unique_gap_free_versions(tmp_path: Path) -> None:
    ctx = mp.get_context("spawn")
    LocalRegistry(tmp_path).close()  # create the schema once, outside the race
    results = _run(_publisher, tmp_path, ctx.Event(), ctx, N_PROCS)
    claimed = {v: payload for _, got in results for v, payload in got}
    assert sorted(claimed) == list(range(N_PROCS * N_PUBLISH))  # unique: no version claimed twice
    with LocalRegistry(tmp_path) as reg:
        assert [v.version for v in reg.get_ecm("shared").versions] == list(range(N_PROCS * N_PUBLISH))
        for version, payload in claimed.items():
            assert reg.get_artifact("shared", version) == payload
        events = reg.history("shared")
        assert chain_problems(events) == []
        # Each worker's own versions are increasing: its publishes were serialised in order.
        for worker, got in results:
            assert [v for v, _ in got] == sorted(v for v, _ in got)
            assert sum(e.actor == f"worker-{worker}" for e in events) == N_PUBLISH
        assert reg.verify().ok


def test_racing_compare_and_swap_promotes_have_one_winner(tmp_path: Path) -> None:
    ctx = mp.get_context("spawn")
    spec = parse_publish_spec(SPEC_YAML)
    with LocalRegistry(tmp_path) as reg:
        for i in range(1 + N_ROUNDS * N_PROCS):
            reg.publish("race", f"v{i}".encode(), spec)
        reg.promote("race", 0)
    results = _run(_promoter, tmp_path, ctx.Barrier(N_PROCS), ctx, N_PROCS * N_ROUNDS)
    winners = []
    for rnd in range(N_ROUNDS):
        this = [r for r in results if r[0] == rnd]
        won = [r for r in this if r[2] == "won"]
        assert len(won) == 1, this
        winners.append(won[0][4])
        for _, _, outcome, seen, message in this:
            if outcome != "won":
                assert outcome == "conflict"
                assert message == (
                    f"cannot promote race: expected active v{seen}, but the active version is v{winners[-1]}"
                )
    with LocalRegistry(tmp_path) as reg:
        assert reg.get_version("race").version == winners[-1]
        assert reg.capability_set().revision == 1 + N_ROUNDS
        assert [dict(reg.capability_set(r + 2).active) for r in range(N_ROUNDS)] == [{"race": w} for w in winners]
        assert reg.verify().ok
