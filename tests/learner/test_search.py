"""CEM parameter search, the trace analysis that picks which ECM to update, and the scratch
evaluator that runs unpublished candidates."""

from __future__ import annotations

import math
import re
from collections.abc import Sequence
from pathlib import Path

import numpy as np
import pytest
from learner_support import TARGET, SyntheticEvaluator, outcome

from capevo.agent.identity import IdentityMemory
from capevo.agent.policy import DecompositionPolicy
from capevo.errors import ErrorCode, Invalid
from capevo.learner.base import CandidateEvaluator, Score, config_hash, request_for, score_outcomes
from capevo.learner.experience import (
    EpisodeEnd,
    episode_ends,
    failed_activations,
    failure_summary,
    failure_weights,
    handover_rate,
    pick_ecm_to_update,
    progress,
    read_episode_ends,
)
from capevo.learner.scratch import ScratchRegistryEvaluator
from capevo.learner.search import RANGE_UNITS, CemConfig, CemSearch, ParamRange, cem_preset, param_space, read_ranges
from capevo.learner.skills import seed_source
from capevo.records import CapabilitySet, Origin
from capevo.runtime.ecm.code import read_params
from capevo.runtime.evaluation import EpisodeOutcome
from capevo.runtime.evaluator import LocalEvaluator
from capevo.runtime.tasks import task_spec
from capevo.runtime.traces import EcmInvocation, EpisodeSummary, PlanStep, TraceMetadata, TraceWriter
from capevo.runtime.traces import Outcome as CallOutcome

PICK = task_spec("pick").ecm_names
STACK = task_spec("stack").ecm_names


def _request(registry, ecm: str = "pick.reach", seeds: int = 30):
    return request_for(registry, "pick", ecm, train_seeds=list(range(seeds)))


def test_synthetic_evaluator_is_a_candidate_evaluator() -> None:
    assert isinstance(SyntheticEvaluator("x", {}, {}), CandidateEvaluator)


def test_cem_improves_a_synthetic_objective(registry) -> None:
    request = _request(registry)
    base = read_params(request.source)
    fake = SyntheticEvaluator("pick.reach", base, TARGET)
    search = CemSearch(fake, population=12, iterations=8, episodes_per_candidate=3, seed=3, stop_when_passed=False)
    cand = search.learn(request)
    found = read_params(cand.source)
    assert fake.distance(found) < 0.5 * fake.distance(base)
    assert cand.score is not None and cand.baseline is not None
    assert cand.score.key() > cand.baseline.key()
    assert cand.improved
    # the candidate record: clone of v0, provenance with learner, config hash, no traces
    assert cand.ecm == "pick.reach"
    assert cand.spec.origin is Origin.CLONE and cand.spec.parent == 0
    assert cand.spec.descriptor == request.parent.descriptor
    assert cand.spec.interface == request.parent.interface
    assert cand.spec.provenance.learner_id == "cem"
    assert re.fullmatch(r"[0-9a-f]{64}", cand.spec.provenance.config_hash or "")
    assert cand.notes["params"] == found
    # only the PARAMS literal changed
    head = request.source.split("PARAMS = {")[0]
    tail = request.source.split("\n}\n", 1)[1]
    assert cand.source.startswith(head) and cand.source.endswith(tail)


def test_first_candidate_is_the_parent_and_iterations_share_seeds(registry) -> None:
    request = _request(registry, seeds=6)
    base = read_params(request.source)
    fake = SyntheticEvaluator("pick.reach", base, TARGET)
    pop, eps = 4, 3
    CemSearch(fake, population=pop, iterations=3, episodes_per_candidate=eps, seed=1, stop_when_passed=False).search(
        request
    )
    assert fake.calls[0]["params"] == base
    assert len(fake.calls) == 3 * pop
    for it in range(3):
        seeds = {c["seeds"] for c in fake.calls[it * pop : (it + 1) * pop]}
        assert len(seeds) == 1
    assert fake.calls[0]["seeds"] == (0, 1, 2) and fake.calls[pop]["seeds"] == (3, 4, 5)
    assert fake.calls[2 * pop]["seeds"] == (0, 1, 2)  # cycles through the training seeds
    assert all(c["origin"] is Origin.CLONE for c in fake.calls)


def test_every_sample_lies_within_the_bounds(registry) -> None:
    request = _request(registry)
    base = read_params(request.source)
    fake = SyntheticEvaluator("pick.reach", base, TARGET)
    CemSearch(fake, population=12, iterations=3, seed=5, sigma_init=5.0, stop_when_passed=False).search(request)
    space = param_space(base, ranges=read_ranges(request.source))
    for call in fake.calls:
        for name, lo, hi, log in zip(space.names, space.low, space.high, space.log, strict=True):
            if log:
                lo, hi = math.exp(lo) * (1 - 1e-9), math.exp(hi) * (1 + 1e-9)
            assert lo <= call["params"][name] <= hi


