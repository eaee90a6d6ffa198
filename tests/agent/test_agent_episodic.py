"""M_ep: append-only JSON Lines episodic memory, torn tails, and a SIGKILLed writer.

Episodic invariants 1-6.
"""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from capevo.agent import EpisodeRecord, EpisodicMemory, iter_episodes, read_episodes
from capevo.errors import Conflict, Corrupt, ErrorCode, Invalid, NotFound
from capevo.runtime.evaluation import EpisodeOutcome

CHILD = Path(__file__).with_name("_episodic_child.py")


def record(i: int, iteration: int | None = None) -> EpisodeRecord:
    return EpisodeRecord(
        iteration=i if iteration is None else iteration,
        task="pick",
        seed=i,
        success=i % 2 == 0,
        reward=0.25 * i,
        steps=10 + i,
        capability_set={"pick.reach": 1, "pick.lift": 2},
        trace=f"runs/{i}.mcap",
    )


def test_append_and_read_back(tmp_path: Path) -> None:
    path = tmp_path / "sub" / "ep.jsonl"
    with EpisodicMemory(path) as m:
        for i in range(5):
            m.append(record(i))
        log = m.read()
    assert log.records == tuple(record(i) for i in range(5))
    assert not log.torn and log.torn_tail_bytes == 0
    assert list(iter_episodes(path)) == list(log.records)
    lines = path.read_bytes().split(b"\n")
    assert lines[-1] == b"" and len(lines) == 6
    assert json.loads(lines[0]) == record(0).to_dict()
    assert (
        lines[0] == b'{"capability_set":{"pick.lift":2,"pick.reach":1},"iteration":0,"reward":0.0,"seed":0,'
        b'"steps":10,"success":true,"task":"pick","trace":"runs/0.mcap"}'
    )


def test_reopening_appends_after_existing_records(tmp_path: Path) -> None:
    path = tmp_path / "ep.jsonl"
    with EpisodicMemory(path) as m:
        m.append(record(0))
    with EpisodicMemory(path) as m:
        assert m.last_iteration == 0 and m.repaired_bytes == 0
        m.append(record(1))
    assert [r.seed for r in read_episodes(path).records] == [0, 1]


def test_record_round_trip_and_from_outcome() -> None:
    r = record(3)
    assert EpisodeRecord.from_dict(r.to_dict()) == r
    assert EpisodeRecord.from_dict({**r.to_dict(), "trace": None}).trace is None
    outcome = EpisodeOutcome(
        seed=7,
        success=True,
        reward=1.5,
        steps=40,
        duration_s=0.1,
        interventions=0,
        unsafe_steps=0,
        ecm_failures=0,
        capability_set={"pick.reach": 2},
        trace_path="t.mcap",
    )
    assert EpisodeRecord.from_outcome(iteration=4, task="pick", outcome=outcome) == EpisodeRecord(
        iteration=4,
        task="pick",
        seed=7,
        success=True,
        reward=1.5,
        steps=40,
        capability_set={"pick.reach": 2},
        trace="t.mcap",
    )


@pytest.mark.parametrize(
    ("change", "message"),
    [
        ({"iteration": -1}, "iteration: must be at least 0, got -1"),
        ({"iteration": True}, "iteration: must be an integer, got True"),
        ({"steps": 1.5}, "steps: must be an integer, got 1.5"),
        ({"success": 1}, "success: must be true or false, got 1"),
        ({"reward": float("nan")}, "reward: must be a finite number, got nan"),
        ({"task": ""}, "task: must be a non-empty string of at most 256 characters, got ''"),
        ({"capability_set": {"pick.reach": -1}}, "capability_set.pick.reach: must be at least 0, got -1"),
        ({"capability_set": [1]}, "capability_set: must be a mapping of ECM name to version, got [1]"),
        ({"trace": 3}, "trace: must be a string or null, got 3"),
    ],
)
def test_bad_records_are_invalid(change: dict[str, object], message: str) -> None:
    with pytest.raises(Invalid) as info:
        EpisodeRecord.from_dict({**record(0).to_dict(), **change})
    assert info.value.code is ErrorCode.INVALID
    assert info.value.message == message


