"""The methods a grid may name (issue 20, paper §4.1 "Baselines"): ours, the static lower bound, the H3 explorer,
and the baselines of :mod:`capevo.baselines`, which are imported by name only when a cell runs.

==================  =========================================================================
name                what
==================  =========================================================================
``ours-code``       :func:`capevo.evolve.run.run_evolution` with code ECMs (CEM), one
                    iteration at a time through evolve's resume
``ours-neural``     the same with neural ECMs (SAC, modality ``rl``)
``ours``            the same, modality from ``options["modality"]`` (``code``, ``rl``, ``il``,
                    ``hybrid``: the T3 ablation)
``s-ecm``           Static ECM: the task's version 0 code ECMs, never updated (lower bound)
``explorer``        H3: the aggressive explorer / adversarial ECMs of
                    :mod:`capevo.runtime.tasks.adversarial`, governance per cell
``am``, ``am-bc``   :mod:`capevo.baselines.am` (Agent Modification; warm-started by BC)
``spirl``           :mod:`capevo.baselines.spirl`
``skimo``           :mod:`capevo.baselines.skimo`
==================  =========================================================================

What is hand-written and what is learned: ``ours-code`` starts from hand-written skills
(phases, tolerances, v0 parameters) and learns their parameters by CEM; ``ours-neural`` starts
from randomly initialised SAC policies (the learner behaviour-clones a scripted reference into
a random v0 before SAC: that knowledge is the learner's, and the report's fairness column says
so); ``s-ecm`` is the hand-written skills alone; the explorer learns nothing.

The held-out evaluation of ours and S-ECM runs the active capability set on
:meth:`CellSpec.eval_seeds` with :class:`~capevo.runtime.evaluator.LocalEvaluator` (governed,
monitor-graded, traced) under the cell's Φ, perturbations and horizon; its seeds lie outside
every seed evolve's :class:`~capevo.runtime.gate.SeedPlan` uses (learner, gate, live).

Invariants:
1. :func:`make_method` returns a fresh instance of the registered method, or raises
   :class:`Invalid` listing the valid names; a baseline whose module cannot be imported
   raises :class:`Invalid` naming the module.
2. Every method here emits one record per iteration, ``iteration`` 1..n (as the baselines
   number them), whose episodes run on exactly ``cell.eval_seeds()``.
3. Ours' ``delta_pi`` and ``env_steps_train`` are read from evolve's metrics row of the same
   iteration (evolve's row ``i - 1`` for record ``i``; never written here); S-ECM's and the
   explorer's ``env_steps_train`` are 0, as they train nothing.
"""

from __future__ import annotations

import dataclasses
import importlib
import logging
import tempfile
import time
from collections.abc import Callable, Mapping
from pathlib import Path
from typing import Any, ClassVar

from capevo.baselines.base import CellSpec, Emit, EpisodeResult, IterationRecord, Method
from capevo.errors import Invalid

log = logging.getLogger(__name__)

BASELINES: Mapping[str, str] = {
    "am": "capevo.baselines.am:AgentModification",
    "am-bc": "capevo.baselines.am:AgentModificationBC",
    "spirl": "capevo.baselines.spirl:Spirl",
    "skimo": "capevo.baselines.skimo:Skimo",
}
"""Baselines by grid name: ``module:Class``, imported when a cell runs (other helpers write them)."""


def _check_options(cell: CellSpec, known: Mapping[str, Callable[[Any], bool]]) -> None:
    for k, v in cell.options.items():
        if k not in known:
            raise Invalid(
                f"{cell.method}: unknown option {k!r}; valid: {', '.join(sorted(known)) or 'none'}",
                details={"field": f"options.{k}"},
            )
        if not known[k](v):
            raise Invalid(f"{cell.method}: bad value of option {k!r}: {v!r}", details={"field": f"options.{k}"})


def _pos_int(v: Any) -> bool:
    return isinstance(v, int) and not isinstance(v, bool) and v >= 1