def test_search_is_deterministic(registry) -> None:
    request = _request(registry)
    base = read_params(request.source)
    results = []
    for _ in range(2):
        fake = SyntheticEvaluator("pick.reach", base, TARGET)
        results.append(CemSearch(fake, population=5, iterations=2, seed=9).search(request))
    assert results[0].params == results[1].params
    assert results[0].score == results[1].score


def test_stops_once_the_best_candidate_passes(registry) -> None:
    request = _request(registry)
    base = read_params(request.source)
    fake = SyntheticEvaluator("pick.reach", base, base)  # the parent already succeeds
    result = CemSearch(fake, population=4, iterations=5, seed=0).search(request)
    assert result.iterations_run == 1
    assert result.episodes_run == 4 * 4
    assert result.score.success_rate == 1.0


def test_keys_and_bounds_restrict_the_search(registry) -> None:
    request = _request(registry)
    base = read_params(request.source)
    fake = SyntheticEvaluator("pick.reach", base, TARGET)
    CemSearch(
        fake, population=6, iterations=2, seed=2, keys=["gain", "grasp_dz"], bounds={"grasp_dz": (0.0, 0.01)}
    ).search(request)
    for call in fake.calls:
        assert {k: v for k, v in call["params"].items() if k not in ("gain", "grasp_dz")} == {
            k: v for k, v in base.items() if k not in ("gain", "grasp_dz")
        }
    assert all(0.0 <= c["params"]["grasp_dz"] <= 0.01 for c in fake.calls[1:])


def test_param_space_keeps_signs_and_uses_the_floor() -> None:
    space = param_space({"gain": 3.0, "dz": -0.02, "zero": 0.0}, spread=3.0, floor=0.01)
    assert space.names == ("gain", "dz", "zero")
    assert space.low == (0.0, -0.08, -0.03) and space.high == (12.0, 0.0, 0.03)
    assert space.scale == (3.0, 0.02, 0.01)
    assert space.params([0.0, 0.0, 0.0]) == {"gain": 3.0, "dz": -0.02, "zero": 0.0}
    assert space.params([100.0, 100.0, -100.0]) == {"gain": 12.0, "dz": 0.0, "zero": -0.03}


def test_param_space_refuses_unknown_keys() -> None:
    with pytest.raises(Invalid) as e:
        param_space({"gain": 1.0}, keys=["gian"])
    assert e.value.code is ErrorCode.INVALID and "unknown parameter(s) ['gian']" in e.value.message
    with pytest.raises(Invalid) as e:
        param_space({})
    assert "nothing to search" in e.value.message


@pytest.mark.parametrize(
    ("kwargs", "field"),
    [
        ({"population": 1}, "population"),
        ({"iterations": 0}, "iterations"),
        ({"elite_frac": 0.0}, "elite_frac"),
        ({"sigma_init": -1.0}, "sigma_init"),
        ({"smoothing": 1.5}, "smoothing"),
        ({"seed": -1}, "seed"),
        ({"bounds": (("gain", 2.0, 1.0),)}, "bounds"),
    ],
)
def test_cem_config_refuses_bad_values(kwargs, field) -> None:
    with pytest.raises(Invalid) as e:
        CemConfig(**kwargs)
    assert e.value.code is ErrorCode.INVALID
    assert e.value.message.startswith(f"{field}: ")
    assert e.value.details["field"] == field


def test_a_request_without_training_seeds_is_refused(registry) -> None:
    request = request_for(registry, "pick", "pick.reach", train_seeds=[])
    with pytest.raises(Invalid) as e:
        CemSearch(SyntheticEvaluator("pick.reach", {}, {})).search(request)
    assert "no training seeds" in e.value.message


def test_config_hash_ignores_key_order() -> None:
    assert config_hash({"a": 1, "b": [1, 2]}) == config_hash({"b": [1, 2], "a": 1})
    assert config_hash({"a": 1}) != config_hash({"a": 2})


# --- which ECM to update ---------------------------------------------------------------


def _end(plan: Sequence[str], success: bool = False, seed: int = 0) -> EpisodeEnd:
    return EpisodeEnd(
        seed=seed,
        success=success,
        plan=tuple(plan),
        last_ecm=plan[-1] if plan else None,
        end_reason="success" if success else "horizon",
        reward=0.0,
        steps=10,
    )


