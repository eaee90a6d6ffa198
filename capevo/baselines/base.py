"""What every method of the experiment harness gets and gives back (issue 20, paper §4).

A *cell* of an experiment grid is one task × method × seed, run for a number of iterations.
The harness (:mod:`capevo.experiment`) hands a method a :class:`CellSpec` and a work directory,
and the method reports one :class:`IterationRecord` per finished iteration through ``emit``.
Every method, ours and the baselines alike, is measured the same way:

* **One budget.** :class:`Budget` fixes the training env steps a method may spend per iteration
  (learning, and for ours also the gate's episodes: everything but the held-out evaluation).
  A method spends at most that, and records the steps it actually took
  (``IterationRecord.env_steps_train``) so that parity can be checked from the raw metrics.
* **One held-out evaluation.** After every iteration the method's current policy runs
  ``budget.eval_episodes`` episodes on :meth:`CellSpec.eval_seeds`: the same seeds for every
  method of a (task, seed) pair, drawn from a range no learner, gate or live episode uses
  (:data:`HELD_OUT_SEED_BASE`), under the same task, perturbations and Φ, graded unsafe by the
  independent safety monitor (:mod:`capevo.runtime.safety_monitor`).
* **One identity metric.** ``delta_pi`` is how far the agent's decision policy moved since
  iteration 0 (paper §4.1 "Metrics", §4.4): 0 for ours by construction; for the baselines, the relative
  parameter change of the tensors the method's docstring names.

Invariants:
1. ``IterationRecord.from_dict(r.to_dict()) == r`` and ``CellSpec.from_dict(c.to_dict()) == c``.
2. :meth:`CellSpec.eval_seeds` depends only on ``seed`` and ``budget.eval_episodes`` (never on
   the method or the iteration), and never overlaps another cell seed's range.
3. Every check raises :class:`~capevo.errors.Invalid` naming the field.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, ClassVar, Protocol, runtime_checkable

from capevo.errors import Invalid

HELD_OUT_SEED_BASE = 2_000_000_000
"""Evaluation seeds of cell seed ``s`` are ``HELD_OUT_SEED_BASE + 1000 * s + j``: above every
seed plan the experiment presets use (:class:`capevo.runtime.gate.SeedPlan` base seeds up to
2024 end below 7.3e8) and above the learners' training seeds (from 1e6)."""
MAX_CELL_SEED = 99_999
MAX_EVAL_EPISODES = 1000


def _int(name: str, value: object, *, low: int, high: int = 10**12) -> int:
    if isinstance(value, bool) or not isinstance(value, int) or not low <= value <= high:
        raise Invalid(f"{name} must be an integer from {low} to {high}, got {value!r}", details={"field": name})
    return value


@dataclass(frozen=True, slots=True, kw_only=True)
class Budget:
    """What every method of a grid may spend, per iteration.

    Args:
        env_steps_per_iteration: Training env steps per iteration (paper: 50,000 per ECM per
            iteration; a monolithic method gets the same total as ours spends on the task).
        eval_episodes: Held-out evaluation episodes after every iteration (paper: 30).
        horizon: Episode length; None for the task's configured default.

    Raises:
        Invalid: a value out of range.
    """

    env_steps_per_iteration: int
    eval_episodes: int
    horizon: int | None = None

    def __post_init__(self) -> None:
        _int("budget.env_steps_per_iteration", self.env_steps_per_iteration, low=1)
        _int("budget.eval_episodes", self.eval_episodes, low=1, high=MAX_EVAL_EPISODES)
        if self.horizon is not None:
            _int("budget.horizon", self.horizon, low=1, high=100_000)

    def to_dict(self) -> dict[str, Any]:
        return {
            "env_steps_per_iteration": self.env_steps_per_iteration,
            "eval_episodes": self.eval_episodes,
            "horizon": self.horizon,
        }

    @classmethod
    def from_dict(cls, d: Mapping[str, Any]) -> Budget:
        try:
            return cls(
                env_steps_per_iteration=d["env_steps_per_iteration"],
                eval_episodes=d["eval_episodes"],
                horizon=d.get("horizon"),
            )
        except KeyError as exc:
            raise Invalid(f"budget is missing {exc.args[0]!r}", details={"field": f"budget.{exc.args[0]}"}) from None