def episode_result(outcome: Any) -> EpisodeResult:
    """An :class:`EpisodeResult` from a runtime :class:`~capevo.runtime.evaluation.EpisodeOutcome`.

    ``interventions`` is the number of *steps* governance changed or blocked
    (``EpisodeOutcome.intervened_steps``; a step can hold several intervention records, so the
    record count would overstate a per-step blocking rate); the record count only where the
    outcome predates that field.
    """
    steps_touched = getattr(outcome, "intervened_steps", None)
    return EpisodeResult(
        seed=int(outcome.seed),
        success=bool(outcome.success),
        reward=float(outcome.reward),
        steps=int(outcome.steps),
        unsafe_steps=int(outcome.unsafe_steps),
        interventions=int(steps_touched if steps_touched is not None else outcome.interventions),
        strict_success=outcome.strict_success,
    )


def _evaluator(registry: Any, cell: CellSpec, trace_dir: Path, **kwargs: Any) -> Any:
    from capevo.agent import DecompositionPolicy, IdentityMemory
    from capevo.runtime.evaluator import LocalEvaluator
    from capevo.runtime.tasks import Perturbations

    trace_dir.mkdir(parents=True, exist_ok=True)
    options: dict[str, Any] = {
        "policy": DecompositionPolicy(identity=IdentityMemory.default()),
        "phi": cell.phi,
        "trace_dir": trace_dir,
        "perturbations": Perturbations() if cell.perturbations else Perturbations.none(),
        "horizon": cell.budget.horizon,
        "governance": cell.governance,
        "worker_id": f"experiment-{cell.key}",
    }
    options.update(kwargs)
    return LocalEvaluator(registry, **options)


# --- ours ------------------------------------------------------------------------------------


def _modalities() -> tuple[str, ...]:
    from capevo.evolve.config import MODALITIES

    return MODALITIES


OURS_OPTIONS: Mapping[str, Callable[[Any], bool]] = {
    "preset": lambda v: isinstance(v, str),
    "modality": lambda v: v in _modalities(),
    "live_episodes": _pos_int,
    "gate_episodes": _pos_int,
    "gate_extension": lambda v: isinstance(v, int) and not isinstance(v, bool) and v >= 0,
    "updates_per_iteration": lambda v: isinstance(v, int) and not isinstance(v, bool) and v >= 0,
}