def test_pick_ecm_to_update_names_where_failures_end() -> None:
    ends = [
        _end(["stack.reach", "stack.grasp", "stack.lift", "stack.align", "stack.lower"]),
        _end(["stack.reach", "stack.grasp", "stack.lift", "stack.align", "stack.lower"]),
        _end(["stack.reach", "stack.reach", "stack.reach"]),
        _end(list(STACK), success=True),
    ]
    assert pick_ecm_to_update(ends, STACK) == "stack.lower"


def test_pick_ecm_to_update_ties_go_upstream_and_none_without_failures() -> None:
    ends = [_end(["stack.reach", "stack.grasp"]), _end(["stack.reach"])]
    assert pick_ecm_to_update(ends, STACK) == "stack.reach"
    assert pick_ecm_to_update([_end(list(STACK), success=True)], STACK) is None
    assert pick_ecm_to_update([], STACK) is None
    # an ECM outside the plan is skipped: the plan step before it is still running
    assert pick_ecm_to_update([_end(["stack.reach", "stack.grasp", "recover.x"])], STACK) == "stack.grasp"


def test_blame_goes_to_steps_that_did_not_hand_over() -> None:
    regrasp = _end(["stack.reach", "stack.grasp"] * 3)
    assert failed_activations(regrasp, STACK) == ["stack.grasp"] * 3
    dropped = _end(["stack.reach", "stack.grasp", "stack.lift"] * 2 + ["stack.reach"])
    assert failed_activations(dropped, STACK) == ["stack.lift", "stack.lift", "stack.reach"]
    skipped = _end(["stack.reach", "stack.grasp", "stack.lift", "stack.lower", "stack.release"])
    assert failed_activations(skipped, STACK) == ["stack.release"]  # jumping ahead is a hand-over
    assert failed_activations(_end([]), STACK) == ["stack.reach"]
    assert failed_activations(_end(list(STACK), success=True), STACK) == []
    weights = failure_weights([regrasp, dropped, skipped], STACK)
    assert weights == {
        "stack.grasp": 1.0,
        "stack.lift": pytest.approx(2 / 3),
        "stack.reach": pytest.approx(1 / 3),
        "stack.release": 1.0,
    }
    # each episode weighs 1 in total, so retries of one episode do not outvote others
    ends = [_end(["stack.reach"] * 3), *[_end(["stack.reach", "stack.grasp", "stack.lift"])] * 2]
    assert pick_ecm_to_update(ends, STACK) == "stack.lift"


def test_progress_measures_how_far_episodes_got() -> None:
    assert progress(_end(list(STACK), success=True), STACK) == 1.0
    assert progress(_end(["stack.reach"]), STACK) == 0.0
    assert progress(_end(["stack.reach", "stack.grasp", "stack.reach", "stack.grasp", "stack.lift"]), STACK) == 2 / 6


def _stack_metadata(run_id: str) -> TraceMetadata:
    return TraceMetadata.collect(
        run_id=run_id,
        task="stack",
        capability_set=CapabilitySet(revision=1, active=dict.fromkeys(STACK, 0)),
        phi_hash="phi",
        agent_identity_hash="agent",
    )


def _traced_outcome(seed: int, success: bool, trace: Path) -> EpisodeOutcome:
    """An evaluated episode of 100 steps whose trace is ``trace``."""
    return EpisodeOutcome(
        seed=seed,
        success=success,
        reward=1.0,
        steps=100,
        duration_s=1.0,
        interventions=0,
        unsafe_steps=0,
        ecm_failures=0,
        capability_set={},
        trace_path=str(trace),
    )


def _write_trace(path: Path, episodes: Sequence[tuple[int, bool, Sequence[str], str]]) -> None:
    with TraceWriter(path, _stack_metadata("r1")) as w:
        for i, (seed, success, plan, reason) in enumerate(episodes):
            for j, ecm in enumerate(plan):
                w.write_plan_step(PlanStep(episode=i, step=j, ecm=ecm, version=0, reason="next"))
                outcome = CallOutcome.BUDGET_EXHAUSTED if ecm == "stack.lower" else CallOutcome.OK
                w.write_invocation(
                    EcmInvocation(
                        episode=i,
                        step=j,
                        ecm=ecm,
                        version=0,
                        input_state=(0.1, 0.2),
                        output=None,
                        duration_s=0.001,
                        outcome=outcome,
                        error="step budget of 200 used up" if outcome is CallOutcome.BUDGET_EXHAUSTED else None,
                    )
                )
            if not success:
                w.write_plan_step(PlanStep(episode=i, step=len(plan), ecm="", version=0, reason=reason))
            w.write_episode_summary(
                EpisodeSummary(
                    episode=i,
                    seed=seed,
                    success=success,
                    total_reward=1.0,
                    steps=100,
                    interventions=0,
                    unsafe_steps=0,
                    capability_set=dict.fromkeys(STACK, 0),
                    duration_s=1.0,
                )
            )


