"""Whole-task demonstrations of a task's version-0 code ECMs, for baselines warm-started by cloning.

Issue 20 asks for Agent Modification warm-started "by behaviour cloning from the same v0
skills' demonstrations, so that the comparison with code ECMs does not rest on knowledge only
one side had". The demonstrator is therefore exactly what ``capevo evolve`` starts from, run
exactly as the runtime runs it; nothing here is a second episode loop or demo collector:

* a registry in the cell's directory gets version 0 of every ECM of the task from
  :func:`capevo.learner.skills.seed_registry` (the code skills ``capevo evolve``'s
  ``ensure_v0`` publishes for the code modalities: hand-written structure, untuned parameters);
* :class:`capevo.runtime.evaluator.LocalEvaluator` runs them with the persistent agent's
  :class:`~capevo.agent.DecompositionPolicy` (default identity) under the cell's Φ, governance,
  perturbations and horizon, and writes one MCAP trace;
* :func:`capevo.runtime.traces.export_transitions` reads the trace back: every ``/env/step``
  row is one demonstration (the task's flat observation as the agent saw it, noise included,
  and the action that ran, after governance), whichever ECM produced it.

Every episode is kept, failed ones too: with the paper's perturbations v0 fails most episodes
(it is "the starting point the learners improve"), and what a clone should inherit is the v0
skills' structure, which a failed episode shows as well. :attr:`V0Demos.successes` says how many
succeeded. The demonstrations' env steps are :attr:`V0Demos.env_steps` (the sum of the episodes'
steps; the runtime's invariant makes it the number of rows), so a method can charge them to its
budget.

Invariants:
1. ``len(v.demos) == v.env_steps == sum(o.steps for o in v.outcomes)``; ``v.episode[i]`` is the
   index (in ``seeds``) of the episode row ``i`` came from.
2. Observation rows have the task's flat observation length (the ``observation_space`` of
   :class:`~capevo.baselines.governed_env.GovernedTaskEnv`), actions its action dimension, both
   float32, actions in [-1, 1].
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from capevo.learner.bc import Demos
from capevo.runtime.envelope import PhiChoice
from capevo.runtime.evaluation import EpisodeOutcome
from capevo.runtime.evaluator import check_seeds
from capevo.runtime.tasks import Perturbations, task_spec

DEMO_SOURCE = "v0 skills"


@dataclass(frozen=True, slots=True, kw_only=True, eq=False)
class V0Demos:
    """Demonstrations of one task's v0 code ECMs (see the module docstring)."""

    demos: Demos
    episode: np.ndarray
    """Per row, the index in ``seeds`` of its episode (int64)."""
    outcomes: tuple[EpisodeOutcome, ...]
    trace: Path

    @property
    def env_steps(self) -> int:
        """Env steps the demonstrations took."""
        return sum(o.steps for o in self.outcomes)

    @property
    def successes(self) -> int:
        return sum(o.success for o in self.outcomes)

    def split(self, episodes: Sequence[int]) -> tuple[Demos, Demos]:
        """The rows of ``episodes`` (indices in ``seeds``) and the rest: a held-out split by episode."""
        mask = np.isin(self.episode, np.asarray(list(episodes), dtype=np.int64))
        d = self.demos

        def part(m: np.ndarray) -> Demos:
            return Demos(obs=d.obs[m], action=d.action[m], source=d.source, episodes=len(set(self.episode[m].tolist())))

        return part(mask), part(~mask)


def v0_demos(
    task: str,
    workdir: str | Path,
    *,
    seeds: Sequence[int],
    phi: PhiChoice = "task",
    governance: bool = True,
    perturbations: bool = True,
    horizon: int | None = None,
) -> V0Demos:
    """Run the task's v0 code ECMs once per seed through the runtime and return what they did.

    Args:
        task: Task id or name (one with built-in skills: all six).
        workdir: Gets ``v0-registry/`` (the seeded registry) and ``demos/`` (the MCAP trace).
        seeds: Task seeds of the demonstration episodes (training seeds, never held-out ones).
        phi: The envelope, as the cell's.
        governance: As the cell's (False: counting mode).
        perturbations: As the cell's.
        horizon: Episode length; None for the task's default.

    Returns:
        The demonstrations, their episodes' outcomes and the trace's path.

    Raises:
        Invalid: an unknown task or one without built-in skills, bad seeds.
    """
    from capevo.agent import DecompositionPolicy, IdentityMemory
    from capevo.learner.skills import seed_registry
    from capevo.registry.local import LocalRegistry
    from capevo.runtime.evaluator import LocalEvaluator
    from capevo.runtime.traces import export_transitions

    spec = task_spec(task)
    seed_list = check_seeds(seeds)
    root = Path(workdir)
    registry = LocalRegistry(root / "v0-registry", actor="baseline-demos")
    try:
        seed_registry(registry, spec.name, reason="v0: manual creation (built-in untuned skill), for demonstrations")
        with LocalEvaluator(
            registry,
            policy=DecompositionPolicy(identity=IdentityMemory.default()),
            phi=phi,
            trace_dir=root / "demos",
            perturbations=Perturbations() if perturbations else Perturbations.none(),
            horizon=horizon,
            governance=governance,
            worker_id="baseline-demos",
        ) as evaluator:
            outcomes = tuple(evaluator.evaluate(spec.name, {}, seed_list))
    finally:
        registry.close()
    trace = Path(str(outcomes[0].trace_path))
    rows = export_transitions(trace)
    demos = Demos(
        # Copies: the exported arrays are read-only and torch wants writable ones.
        obs=np.array(rows.obs, dtype=np.float32),
        action=np.clip(np.array(rows.action, dtype=np.float32), -1.0, 1.0),
        source=DEMO_SOURCE,
        episodes=len(outcomes),
        episodes_seen=len(outcomes),
        traces=(str(trace),),
    )
    return V0Demos(demos=demos, episode=np.asarray(rows.episode, dtype=np.int64), outcomes=outcomes, trace=trace)