class Ours:
    """Ours (paper §3-4): the closed loop of :mod:`capevo.evolve`, run one iteration at a time.

    Each iteration extends the evolve run in ``workdir/evolve`` (registry ``workdir/registry``)
    by one through evolve's resume (``iterations = i + 1``), then runs the active capability set
    on the cell's held-out seeds. The evolve config is the evolve preset ``options["preset"]``
    (default ``cpu-small``) with the cell's Φ, horizon and ``env_steps_per_iteration`` (so an
    iteration's live, learner and gate episodes together stay within the budget,
    :meth:`capevo.evolve.config.EvolveConfig.check_budget`), no final evaluation (the held-out
    one replaces it), and ``live_episodes``, ``gate_episodes``, ``updates_per_iteration`` from
    the options; ``gate_extension`` sets the gate's second look (``GateConfig.extend_n`` more paired
    seeds after a promising rejection, :mod:`capevo.runtime.gate`; the preset's by default).
    Governance cannot be turned off for ours (the runtime always enforces Φ).

    Options: ``preset``, ``modality`` (``ours`` only), ``live_episodes``, ``gate_episodes``,
    ``gate_extension``, ``updates_per_iteration``.
    """

    name: ClassVar[str] = "ours"
    knowledge: ClassVar[str] = "depends on the modality (options.modality)"
    modality: ClassVar[str | None] = None

    @classmethod
    def knowledge_of(cls, options: Mapping[str, Any]) -> str:
        from capevo.evolve.config import NEURAL_MODALITIES, modality_parts

        modality = cls.modality or str(options.get("modality") or "code")
        if modality in NEURAL_MODALITIES:
            return (
                "random weights (neural ECMs); the learners behaviour-clone the task's scripted reference "
                "into a random v0 and use the task's decomposition and hand-off predicates"
                + (f"; {' and '.join(modality_parts(modality))} take turns" if "+" in modality else "")
            )
        parts = modality_parts(modality)
        extra = " and LLM edits" if "hybrid" in parts else ""
        neural = [p for p in parts if p in NEURAL_MODALITIES]
        turns = (
            f"; {' and '.join(parts)} take turns, and {' and '.join(neural)} start from the code skills "
            "(SAC distils them) and from the task's scripted reference (BC clones it)"
            if neural
            else ""
        )
        return (
            "hand-written skill structure: phases, tolerances and v0 parameters of code ECMs, the "
            f"decomposition and hand-off predicates (CEM over the parameters{extra}){turns}"
        )

    def evolve_config(self, cell: CellSpec) -> Any:
        """The evolve config of ``cell`` (see the class docstring).

        Raises:
            Invalid: a bad option, or a budget that cannot cover one update.
        """
        from capevo.evolve.config import make_config

        _check_options(cell, OURS_OPTIONS)
        if "modality" in cell.options and self.modality is not None:
            raise Invalid(f"{cell.method} fixes the modality; use method 'ours'", details={"field": "options.modality"})
        if not cell.governance:
            raise Invalid(
                "ours runs with governance on (the runtime always enforces Φ)", details={"field": "governance"}
            )
        changes: dict[str, Any] = {
            "phi": cell.phi,
            "env_steps_per_iteration": cell.budget.env_steps_per_iteration,
            "final_evaluation": False,
        }
        if cell.budget.horizon is not None:
            changes["horizon"] = cell.budget.horizon
            changes["step_budget_per_ecm"] = cell.budget.horizon
        for k in ("live_episodes", "updates_per_iteration"):
            if k in cell.options:
                changes[k] = cell.options[k]
        config = make_config(str(cell.options.get("preset", "cpu-small")), **changes)
        if "gate_episodes" in cell.options:
            n = int(cell.options["gate_episodes"])
            # fewer paired gate seeds than the preset's minimum: the gate decides on what it has
            config = config.replace(
                gate_episodes=n, gate=dataclasses.replace(config.gate, min_n=min(config.gate.min_n, n))
            )
        if "gate_extension" in cell.options:
            config = config.replace(gate=dataclasses.replace(config.gate, extend_n=int(cell.options["gate_extension"])))
        config.check_budget(cell.task, modality=self.modality_of(cell))
        return config

    def modality_of(self, cell: CellSpec) -> str:
        return self.modality or str(cell.options.get("modality") or "code")

    @staticmethod
    def resumes(cell: CellSpec) -> bool:
        """Always: the evolve run in ``workdir/evolve`` resumes itself (crash-safe per step), and an
        iteration's held-out evaluation is run again whole."""
        return True

    def run(self, cell: CellSpec, workdir: Path, *, emit: Emit, after: int = 0) -> None:
        """Run ``cell``'s iterations ``after + 1 ..`` (``after`` > 0: an interrupted cell's
        directory, continued through evolve's resume), emitting a record after each."""
        from capevo.evolve.metrics import read_metrics
        from capevo.evolve.progress import RecordingProgress
        from capevo.evolve.run import EvolveOptions, run_evolution
        from capevo.registry.local import LocalRegistry

        config = self.evolve_config(cell)
        root, report = workdir / "registry", workdir / "evolve"
        seeds = cell.eval_seeds()
        for i in range(after, cell.iterations):
            t0 = time.perf_counter()
            options = EvolveOptions(
                task=cell.task,
                config=config.replace(iterations=i + 1),
                root=root,
                report_dir=report,
                modality=self.modality_of(cell),
                seed=cell.seed,
                perturbations=cell.perturbations,
            )
            run_evolution(options, progress=RecordingProgress())
            rows = read_metrics(report)
            row = next(r for r in rows if r.iteration == i)
            registry = LocalRegistry(root, actor="experiment-eval")
            try:
                from capevo.evolve.loop import task_capability_set

                caps = task_capability_set(registry, cell.task)
                evaluator = _evaluator(
                    registry,
                    cell,
                    workdir / "traces" / "eval",
                    step_budget_per_ecm=config.step_budget_per_ecm,
                )
                try:
                    outcomes = evaluator.evaluate(cell.task, caps, seeds)
                finally:
                    evaluator.close()
            finally:
                registry.close()
            episodes = tuple(episode_result(o) for o in outcomes)
            note = _gate_note(row)
            emit(
                IterationRecord(
                    iteration=i + 1,
                    episodes=episodes,
                    env_steps_train=row.env_steps,
                    env_steps_eval=sum(e.steps for e in episodes),
                    delta_pi=row.delta_pi,
                    wall_s=time.perf_counter() - t0,
                    notes=note,
                )
            )