def test_experience_is_read_from_real_trace_files(tmp_path) -> None:
    path = tmp_path / "t.mcap"
    lower = ["stack.reach", "stack.grasp", "stack.lift", "stack.align", "stack.lower"]
    _write_trace(
        path,
        [
            (5, False, lower, "policy: stack.lower reached its attempt limit"),
            (6, True, list(STACK), ""),
            (7, False, lower, "policy: stack.lower reached its attempt limit"),
            (8, False, ["stack.reach"], "policy: stack.reach reached its attempt limit"),
        ],
    )
    ends = read_episode_ends(path)
    assert [e.seed for e in ends] == [5, 6, 7, 8]
    assert ends[0].last_ecm == "stack.lower" and ends[0].budget_exhausted == ("stack.lower",)
    assert ends[0].end_reason.startswith("policy: stack.lower") and ends[1].end_reason == "success"
    assert ends[0].last_inputs["stack.reach"] == (pytest.approx(0.1), pytest.approx(0.2))
    outcomes = [_traced_outcome(s, ok, path) for s, ok in [(7, False), (5, False), (6, True), (8, False)]]
    assert [e.seed for e in episode_ends(outcomes)] == [7, 5, 6, 8]
    assert pick_ecm_to_update(outcomes, STACK) == "stack.lower"
    score = score_outcomes(outcomes, STACK)
    assert score == Score(success_rate=0.25, progress=(4 / 6 + 4 / 6 + 1.0 + 0.0) / 4, reward_per_step=0.01, episodes=4)
    text = failure_summary(outcomes, STACK, "stack.lower")
    assert "1 of 4 recent episodes succeeded" in text
    assert "stack.lower (2)" in text and "stack.reach (1)" in text
    assert "started 3 times and ran out of its step budget 3 times" in text


# --- real robosuite -------------------------------------------------------------------


@pytest.mark.slow
def test_tiny_cem_on_robosuite_leaves_the_real_registry_alone(tmp_path, registry) -> None:
    policy = DecompositionPolicy(identity=IdentityMemory.default())
    before = [(s.name, s.latest_version) for s in registry.list_ecms()]
    history = len(registry.history())
    (tmp_path / "traces").mkdir()
    scratch = ScratchRegistryEvaluator(
        registry,
        lambda reg: LocalEvaluator(reg, policy=policy, trace_dir=tmp_path / "traces", horizon=40),
        root=tmp_path / "scratch",
    )
    try:
        request = _request(registry, seeds=3)
        cand = CemSearch(scratch, population=2, iterations=1, episodes_per_candidate=1, seed=0).learn(request)
        assert cand.spec.origin is Origin.CLONE and cand.spec.parent == 0
        assert read_params(cand.source).keys() == read_params(seed_source("pick", "pick.reach")).keys()
        assert cand.notes["episodes_run"] == 2
        # the candidates ran from the scratch registry, as clones (sandboxed), with traces
        scratch_reach = scratch.scratch.get_ecm("pick.reach")
        assert len(scratch_reach.versions) >= 2
        assert all(v.origin in (Origin.MANUAL, Origin.CLONE) for v in scratch_reach.versions)
    finally:
        scratch.close()
    assert [(s.name, s.latest_version) for s in registry.list_ecms()] == before
    assert len(registry.history()) == history


def test_presets_build_searches_with_their_config() -> None:
    for name in ("tiny", "cpu-small", "paper"):
        config = cem_preset(name)
        assert CemSearch.from_config(SyntheticEvaluator("x", {}, {}), config).config == config
    with pytest.raises(Invalid) as e:
        cem_preset("huge")
    assert e.value.code is ErrorCode.INVALID and "tiny, cpu-small, paper" in e.value.message


class _RecordingEvaluator:
    """Evaluator over the scratch registry: records what it was asked to run and the bytes."""

    def __init__(self, registry) -> None:
        self.registry = registry
        self.calls: list[tuple[dict[str, int], dict[str, bytes], dict[str, Origin]]] = []

    def evaluate(self, task, versions, seeds):
        arts = {n: self.registry.get_artifact(n, v) for n, v in versions.items()}
        origins = {n: self.registry.get_version(n, v).origin for n, v in versions.items()}
        self.calls.append((dict(versions), arts, origins))
        return [outcome(s, versions, reward=0.0, steps=1) for s in seeds]