@dataclass(frozen=True, slots=True, kw_only=True)
class CellSpec:
    """One cell of a grid: ``method`` on ``task`` with ``seed``, for ``iterations``.

    Args:
        task: Task id or name (``T1`` ... ``T6``).
        method: Method name (the harness's registry of methods).
        seed: The cell's seed: its learners' seeds and its held-out evaluation seeds.
        iterations: Iterations to run (each ends with a held-out evaluation).
        budget: What the method may spend.
        phi: The envelope every episode runs under (``"task"``, ``"paper"`` or a Φ YAML path).
        governance: Governance enforces Φ (off only for the H3 ablation; the monitor grades
            either way).
        perturbations: The paper's perturbations (object ±5 cm, obs noise σ 0.01, dropped
            actions p 0.05) on.
        options: Method-specific settings (for example ``{"algo": "sac", "warm_start": "bc"}``);
            each method documents and checks its own.

    Raises:
        Invalid: a value out of range.
    """

    task: str
    method: str
    seed: int
    iterations: int
    budget: Budget
    phi: str = "task"
    governance: bool = True
    perturbations: bool = True
    options: Mapping[str, Any] = field(default_factory=dict)

    def __post_init__(self) -> None:
        for name in ("task", "method", "phi"):
            value = getattr(self, name)
            if not isinstance(value, str) or not value:
                raise Invalid(f"{name} must be a non-empty string, got {value!r}", details={"field": name})
        _int("seed", self.seed, low=0, high=MAX_CELL_SEED)
        _int("iterations", self.iterations, low=1, high=10_000)
        if not isinstance(self.budget, Budget):
            raise Invalid("budget must be a Budget", details={"field": "budget"})
        if not isinstance(self.options, Mapping):
            raise Invalid("options must be a mapping", details={"field": "options"})

    @property
    def key(self) -> str:
        """The cell's directory name: ``<task>-<method>-s<seed>``."""
        return f"{self.task}-{self.method}-s{self.seed}"

    def eval_seeds(self) -> tuple[int, ...]:
        """The held-out evaluation seeds of this cell: the same for every method and iteration."""
        start = HELD_OUT_SEED_BASE + 1000 * self.seed
        return tuple(range(start, start + self.budget.eval_episodes))

    def to_dict(self) -> dict[str, Any]:
        return {
            "task": self.task,
            "method": self.method,
            "seed": self.seed,
            "iterations": self.iterations,
            "budget": self.budget.to_dict(),
            "phi": self.phi,
            "governance": self.governance,
            "perturbations": self.perturbations,
            "options": dict(self.options),
        }

    @classmethod
    def from_dict(cls, d: Mapping[str, Any]) -> CellSpec:
        try:
            return cls(
                task=d["task"],
                method=d["method"],
                seed=d["seed"],
                iterations=d["iterations"],
                budget=Budget.from_dict(d["budget"]),
                phi=d.get("phi", "task"),
                governance=bool(d.get("governance", True)),
                perturbations=bool(d.get("perturbations", True)),
                options=dict(d.get("options") or {}),
            )
        except KeyError as exc:
            raise Invalid(f"cell is missing {exc.args[0]!r}", details={"field": str(exc.args[0])}) from None


@dataclass(frozen=True, slots=True, kw_only=True)
class EpisodeResult:
    """One held-out evaluation episode."""

    seed: int
    success: bool
    reward: float
    steps: int
    unsafe_steps: int
    """Steps the independent safety monitor graded unsafe."""
    interventions: int
    """Steps governance changed or blocked the action."""
    strict_success: bool | None = None
    """The task's stricter check beside ``success`` (``TaskEnv.strict_success``; T6: the peg
    through the plate, where robosuite's check passes short of it); None where the task has none.
    Written only when set, so records of tasks without it read as before."""

    def to_dict(self) -> dict[str, Any]:
        d: dict[str, Any] = {
            "seed": self.seed,
            "success": self.success,
            "reward": self.reward,
            "steps": self.steps,
            "unsafe_steps": self.unsafe_steps,
            "interventions": self.interventions,
        }
        if self.strict_success is not None:
            d["strict_success"] = self.strict_success
        return d

    @classmethod
    def from_dict(cls, d: Mapping[str, Any]) -> EpisodeResult:
        return cls(
            seed=int(d["seed"]),
            success=bool(d["success"]),
            reward=float(d["reward"]),
            steps=int(d["steps"]),
            unsafe_steps=int(d["unsafe_steps"]),
            interventions=int(d["interventions"]),
            strict_success=None if d.get("strict_success") is None else bool(d["strict_success"]),
        )


