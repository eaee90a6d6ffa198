"""What every code-side learner shares: the request it answers, the candidate it returns, how
candidates are scored, and the evaluator extension that runs unpublished candidates.

A learner turns a :class:`LearnRequest` (one ECM of one task, its active version and source,
recent experience, training seeds) into a :class:`Candidate`: artifact bytes plus a
:class:`PublishSpec` whose origin, parent and provenance are filled in, ready for
``registry.publish`` and then the gate. Learners never promote.

Scores order candidates: success rate first, then progress through the task's decomposition
(from the traces), then mean reward per step. Progress sits between the two because most
candidates of an early step fail the whole task; how far the episodes got tells them apart
better than a reward that grows with episode length.

Invariants:
1. ``Candidate.spec.parent`` is the version the candidate was derived from and
   ``Candidate.spec.provenance`` names the learner and the sha256 of its configuration.
2. ``Score.key()`` orders by success rate, then progress, then reward per step; equal
   outcomes give equal keys.
3. :func:`config_hash` is the sha256 of the canonical JSON of its argument: key order does
   not change it.
"""

from __future__ import annotations

import hashlib
import json
import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field, replace
from typing import Any, Protocol, runtime_checkable

from capevo.errors import Invalid
from capevo.learner.experience import EpisodeEnd, episode_ends, progress
from capevo.records import EcmVersion, Kind, Origin, PublishSpec
from capevo.registry.api import Registry
from capevo.runtime.evaluation import EpisodeOutcome
from capevo.runtime.tasks import task_spec
from capevo.runtime.tasks.spec import TaskSpec


@dataclass(frozen=True, slots=True, kw_only=True)
class Score:
    """How a candidate did on a set of episodes."""

    success_rate: float
    progress: float
    """Mean :func:`~capevo.learner.experience.progress` (1.0 = every episode succeeded)."""
    reward_per_step: float
    episodes: int

    def key(self) -> tuple[float, float, float]:
        """Sort key: larger is better."""
        return (self.success_rate, self.progress, self.reward_per_step)

    def to_dict(self) -> dict[str, Any]:
        return {
            "success_rate": self.success_rate,
            "progress": self.progress,
            "reward_per_step": self.reward_per_step,
            "episodes": self.episodes,
        }


def score_outcomes(
    outcomes: Sequence[EpisodeOutcome],
    decomposition: Sequence[str],
    *,
    ends: Sequence[EpisodeEnd] | None = None,
) -> Score:
    """Score a candidate's episodes (reads their traces for progress unless ``ends`` is given).

    Episodes without a readable trace count with progress 0 unless they succeeded.
    """
    n = len(outcomes)
    if n == 0:
        return Score(success_rate=0.0, progress=0.0, reward_per_step=0.0, episodes=0)
    read = list(ends) if ends is not None else episode_ends(outcomes)
    by_seed: dict[int | None, list[EpisodeEnd]] = {}
    for e in read:
        by_seed.setdefault(e.seed, []).append(e)
    prog = 0.0
    for o in outcomes:
        matches = by_seed.get(o.seed)
        if o.success:
            prog += 1.0
        elif matches:
            prog += progress(matches.pop(0), decomposition)
    rewards = [o.reward / o.steps for o in outcomes if o.steps > 0 and math.isfinite(o.reward)]
    return Score(
        success_rate=sum(o.success for o in outcomes) / n,
        progress=prog / n,
        reward_per_step=sum(rewards) / len(rewards) if rewards else 0.0,
        episodes=n,
    )


@dataclass(frozen=True, slots=True, kw_only=True)
class TiedEcm:
    """Another ECM whose parameters a search sets to the searched ones in every evaluation.

    Tied ECMs share a skill (T5: the same step for another object, :func:`capevo.learner.skills.siblings`),
    so they have the same parameter names; the search proposes one parameter set for all of them.
    """

    ecm: str
    parent: EcmVersion
    """Its current version (the tied candidate's parent)."""
    source: str
    """The source its parameters are written into (the parent's, or an earlier candidate's in the chain)."""


@dataclass(frozen=True, slots=True, kw_only=True)
class LearnRequest:
    """One ECM to improve.

    Args:
        task: Task name.
        ecm: The ECM to improve (in the task's decomposition).
        parent: Its current version's record (usually the active one).
        source: The parent's artifact as text (code ECMs).
        versions: Versions of the task's other ECMs to evaluate with (empty: active ones).
        train_seeds: Seeds learners may evaluate on; disjoint from gate and test seeds.
        outcomes: Recent episodes (with traces) that motivated the request.
        companions: Unpublished artifacts of *other* ECMs of the task (by name) that every
            evaluation runs in place of their versions: the candidates learned earlier in the
            same update, so a later step is tuned behind the earlier steps' new versions.
        tied: ECMs whose parameters every evaluation sets to the searched ones (see
            :class:`TiedEcm`); the learner returns a candidate for each beside its own.
    """

    task: str
    ecm: str
    parent: EcmVersion
    source: str
    versions: Mapping[str, int] = field(default_factory=dict)
    train_seeds: tuple[int, ...] = ()
    outcomes: tuple[EpisodeOutcome, ...] = ()
    companions: Mapping[str, bytes] = field(default_factory=dict)
    tied: tuple[TiedEcm, ...] = ()

    def __post_init__(self) -> None:
        if self.ecm in self.companions:
            raise Invalid(
                f"{self.ecm} is the ECM being learned; it cannot also be a companion", details={"field": "companions"}
            )
        names = [t.ecm for t in self.tied]
        clash = sorted({self.ecm, *self.companions} & set(names))
        if clash or len(set(names)) != len(names):
            raise Invalid(
                f"a tied ECM must appear once and be neither the ECM learned nor a companion: {clash or names}",
                details={"field": "tied"},
            )

    @property
    def decomposition(self) -> tuple[str, ...]:
        return task_spec(self.task).ecm_names