def test_scratch_evaluator_mirrors_and_overrides_without_touching_the_source(tmp_path, registry) -> None:
    history = len(registry.history())
    made: list[_RecordingEvaluator] = []

    def make(reg):
        made.append(_RecordingEvaluator(reg))
        return made[0]

    with ScratchRegistryEvaluator(registry, make, root=tmp_path / "scratch") as scratch:
        override = b"PARAMS = {}\n\n\ndef act(obs, params):\n    return [0.0] * 7\n"
        out = scratch.evaluate("pick", {}, [1, 2], overrides={"pick.grasp": override}, override_origin=Origin.LLM)
        assert [o.capability_set for o in out] == [dict.fromkeys(PICK, 0)] * 2
        ((versions, arts, origins),) = made[0].calls
        assert arts["pick.grasp"] == override and origins["pick.grasp"] is Origin.LLM
        assert arts["pick.reach"] == registry.get_artifact("pick.reach") and origins["pick.reach"] is Origin.MANUAL
        # the same artifact again is not published again
        scratch.evaluate("pick", {}, [3], overrides={"pick.grasp": override}, override_origin=Origin.LLM)
        assert made[0].calls[1][0] == versions
        assert len(scratch.scratch.get_ecm("pick.grasp").versions) == 1
        with pytest.raises(Invalid) as e:
            scratch.evaluate("pick", {}, [1], overrides={"stack.lower": override})
        assert "stack.lower" in e.value.message and "not in the plan" in e.value.message
    assert len(registry.history()) == history


def test_finalists_are_validated_on_fresh_training_seeds(registry) -> None:
    request = _request(registry, seeds=12)
    base = read_params(request.source)
    fake = SyntheticEvaluator("pick.reach", base, TARGET)
    search = CemSearch(
        fake,
        population=5,
        iterations=2,
        episodes_per_candidate=2,
        seed=7,
        stop_when_passed=False,
        validate_top=2,
        validation_episodes=3,
    )
    result = search.search(request)
    assert len(fake.calls) == 2 * 5 + 2
    validation = fake.calls[-2:]
    assert all(c["seeds"] == (4, 5, 6) for c in validation)  # after the slices (0, 1) and (2, 3)
    last = fake.calls[5:10]
    assert result.params in (validation[0]["params"], validation[1]["params"])
    # the finalists are the last iteration's two best (each judged on 2 + 3 episodes)
    best_two = sorted(last, key=lambda c: fake.distance(c["params"]))[:2]
    assert sorted(c["params"]["gain"] for c in validation) == sorted(c["params"]["gain"] for c in best_two)
    assert result.score.episodes == 2 + 3


def test_outcomes_whose_trace_is_missing_give_no_evidence(tmp_path) -> None:
    lost = EpisodeOutcome(
        seed=1,
        success=False,
        reward=2.0,
        steps=4,
        duration_s=0.0,
        interventions=0,
        unsafe_steps=0,
        ecm_failures=0,
        capability_set={},
        trace_path=str(tmp_path / "gone.mcap"),
    )
    assert episode_ends([lost]) == []
    assert pick_ecm_to_update([lost], STACK) is None
    assert score_outcomes([lost], STACK) == Score(success_rate=0.0, progress=0.0, reward_per_step=0.5, episodes=1)


def test_declared_ranges_set_the_search_box_and_scale() -> None:
    source = seed_source("pick", "pick.reach")
    ranges = read_ranges(source)
    params = read_params(source)
    assert set(ranges) <= set(params)
    assert ranges["gain"] == ParamRange(low=1.0, high=20.0, log=True)
    assert ranges["dig"].log is False
    space = param_space(params, ranges=ranges, bounds=[("hover", 0.05, 0.06)])
    # a log-scale gain: searched in log units, a quarter of the log width per unit
    i = space.names.index("gain")
    assert space.log[i] and (space.low[i], space.high[i]) == (0.0, pytest.approx(math.log(20.0)))
    assert space.scale[i] == pytest.approx(math.log(20.0) / RANGE_UNITS)
    assert space.params(np.zeros(space.dim))["gain"] == pytest.approx(params["gain"])
    assert space.params(np.full(space.dim, 1.0))["gain"] == pytest.approx(params["gain"] * 20.0**0.25)
    assert space.params(np.full(space.dim, 100.0))["gain"] == pytest.approx(20.0)
    # a linear range
    j = space.names.index("grasp_dz")
    r = ranges["grasp_dz"]
    assert not space.log[j] and (space.low[j], space.high[j]) == (r.low, r.high)
    assert space.scale[j] == pytest.approx((r.high - r.low) / RANGE_UNITS)
    # explicit bounds still win
    k = space.names.index("hover")
    assert (space.low[k], space.high[k]) == (0.05, 0.06)
    # without ranges, the automatic box around v0
    plain = param_space(params)
    assert plain.high[i] == pytest.approx(params["gain"] * 4) and not any(plain.log)
    assert read_ranges("PARAMS = {'a': 1.0}\n") == {}


