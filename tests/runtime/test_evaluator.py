"""LocalEvaluator: seeded T1 episodes from a real registry, one real MCAP trace per call.

Invariants of :mod:`capevo.runtime.evaluator`: one outcome per seed in order with the trace's
metadata and summaries matching (1), loaded versions released (2), equal seeds and versions
give equal outcomes (3).
"""

from __future__ import annotations

import dataclasses
import os
from collections.abc import Iterator
from pathlib import Path

import pytest
from runtime_support import LIFT, chunk_compressions, publish, publish_pick

from capevo.agent.fingerprint import identity_hash
from capevo.agent.identity import IdentityMemory
from capevo.agent.policy import DecompositionPolicy
from capevo.errors import Invalid, NotFound
from capevo.records import Origin
from capevo.registry.local import LocalRegistry
from capevo.runtime.evaluation import EpisodeOutcome, Evaluator
from capevo.runtime.evaluator import LocalEvaluator
from capevo.runtime.governance import Phi
from capevo.runtime.traces import TraceReader, package_versions
from capevo.runtime.traces.writer import COMPRESSIONS

HORIZON = 30


@pytest.fixture(scope="module")
def policy() -> DecompositionPolicy:
    return DecompositionPolicy(identity=IdentityMemory.default())


@pytest.fixture(scope="module")
def setup(tmp_path_factory: pytest.TempPathFactory, policy: DecompositionPolicy) -> Iterator[tuple]:
    root = tmp_path_factory.mktemp("evaluator")
    registry = LocalRegistry(root / "registry", actor="tester")
    publish_pick(registry)
    slow_lift = publish(registry, "pick.lift", LIFT.replace('"speed": 1.0', '"speed": 0.5'))
    evaluator = LocalEvaluator(
        registry,
        policy=policy,
        trace_dir=root / "traces",
        horizon=HORIZON,
        agent_identity_hash=identity_hash(policy, policy.identity),
    )
    yield registry, evaluator, slow_lift, root
    evaluator.close()
    registry.close()


def without_duration(outcomes: list[EpisodeOutcome]) -> list[EpisodeOutcome]:
    return [dataclasses.replace(o, duration_s=0.0, trace_path=None) for o in outcomes]


@pytest.mark.slow
def test_evaluate_runs_one_episode_per_seed_into_one_trace(setup: tuple, policy: DecompositionPolicy) -> None:
    registry, evaluator, slow_lift, _ = setup
    assert isinstance(evaluator, Evaluator)
    progress: list[tuple[int, int, int]] = []
    evaluator.progress = lambda done, total, o: progress.append((done, total, o.seed))
    try:
        outcomes = evaluator.evaluate("T1", {}, [5, 3])
    finally:
        evaluator.progress = None
    assert [o.seed for o in outcomes] == [5, 3]
    assert progress == [(1, 2, 5), (2, 2, 3)]
    path = outcomes[0].trace_path
    assert path is not None and all(o.trace_path == path for o in outcomes)
    assert all(o.capability_set == {"pick.reach": 0, "pick.grasp": 0, "pick.lift": slow_lift.version} for o in outcomes)
    assert all(0 < o.steps <= HORIZON and o.unsafe_steps == 0 and o.ecm_failures == 0 for o in outcomes)
    with TraceReader(path) as reader:
        meta = reader.metadata()
        summaries = list(reader.episode_summaries())
        steps = list(reader.env_steps())
    assert meta.task == "pick"
    assert meta.seeds == (5, 3)
    # The default envelope is the task's scene-aware one; every outcome says which ran.
    assert meta.phi_hash == Phi.for_task("pick").hash == evaluator.phi_for("T1").hash
    assert all(o.phi_hash == meta.phi_hash for o in outcomes)
    assert meta.agent_identity_hash == identity_hash(policy, policy.identity)
    assert meta.registry_revision == registry.capability_set().revision
    assert dict(meta.capability_set.active) == dict(outcomes[0].capability_set)
    assert meta.package_versions == package_versions()
    assert [(s.episode, s.seed) for s in summaries] == [(0, 5), (1, 3)]
    assert [s.steps for s in summaries] == [o.steps for o in outcomes]
    assert [s.success for s in summaries] == [o.success for o in outcomes]
    assert len(steps) == sum(o.steps for o in outcomes)