def test_unknown_and_missing_fields_are_invalid() -> None:
    with pytest.raises(Invalid) as info:
        EpisodeRecord.from_dict({**record(0).to_dict(), "mood": "happy"})
    assert info.value.message == "mood: unknown field"
    d = record(0).to_dict()
    del d["seed"]
    with pytest.raises(Invalid) as info:
        EpisodeRecord.from_dict(d)
    assert info.value.message == "seed: missing"


def test_iterations_never_go_backwards(tmp_path: Path) -> None:
    with EpisodicMemory(tmp_path / "ep.jsonl") as m:
        m.append(record(0, iteration=2))
        m.append(record(1, iteration=2))  # several episodes per iteration are fine
        with pytest.raises(Invalid) as info:
            m.append(record(2, iteration=1))
        assert info.value.code is ErrorCode.INVALID
        assert info.value.message == "iteration: 1 is before the last recorded iteration 2"
    with EpisodicMemory(tmp_path / "ep.jsonl") as m, pytest.raises(Invalid):
        m.append(record(3, iteration=1))  # remembered across reopening


def test_one_writer_at_a_time(tmp_path: Path) -> None:
    path = tmp_path / "ep.jsonl"
    with EpisodicMemory(path):
        with pytest.raises(Conflict) as info:
            EpisodicMemory(path)
        assert info.value.code is ErrorCode.CONFLICT
        assert info.value.message == f"episodic memory {path} is already open for writing by another writer"
    EpisodicMemory(path).close()  # free again once closed


def test_closed_memory_refuses_appends(tmp_path: Path) -> None:
    m = EpisodicMemory(tmp_path / "ep.jsonl")
    m.close()
    m.close()
    with pytest.raises(Invalid) as info:
        m.append(record(0))
    assert info.value.message == f"episodic memory {tmp_path / 'ep.jsonl'} is closed"


def test_a_torn_last_line_is_ignored_reported_and_cut_before_the_next_append(tmp_path: Path) -> None:
    path = tmp_path / "ep.jsonl"
    with EpisodicMemory(path) as m:
        m.append(record(0))
        m.append(record(1))
    torn = json.dumps(record(2).to_dict()).encode()[:37]
    with path.open("ab") as f:
        f.write(torn)
    log = read_episodes(path)
    assert [r.seed for r in log.records] == [0, 1]
    assert log.torn and log.torn_tail_bytes == 37
    assert [r.seed for r in iter_episodes(path)] == [0, 1]
    with EpisodicMemory(path) as m:
        assert m.repaired_bytes == 37 and m.last_iteration == 1
        m.append(record(2))
    log = read_episodes(path)
    assert [r.seed for r in log.records] == [0, 1, 2] and not log.torn


def test_a_file_that_is_only_a_torn_line(tmp_path: Path) -> None:
    path = tmp_path / "ep.jsonl"
    path.write_bytes(b'{"iterat')
    assert read_episodes(path).records == () and read_episodes(path).torn_tail_bytes == 8
    with EpisodicMemory(path) as m:
        assert m.repaired_bytes == 8 and m.last_iteration is None
        m.append(record(0))
    assert read_episodes(path).records == (record(0),)


def test_long_records_beyond_the_tail_chunk(tmp_path: Path) -> None:
    path = tmp_path / "ep.jsonl"
    big = {f"ecm.{i:05d}": i for i in range(6000)}  # one line > 64 KiB
    with EpisodicMemory(path) as m:
        m.append(EpisodeRecord(iteration=0, task="t", seed=0, success=True, reward=1.0, steps=1, capability_set=big))
        m.append(EpisodeRecord(iteration=5, task="t", seed=1, success=True, reward=1.0, steps=1, capability_set=big))
    with path.open("ab") as f:
        f.write(b"x" * 70_000)
    with EpisodicMemory(path) as m:
        assert m.last_iteration == 5 and m.repaired_bytes == 70_000
    assert len(read_episodes(path).records) == 2