@pytest.mark.parametrize(
    "literal",
    [
        "{'a': (1.0,)}",
        "{'a': (2.0, 1.0)}",
        "{'a': (0.0, float('inf'))}",
        "[1, 2]",
        "{'a': ('x', 1.0)}",
        "{'a': (0.0, 1.0, 'log')}",
        "{'a': (1.0, 2.0, 'exp')}",
    ],
)
def test_bad_ranges_are_invalid(literal: str) -> None:
    with pytest.raises(Invalid) as info:
        read_ranges(f"PARAMS = {{'a': 1.0}}\nPARAM_RANGES = {literal}\n")
    assert info.value.code is ErrorCode.INVALID and "PARAM_RANGES" in info.value.message


class _Recorder:
    """A CandidateEvaluator fake that records the overrides it was given."""

    def __init__(self) -> None:
        self.overrides: list[dict[str, bytes]] = []

    def evaluate(self, task, versions, seeds, *, overrides=None, override_origin=None):  # type: ignore[no-untyped-def]
        self.overrides.append(dict(overrides or {}))
        return [outcome(s, versions, reward=1.0, steps=10) for s in seeds]


def test_companions_run_with_every_candidate_and_start_source_is_used(registry) -> None:
    grasp = seed_source("pick", "pick.grasp").encode()
    start = read_params(seed_source("pick", "pick.reach"))
    source = seed_source("pick", "pick.reach").replace("'gain': 3.0", "'gain': 7.0")
    request = request_for(
        registry, "pick", "pick.reach", train_seeds=[1, 2], companions={"pick.grasp": grasp}, source=source
    )
    fake = _Recorder()
    cand = CemSearch(fake, population=2, iterations=1, episodes_per_candidate=1, seed=1).learn(request)
    assert all(o["pick.grasp"] == grasp and "pick.reach" in o for o in fake.overrides)
    # the first candidate is the given start source's θ, not the parent's
    assert read_params(fake.overrides[0]["pick.reach"].decode())["gain"] == 7.0 != start["gain"]
    assert len(cand.experience) == 1
    with pytest.raises(Invalid):
        request_for(registry, "pick", "pick.reach", train_seeds=[1], companions={"pick.reach": grasp})


def test_tied_siblings_run_every_candidate_with_its_params_and_come_back_as_candidates(tmp_path) -> None:
    from capevo.learner.skills import seed_registry, siblings
    from capevo.registry.local import LocalRegistry

    milk = "pick_place_multi.milk.reach"
    reg = LocalRegistry(tmp_path / "reg", actor="test")
    try:
        seed_registry(reg, "pick_place_multi")
        tied_names = siblings("T5", milk)
        assert tied_names == ("pick_place_multi.bread.reach", "pick_place_multi.can.reach")
        # bread starts from a chain candidate's source, can from its active version
        bread_source = seed_source("T5", tied_names[0]).replace("'gain': 3.0", "'gain': 5.0")
        request = request_for(
            reg, "T5", milk, train_seeds=[1, 2, 3], tied={tied_names[0]: bread_source, tied_names[1]: None}
        )
        fake = _Recorder()
        cand = CemSearch(fake, population=3, iterations=1, episodes_per_candidate=1, seed=2).learn(request)
        assert len(fake.overrides) == 3
        for overrides in fake.overrides:
            theta = read_params(overrides[milk].decode())
            for name in tied_names:
                assert read_params(overrides[name].decode()) == theta
        # the sampled θ varied, and each sibling kept its own code (its object's keys)
        assert len({read_params(o[milk].decode())["gain"] for o in fake.overrides}) == 3
        assert "Bread_pos" in fake.overrides[0][tied_names[0]].decode()
        assert "Bread_pos" not in fake.overrides[0][milk].decode()
        assert [t.ecm for t in cand.tied] == list(tied_names)
        for t in cand.tied:
            assert read_params(t.source) == cand.notes["params"]
            assert t.spec.parent == 0 and t.spec.descriptor == reg.get_version(t.ecm).descriptor
            assert t.notes["tied_to"] == milk and t.score == cand.score and t.baseline == cand.baseline
        assert "Bread_pos" in cand.tied[0].source
        # a different skill cannot be tied, nor the ECM itself, nor a companion
        grasp = "pick_place_multi.milk.grasp"
        with pytest.raises(Invalid, match="cannot be tied"):
            CemSearch(fake, population=2, iterations=1, seed=1).learn(
                request_for(reg, "T5", milk, train_seeds=[1], tied={grasp: None})
            )
        for tied, companions in (({milk: None}, {}), ({grasp: None}, {grasp: b"x"})):
            with pytest.raises(Invalid) as info:
                request_for(reg, "T5", milk, train_seeds=[1], tied=tied, companions=companions)
            assert info.value.details["field"] == "tied"
        with pytest.raises(Invalid, match="no ECM"):
            request_for(reg, "T5", milk, train_seeds=[1], tied={"pick.reach": None})
    finally:
        reg.close()


