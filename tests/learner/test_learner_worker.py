"""The learner worker as a real process against a real registry server process over Zenoh.

Loopback TCP, multicast scouting off. ``--once`` publishes one candidate with provenance (1, 2);
two learners at once publish distinct versions; in watch mode new episodes in the trace
directory fire the trigger (3) and SIGTERM shuts the worker down cleanly (4).
"""

from __future__ import annotations

import json
import os
import re
import signal
import subprocess
import time
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from neural_support import (
    REPO,
    Proc,
    learner_args,
    read_events,
    start_learner,
    start_registry,
    subprocess_env,
    write_scripted_trace,
)
from procs import free_tcp_port

from capevo.learner.neural_seed import seed_policy
from capevo.records import Kind, Origin, State
from capevo.registry.client import Client

pytestmark = [pytest.mark.slow, pytest.mark.zenoh]

ECM = "pick.reach"
HEX64 = re.compile(r"^[0-9a-f]{64}$")


@dataclass
class Server:
    endpoint: str
    proc: Proc
    root: Path


@pytest.fixture(scope="module")
def server(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Server]:
    root = tmp_path_factory.mktemp("learner-worker")
    port = free_tcp_port()
    proc = start_registry(root / "registry", port)
    endpoint = f"tcp/127.0.0.1:{port}"
    with Client([endpoint], actor="tests") as client:
        artifact, spec = seed_policy("T1", ECM, net_arch=(32, 32), seed=0)
        record = client.publish(ECM, artifact, spec)
        client.promote(ECM, record.version)
    yield Server(endpoint=endpoint, proc=proc, root=root)
    assert proc.stop() == 0, proc.log_text()


def _run_once(server: Server, *extra: Any, timeout: float = 240.0) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        learner_args(server.endpoint, "--ecm", ECM, "--preset", "tiny", "--once", *extra),
        capture_output=True,
        text=True,
        env=subprocess_env(),
        cwd=REPO,
        timeout=timeout,
    )


def _events(stdout: str) -> list[dict[str, Any]]:
    return [json.loads(line) for line in stdout.splitlines() if line.strip()]


def _published(events: list[dict[str, Any]]) -> dict[str, Any]:
    found = [e for e in events if e["event"] == "published"]
    assert len(found) == 1, events
    return found[0]


def test_once_publishes_an_il_candidate_with_provenance(server: Server) -> None:
    done = _run_once(server, "--modality", "il", "--learner-id", "il-proc-1")
    assert done.returncode == 0, done.stderr[-4000:]
    events = _events(done.stdout)
    assert [e["event"] for e in events] == ["ready", "training", "published", "stopped"]
    event = _published(events)
    with Client([server.endpoint], actor="checker") as client:
        record = client.get_version(ECM, event["version"])
        assert client.get_version(ECM).version == 0  # learners never promote
    assert record.state is State.CANDIDATE and record.kind is Kind.NEURAL and record.origin is Origin.IL
    assert record.parent == 0
    assert record.provenance.learner_id == "il-proc-1" == record.created_by
    assert HEX64.match(record.provenance.config_hash or "")
    assert event["provenance"] == record.provenance.to_dict()
    # the tiny preset's one DAgger round adds the clone's own states, labelled by the reference
    assert event["notes"]["demos"]["source"] == "scripted+dagger"
    assert [r["round"] for r in event["notes"]["dagger"]["rounds"]] == [1]


def test_two_learners_at_once_publish_distinct_versions(server: Server, tmp_path: Path) -> None:
    procs = [
        start_learner(
            server.endpoint, tmp_path / f"{m}.log", "--ecm", ECM, "--preset", "tiny", "--once", "--modality", m
        )
        for m in ("rl", "il")
    ]
    try:
        published = [_published(read_events(p, "published", timeout=240)) for p in procs]
        for p in procs:
            assert p.proc.wait(timeout=60) == 0, p.log_text()[-4000:]
    finally:
        for p in procs:
            p.stop()
    versions = {e["version"] for e in published}
    ids = {e["learner_id"] for e in published}
    assert len(versions) == 2 and len(ids) == 2
    with Client([server.endpoint], actor="checker") as client:
        records = {v.version: v for v in client.get_ecm(ECM).versions}
    assert {records[v].origin for v in versions} == {Origin.RL, Origin.IL}
    for e in published:
        record = records[e["version"]]
        assert record.state is State.CANDIDATE and record.parent == 0
        assert record.provenance.learner_id == e["learner_id"]
        assert HEX64.match(record.provenance.config_hash or "")


