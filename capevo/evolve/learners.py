"""Where each iteration's candidate comes from: a learner in this process (one per modality), or
learner workers that publish candidates to the registry themselves.

Modalities (registered with :func:`register_modality`, built with :func:`make_updater`):

* ``code``: CEM over the chosen code ECM's ``PARAMS`` (:class:`~capevo.learner.search.CemSearch`),
  candidates run unpublished in a private scratch registry; origin ``clone``. It runs behind an
  update request's companions (the loop's chain) and returns the winner's own training episodes
  as the proposal's experience.
* ``hybrid``: an LLM edit (``CAPEVO_LLM_BASE_URL``) then CEM (:class:`~capevo.learner.hybrid.HybridLearner`);
  without an endpoint it is CEM alone (the note says so).
* ``rl``: SAC (:class:`~capevo.learner.rl.SacLearner`), continuing from its own latest candidate
  and replay buffer (a random-init v0 and every later update of its lineage are first behaviour-cloned); origin ``rl``.
* ``il``: behaviour cloning (:class:`~capevo.learner.bc.BcLearner`) from the set's successful
  traces and the task's scripted reference, on every demonstration gathered so far, continuing
  from its own latest candidate; origin ``il``.
* combined (``il+rl``, ``hybrid+rl``, ``hybrid+il``, ``hybrid+il+rl``; the paper's Table 8):
  :class:`TurnUpdater`, the named modalities taking turns, one iteration each.

:class:`RemoteCandidates` instead waits for a candidate that a learner worker
(``capevo learner serve``) publishes, and hands it to the gate.

Every learner trains on the run's training seeds only (:meth:`SeedPlan.train`), never on
gate or live seeds.

Invariants:
1. :func:`make_updater` raises :class:`Invalid` listing the valid modalities for an unknown one.
2. A :class:`Proposal` carries either an unpublished ``candidate`` or an already published
   ``record`` (remote learners), never both.
3. Neural learners' training episodes use task seeds inside the run's training range.
"""

from __future__ import annotations

import dataclasses
import logging
import time
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Protocol

from capevo.errors import Invalid
from capevo.evolve.config import COMBINED_MODALITIES, EvolveConfig, modality_parts
from capevo.evolve.progress import ProgressSink
from capevo.learner.base import Candidate, LearnRequest
from capevo.records import EcmVersion, Kind, State
from capevo.registry.api import Registry
from capevo.runtime.evaluation import EpisodeOutcome
from capevo.runtime.gate import SeedPlan
from capevo.runtime.tasks import Perturbations, task_spec

log = logging.getLogger(__name__)


@dataclass(frozen=True, slots=True, kw_only=True)
class UpdateRequest:
    """One iteration's update: which ECM, the experience, the seeds the learner may use."""

    task: str
    ecm: str
    iteration: int
    outcomes: tuple[EpisodeOutcome, ...]
    plan: SeedPlan
    seed: int
    """The run's seed; learners seed their samplers with ``seed + slot``."""
    companions: Mapping[str, bytes] = field(default_factory=dict)
    """Candidates of other ECMs learned earlier in this iteration's chain (unpublished
    artifacts by ECM name): the learner evaluates behind them."""
    source: str | None = None
    """Start from this source (an earlier candidate of the same ECM in the chain) instead of
    the active version's."""
    slot: int | None = None
    """Which stretch of training seeds (and sampler seed) this update uses; distinct updates
    of one run get distinct slots. Default: ``iteration``."""

    max_env_steps: int | None = None
    """Env steps this update's learner may spend (None: its preset's budget)."""

    @property
    def seed_slot(self) -> int:
        return self.iteration if self.slot is None else self.slot