def test_a_bad_middle_line_is_corrupt_naming_it(tmp_path: Path) -> None:
    path = tmp_path / "ep.jsonl"
    with EpisodicMemory(path) as m:
        m.append(record(0))
    with path.open("ab") as f:
        f.write(b"not json\n")
        f.write(json.dumps(record(1).to_dict()).encode() + b"\n")
    with pytest.raises(Corrupt) as info:
        read_episodes(path)
    assert info.value.code is ErrorCode.CORRUPT
    assert info.value.message.startswith(f"{path}:2: not a JSON episode record: ")
    assert info.value.details["line"] == 2


def test_a_bad_field_in_a_line_is_corrupt(tmp_path: Path) -> None:
    path = tmp_path / "ep.jsonl"
    path.write_text(json.dumps({**record(0).to_dict(), "steps": -3}) + "\n")
    with pytest.raises(Corrupt) as info:
        read_episodes(path)
    assert info.value.message == f"{path}:1: bad episode record: steps: must be at least 0, got -3"
    with pytest.raises(Corrupt) as info:
        EpisodicMemory(path)  # no appending after a corrupt record
    assert info.value.code is ErrorCode.CORRUPT


def test_reading_a_missing_file_is_not_found(tmp_path: Path) -> None:
    with pytest.raises(NotFound) as info:
        read_episodes(tmp_path / "nope.jsonl")
    assert info.value.code is ErrorCode.NOT_FOUND
    assert info.value.message == f"no episodic memory at {tmp_path / 'nope.jsonl'}"


@settings(max_examples=150, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(tail=st.binary(max_size=200))
def test_any_appended_bytes_read_as_a_prefix_or_corrupt(tmp_path: Path, tail: bytes) -> None:
    path = tmp_path / "fuzz.jsonl"
    path.write_bytes(b"".join(json.dumps(record(i).to_dict()).encode() + b"\n" for i in range(2)) + tail)
    try:
        log = read_episodes(path)
    except Corrupt as exc:
        assert exc.message.startswith(f"{path}:")
        return
    assert log.records[:2] == (record(0), record(1))
    assert log.torn_tail_bytes == (len(tail) - tail.rfind(b"\n") - 1 if not tail.endswith(b"\n") else 0)


@pytest.mark.timeout(60)
def test_sigkilled_writer_loses_no_acknowledged_episode(tmp_path: Path) -> None:
    path = tmp_path / "ep.jsonl"
    child = subprocess.Popen(
        [sys.executable, str(CHILD), str(path)], stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True
    )
    acknowledged = -1
    try:
        assert child.stdout is not None
        deadline = time.monotonic() + 30
        while acknowledged < 60 and time.monotonic() < deadline:
            line = child.stdout.readline()
            if not line:
                child.wait(timeout=10)
                raise AssertionError(
                    f"child exited with {child.returncode}: {child.stderr.read() if child.stderr else ''}"
                )
            acknowledged = int(line)
    finally:
        os.kill(child.pid, signal.SIGKILL)
        child.wait(timeout=10)
    assert child.returncode == -signal.SIGKILL
    assert acknowledged >= 60
    log = read_episodes(path)
    seeds = [r.seed for r in log.records]
    # Every append that returned before the kill is there, in order, and nothing else.
    assert seeds == list(range(len(seeds)))
    assert len(seeds) >= acknowledged + 1
    assert log.records[acknowledged].capability_set["pick.lift"] == 1 + acknowledged // 10
    # The kernel released the dead writer's lock: a new writer continues the log.
    with EpisodicMemory(path) as m:
        m.append(record(len(seeds), iteration=10_000))
    assert len(read_episodes(path).records) == len(seeds) + 1