def test_watch_mode_learns_when_episodes_arrive_and_stops_on_sigterm(server: Server, tmp_path: Path) -> None:
    traces = tmp_path / "traces"
    traces.mkdir()
    learner = start_learner(
        server.endpoint,
        tmp_path / "watch.log",
        "--ecm",
        ECM,
        "--preset",
        "tiny",
        "--modality",
        "il",
        "--traces",
        traces,
        "--min-episodes",
        2,
        "--margin",
        0,
        "--poll",
        0.2,
    )
    try:
        read_events(learner, "ready", timeout=60)
        staging = tmp_path / "staging.mcap"
        episodes = write_scripted_trace(
            staging, seeds=[0, 1], horizons=[80, 10], versions={ECM: 0}, inputs={}, run_id="watch-run"
        )
        assert [e.success for e in episodes] == [True, False]
        os.replace(staging, traces / "pick-watch.mcap")
        events = read_events(learner, "published", timeout=240)
        kinds = [e["event"] for e in events]
        assert kinds[-3:] == ["trigger", "training", "published"], kinds
        trigger = events[-3]
        assert (trigger["reason"], trigger["new_episodes"], trigger["active"]) == ("count", 2, 0)
        published = events[-1]
        # the watched traces' successful steps, and the scripted reference's rollouts beside them
        assert published["notes"]["demos"]["source"] == "traces+scripted+dagger"  # tiny: one DAgger round
        assert published["provenance"]["traces"] == [str((traces / "pick-watch.mcap").resolve())]
        learner.proc.send_signal(signal.SIGTERM)
        stopped = read_events(learner, "stopped", timeout=60)[-1]
        assert stopped["published"] == 1
        assert learner.proc.wait(timeout=60) == 0, learner.log_text()[-4000:]
    finally:
        learner.stop()


def test_once_without_an_active_version_fails_with_one_error_line(server: Server) -> None:
    done = subprocess.run(
        learner_args(server.endpoint, "--ecm", "pick.lift", "--modality", "rl", "--preset", "tiny", "--once"),
        capture_output=True,
        text=True,
        env=subprocess_env(),
        cwd=REPO,
        timeout=120,
    )
    assert done.returncode == 4, done.stderr
    assert "Traceback" not in done.stderr
    errors = [line for line in done.stderr.splitlines() if line.startswith("error [")]
    assert len(errors) == 1
    assert errors[0].startswith("error [not_found]: pick.lift has no active version to learn from;")