@dataclass(frozen=True, slots=True, kw_only=True)
class Proposal:
    """What an updater produced."""

    learner: str
    candidate: Candidate | None = None
    record: EcmVersion | None = None
    episodes: int = 0
    """Training episodes the learner ran."""
    steps: int = 0
    """Env steps the learner's own episodes took: every CEM episode's, SAC's training steps
    (not the scripted rollouts that warm-start a random v0), BC's demonstration rows (a lower
    bound)."""
    notes: Mapping[str, Any] = field(default_factory=dict)
    experience: tuple[EpisodeOutcome, ...] = ()
    """The candidate's own training episodes (traced), when the learner kept them."""

    def __post_init__(self) -> None:
        if (self.candidate is None) == (self.record is None):
            raise Invalid("a proposal holds exactly one of candidate and record", details={"field": "candidate"})


class Updater(Protocol):
    """Produces the candidate of one iteration."""

    name: str

    def propose(self, request: UpdateRequest, progress: ProgressSink) -> Proposal | None:
        """A candidate for ``request.ecm`` (None: nothing to propose this iteration).

        Raises:
            CapevoError: the learner failed.
        """
        ...

    def close(self) -> None: ...


@dataclass(frozen=True, slots=True, kw_only=True)
class UpdaterContext:
    """What a local updater is built with."""

    registry: Registry
    task: str
    config: EvolveConfig
    policy: Any
    """π_A (the persistent agent) for the learner's own evaluation episodes."""
    agent_identity_hash: str
    perturbations: Perturbations
    trace_dir: Path
    """Where the learner's training episodes write their traces."""
    state_dir: Path | None = None
    """Where neural learners keep their state between iterations (latest candidate, replay
    buffer, demonstrations: :mod:`capevo.learner.continuation`); None starts each update afresh."""
    candidate_evaluator: Any = None
    """Runs code learners' candidate episodes (a :class:`~capevo.learner.base.CandidateEvaluator`)
    in place of an in-process evaluator over a scratch registry: with ``--connect``, a
    :class:`~capevo.runtime.remote_evaluator.RemoteEvaluator`, so CEM samples run on the same runtime
    workers as the live and gate episodes, sent inline (issue 19). The code updater closes it;
    neural updaters ignore it (their candidates are published versions)."""


UpdaterFactory = Callable[[UpdaterContext], Updater]
_MODALITIES: dict[str, UpdaterFactory] = {}


def register_modality(name: str) -> Callable[[UpdaterFactory], UpdaterFactory]:
    """Decorator: build the in-process updater of modality ``name`` with ``fn``."""

    def deco(fn: UpdaterFactory) -> UpdaterFactory:
        _MODALITIES[name] = fn
        return fn

    return deco


def modality_names() -> tuple[str, ...]:
    return tuple(_MODALITIES)


def make_updater(modality: str, context: UpdaterContext) -> Updater:
    """The in-process updater for ``modality``.

    Raises:
        Invalid: unknown modality; the message lists the valid ones.
    """
    factory = _MODALITIES.get(modality)
    if factory is None:
        raise Invalid(f"unknown modality {modality!r}; valid: {', '.join(_MODALITIES)}", details={"field": "modality"})
    return factory(context)


# --- code: CEM over PARAMS ----------------------------------------------------------------


