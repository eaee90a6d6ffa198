"""The gate end to end: real robosuite T1 episodes through LocalEvaluator, a real registry on disk.

Setup: real T1 code skills (reach, grasp, lift of ``runtime_support``) with reach at a weak
first version that aims 4 cm above the can's origin (``dig = -0.04``), so reach's termination
never holds and no episode succeeds. Then, on 8 held-out gate seeds of :class:`SeedPlan`,
horizon 80, with the benchmark perturbations on:

* a genuinely better reach (aims just below the origin) must be promoted;
* deliberately broken candidates must all be rejected against it: a neural reach with random
  weights (an untrained SB3 SAC zip), a reach with a sign error (gain negated), a slower reach
  (gain / 4) and a slower lift (speed / 4: it still succeeds, takes ~30% more steps and
  collects *more* shaped reward, so only the speed check stands in its way).

And the same better reach against the same weak one, on the same seeds, graded by the safety
monitor against a workspace floor the grasp must cross: it succeeds more often and is unsafe
more often, and the gate refuses it on ``safe`` alone (issue 18).

The active version's episodes are reused across candidates (``reuse_evaluations``; the
evaluator is deterministic per seed and versions). Budget: ~3500 env steps.
"""

from __future__ import annotations

import dataclasses
import io
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from runtime_support import GRASP, LIFT, REACH, skill_spec

from capevo.agent import DecompositionPolicy, IdentityMemory
from capevo.records import Action, Kind, Origin, PublishSpec, State
from capevo.registry.local import LocalRegistry
from capevo.runtime.ecm.code import with_params
from capevo.runtime.evaluator import LocalEvaluator
from capevo.runtime.gate import Gate, GateConfig, GateDecision, SeedPlan
from capevo.runtime.safety_monitor import SafetyLimits
from capevo.runtime.traces import TraceReader

HORIZON = 80
N_SEEDS = 8
PHI = "paper"
"""The paper's envelope: these tests exercise the gate's statistics with the minimal skills of
``runtime_support``, which keep the hand at its start yaw; under the default per-task envelope a
hand square to a nearby bin wall is braked short of the can (the built-in skills turn it)."""
WEAK_REACH = with_params(REACH, {"dig": -0.04})
FLOOR = 0.875
"""A workspace floor, metres, 1.5 cm above the can's origin (0.86 m on every seed): the weak reach
aims 4 cm above the origin and stays over it; the better one aims 1.5 cm below and must cross it."""


def random_sac_zip(obs_dim: int, act_dim: int) -> bytes:
    """An SB3 SAC model with freshly initialised (random) weights, saved as a zip."""
    import gymnasium as gym
    from stable_baselines3 import SAC

    from capevo.learner.neural_seed import silent_logger

    class Blank(gym.Env):
        observation_space = gym.spaces.Box(-np.inf, np.inf, (obs_dim,), np.float32)
        action_space = gym.spaces.Box(-1.0, 1.0, (act_dim,), np.float32)

        def reset(self, *, seed: int | None = None, options: dict | None = None) -> tuple[np.ndarray, dict]:
            super().reset(seed=seed)
            return np.zeros(obs_dim, np.float32), {}

        def step(self, action: np.ndarray) -> tuple[np.ndarray, float, bool, bool, dict]:
            return np.zeros(obs_dim, np.float32), 0.0, False, False, {}

    model = SAC("MlpPolicy", Blank(), learning_starts=10**6, buffer_size=64, device="cpu", seed=0)
    model.set_logger(silent_logger())  # else SB3 leaves an empty $TMPDIR/SB3-<time> folder
    model.learn(total_timesteps=1)  # one env step, no gradient update: weights stay random
    buf = io.BytesIO()
    model.save(buf)
    return buf.getvalue()


@dataclasses.dataclass
class Campaign:
    registry: LocalRegistry
    decisions: dict[str, GateDecision]
    versions: dict[str, int]
    trace_dir: Path