def test_watch_counts_only_the_active_versions_episodes_and_resets_on_promotion(tmp_path: Path) -> None:
    """In-process worker over a real LocalRegistry: a promotion resets the trigger; episodes of
    the old version no longer count; one update per firing, parent = the active version."""
    import threading

    from capevo.learner.trigger import TriggerConfig
    from capevo.learner.worker import LearnerConfig, LearnerWorker
    from capevo.registry.local import LocalRegistry

    root = tmp_path / "registry"
    setup = LocalRegistry(root, actor="tests")
    artifact, spec = seed_policy("T1", ECM, net_arch=(32, 32), seed=0)
    setup.promote(ECM, setup.publish(ECM, artifact, spec).version)
    traces = tmp_path / "traces"
    traces.mkdir()
    staging = tmp_path / "staging"
    staging.mkdir()
    old = write_scripted_trace(staging / "a.mcap", seeds=[0, 1], horizons=[80, 10], versions={ECM: 0}, inputs={})
    events: list[dict[str, Any]] = []
    config = LearnerConfig(
        ecm=ECM,
        modality="il",
        preset="tiny",
        learner_id="il-watch",
        traces=(traces,),
        trigger=TriggerConfig(min_new_episodes=2, degradation_margin=None),
        poll_interval_s=0.1,
        torch_threads=1,
    )
    worker = LearnerWorker(config, lambda: LocalRegistry(root, actor="il-watch"), emit=events.append)
    stop = threading.Event()
    thread = threading.Thread(target=worker.run, args=(stop,), kwargs={"handle_signals": False})
    thread.start()

    def wait_for(n_published: int, timeout: float = 120.0) -> None:
        deadline = time.monotonic() + timeout
        while len(worker.published) < n_published and time.monotonic() < deadline:
            assert thread.is_alive(), events
            time.sleep(0.1)
        assert len(worker.published) == n_published, events

    try:
        os.replace(staging / "a.mcap", traces / "a.mcap")
        wait_for(1)
        first = worker.published[0]
        assert first.parent == 0 and first.provenance.learner_id == "il-watch"
        setup.promote(ECM, first.version)  # the gate took it: evidence about v0 is now stale
        time.sleep(0.5)
        # more v0 episodes must not count for the new version
        write_scripted_trace(staging / "b.mcap", seeds=[2, 3], horizons=[80, 10], versions={ECM: 0}, inputs={})
        os.replace(staging / "b.mcap", traces / "b.mcap")
        time.sleep(1.0)
        assert len(worker.published) == 1, events
        write_scripted_trace(
            staging / "c.mcap", seeds=[4, 5], horizons=[80, 10], versions={ECM: first.version}, inputs={}
        )
        os.replace(staging / "c.mcap", traces / "c.mcap")
        wait_for(2)
        assert worker.published[1].parent == first.version
    finally:
        stop.set()
        thread.join(timeout=120)
        setup.close()
    assert not thread.is_alive()
    triggers = [e for e in events if e["event"] == "trigger"]
    assert [(t["reason"], t["new_episodes"], t["active"]) for t in triggers] == [
        ("count", 2, 0),
        ("count", 2, first.version),
    ]
    assert events[-1] == {"event": "stopped", "learner_id": "il-watch", "published": 2}
    assert old[0].success


@pytest.mark.parametrize(
    ("kwargs", "text"),
    [
        ({"ecm": ECM, "modality": "dreaming"}, "unknown modality 'dreaming'; valid: rl, il, code, hybrid"),
        (
            {"ecm": "pick.fly", "modality": "rl"},
            "task 'pick' has no ECM 'pick.fly'; valid: pick.reach, pick.grasp, pick.lift",
        ),
        ({"ecm": ECM, "modality": "rl", "preset": "huge"}, "unknown preset 'huge'; valid: tiny, cpu-small, paper"),
        (
            {"ecm": ECM, "modality": "code", "seed_plan": 10**6},
            "seed_plan: seed plan 1000000 with block 100000 reaches past 2147483647",
        ),
    ],
)
def test_bad_learner_configs_are_refused(kwargs: dict[str, Any], text: str) -> None:
    from capevo.errors import ErrorCode, Invalid
    from capevo.learner.worker import LearnerConfig

    with pytest.raises(Invalid) as info:
        LearnerConfig(**kwargs)
    assert info.value.code is ErrorCode.INVALID
    assert info.value.message == text


@settings(max_examples=200, deadline=None)
@given(plan=st.integers(0, 7000), seed=st.integers(0, 10**9))
def test_worker_training_seeds_stay_in_the_plans_training_block(plan: int, seed: int) -> None:
    from capevo.learner.worker import TRAIN_SEEDS, worker_training_seeds
    from capevo.runtime.gate import SeedPlan

    p = SeedPlan(base_seed=plan)
    seeds = worker_training_seeds(p, seed)
    assert len(set(seeds)) == TRAIN_SEEDS
    assert all(p.purpose_of(s) == "train" for s in seeds)
    # In particular never the seeds any plan's gate uses: those of this plan are the only ones here.
    assert not set(seeds) & set(p.range("gate"))


def test_neural_training_episodes_run_in_the_plans_training_block() -> None:
    from capevo.learner.worker import LearnerConfig, LearnerWorker
    from capevo.runtime.gate import SeedPlan

    plan = SeedPlan(base_seed=3)
    for seed in (0, 7, 123_456):
        config = LearnerConfig(ecm=ECM, modality="rl", seed=seed, seed_plan=3)
        worker = LearnerWorker(config, open_registry=lambda: pytest.fail("no registry is needed"))
        env = worker.preset.env
        first, last = env.seed_base + env.seed, env.seed_base + env.seed + 10_000  # 10k episodes: beyond paper budget
        assert plan.purpose_of(first) == plan.purpose_of(last) == "train"
