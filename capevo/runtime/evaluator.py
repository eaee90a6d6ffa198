"""The in-process evaluator: seeded episodes of a capability set, one MCAP trace per call.

:class:`LocalEvaluator` implements :class:`capevo.runtime.evaluation.Evaluator`. The gate
calls ``evaluate(task, versions, seeds)`` for the active and for the candidate set with the
same seeds; each call loads the versions (:class:`LoadedCapabilitySet`, artifacts through
the cache), runs one episode per seed on one reused environment (``reset(seed=s)``), writes
one trace file, and returns one :class:`EpisodeOutcome` per seed, in seed order.

Invariants:
1. ``evaluate`` returns exactly ``len(seeds)`` outcomes, the i-th for ``seeds[i]``, each with
   ``trace_path`` naming the call's trace file, which holds one ``/episode/summary`` per seed
   (episode index i) and metadata naming the registry revision, Φ's hash, the agent's
   identity hash, the seeds and the package versions.
2. The versions loaded for a call are released (sandbox workers killed) before it returns,
   whether it succeeds or raises.
3. One environment per task is built and reused; with equal settings, equal seeds and equal
   versions give equal outcomes (up to ``duration_s``).
"""

from __future__ import annotations

import contextlib
import logging
import os
import time
import uuid
from collections.abc import Callable, Mapping, Sequence
from pathlib import Path
from typing import Any

from capevo.errors import Invalid, Unavailable
from capevo.records import CapabilitySet
from capevo.registry.api import Registry
from capevo.runtime.artifact_cache import ArtifactStore, MemoryArtifactCache
from capevo.runtime.capabilities import DEFAULT_RECOVERY, LoadedCapabilitySet
from capevo.runtime.ecm import LoadOptions
from capevo.runtime.envelope import PhiChoice, check_phi_choice, resolve_phi
from capevo.runtime.episode import DEFAULT_STEP_BUDGET, DEFAULT_TIMEOUT_S, make_governor, run_episode
from capevo.runtime.evaluation import EpisodeOutcome
from capevo.runtime.governance import Phi
from capevo.runtime.policy import DecisionPolicy
from capevo.runtime.safety_monitor import SafetyLimits
from capevo.runtime.tasks import Perturbations, TaskEnv, make_task, task_spec
from capevo.runtime.traces import (
    DEFAULT_COMPRESSION,
    TraceMetadata,
    TraceWriter,
    check_compression,
)

log = logging.getLogger(__name__)

Progress = Callable[[int, int, EpisodeOutcome], Any]
"""``progress(done, total, outcome)`` after each episode."""
MAX_SEEDS_PER_CALL = 10_000
UNKNOWN_IDENTITY = "unspecified"


def check_seeds(seeds: Sequence[int]) -> list[int]:
    """``seeds`` as a list of non-negative ints.

    Raises:
        Invalid: not a sequence of non-negative integers, empty, or longer than
            :data:`MAX_SEEDS_PER_CALL`.
    """
    if isinstance(seeds, (str, bytes)) or not isinstance(seeds, Sequence):
        raise Invalid(f"seeds must be a list of integers, got {type(seeds).__name__}", details={"field": "seeds"})
    out = []
    for s in seeds:
        if isinstance(s, bool) or not isinstance(s, int) or s < 0:
            raise Invalid(f"seeds must be non-negative integers, got {s!r}", details={"field": "seeds"})
        out.append(int(s))
    if not out:
        raise Invalid("seeds: give at least one seed", details={"field": "seeds"})
    if len(out) > MAX_SEEDS_PER_CALL:
        raise Invalid(f"seeds: {len(out)} given; at most {MAX_SEEDS_PER_CALL} per call", details={"field": "seeds"})
    return out


def check_versions(versions: Mapping[str, int]) -> dict[str, int]:
    """``versions`` as ``{name: int}``.

    Raises:
        Invalid: not a mapping of names to non-negative integers.
    """
    if not isinstance(versions, Mapping):
        raise Invalid(f"versions must be a mapping, got {type(versions).__name__}", details={"field": "versions"})
    out = {}
    for name, v in versions.items():
        if not isinstance(name, str) or isinstance(v, bool) or not isinstance(v, int) or v < 0:
            raise Invalid(
                f"versions must map ECM names to non-negative integers, got {name!r}: {v!r}",
                details={"field": "versions"},
            )
        out[name] = int(v)
    return out