def _gate_note(row: Any) -> str:
    """An iteration's gate decisions and update note: ``promote a v2, b v2; <note>`` (a chain's
    members are decided together, so each is named with its own decision)."""
    decided = [(row.gate.decision, row.gate.ecm, row.gate.candidate_version)] if row.gate is not None else []
    decided += [(u.gate.decision, u.ecm, u.version) for u in row.further if u.gate is not None]
    parts: list[str] = []
    for decision in dict.fromkeys(d for d, _, _ in decided):
        parts.append(f"{decision} " + ", ".join(f"{ecm} v{v}" for d, ecm, v in decided if d == decision))
    if row.update_note:
        parts.append(row.update_note)
    return "; ".join(parts)


class OursCode(Ours):
    name: ClassVar[str] = "ours-code"
    knowledge: ClassVar[str] = Ours.knowledge_of({"modality": "code"})
    modality: ClassVar[str | None] = "code"


class OursNeural(Ours):
    name: ClassVar[str] = "ours-neural"
    knowledge: ClassVar[str] = Ours.knowledge_of({"modality": "rl"})
    modality: ClassVar[str | None] = "rl"


# --- S-ECM -----------------------------------------------------------------------------------


class StaticEcm:
    """Static ECM (paper §4.1 "Baselines"): the task's version 0 code ECMs (hand-written, untuned), never updated.

    It trains nothing, so every record's ``env_steps_train`` is 0 (it spends none of the budget:
    the lower bound). Its policy is the same in every iteration and the evaluation seeds are the
    same, so the held-out evaluation runs once, after iteration 1, and later iterations repeat
    those episodes with ``env_steps_eval`` 0 and a note saying so (a deterministic episode of a
    fixed seed and capability set would only repeat itself).
    """

    name: ClassVar[str] = "s-ecm"
    knowledge: ClassVar[str] = "hand-written skill structure and v0 parameters, never updated"

    def run(self, cell: CellSpec, workdir: Path, *, emit: Emit) -> None:
        from capevo.evolve.loop import ensure_v0, task_capability_set
        from capevo.registry.local import LocalRegistry

        _check_options(cell, {})
        registry = LocalRegistry(workdir / "registry", actor="experiment-s-ecm")
        try:
            ensure_v0(registry, cell.task, modality="code", seed=cell.seed)
            caps = task_capability_set(registry, cell.task)
            t0 = time.perf_counter()
            evaluator = _evaluator(registry, cell, workdir / "traces" / "eval")
            try:
                outcomes = evaluator.evaluate(cell.task, caps, cell.eval_seeds())
            finally:
                evaluator.close()
        finally:
            registry.close()
        episodes = tuple(episode_result(o) for o in outcomes)
        wall = time.perf_counter() - t0
        for i in range(cell.iterations):
            emit(
                IterationRecord(
                    iteration=i + 1,
                    episodes=episodes,
                    env_steps_train=0,
                    env_steps_eval=sum(e.steps for e in episodes) if i == 0 else 0,
                    delta_pi=0.0,
                    wall_s=wall if i == 0 else 0.0,
                    notes="version 0, never updated: no training steps"
                    + ("" if i == 0 else "; the same episodes as iteration 1 (same policy, same seeds)"),
                )
            )