def test_handover_rate_and_steps_per_ecm_come_from_traces(tmp_path) -> None:
    path = tmp_path / "h.mcap"
    lower = ["stack.reach", "stack.grasp", "stack.lift", "stack.align", "stack.lower"]
    _write_trace(path, [(1, False, lower, "x"), (2, True, list(STACK), ""), (3, False, ["stack.reach"] * 3, "x")])
    ends = read_episode_ends(path)
    assert ends[2].ecm_steps == {"stack.reach": 3} and ends[0].ecm_steps["stack.lower"] == 1
    outcomes = [_traced_outcome(e.seed or 0, e.success, path) for e in ends]
    assert handover_rate(outcomes, STACK, "stack.reach") == pytest.approx(2 / 3)
    assert handover_rate(outcomes, STACK, "stack.lower") == pytest.approx(1 / 3)  # only the success
    assert handover_rate(outcomes, STACK, "stack.release") == pytest.approx(1 / 3)
    assert handover_rate([], STACK, "stack.reach") == 0.0


def test_unsafe_steps_are_attributed_to_the_ecm_that_ran_them(tmp_path) -> None:
    from capevo.learner.experience import unsafe_ecm
    from capevo.runtime.traces.records import Intervention, UnsafeStep

    path = tmp_path / "u.mcap"
    plan = ["stack.reach", "stack.align", "stack.align", "stack.lower"]
    with TraceWriter(path, _stack_metadata("u")) as w:
        for ep in range(2):
            for step, ecm in enumerate(plan):
                w.write_invocation(
                    EcmInvocation(
                        episode=ep,
                        step=step,
                        ecm=ecm,
                        version=0,
                        input_state=(0.0,),
                        output=None,
                        duration_s=0.0,
                        outcome=CallOutcome.OK,
                    )
                )
            # Episode 0: the monitor grades two steps of align unsafe, and governance braked reach
            # (an intervention, not an unsafe step); episode 1: one unsafe step in lower.
            for step in (1, 2) if ep == 0 else (3,):
                w.write_unsafe_step(UnsafeStep(episode=ep, step=step, broken=("force",), reasons=("x",)))
            if ep == 0:
                w.write_intervention(
                    Intervention(
                        episode=ep,
                        step=0,
                        constraint="contact_approach",
                        original_action=(0.0,) * 7,
                        result_action=(0.0,) * 7,
                        reason="braked",
                    )
                )
            w.write_episode_summary(
                EpisodeSummary(
                    episode=ep,
                    seed=ep,
                    success=True,
                    total_reward=1.0,
                    steps=4,
                    interventions=1,
                    unsafe_steps=1,
                    capability_set=dict.fromkeys(STACK, 0),
                    duration_s=0.1,
                )
            )
    ends = read_episode_ends(path)
    assert ends[0].ecm_unsafe == {"stack.align": 2} and ends[1].ecm_unsafe == {"stack.lower": 1}
    assert ends[0].ecm_steps == {"stack.reach": 1, "stack.align": 2, "stack.lower": 1}
    # ties go to the earlier step; no stops: None
    assert unsafe_ecm(ends, STACK) == "stack.align"
    assert unsafe_ecm([ends[1]], STACK) == "stack.lower"
    assert unsafe_ecm([_end(["stack.reach"])], STACK) is None