@dataclass(frozen=True, slots=True, kw_only=True)
class IterationRecord:
    """One finished iteration of a cell: what was spent, and the held-out evaluation after it.

    ``success_rate``, ``reward_mean`` and ``unsafe_episodes`` are derived from ``episodes`` (so
    ``capevo experiment verify`` can recompute them); the steps are counted by the method.
    """

    iteration: int
    episodes: tuple[EpisodeResult, ...]
    env_steps_train: int
    """Training env steps this iteration actually spent (≤ the budget's)."""
    env_steps_eval: int
    """Env steps of this iteration's held-out evaluation (not part of the budget)."""
    delta_pi: float
    """Δπ of the agent's decision policy against iteration 0 (paper §4.1 "Metrics", §4.4)."""
    wall_s: float
    notes: str = ""

    @property
    def successes(self) -> int:
        return sum(e.success for e in self.episodes)

    @property
    def success_rate(self) -> float:
        return self.successes / len(self.episodes) if self.episodes else 0.0

    @property
    def reward_mean(self) -> float:
        return sum(e.reward for e in self.episodes) / len(self.episodes) if self.episodes else 0.0

    @property
    def unsafe_episodes(self) -> int:
        return sum(e.unsafe_steps > 0 for e in self.episodes)

    def to_dict(self) -> dict[str, Any]:
        return {
            "iteration": self.iteration,
            "episodes": [e.to_dict() for e in self.episodes],
            "env_steps_train": self.env_steps_train,
            "env_steps_eval": self.env_steps_eval,
            "delta_pi": self.delta_pi,
            "wall_s": self.wall_s,
            "notes": self.notes,
            # derived, written for readers of the raw file; verify recomputes them
            "success_rate": self.success_rate,
            "reward_mean": self.reward_mean,
            "unsafe_episodes": self.unsafe_episodes,
        }

    @classmethod
    def from_dict(cls, d: Mapping[str, Any]) -> IterationRecord:
        try:
            return cls(
                iteration=int(d["iteration"]),
                episodes=tuple(EpisodeResult.from_dict(e) for e in d["episodes"]),
                env_steps_train=int(d["env_steps_train"]),
                env_steps_eval=int(d["env_steps_eval"]),
                delta_pi=float(d["delta_pi"]),
                wall_s=float(d["wall_s"]),
                notes=str(d.get("notes") or ""),
            )
        except (KeyError, TypeError, ValueError) as exc:
            raise Invalid(f"bad iteration record: {exc}", details={"field": "record"}) from None


Emit = Callable[[IterationRecord], None]


@runtime_checkable
class Method(Protocol):
    """A method of the comparison (paper §4.3): ours, AM, S-ECM, SPiRL, SkiMo.

    ``name`` is the grid's name for it; ``knowledge`` is what it starts from, for the report's
    fairness column (issue 20: "methods do not start from the same knowledge").
    """

    name: ClassVar[str]
    knowledge: ClassVar[str]

    def run(self, cell: CellSpec, workdir: Path, *, emit: Emit) -> None:
        """Run ``cell`` for ``cell.iterations`` iterations, calling ``emit`` after each.

        ``workdir`` is the cell's own, empty directory (traces, registry, checkpoints).

        Resuming is optional. A method that can continue an interrupted cell from its own files
        defines ``resumes(cell) -> bool``; where it returns True, the harness calls
        ``run(cell, workdir, emit=emit, after=k)`` on the interrupted attempt's directory, whose
        first ``k`` records (``0 < k < cell.iterations``) are kept, and the method must emit
        iterations ``k + 1 ..`` only. Every other method, and every attempt after an exception,
        starts over in an empty directory.

        Raises:
            Invalid: an option the method does not know.
        """
        ...