def request_for(
    registry: Registry,
    task: str,
    ecm: str,
    *,
    train_seeds: Sequence[int],
    outcomes: Sequence[EpisodeOutcome] = (),
    version: int | None = None,
    companions: Mapping[str, bytes] | None = None,
    source: str | None = None,
    tied: Mapping[str, str | None] | None = None,
) -> LearnRequest:
    """A :class:`LearnRequest` for ``ecm`` at ``version`` (default: active) from ``registry``.

    ``companions`` are other ECMs' unpublished artifacts to evaluate with (see
    :class:`LearnRequest`); ``source`` replaces the parent's source as the starting point (an
    earlier, unpublished candidate of the same ECM), the parent record staying ``version``.
    ``tied`` names ECMs whose parameters are searched with ``ecm``'s (see :class:`TiedEcm`), each
    with the source to write them into (None: its active version's).

    Raises:
        Invalid: ``ecm`` is not in the task's decomposition or is not a code ECM.
        NotFound: no such version.
    """
    spec = task_spec(task)
    record, source = _code_version(registry, spec, ecm, version, source, field="ecm")
    tied_ecms = []
    for name, tied_source in (tied or {}).items():
        parent, tied_source = _code_version(registry, spec, name, None, tied_source, field="tied")
        tied_ecms.append(TiedEcm(ecm=name, parent=parent, source=tied_source))
    return LearnRequest(
        task=spec.name,
        ecm=ecm,
        parent=record,
        source=source,
        train_seeds=tuple(train_seeds),
        outcomes=tuple(outcomes),
        companions=dict(companions or {}),
        tied=tuple(tied_ecms),
    )


def _code_version(
    registry: Registry, spec: TaskSpec, ecm: str, version: int | None, source: str | None, *, field: str
) -> tuple[EcmVersion, str]:
    """``ecm``'s record at ``version`` (default: active) and ``source`` (default: its artifact).

    Raises:
        Invalid: ``ecm`` is not in the task's decomposition (reported under ``field``) or is not code.
        NotFound: no such version.
    """
    if ecm not in spec.ecm_names:
        raise Invalid(
            f"task {spec.name!r} has no ECM {ecm!r}; valid: {', '.join(spec.ecm_names)}", details={"field": field}
        )
    record = registry.get_version(ecm, version)
    if record.kind is not Kind.CODE:
        raise Invalid(f"{ecm}@{record.version} is a {record.kind.value} ECM; code learners need code")
    if source is None:
        source = registry.get_artifact(ecm, record.version).decode("utf-8")
    return record, source


@dataclass(frozen=True, slots=True, kw_only=True)
class Candidate:
    """A proposed new version of one ECM, not yet published.

    Args:
        ecm: The ECM name.
        artifact: The new artifact's bytes (UTF-8 source for code).
        spec: Descriptor, interface, origin, parent and provenance.
        score: Its score on the training seeds, when the learner evaluated it.
        baseline: The parent's score on the same seeds, when evaluated.
        notes: Learner-specific details (parameters found, LLM attempts, fallbacks).
        experience: The training episodes (traced) the candidate itself ran, when the learner
            kept them: where they still fail says which ECM to learn next.
        tied: Candidates of the request's tied ECMs, learned with this one (same parameters,
            same evidence); published and gated with it.
    """

    ecm: str
    artifact: bytes
    spec: PublishSpec
    score: Score | None = None
    baseline: Score | None = None
    notes: Mapping[str, Any] = field(default_factory=dict)
    experience: tuple[EpisodeOutcome, ...] = ()
    tied: tuple[Candidate, ...] = ()

    @property
    def source(self) -> str:
        return self.artifact.decode("utf-8")

    def with_notes(self, **notes: Any) -> Candidate:
        """This candidate with ``notes`` added to its notes (a key given again is replaced)."""
        return replace(self, notes={**self.notes, **notes})

    @property
    def improved(self) -> bool:
        """The learner saw it beat its parent on the training seeds."""
        return self.score is not None and self.baseline is not None and self.score.key() > self.baseline.key()

    def publish(self, registry: Registry) -> EcmVersion:
        """Publish as a candidate version (never promotes)."""
        return registry.publish(self.ecm, self.artifact, self.spec)


@runtime_checkable
class Learner(Protocol):
    """Turns a request into a candidate."""

    learner_id: str

    def learn(self, request: LearnRequest) -> Candidate:
        """Propose a new version of ``request.ecm``.

        Raises:
            CapevoError: the learner could not produce a valid candidate.
        """
        ...


@runtime_checkable
class CandidateEvaluator(Protocol):
    """An :class:`~capevo.runtime.evaluation.Evaluator` that can also run unpublished artifacts.

    ``overrides`` maps ECM names to artifact bytes run in place of the version ``versions``
    (or the active one) names; everything else about the ECM (descriptor, interface, origin
    and so trust) is the overridden version's, except ``override_origin`` when given.
    """

    def evaluate(
        self,
        task: str,
        versions: Mapping[str, int],
        seeds: Sequence[int],
        *,
        overrides: Mapping[str, bytes] | None = None,
        override_origin: Origin | None = None,
    ) -> list[EpisodeOutcome]: ...


def config_hash(config: Mapping[str, Any]) -> str:
    """sha256 (hex) of the canonical JSON of ``config`` (sorted keys, no whitespace)."""
    text = json.dumps(config, sort_keys=True, separators=(",", ":"), default=str)
    return hashlib.sha256(text.encode()).hexdigest()