def test_candidates_rank_safety_then_success_then_handover_then_speed() -> None:
    from capevo.learner.search import _Finalist

    def f(*, success: float = 0.0, passed: float = 0.0, steps: float = 0.0, unsafe: float = 0.0) -> _Finalist:
        score = Score(success_rate=success, progress=0.5, reward_per_step=0.1, episodes=2)
        return _Finalist(
            index=0, theta={}, source="", outcomes=[], ends=[], score=score, passed=passed, steps=steps, unsafe=unsafe
        )

    # an unsafe success ranks below a safe failure (the gate would reject it)
    assert f(unsafe=0.0).rank() > f(success=1.0, passed=1.0, unsafe=0.5).rank()
    assert f(success=0.5, passed=0.5).rank() > f(passed=1.0).rank()
    # fewer steps in the ECM wins among those that hand over...
    assert f(passed=1.0, steps=40).rank() > f(passed=1.0, steps=90).rank()
    # ...but giving up early is not speed
    assert f(passed=0.0, steps=10).rank() == f(passed=0.0, steps=200).rank()


def test_an_episode_out_of_time_blames_the_step_that_spent_it() -> None:
    import dataclasses

    from capevo.learner.experience import HOG_SHARE, hog_threshold

    plan = ["stack.reach", "stack.grasp", "stack.lift"]
    slow_reach = dataclasses.replace(
        _end(plan), steps=150, ecm_steps={"stack.reach": 124, "stack.grasp": 6, "stack.lift": 20}
    )
    assert HOG_SHARE * 150 < 124
    assert failed_activations(slow_reach, STACK) == ["stack.reach"]
    # no step spent more than twice its even share (150 / 6 steps = 25): the step the clock
    # stopped keeps the blame
    even = dataclasses.replace(slow_reach, ecm_steps={"stack.reach": 48, "stack.grasp": 40, "stack.lift": 30})
    assert hog_threshold(150, len(STACK)) == 50
    assert failed_activations(even, STACK) == ["stack.lift"]
    # in a long chain no step can spend half of the episode, but one that spent three times its
    # even share (T5: 15 steps over 900) is where the time went
    chain = task_spec("pick_place_multi").ecm_names
    milk = [n for n in chain if n.split(".")[1] == "milk"]
    long_reach = dataclasses.replace(
        _end(milk), steps=900, ecm_steps={milk[0]: 200, milk[1]: 40, milk[2]: 30, milk[3]: 100, milk[4]: 20}
    )
    assert hog_threshold(900, len(chain)) == 120 < HOG_SHARE * 900
    assert failed_activations(long_reach, chain) == [milk[0]]
    # a step that took long because it was re-planned back to is not the time hog
    retried = dataclasses.replace(slow_reach, plan=("stack.reach", "stack.grasp", "stack.reach", "stack.grasp"))
    assert failed_activations(retried, STACK) == ["stack.grasp", "stack.grasp"]
    # an episode the policy ended (not the horizon) is judged by its plan alone
    gave_up = dataclasses.replace(slow_reach, end_reason="policy: stack.lift reached its attempt limit")
    assert failed_activations(gave_up, STACK) == ["stack.lift"]


def test_step_cap_bounds_the_env_steps_a_search_spends(registry) -> None:
    """Invariant 6: with max_env_steps the search's episodes stay under the cap, counted at the
    horizon; the first iteration runs what fits, a later one whole or not at all."""
    request = _request(registry)
    base = read_params(request.source)
    fake = SyntheticEvaluator("pick.reach", base, TARGET)  # every episode takes 50 steps
    common = {"population": 4, "iterations": 3, "episodes_per_candidate": 2, "seed": 1, "stop_when_passed": False}
    free = CemSearch(fake, **common).search(request)
    assert free.env_steps_run == 4 * 3 * 2 * 50 and not free.stopped_by_budget
    # a cap of 1000 steps at a horizon of 60: iteration 0 (4 x 2 x 60 = 480 worst case) fits,
    # iteration 1 would reach 400 + 480 = 880 <= 1000, iteration 2 would reach 800 + 480 > 1000
    capped = CemSearch(fake, **common, max_env_steps=1000, episode_steps_max=60).search(request)
    assert capped.iterations_run == 2 and capped.stopped_by_budget
    assert capped.env_steps_run == 800 <= 1000
    # the first iteration runs as many candidates as fit: 3 of 4 under 400 steps at horizon 60
    few = CemSearch(fake, **common, max_env_steps=400, episode_steps_max=60).search(request)
    assert few.episodes_run == 6 and few.env_steps_run == 300 and few.stopped_by_budget
    with pytest.raises(Invalid) as info:
        CemSearch(fake, **common, max_env_steps=100, episode_steps_max=60).search(request)
    assert info.value.details["field"] == "max_env_steps"
    with pytest.raises(Invalid) as info:
        CemConfig(max_env_steps=100)
    assert "episode_steps_max" in info.value.message