class CemUpdater:
    """``code`` (and, with an LLM endpoint, ``hybrid``) updates through CEM: its samples run in a
    scratch registry in this process, or on the runtime workers when the context gives a
    :attr:`~UpdaterContext.candidate_evaluator`."""

    supports_companions = True
    """It evaluates behind :attr:`UpdateRequest.companions` (so the loop may chain updates)."""

    def __init__(self, context: UpdaterContext, *, hybrid: bool = False) -> None:
        from capevo.learner.scratch import ScratchRegistryEvaluator
        from capevo.runtime.evaluator import LocalEvaluator

        self.context = context
        self.hybrid = hybrid
        self.name = "hybrid" if hybrid else "cem"
        cfg = context.config
        if hybrid and cfg.cem.tie_siblings:
            raise Invalid(
                "tie_siblings needs the code modality: an LLM edit changes one ECM's code",
                details={"field": "cem.tie_siblings"},
            )
        context.trace_dir.mkdir(parents=True, exist_ok=True)
        self.scratch: Any = None
        self.evaluator: Any = context.candidate_evaluator
        if self.evaluator is not None:
            return

        def inner(scratch: Registry) -> Any:
            return LocalEvaluator(
                scratch,
                policy=context.policy,
                trace_dir=context.trace_dir,
                perturbations=context.perturbations,
                phi=cfg.phi,
                horizon=cfg.horizon,
                step_budget_per_ecm=cfg.step_budget_per_ecm,
                agent_identity_hash=context.agent_identity_hash,
                worker_id="evolve-learner",
            )

        self.scratch = self.evaluator = ScratchRegistryEvaluator(context.registry, inner)

    def propose(self, request: UpdateRequest, progress: ProgressSink) -> Proposal | None:
        from capevo.learner.base import request_for
        from capevo.learner.search import CemSearch

        cem = self.context.config.cem
        slot = request.seed_slot
        train = request.plan.train(cem.train_seeds_per_update, offset=slot * cem.train_seeds_per_update)
        tied: dict[str, str | None] = {}
        if cem.tie_siblings:
            from capevo.learner.skills import siblings

            # a sibling already in the chain takes the searched θ into its chain candidate
            tied = {
                e: (request.companions[e].decode("utf-8") if e in request.companions else None)
                for e in siblings(request.task, request.ecm)
            }
        learn_request = request_for(
            self.context.registry,
            request.task,
            request.ecm,
            train_seeds=train,
            outcomes=request.outcomes,
            companions={k: v for k, v in request.companions.items() if k != request.ecm and k not in tied},
            source=request.source,
            tied=tied,
        )
        progress.learner_started(total=cem.episodes_per_update, unit="CEM episodes")
        episodes = 0

        def on_event(event: Any) -> None:
            nonlocal episodes
            episodes += len(event.seeds)
            progress.learner_advance(len(event.seeds))

        config = cem.search_config(
            seed=request.seed + slot,
            max_env_steps=request.max_env_steps,
            episode_steps_max=self.context.config.episode_steps_max(request.task),
        )
        search = CemSearch.from_config(self.evaluator, config, progress=on_event)
        learner: Any = search
        if self.hybrid:
            learner = _hybrid(search, self.evaluator)
        candidate: Candidate = learner.learn(learn_request)
        notes = dict(candidate.notes)
        return Proposal(
            learner=str(notes.get("learner") or getattr(learner, "learner_id", self.name)),
            candidate=candidate,
            episodes=int(notes.get("episodes_run") or episodes),
            steps=int(notes.get("env_steps_run") or 0),
            notes={
                "params": notes.get("params"),
                "train_score": candidate.score.to_dict() if candidate.score else None,
                "train_baseline": candidate.baseline.to_dict() if candidate.baseline else None,
                **({"fallback": notes["fallback"]} if "fallback" in notes else {}),
                **({"stopped_by_budget": True} if notes.get("stopped_by_budget") else {}),
            },
            experience=tuple(candidate.experience),
        )

    def close(self) -> None:
        if self.scratch is not None:
            self.scratch.close()
        elif self.evaluator is not None:
            self.evaluator.close()


def _hybrid(search: Any, evaluator: Any) -> Any:
    from capevo.learner.chat import Chat, ChatConfig
    from capevo.learner.hybrid import HybridLearner
    from capevo.learner.synthesis import LlmSynthesis

    config = ChatConfig.from_env()
    chat = Chat(config) if config is not None else None
    return HybridLearner(LlmSynthesis(chat, evaluator=evaluator), search)


@register_modality("code")
def _code(context: UpdaterContext) -> Updater:
    return CemUpdater(context)


@register_modality("hybrid")
def _hybrid_modality(context: UpdaterContext) -> Updater:
    return CemUpdater(context, hybrid=True)