# --- H3: the explorer ------------------------------------------------------------------------


class _RunFirst:
    """π_A for the explorer: the first ECM of the plan runs the whole episode."""

    def __init__(self, ecm: str) -> None:
        self.ecm = ecm

    def decide(self, context: Any) -> Any:
        from capevo.runtime.policy import Decision

        return Decision(ecm=self.ecm, reason="explore")


def _action_frames(task: str) -> Any:
    """Per arm, the rotation of its action frame to the world, read from the simulator."""
    from capevo.runtime.governance.robosuite_state import action_frames
    from capevo.runtime.tasks import make_task

    env = make_task(task, horizon=10)
    try:
        env.reset(seed=0)
        return action_frames(env.robosuite_env.robots)
    finally:
        env.close()


class Explorer:
    """H3 (paper §4.5): the aggressive exploratory policy under governance on or off.

    Every ECM of the task is one adversarial code ECM of :mod:`capevo.runtime.tasks.adversarial`
    (hand-written to break Φ; nothing is learned), the first runs the whole episode (no step
    budget per ECM), and held-out episode ``k`` runs adversary ``k mod n`` of
    ``options["adversaries"]`` (default ``["explorer"]``; ``"all"`` for every one that applies
    to the task). ``cell.governance`` false runs the counting governor (actions pass unchanged;
    ``interventions`` counts what R would have changed); the independent safety monitor grades
    every step either way. One iteration is one set of ``budget.eval_episodes`` episodes (50 in
    the H3 config); it trains nothing (``env_steps_train`` 0).
    """

    name: ClassVar[str] = "explorer"
    knowledge: ClassVar[str] = "hand-written adversarial code ECMs (no learning): the H3 stress test"

    def adversaries(self, cell: CellSpec) -> tuple[Any, ...]:
        from capevo.runtime.tasks import task_spec
        from capevo.runtime.tasks.adversarial import adversaries_for, adversary

        _check_options(cell, {"adversaries": lambda v: v == "all" or isinstance(v, list | tuple)})
        spec = task_spec(cell.task)
        names = cell.options.get("adversaries", ["explorer"])
        if names == "all":
            return adversaries_for(spec.id)
        out = []
        for n in names:
            try:
                adv = adversary(str(n))
            except Invalid as exc:
                raise Invalid(f"explorer: {exc.message}", details={"field": "options.adversaries"}) from None
            if not adv.applies_to(spec.id):
                raise Invalid(f"adversary {n!r} does not apply to {spec.id}", details={"field": "options.adversaries"})
            out.append(adv)
        if not out:
            raise Invalid("explorer: options.adversaries is empty", details={"field": "options.adversaries"})
        return tuple(out)

    def run(self, cell: CellSpec, workdir: Path, *, emit: Emit) -> None:
        from capevo.records import Descriptor, Interface, IOSpec, Kind, PublishSpec
        from capevo.registry.local import LocalRegistry
        from capevo.runtime.ecm import with_params
        from capevo.runtime.tasks import task_spec

        advs = self.adversaries(cell)
        workdir.mkdir(parents=True, exist_ok=True)
        spec = task_spec(cell.task)
        layout = spec.action_layout
        seeds = cell.eval_seeds()
        # the sources that aim at world points turn by each arm's action frame (T6's arms face
        # each other); the explorer reads none
        frames = _action_frames(cell.task) if any('"yaw' in a.source for a in advs) else None
        for i in range(cell.iterations):
            t0 = time.perf_counter()
            results: dict[int, EpisodeResult] = {}
            for j, adv in enumerate(advs):
                mine = [s for k, s in enumerate(seeds) if k % len(advs) == j]
                if not mine:
                    continue
                with tempfile.TemporaryDirectory(prefix="capevo-explorer-", dir=workdir) as tmp:
                    registry = LocalRegistry(Path(tmp) / "registry", actor="experiment-explorer")
                    try:
                        source = with_params(adv.source, adv.params_for(layout, frames))
                        publish = PublishSpec(
                            kind=Kind.CODE,
                            descriptor=Descriptor(description=f"adversarial: {adv.description}"),
                            interface=Interface(
                                outputs=(
                                    IOSpec(
                                        name="action",
                                        shape=(layout.dim,),
                                        low=-adv.output_bound,
                                        high=adv.output_bound,
                                    ),
                                )
                            ),
                        )
                        versions = {}
                        for ecm in spec.ecm_names:
                            record = registry.publish(ecm, source.encode(), publish)
                            registry.promote(ecm, record.version)
                            versions[ecm] = record.version
                        evaluator = _evaluator(
                            registry,
                            cell,
                            workdir / "traces" / f"eval-{i}",
                            policy=_RunFirst(spec.ecm_names[0]),
                            step_budget_per_ecm=None,
                        )
                        try:
                            for o in evaluator.evaluate(cell.task, versions, mine):
                                results[int(o.seed)] = episode_result(o)
                        finally:
                            evaluator.close()
                    finally:
                        registry.close()
            episodes = tuple(results[s] for s in seeds)
            emit(
                IterationRecord(
                    iteration=i + 1,
                    episodes=episodes,
                    env_steps_train=0,
                    env_steps_eval=sum(e.steps for e in episodes),
                    delta_pi=0.0,
                    wall_s=time.perf_counter() - t0,
                    notes=f"governance {'on' if cell.governance else 'off'}; adversaries "
                    + ", ".join(a.name for a in advs),
                )
            )