class LocalEvaluator:
    """Runs evaluation episodes in this process.

    Args:
        registry: Where versions and artifacts come from.
        policy: π_A.
        phi: The safety envelope: ``"task"`` (default: the scene-aware per-task Φ of the task
            being evaluated), ``"paper"`` (the paper's Φ), a Φ YAML path or a :class:`Phi`
            (see :mod:`capevo.runtime.envelope`).
        safety_limits: The hard limits the safety monitor grades ``unsafe`` against (each
            outcome's ``unsafe_steps``); default the paper's :class:`SafetyLimits`.
        trace_dir: Directory for the trace files (one per ``evaluate`` call); None writes
            no trace (``trace_path`` is then None).
        trace_compression: The traces' chunk compression: ``"lz4"``, ``"zstd"`` or ``"none"``
            (see :data:`capevo.runtime.traces.writer.COMPRESSIONS`).
        perturbations: Task perturbations; default all on (the benchmark setting).
        horizon: Episode length; default each task's own.
        step_budget_per_ecm: Steps one ECM activation may take.
        timeout_s: Per-call ECM compute limit.
        governance: False runs the evaluation-only counting mode (actions pass unchanged).
        agent_identity_hash: The persistent agent's identity hash, recorded in traces; the caller
            computes it (the runtime lies below the agent and does not know how); default
            ``"unspecified"``.
        cache: Artifact cache shared across calls; default in memory.
        load_options: Trust policy and sandbox settings.
        recovery: ECM recovery mode (see :data:`capevo.runtime.capabilities.RECOVERY_MODES`).
        progress: Called after every episode as ``progress(done, total, outcome)``.
        worker_id: Recorded in traces.
        env: A prebuilt environment to reuse for its task (the runtime worker shares its own).
        env_kwargs: Extra robosuite arguments for the environments built here.
        should_stop: Polled between episodes; True abandons the call with :class:`Unavailable`
            (a worker shutting down).

    Raises:
        Invalid: bad ``trace_dir``, ``trace_compression`` or settings.
    """

    def __init__(
        self,
        registry: Registry,
        *,
        policy: DecisionPolicy,
        phi: PhiChoice = None,
        safety_limits: SafetyLimits | None = None,
        trace_dir: str | os.PathLike[str] | None,
        trace_compression: str = DEFAULT_COMPRESSION,
        perturbations: Perturbations | None = None,
        horizon: int | None = None,
        step_budget_per_ecm: int | None = DEFAULT_STEP_BUDGET,
        timeout_s: float = DEFAULT_TIMEOUT_S,
        governance: bool = True,
        agent_identity_hash: str | None = None,
        cache: ArtifactStore | None = None,
        load_options: LoadOptions | None = None,
        recovery: str = DEFAULT_RECOVERY,
        progress: Progress | None = None,
        worker_id: str = "",
        env: TaskEnv | None = None,
        env_kwargs: Mapping[str, Any] | None = None,
        should_stop: Callable[[], bool] | None = None,
    ) -> None:
        self.registry = registry
        self.should_stop = should_stop
        self.policy = policy
        self.phi_choice: PhiChoice = phi if phi is None or isinstance(phi, Phi) else check_phi_choice(os.fspath(phi))
        self._phis: dict[str, Phi] = {}
        self.safety_limits = safety_limits if safety_limits is not None else SafetyLimits()
        self.trace_dir = Path(trace_dir) if trace_dir is not None else None
        self.trace_compression = check_compression(trace_compression)
        self.perturbations = perturbations if perturbations is not None else Perturbations()
        self.horizon = horizon
        self.step_budget_per_ecm = step_budget_per_ecm
        self.timeout_s = timeout_s
        self.governance = governance
        self.agent_identity_hash = agent_identity_hash or UNKNOWN_IDENTITY
        self.cache: ArtifactStore = cache if cache is not None else MemoryArtifactCache()
        self.load_options = load_options
        self.recovery = recovery
        self.progress = progress
        self.worker_id = worker_id
        self.env_kwargs = dict(env_kwargs or {})
        self._envs: dict[str, TaskEnv] = {}
        self._owned: set[str] = set()
        if env is not None:
            self._envs[env.task_spec.name] = env

    def environment(self, task: str) -> TaskEnv:
        """The (reused) environment of ``task``; built on first use.

        Raises:
            Invalid: unknown task.
        """
        name = task_spec(task).name
        env = self._envs.get(name)
        if env is None:
            env = make_task(name, perturbations=self.perturbations, horizon=self.horizon, **self.env_kwargs)
            self._envs[name] = env
            self._owned.add(name)
        return env

    def phi_for(self, task: str) -> Phi:
        """The envelope ``task``'s episodes run under (:attr:`phi_choice` resolved for it).

        Raises:
            Invalid: unknown task, or a Φ file that does not load.
        """
        name = task_spec(task).name
        phi = self._phis.get(name)
        if phi is None:
            phi = self._phis[name] = resolve_phi(self.phi_choice, task_spec(name))
        return phi

    def evaluate(self, task: str, versions: Mapping[str, int], seeds: Sequence[int]) -> list[EpisodeOutcome]:
        """Run one episode per seed with ``versions`` (active versions for ECMs not named).

        Returns:
            One outcome per seed, in order; each has ``trace_path`` set.

        Raises:
            Invalid: unknown task, bad seeds or versions, versions that do not compose.
            NotFound: an ECM has no active version and none was given.
            Unavailable, Timeout: the registry cannot be reached while loading (or ``should_stop``).
        """
        seed_list = check_seeds(seeds)
        pinned = check_versions(versions)
        spec = task_spec(task)
        phi = self.phi_for(spec.name)
        env = self.environment(spec.name)
        env.reset(seed=seed_list[0])
        shapes = {k: tuple(v.shape) for k, v in env.obs_dict.items()}
        with LoadedCapabilitySet(
            self.registry,
            spec.name,
            versions=pinned,
            cache=self.cache,
            load_options=self.load_options,
            recovery=self.recovery,
            observation_shapes=shapes,
        ) as caps:
            run_id = f"eval-{time.strftime('%Y%m%dT%H%M%SZ', time.gmtime())}-{uuid.uuid4().hex[:8]}"
            metadata = TraceMetadata.collect(
                run_id=run_id,
                task=spec.name,
                capability_set=CapabilitySet(revision=caps.revision, active=caps.versions),
                phi_hash=phi.hash,
                agent_identity_hash=self.agent_identity_hash,
                seeds=seed_list,
                worker_id=self.worker_id,
            )
            governor = make_governor(env, phi, enforce=self.governance)
            outcomes: list[EpisodeOutcome] = []
            path = self.trace_dir / f"{spec.name}-{run_id}.mcap" if self.trace_dir is not None else None
            sink_cm = (
                TraceWriter(path, metadata, compression=self.trace_compression)
                if path is not None
                else contextlib.nullcontext(None)
            )
            with sink_cm as sink:
                for i, seed in enumerate(seed_list):
                    if self.should_stop is not None and self.should_stop():
                        raise Unavailable(
                            f"evaluation of {spec.name} abandoned after {i} of {len(seed_list)} episodes: "
                            "the runtime is shutting down"
                        )
                    outcome = run_episode(
                        env,
                        caps,
                        self.policy,
                        governor,
                        sink,
                        seed=seed,
                        episode=i,
                        step_budget_per_ecm=self.step_budget_per_ecm,
                        timeout_s=self.timeout_s,
                        trace_path=str(path) if path is not None else None,
                        safety_limits=self.safety_limits,
                    )
                    outcomes.append(outcome)
                    if self.progress is not None:
                        self.progress(i + 1, len(seed_list), outcome)
        log.info(
            "evaluated %s %s on %d seeds: %d/%d successes; trace %s",
            spec.name,
            caps.versions,
            len(seed_list),
            sum(o.success for o in outcomes),
            len(outcomes),
            path,
        )
        return outcomes

    def close(self) -> None:
        """Close the environments this evaluator built (not one it was given)."""
        for name in list(self._owned):
            env = self._envs.pop(name, None)
            if env is not None:
                env.close()
        self._owned.clear()

    def __enter__(self) -> LocalEvaluator:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