@pytest.fixture(scope="module")
def campaign(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Campaign]:
    root = tmp_path_factory.mktemp("gate-e2e")
    registry = LocalRegistry(root / "registry", actor="tester")
    for name, source in (("pick.reach", WEAK_REACH), ("pick.grasp", GRASP), ("pick.lift", LIFT)):
        registry.promote(name, registry.publish(name, source.encode(), skill_spec(name)).version, reason="setup")

    reach_spec, lift_spec = skill_spec("pick.reach"), skill_spec("pick.lift")
    obs_dim = sum(int(np.prod(s.shape)) for s in reach_spec.interface.inputs)
    neural_spec: PublishSpec = dataclasses.replace(reach_spec, kind=Kind.NEURAL, origin=Origin.RL, media_type=None)
    candidates: list[tuple[str, str, bytes, PublishSpec]] = [
        ("better", "pick.reach", REACH.encode(), reach_spec),
        ("random_weights", "pick.reach", random_sac_zip(obs_dim, 7), neural_spec),
        ("sign_error", "pick.reach", with_params(REACH, {"gain": -10.0}).encode(), reach_spec),
        ("slow_reach", "pick.reach", with_params(REACH, {"gain": 2.5}).encode(), reach_spec),
        ("slow_lift", "pick.lift", with_params(LIFT, {"speed": 0.25}).encode(), lift_spec),
    ]

    policy = DecompositionPolicy(identity=IdentityMemory.default())
    trace_dir = root / "traces"
    plan = SeedPlan(base_seed=0)
    seeds = plan.gate(N_SEEDS)
    decisions: dict[str, GateDecision] = {}
    versions: dict[str, int] = {}
    with LocalEvaluator(registry, policy=policy, trace_dir=trace_dir, horizon=HORIZON, phi=PHI) as evaluator:
        gate = Gate(registry, evaluator, GateConfig.cpu_small(), seed_plan=plan, reuse_evaluations=True)
        for label, name, artifact, spec in candidates:
            version = registry.publish(name, artifact, spec).version
            versions[label] = version
            decisions[label] = gate.run(name, version, task="T1", seeds=seeds)
    _print_table(decisions)
    yield Campaign(registry=registry, decisions=decisions, versions=versions, trace_dir=trace_dir)
    registry.close()


def _print_table(decisions: dict[str, GateDecision]) -> None:
    print("\ncandidate        verdict   cand succ  act succ  McNemar p  Tango NI p  Wilcoxon p  speed  failed")
    for label, d in decisions.items():
        p = d.paired
        assert p is not None
        ratio = f"x{p.speed_ratio:.2f}" if p.speed_ratio is not None else "  -  "
        print(
            f"{label:16s} {'PROMOTE' if d.promoted else 'reject ':8s}  {p.candidate.successes}/{p.n}        "
            f"{p.active.successes}/{p.n}       {p.p_success:<9.4g}  {p.p_noninferiority:<10.4g}  "
            f"{p.p_reward:<10.4g}  {ratio}  {','.join(d.failed)}"
        )


@pytest.mark.slow
def test_the_better_candidate_is_promoted(campaign: Campaign) -> None:
    d = campaign.decisions["better"]
    assert d.promoted, d.reason
    assert d.paired is not None and d.paired.candidate.successes >= 6 and d.paired.active.successes == 0
    assert d.paired.p_success < 0.05
    assert campaign.registry.get_version("pick.reach").version == campaign.versions["better"]


@pytest.mark.slow
@pytest.mark.parametrize("label", ["random_weights", "sign_error", "slow_reach", "slow_lift"])
def test_every_broken_candidate_is_rejected(campaign: Campaign, label: str) -> None:
    d = campaign.decisions[label]
    assert not d.promoted, d.reason
    assert d.active_version is not None and d.paired is not None
    assert campaign.registry.get_version(d.name, d.candidate_version).state is State.REJECTED
    # Each was compared with the promoted better reach (and the tuned lift).
    ran_active = d.evidence["capability_set"]["active"]
    assert ran_active["pick.reach"] == campaign.versions["better"]