# --- neural: SAC and BC -------------------------------------------------------------------


def training_seed_window(plan: SeedPlan, iteration: int) -> tuple[int, int]:
    """``(seed_base, seed)`` for a neural learner's :class:`~capevo.learner.ecm_env.EcmEnvConfig` in ``iteration``.

    Training episode k then runs task seed ``seed_base + seed + k`` (plus SB3's reset seed):
    inside the plan's training range for the first half of the range's length in episodes,
    each iteration starting its own stretch (SeedPlan blocks are 100 000 seeds), so training
    never touches a gate or live seed.
    """
    train = plan.range("train")
    half = len(train) // 2
    stretch = max(1, half // 100)
    return train.start, (iteration * stretch) % max(1, half - stretch)


class NeuralUpdater:
    """``rl`` (SAC warm start) and ``il`` (behaviour cloning) updates of neural ECMs."""

    def __init__(self, context: UpdaterContext, *, modality: str) -> None:
        from capevo.learner.presets import make_preset

        self.context = context
        self.modality = modality
        self.name = "sac" if modality == "rl" else "bc"
        self.preset = make_preset(context.config.learner_preset)

    def _request(self, request: UpdateRequest) -> LearnRequest:
        registry = self.context.registry
        parent = registry.get_version(request.ecm)
        source = registry.get_artifact(request.ecm, parent.version).decode() if parent.kind is Kind.CODE else ""
        return LearnRequest(
            task=task_spec(request.task).name,
            ecm=request.ecm,
            parent=parent,
            source=source,
            train_seeds=tuple(request.plan.train(1, offset=request.iteration)),
            outcomes=request.outcomes,
        )

    def propose(self, request: UpdateRequest, progress: ProgressSink) -> Proposal | None:
        from capevo.learner.bc import BcLearner
        from capevo.learner.rl import SacLearner

        seed = request.seed + request.iteration
        preset = self.preset.with_seed(seed).with_perturbations(self.context.perturbations)
        base, offset = training_seed_window(request.plan, request.iteration)
        env = dataclasses.replace(preset.env, seed_base=base, seed=offset, phi=self.context.config.phi)
        learn_request = self._request(request)
        if self.modality == "rl":
            # under the iteration's step budget (issue 20) the clone's demonstrations come out of
            # it and SAC trains on the rest: no less (every method of a comparison spends the same
            # budget) and no more. No check runs there (SacLearner), and DAgger stays off so that
            # SAC gets the budget, as in the grids run so far.
            budget = request.max_env_steps
            if budget is not None:
                preset = dataclasses.replace(
                    preset,
                    bc=dataclasses.replace(preset.bc, dagger_rounds=0),
                )
            progress.learner_started(total=budget or preset.sac.total_steps, unit="SAC steps")
            # a random-init v0, and every later update of its lineage, is first cloned from the
            # scripted reference and the set's successes (all the rows gathered so far)
            clone_from = BcLearner(
                config=preset.bc,
                env_config=env,
                registry=self.context.registry,
                scripted_episodes=preset.scripted_episodes,
                env_step_budget=budget,
            )
            sac = SacLearner(
                config=preset.sac,
                env_config=env,
                shaping=preset.shaping,
                registry=self.context.registry,
                distill=dataclasses.replace(preset.bc, net_arch=preset.sac.net_arch),
                distill_episodes=preset.distill_episodes,
                bc=clone_from,
                state_dir=self.context.state_dir,
                env_step_budget=budget,
            )
            candidate = sac.learn(learn_request)
            progress.learner_advance(budget or preset.sac.total_steps)
            train_report = dict(candidate.notes.get("train") or {})
            dagger = dict(candidate.notes.get("dagger") or {})
            check = dict(candidate.notes.get("check") or {})
            return Proposal(
                learner=sac.learner_id,
                candidate=candidate,
                episodes=int(train_report.get("episodes") or 0),
                # every simulated step: the clone's demonstrations, DAgger, the check and SAC's,
                # the predecessors' prefixes included
                steps=int(candidate.notes["env_steps"]["total"]),
                notes={
                    "warm_start": candidate.notes.get("warm_start"),
                    "train": train_report,
                    "dagger": dagger,
                    "check": check,
                },
            )
        progress.learner_started(total=preset.bc.epochs * (1 + preset.bc.dagger_rounds), unit="BC epochs")
        bc = BcLearner(
            config=preset.bc,
            env_config=env,
            registry=self.context.registry,
            scripted_episodes=preset.scripted_episodes,
            progress=lambda epoch, epochs, loss: progress.learner_advance(1),
            state_dir=self.context.state_dir,
            # the demonstrations and DAgger's rounds stop where the iteration's budget does
            env_step_budget=request.max_env_steps,
        )
        candidate = bc.learn(learn_request)
        demos = dict(candidate.notes.get("demos") or {})
        dagger = dict(candidate.notes.get("dagger") or {})
        return Proposal(
            learner=bc.learner_id,
            candidate=candidate,
            episodes=int(demos.get("episodes_seen") or 0),
            # every simulated step of the scripted demonstrations (kept or not) and of DAgger's
            # rollouts, the predecessors' prefixes included
            steps=int(candidate.notes["env_steps"]["total"]),
            notes={"demos": demos, "bc": candidate.notes.get("bc"), "dagger": dagger},
        )

    def close(self) -> None:
        return None


@register_modality("rl")
def _rl(context: UpdaterContext) -> Updater:
    return NeuralUpdater(context, modality="rl")


@register_modality("il")
def _il(context: UpdaterContext) -> Updater:
    return NeuralUpdater(context, modality="il")


# --- combined: modalities taking turns -------------------------------------------------------

CODE_PARTS = frozenset({"code", "hybrid"})
"""Modalities that tune a code ECM's parameters (or edit its code): they cannot update a neural version."""


class TurnUpdater:
    """Several modalities taking turns: iteration ``i`` is the turn of ``parts[i % len(parts)]``.

    This is what capevo runs for the paper's combined rows of Table 8 (§4.6: RL + IL, RL + LLM,
    IL + LLM, all three). The paper does not say how its modalities combine; here each keeps its
    own learner and state (neural learners in ``<state_dir>/<part>/``), and the gate judges every
    candidate alike. What a turn can do depends on what the ECM's active version is:

    * a code part (``code``, ``hybrid``) cannot tune a neural version, so on an ECM whose active
      version is neural it passes the turn to the next part that can;
    * ``rl`` on a code version first distils the code skill into its actor
      (:mod:`capevo.learner.rl`), so SAC starts from what the hand-written skill does; ``il``
      clones the scripted reference and the set's successes whatever the parent is.

    Version 0 is the hand-written code skill when a code part is named, a random-init neural
    policy otherwise (:data:`~capevo.evolve.config.NEURAL_MODALITIES`). Chains (several ECMs in
    one iteration) are off: one ECM per iteration, whichever part's turn it is.

    Invariants:
    1. Iteration ``i`` asks ``parts[i % k]`` first, then the following parts in order; the
       proposal's notes (``turn``) and its learner (``<part>/<learner>``) name the part that made it.
    2. A code part is never asked to update an ECM whose active version is neural.
    """

    supports_companions = False

    def __init__(self, context: UpdaterContext, parts: Sequence[str]) -> None:
        if len(parts) < 2 or len(set(parts)) != len(parts) or "+" in "".join(parts):
            raise Invalid(f"a combination needs two or more distinct single modalities, got {list(parts)}")
        self.parts = tuple(parts)
        self.name = "+".join(self.parts)
        self._context = context
        self._updaters: dict[str, Updater] = {}

    def _updater(self, part: str) -> Updater:
        if part not in self._updaters:
            state = self._context.state_dir
            context = dataclasses.replace(self._context, state_dir=state / part if state is not None else None)
            self._updaters[part] = make_updater(part, context)
        return self._updaters[part]

    def turn_order(self, iteration: int) -> tuple[str, ...]:
        """The parts in the order iteration ``iteration`` asks them (invariant 1)."""
        k = iteration % len(self.parts)
        return self.parts[k:] + self.parts[:k]

    def propose(self, request: UpdateRequest, progress: ProgressSink) -> Proposal | None:
        active_kind = self._context.registry.get_version(request.ecm).kind
        for part in self.turn_order(request.iteration):
            if part in CODE_PARTS and active_kind is Kind.NEURAL:
                continue  # invariant 2: parameters to tune exist only in a code version
            proposal = self._updater(part).propose(request, progress)
            if proposal is None:
                return None
            return dataclasses.replace(
                proposal, learner=f"{part}/{proposal.learner}", notes={**proposal.notes, "turn": part}
            )
        return None

    def close(self) -> None:
        for updater in self._updaters.values():
            updater.close()


def _combined(parts: tuple[str, ...]) -> UpdaterFactory:
    return lambda context: TurnUpdater(context, parts)


for _name in COMBINED_MODALITIES:
    register_modality(_name)(_combined(modality_parts(_name)))


# --- remote learners ----------------------------------------------------------------------


def waiting_candidates(registry: Registry, names: Sequence[str]) -> list[EcmVersion]:
    """Versions in state ``candidate`` among the ECMs ``names`` (absent ECMs skipped), oldest first."""
    from capevo.errors import NotFound

    out: list[EcmVersion] = []
    for name in names:
        try:
            detail = registry.get_ecm(name)
        except NotFound:
            continue
        out.extend(v for v in detail.versions if v.state is State.CANDIDATE)
    return sorted(out, key=lambda v: (v.created_at, v.name, v.version))


class RemoteCandidates:
    """Waits for a candidate that a learner worker publishes (``capevo learner serve``).

    Args:
        registry: Polled for versions in state ``candidate`` of the task's ECMs.
        timeout_s: How long one iteration waits; None waits forever.
        poll_s: Pause between polls.
        should_stop: Polled while waiting; True gives up.
    """

    name = "remote"

    def __init__(
        self,
        registry: Registry,
        *,
        timeout_s: float | None = 600.0,
        poll_s: float = 1.0,
        should_stop: Callable[[], bool] | None = None,
    ) -> None:
        self.registry = registry
        self.timeout_s = timeout_s
        self.poll_s = poll_s
        self.should_stop = should_stop

    def propose(self, request: UpdateRequest, progress: ProgressSink) -> Proposal | None:
        names = task_spec(request.task).ecm_names
        progress.message(
            f"waiting for a learner worker to publish a candidate of {', '.join(names)} "
            f"(e.g. capevo learner serve --ecm {request.ecm} --once)"
        )
        deadline = None if self.timeout_s is None else time.monotonic() + self.timeout_s
        while True:
            found = waiting_candidates(self.registry, names)
            if found:
                record = found[0]
                return Proposal(
                    learner=record.provenance.learner_id or f"remote:{record.created_by}",
                    record=record,
                    notes={"published_by": record.created_by, "origin": record.origin.value},
                )
            if deadline is not None and time.monotonic() >= deadline:
                return None
            if self.should_stop is not None and self.should_stop():
                return None
            time.sleep(self.poll_s)

    def close(self) -> None:
        return None


__all__ = [
    "CemUpdater",
    "NeuralUpdater",
    "Proposal",
    "RemoteCandidates",
    "TurnUpdater",
    "UpdateRequest",
    "Updater",
    "UpdaterContext",
    "make_updater",
    "modality_names",
    "register_modality",
    "training_seed_window",
    "waiting_candidates",
]
