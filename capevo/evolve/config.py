"""Budgets of one ``capevo evolve`` run, by preset name: ``tiny`` (tests), ``cpu-small`` (the demo),
``paper``.

=================================  =============  ==============  ================
setting                            tiny           cpu-small       paper
=================================  =============  ==============  ================
iterations (default)               2              3               20
live episodes per iteration        3              6               20
episode horizon                    40             task default    task default
gate: paired held-out seeds N      4              10              30
gate thresholds                    min_n 4,       GateConfig.     GateConfig.
                                   δ 0.3          cpu_small()     standard()
monitor (window / min episodes)    6 / 3          20 / 8          50 / 20
CEM population / iterations        2 / 1          6 / 3           8 / 5
CEM episodes per candidate         1              2               4
CEM min iterations / validation    1 / none       2 / top 2 x 4   2 / top 3 x 16
ECMs learned per iteration         2 (chain)      one per task    one per task
                                                  step (chain)    step (chain)
neural learner budget              learner        learner         learner
                                   preset tiny    preset          preset paper
                                                  cpu-small
final evaluation (v0 seeds again)  yes            yes             yes
=================================  =============  ==============  ================

Every learner budget (SAC steps, BC epochs, the CEM population, iterations and episodes per
candidate) is :mod:`capevo.learner.presets`' preset of the same name, so an in-process update
and a ``capevo learner serve --preset P`` worker spend the same. One cpu-small CEM update costs at
most 6 x 3 x 2 + 2 x 4 = 44 training episodes (at least 6 x 2 x 2 + 8 = 32); a chained iteration
spends that per ECM learned plus 2 x 10 gate episodes per candidate.

Invariants:
1. :func:`make_config` returns the registered preset of that name, or raises :class:`Invalid`
   listing the valid names.
2. Every preset's config is valid (its checks pass when it is built).
3. ``EvolveConfig.from_dict(c.to_dict()) == c``.
4. :meth:`EvolveConfig.resume_mismatches` ignores ``iterations`` only: a resumed run may be
   extended or shortened, nothing else may change under it.
5. With ``env_steps_per_iteration`` set, an iteration's live, gate and learner episodes take at
   most that many env steps (the loop reserves the live episodes and each gate at the horizon
   and caps the learners with the rest); :meth:`EvolveConfig.check_budget` refuses a budget
   that cannot cover one update.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any

from capevo.errors import Invalid
from capevo.runtime.envelope import DEFAULT_PHI, PHI_PAPER, check_phi_choice
from capevo.runtime.gate import GateConfig
from capevo.runtime.monitor import MonitorConfig

if TYPE_CHECKING:
    from capevo.learner.search import CemConfig

SINGLE_MODALITIES: tuple[str, ...] = ("code", "rl", "il", "hybrid")
"""How candidates are learned: CEM over a code skill's parameters, SAC, behaviour cloning, or an
LLM edit followed by CEM."""
COMBINED_MODALITIES: tuple[str, ...] = ("il+rl", "hybrid+rl", "hybrid+il", "hybrid+il+rl")
"""The paper's combined rows of Table 8 (§4.6): the modalities named take turns, one iteration
each, in the order written (:class:`capevo.evolve.learners.TurnUpdater`)."""
MODALITIES: tuple[str, ...] = SINGLE_MODALITIES + COMBINED_MODALITIES
NEURAL_MODALITIES: frozenset[str] = frozenset({"rl", "il", "il+rl"})
"""Modalities whose version 0 is a randomly initialised neural policy (every part is neural)."""


def modality_parts(modality: str) -> tuple[str, ...]:
    """The single modalities of ``modality``, in turn order (one for a single modality)."""
    return tuple(modality.split("+"))


def _int(name: str, value: object, *, low: int, high: int = 10**9) -> int:
    if isinstance(value, bool) or not isinstance(value, int) or not low <= value <= high:
        raise Invalid(f"{name} must be an integer from {low} to {high}, got {value!r}", details={"field": name})
    return value


@dataclass(frozen=True, slots=True, kw_only=True)
class CemSettings:
    """The CEM search a ``code`` (or ``hybrid``) update runs (see :class:`capevo.learner.search.CemSearch`).

    Args:
        population: Candidates per CEM iteration (the first is the parent's θ).
        elite_frac: Fraction the Gaussian is refitted to.
        iterations: CEM iterations at most.
        episodes_per_candidate: Training episodes per candidate.
        sigma_init: Initial standard deviation, in units of each parameter's scale.
        validate_top: How many of the last CEM iteration's best candidates are validated.
        validation_episodes: Extra training episodes for each of them (0: no validation); the
            candidate is the best on all its episodes, not the luckiest of one small batch.
        min_iterations: CEM iterations run before a search may stop early (its best candidate
            got every episode past the ECM): one lucky batch of 2 episodes is not evidence.
        tie_siblings: Search one parameter set for an ECM and its siblings
            (:func:`capevo.learner.skills.siblings`: T5's same step for its other objects),
            evaluated and published together; ``code`` modality only. Off by default, as in
            every run before it.

    Raises:
        Invalid: a value out of range.
    """

    population: int = 8
    elite_frac: float = 0.25
    iterations: int = 3
    episodes_per_candidate: int = 4
    sigma_init: float = 1.0
    validate_top: int = 2
    validation_episodes: int = 0
    min_iterations: int = 1
    tie_siblings: bool = False

    def __post_init__(self) -> None:
        if not isinstance(self.tie_siblings, bool):
            raise Invalid(
                f"cem.tie_siblings must be true or false, got {self.tie_siblings!r}",
                details={"field": "cem.tie_siblings"},
            )
        # the search's own checks, reported under this config's field names
        try:
            self.search_config()
        except Invalid as exc:
            name = f"cem.{exc.details.get('field', '')}"
            raise Invalid(f"cem.{exc.message}", details={"field": name}) from None

    def search_config(
        self, *, seed: int = 0, max_env_steps: int | None = None, episode_steps_max: int | None = None
    ) -> CemConfig:
        """The :class:`~capevo.learner.search.CemConfig` one update searches with (sampler ``seed``;
        at most ``max_env_steps`` env steps with episodes of up to ``episode_steps_max``).

        Raises:
            Invalid: a value out of range.
        """
        from capevo.learner.search import CemConfig

        return CemConfig(
            population=self.population,
            elite_frac=self.elite_frac,
            iterations=self.iterations,
            episodes_per_candidate=self.episodes_per_candidate,
            sigma_init=self.sigma_init,
            validate_top=self.validate_top,
            validation_episodes=self.validation_episodes,
            min_iterations=min(self.min_iterations, self.iterations),
            seed=seed,
            max_env_steps=max_env_steps,
            episode_steps_max=episode_steps_max if max_env_steps is not None else None,
        )

    @property
    def train_seeds_per_update(self) -> int:
        """Training seeds one search uses (each CEM iteration takes a fresh slice, validation
        another)."""
        return self.iterations * self.episodes_per_candidate + self.validation_episodes

    @property
    def episodes_per_update(self) -> int:
        """Training episodes one search runs at most."""
        search = self.population * self.iterations * self.episodes_per_candidate
        return search + min(self.validate_top, self.population) * self.validation_episodes

    def to_dict(self) -> dict[str, Any]:
        return {
            "population": self.population,
            "elite_frac": self.elite_frac,
            "iterations": self.iterations,
            "episodes_per_candidate": self.episodes_per_candidate,
            "sigma_init": self.sigma_init,
            "validate_top": self.validate_top,
            "validation_episodes": self.validation_episodes,
            "min_iterations": self.min_iterations,
            "tie_siblings": self.tie_siblings,
        }

    @classmethod
    def from_dict(cls, d: Mapping[str, Any]) -> CemSettings:
        return cls(**{k: d[k] for k in cls.__dataclass_fields__ if k in d})

    @classmethod
    def of_learner_preset(cls, name: str, **changes: Any) -> CemSettings:
        """The CEM budget of learner preset ``name`` (:mod:`capevo.learner.presets`), with ``changes``."""
        from capevo.learner.presets import make_preset

        p = make_preset(name)
        base = {
            "population": p.cem_population,
            "iterations": p.cem_iterations,
            "episodes_per_candidate": p.cem_episodes,
        }
        return cls(**{**base, **changes})


@dataclass(frozen=True, slots=True, kw_only=True)
class EvolveConfig:
    """Everything fixed about one evolution run.

    Args:
        preset: The preset this config came from (recorded in the report).
        iterations: Closed-loop iterations to run.
        live_episodes: Live (deployment) episodes per iteration: the experience and the metrics.
        gate_episodes: Paired held-out seeds N per gate decision.
        horizon: Episode length; None for each task's default.
        step_budget_per_ecm: Steps one ECM activation may take.
        gate: The gate's decision thresholds.
        monitor: The degradation monitor's window and threshold.
        cem: The CEM search of code/hybrid updates.
        learner_preset: Name of the neural learners' budget (:mod:`capevo.learner.presets`).
        final_evaluation: After the last iteration, run the final capability set on the first
            iteration's live seeds (a paired start-vs-final comparison).
        updates_per_iteration: How many ECMs one iteration may learn in sequence (a chain:
            each is learned behind the previous ones' candidates, on the ECM where the previous
            candidate's own training episodes still fail); 0 means as many as the task's
            decomposition has steps, 1 is one ECM per iteration. Code modalities only.
        phi: The safety envelope every episode of the run (live, learner, gate, final) runs
            under, fixed for the run: ``"task"`` (default: the task's scene-aware Φ),
            ``"paper"`` (the paper's Φ alone) or a Φ YAML path (:mod:`capevo.runtime.envelope`).
        env_steps_per_iteration: Env steps one iteration may spend on live, gate and learner
            episodes together (issue 20: every method of a comparison gets the same budget);
            None for no cap. The live episodes and a gate per update are reserved at the horizon
            (:meth:`step_reserve`), the learner gets what is left (a CEM step cap, SAC's total
            steps). Checked against a task by :meth:`learner_step_cap`.

    Raises:
        Invalid: a value out of range.
    """

    preset: str
    iterations: int
    live_episodes: int
    gate_episodes: int
    horizon: int | None = None
    step_budget_per_ecm: int = 200
    gate: GateConfig = field(default_factory=GateConfig)
    monitor: MonitorConfig = field(default_factory=MonitorConfig)
    cem: CemSettings = field(default_factory=CemSettings)
    learner_preset: str = "paper"
    final_evaluation: bool = True
    updates_per_iteration: int = 1
    phi: str = DEFAULT_PHI
    env_steps_per_iteration: int | None = None

    def __post_init__(self) -> None:
        check_phi_choice(self.phi)
        if self.env_steps_per_iteration is not None:
            _int("env_steps_per_iteration", self.env_steps_per_iteration, low=1, high=10**12)
        _int("iterations", self.iterations, low=0, high=100_000)
        _int("updates_per_iteration", self.updates_per_iteration, low=0, high=10_000)
        _int("live_episodes", self.live_episodes, low=1, high=10_000)
        _int("gate_episodes", self.gate_episodes, low=1, high=10_000)
        if self.horizon is not None:
            _int("horizon", self.horizon, low=1, high=1_000_000)
        _int("step_budget_per_ecm", self.step_budget_per_ecm, low=1, high=1_000_000)
        if not isinstance(self.gate, GateConfig):
            raise Invalid("gate must be a GateConfig", details={"field": "gate"})
        if not isinstance(self.monitor, MonitorConfig):
            raise Invalid("monitor must be a MonitorConfig", details={"field": "monitor"})
        if not isinstance(self.cem, CemSettings):
            raise Invalid("cem must be a CemSettings", details={"field": "cem"})
        if self.gate_episodes < self.gate.min_n:
            raise Invalid(
                f"gate_episodes ({self.gate_episodes}) is below the gate's min_n ({self.gate.min_n}): "
                "no candidate could ever be promoted",
                details={"field": "gate_episodes"},
            )
        from capevo.learner.presets import preset_names

        if self.learner_preset not in preset_names():
            raise Invalid(
                f"unknown learner preset {self.learner_preset!r}; valid: {', '.join(preset_names())}",
                details={"field": "learner_preset"},
            )

    def replace(self, **changes: Any) -> EvolveConfig:
        """A copy with ``changes`` applied (validated again)."""
        return dataclasses.replace(self, **changes)

    def to_dict(self) -> dict[str, Any]:
        return {
            "preset": self.preset,
            "iterations": self.iterations,
            "live_episodes": self.live_episodes,
            "gate_episodes": self.gate_episodes,
            "horizon": self.horizon,
            "step_budget_per_ecm": self.step_budget_per_ecm,
            "gate": self.gate.to_dict(),
            "monitor": self.monitor.to_dict(),
            "cem": self.cem.to_dict(),
            "learner_preset": self.learner_preset,
            "final_evaluation": self.final_evaluation,
            "updates_per_iteration": self.updates_per_iteration,
            "phi": self.phi,
            "env_steps_per_iteration": self.env_steps_per_iteration,
        }

    @classmethod
    def from_dict(cls, d: Mapping[str, Any]) -> EvolveConfig:
        """Inverse of :meth:`to_dict`.

        Raises:
            Invalid: a missing or bad field.
        """
        try:
            return cls(
                preset=str(d["preset"]),
                iterations=d["iterations"],
                live_episodes=d["live_episodes"],
                gate_episodes=d["gate_episodes"],
                horizon=d.get("horizon"),
                step_budget_per_ecm=d.get("step_budget_per_ecm", 200),
                gate=GateConfig.from_dict(d.get("gate") or {}),
                monitor=MonitorConfig(**dict(d.get("monitor") or {})),
                cem=CemSettings.from_dict(d.get("cem") or {}),
                learner_preset=d.get("learner_preset", "paper"),
                final_evaluation=bool(d.get("final_evaluation", True)),
                updates_per_iteration=d.get("updates_per_iteration", 1),
                # Runs recorded before the envelope was a setting ran under the paper's Φ.
                phi=d.get("phi", PHI_PAPER),
                env_steps_per_iteration=d.get("env_steps_per_iteration"),
            )
        except (KeyError, TypeError) as exc:
            raise Invalid(f"bad evolve config: {exc}", details={"field": "config"}) from None

    def episode_steps_max(self, task: str) -> int:
        """Most env steps one episode of ``task`` can take under this config (its horizon)."""
        from capevo.runtime.tasks import task_spec

        return int(self.horizon if self.horizon is not None else task_spec(task).default_horizon)

    def step_reserve(self, task: str, *, updates: int = 1) -> int:
        """Env steps reserved for one iteration's live episodes and the gates of ``updates``
        candidates (both sides of each pair), every episode at the horizon."""
        h = self.episode_steps_max(task)
        return self.live_episodes * h + updates * 2 * self.gate_seeds_max * h

    @property
    def gate_seeds_max(self) -> int:
        """Paired seeds one gate decision may use: N, plus a second look's (``gate.extend_n``)."""
        return self.gate_episodes + self.gate.extend_n

    def learner_step_cap(self, task: str, *, updates: int = 1) -> int | None:
        """Env steps the learners of one iteration may spend on ``task`` (None: no cap).

        Raises:
            Invalid: :attr:`env_steps_per_iteration` cannot cover the live episodes and one gate
                at the horizon (the message gives the numbers).
        """
        if self.env_steps_per_iteration is None:
            return None
        reserve = self.step_reserve(task, updates=updates)
        if self.env_steps_per_iteration <= reserve:
            h = self.episode_steps_max(task)
            raise Invalid(
                f"env_steps_per_iteration ({self.env_steps_per_iteration}) cannot cover one iteration's "
                f"{self.live_episodes} live and {updates} x 2 x {self.gate_seeds_max} gate episodes of up to "
                f"{h} steps ({reserve} steps) and leave any for learning",
                details={"field": "env_steps_per_iteration"},
            )
        return self.env_steps_per_iteration - reserve

    def smallest_update(self, task: str, *, modality: str) -> int:
        """Env steps one learner needs at the least: one CEM candidate's episodes at the horizon
        (code modalities), one SAC step (neural)."""
        if all(part in NEURAL_MODALITIES for part in modality_parts(modality)):
            return 1
        return self.cem.episodes_per_candidate * self.episode_steps_max(task)

    def check_budget(self, task: str, *, modality: str) -> None:
        """Check that :attr:`env_steps_per_iteration` covers one iteration of ``task``.

        Raises:
            Invalid: it cannot cover the live episodes, one gate and the smallest update, all
                at the horizon (the message gives the numbers).
        """
        cap = self.learner_step_cap(task)
        need = self.smallest_update(task, modality=modality)
        if cap is not None and cap < need:
            raise Invalid(
                f"env_steps_per_iteration ({self.env_steps_per_iteration}) leaves {cap} env steps for learning "
                f"after the live episodes and one gate at the horizon ({self.step_reserve(task)} steps), "
                f"fewer than one update needs ({need})",
                details={"field": "env_steps_per_iteration"},
            )

    def resume_mismatches(self, other: EvolveConfig) -> list[str]:
        """Fields (other than ``iterations``) where ``other`` differs from this config."""
        mine, theirs = self.to_dict(), other.to_dict()
        return sorted(k for k in mine if k != "iterations" and mine[k] != theirs.get(k))


_PRESETS: dict[str, Callable[[], EvolveConfig]] = {}


def register_config(name: str) -> Callable[[Callable[[], EvolveConfig]], Callable[[], EvolveConfig]]:
    """Decorator: register an :class:`EvolveConfig` factory as preset ``name``."""

    def deco(fn: Callable[[], EvolveConfig]) -> Callable[[], EvolveConfig]:
        _PRESETS[name] = fn
        return fn

    return deco


def config_names() -> tuple[str, ...]:
    """Registered preset names."""
    return tuple(_PRESETS)


def make_config(name: str, **overrides: Any) -> EvolveConfig:
    """The preset called ``name``, with ``overrides`` (``None`` values are ignored).

    Raises:
        Invalid: unknown name (the message lists the valid ones) or a bad override.
    """
    factory = _PRESETS.get(name)
    if factory is None:
        raise Invalid(f"unknown preset {name!r}; valid: {', '.join(_PRESETS)}", details={"field": "preset"})
    config = factory()
    changes = {k: v for k, v in overrides.items() if v is not None}
    unknown = sorted(set(changes) - set(EvolveConfig.__dataclass_fields__))
    if unknown:
        raise Invalid(f"unknown config field(s) {unknown}", details={"field": unknown[0]})
    return config.replace(**changes) if changes else config


@register_config("tiny")
def _tiny() -> EvolveConfig:
    return EvolveConfig(
        preset="tiny",
        iterations=2,
        live_episodes=3,
        gate_episodes=4,
        horizon=40,
        step_budget_per_ecm=40,
        gate=GateConfig(min_n=4, alpha=0.05, delta=0.3, max_slowdown=None, first_min_success=0.5),
        monitor=MonitorConfig(window=6, min_episodes=3, margin=0.1),
        cem=CemSettings.of_learner_preset("tiny", elite_frac=0.5),
        learner_preset="tiny",
        updates_per_iteration=2,
    )


@register_config("cpu-small")
def _cpu_small() -> EvolveConfig:
    return EvolveConfig(
        preset="cpu-small",
        iterations=3,
        live_episodes=6,
        gate_episodes=10,
        gate=GateConfig.cpu_small(),
        monitor=MonitorConfig.cpu_small(),
        cem=CemSettings.of_learner_preset("cpu-small", elite_frac=0.34, validation_episodes=4, min_iterations=2),
        learner_preset="cpu-small",
        updates_per_iteration=0,
    )


@register_config("paper")
def _paper() -> EvolveConfig:
    return EvolveConfig(
        preset="paper",
        iterations=20,
        live_episodes=20,
        gate_episodes=30,
        gate=GateConfig.standard(),
        monitor=MonitorConfig(),
        cem=CemSettings.of_learner_preset("paper", validate_top=3, validation_episodes=16, min_iterations=2),
        learner_preset="paper",
        updates_per_iteration=0,
    )


__all__ = [
    "COMBINED_MODALITIES",
    "MODALITIES",
    "NEURAL_MODALITIES",
    "SINGLE_MODALITIES",
    "CemSettings",
    "EvolveConfig",
    "config_names",
    "make_config",
    "modality_parts",
    "register_config",
]