@pytest.mark.slow
def test_same_seeds_and_versions_give_the_same_outcomes_and_pins_apply(setup: tuple) -> None:
    _, evaluator, slow_lift, _ = setup
    a = evaluator.evaluate("pick", {"pick.lift": 0}, [1])
    b = evaluator.evaluate("pick", {"pick.lift": 0}, [1])
    assert a[0].trace_path != b[0].trace_path
    assert without_duration(a) == without_duration(b)
    assert a[0].capability_set["pick.lift"] == 0 != slow_lift.version


@pytest.mark.slow
def test_trace_compression_changes_the_chunks_not_the_records(setup: tuple, policy: DecompositionPolicy) -> None:
    registry, evaluator, _, root = setup
    plain = LocalEvaluator(registry, policy=policy, trace_dir=root / "plain", trace_compression="none", horizon=HORIZON)
    try:
        (uncompressed,) = plain.evaluate("T1", {"pick.lift": 0}, [6])
    finally:
        plain.close()
    (compressed,) = evaluator.evaluate("T1", {"pick.lift": 0}, [6])
    assert compressed.trace_path is not None and uncompressed.trace_path is not None
    assert chunk_compressions(Path(compressed.trace_path)) == {"lz4"}
    assert chunk_compressions(Path(uncompressed.trace_path)) == {COMPRESSIONS["none"]}
    with TraceReader(compressed.trace_path) as a, TraceReader(uncompressed.trace_path) as b:
        assert list(a.env_steps()) == list(b.env_steps())
        assert list(a.plan_steps()) == list(b.plan_steps())
    assert without_duration([compressed]) == without_duration([uncompressed])


def test_an_unknown_trace_compression_is_refused(setup: tuple, policy: DecompositionPolicy) -> None:
    registry, _, _, root = setup
    with pytest.raises(Invalid) as err:
        LocalEvaluator(registry, policy=policy, trace_dir=root / "never", trace_compression="brotli")
    assert err.value.message == "unknown trace compression 'brotli'; valid: lz4, zstd, none"
    assert err.value.details == {"field": "compression"}


@pytest.mark.slow
def test_untrusted_versions_are_released_after_each_call(setup: tuple) -> None:
    registry, evaluator, _, _ = setup
    llm = publish(registry, "pick.grasp", "def act(obs, params):\n    return [0.0] * 6 + [1.0]\n", origin=Origin.LLM)
    during: list[int] = []
    evaluator.progress = lambda *_: during.append(_sandbox_children())
    try:
        before = _sandbox_children()
        outcomes = evaluator.evaluate("T1", {}, [0])
        assert outcomes[0].capability_set["pick.grasp"] == llm.version
        assert during == [before + 1]  # the untrusted grasp ran in its own sandbox worker...
        assert _sandbox_children() == before  # ...which was killed with the set
    finally:
        evaluator.progress = None
        registry.rollback("pick.grasp", reason="test cleanup")


def _sandbox_children() -> int:
    """Live child processes of this one that are sandbox workers (``python -I -B -c ...``)."""
    me = str(os.getpid())
    count = 0
    for entry in Path("/proc").iterdir():
        if not entry.name.isdigit():
            continue
        try:
            ppid = (entry / "stat").read_text().rsplit(")", 1)[1].split()[1]
            argv = (entry / "cmdline").read_bytes().split(b"\0")
        except (OSError, IndexError):
            continue
        if ppid == me and argv[1:4] == [b"-I", b"-B", b"-c"]:
            count += 1
    return count


def test_bad_seeds_and_versions_are_refused_before_anything_runs(setup: tuple) -> None:
    _, evaluator, _, _ = setup
    for seeds, message in (
        ([], "seeds: give at least one seed"),
        ([1, -2], "seeds must be non-negative integers, got -2"),
        ("012", "seeds must be a list of integers, got str"),
    ):
        with pytest.raises(Invalid) as err:
            evaluator.evaluate("T1", {}, seeds)  # type: ignore[arg-type]
        assert err.value.message == message
    with pytest.raises(Invalid) as err:
        evaluator.evaluate("T1", {"pick.lift": "2"}, [0])  # type: ignore[dict-item]
    assert err.value.message == "versions must map ECM names to non-negative integers, got 'pick.lift': '2'"


@pytest.mark.slow
def test_unknown_version_is_not_found(setup: tuple) -> None:
    _, evaluator, _, _ = setup
    with pytest.raises(NotFound) as err:
        evaluator.evaluate("T1", {"pick.lift": 99}, [0])
    assert err.value.code.value == "not_found"