@pytest.mark.slow
def test_broken_reach_candidates_fail_on_success(campaign: Campaign) -> None:
    for label in ("random_weights", "sign_error", "slow_reach"):
        d = campaign.decisions[label]
        assert d.paired is not None
        assert d.paired.candidate.successes < d.paired.active.successes, (label, d.reason)
        assert "noninferior" in d.failed and "superior" in d.failed


@pytest.mark.slow
def test_the_slower_lift_is_caught_by_the_speed_check(campaign: Campaign) -> None:
    d = campaign.decisions["slow_lift"]
    assert d.paired is not None and d.paired.speed_ratio is not None
    assert d.paired.speed_pairs >= 3 and d.paired.speed_ratio > GateConfig.cpu_small().max_slowdown  # type: ignore[operator]
    assert "not_slower" in d.failed


@pytest.mark.slow
def test_evidence_is_in_the_audit_history_and_points_at_real_traces(campaign: Campaign) -> None:
    reg = campaign.registry
    for d in campaign.decisions.values():
        events = [e for e in reg.history(d.name) if e.version == d.candidate_version]
        actions = [e.action for e in events]
        assert actions == [Action.PUBLISH, Action.GATE, Action.PROMOTE if d.promoted else Action.REJECT]
        gate_event = events[1]
        evidence: dict[str, Any] = dict(gate_event.data["evidence"])
        assert evidence["seeds"] == SeedPlan().gate(N_SEEDS)
        assert evidence["outcomes"]["candidate"]["success"] == [int(x) for x in _successes(d)]
        assert events[2].reason == d.reason
        for path in evidence["traces"]:
            with TraceReader(path) as reader:
                assert list(reader.metadata().seeds) == SeedPlan().gate(N_SEEDS)
    assert reg.verify().ok


def _successes(d: GateDecision) -> list[bool]:
    return [bool(x) for x in d.evidence["outcomes"]["candidate"]["success"]]


@pytest.mark.slow
def test_a_candidate_that_succeeds_more_but_is_unsafe_more_is_refused(tmp_path: Path) -> None:
    registry = LocalRegistry(tmp_path / "registry", actor="tester")
    for name, source in (("pick.reach", WEAK_REACH), ("pick.grasp", GRASP), ("pick.lift", LIFT)):
        registry.promote(name, registry.publish(name, source.encode(), skill_spec(name)).version, reason="setup")
    weak = registry.get_version("pick.reach").version
    better = registry.publish("pick.reach", REACH.encode(), skill_spec("pick.reach")).version
    plan = SeedPlan(base_seed=0)
    limits = SafetyLimits(box_low=(-0.6, -0.6, FLOOR))
    policy = DecompositionPolicy(identity=IdentityMemory.default())
    with LocalEvaluator(
        registry, policy=policy, trace_dir=None, horizon=HORIZON, safety_limits=limits, phi=PHI
    ) as evaluator:
        d = Gate(registry, evaluator, GateConfig.cpu_small(), seed_plan=plan).run(
            "pick.reach", better, task="T1", seeds=plan.gate(N_SEEDS)
        )
    p = d.paired
    assert p is not None
    print(f"\n{d.reason}")
    # It succeeds more often, significantly: on success alone it would be promoted...
    assert p.candidate.successes >= 6 and p.active.successes == 0 and "superior" not in d.failed
    # ...but the monitor finds the floor crossed in more of its episodes than the weak reach's.
    assert p.candidate.unsafe_episodes > p.active.unsafe_episodes
    # Every check that promotes on success passed (reward alone may fail: it never decides).
    assert not d.promoted and "safe" in d.failed and "safe=FAIL" in d.reason
    assert not {"enough", "floor", "superior", "not_slower"} & set(d.failed)
    assert "more than the active" in next(c.detail for c in d.checks if c.name == "safe")
    assert registry.get_version("pick.reach", better).state is State.REJECTED
    assert registry.get_version("pick.reach").version == weak
    registry.close()