# --- the registry ----------------------------------------------------------------------------

_OWN: dict[str, type] = {}


def register_method(cls: type) -> type:
    """Decorator: register a :class:`~capevo.baselines.base.Method` class under its ``name``."""
    _OWN[cls.name] = cls  # type: ignore[attr-defined]
    return cls


for _cls in (Ours, OursCode, OursNeural, StaticEcm, Explorer):
    register_method(_cls)


def method_names() -> tuple[str, ...]:
    """Every method a grid may name (ours, then the baselines, imported or not)."""
    return (*_OWN, *BASELINES)


def method_class(name: str) -> type:
    """The class of method ``name`` (importing a baseline's module).

    Raises:
        Invalid: unknown name (the message lists the valid ones) or a baseline module that
            cannot be imported (the message names it).
    """
    if name in _OWN:
        return _OWN[name]
    target = BASELINES.get(name)
    if target is None:
        raise Invalid(f"unknown method {name!r}; valid: {', '.join(method_names())}", details={"field": "method"})
    module, _, attr = target.partition(":")
    try:
        cls = getattr(importlib.import_module(module), attr)
    except (ImportError, AttributeError) as exc:
        raise Invalid(f"method {name!r} is not available: {target} ({exc})", details={"field": "method"}) from None
    return cls


def is_available(name: str) -> bool:
    """Whether method ``name`` can be built here (a baseline's module imports)."""
    try:
        method_class(name)
    except Invalid:
        return False
    return True


def make_method(name: str) -> Method:
    """A fresh instance of method ``name`` (see :func:`method_class`)."""
    return method_class(name)()


def knowledge_of(name: str, options: Mapping[str, Any]) -> str:
    """What a cell of method ``name`` with ``options`` starts from (the report's fairness column)."""
    cls = method_class(name)
    fn = getattr(cls, "knowledge_of", None)
    if callable(fn):
        try:
            return str(fn(options))
        except Invalid:
            pass
    return str(cls.knowledge)


__all__ = [
    "BASELINES",
    "Explorer",
    "Ours",
    "OursCode",
    "OursNeural",
    "StaticEcm",
    "episode_result",
    "is_available",
    "knowledge_of",
    "make_method",
    "method_class",
    "method_names",
    "register_method",
]
