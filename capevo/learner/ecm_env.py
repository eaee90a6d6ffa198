"""The environment a neural ECM learns in: one step of a task's decomposition, as it runs for real.

Choice of training setting, and why: an ECM is an *option*. At run time it starts in the
state its predecessor left (the predecessor's termination predicate held, or its budget ran
out), it sees only its interface inputs, every action goes through governance, and it ends
when its own termination predicate holds. :class:`EcmEnv` reproduces exactly that:

* ``reset`` resets the task with a training seed and drives the predecessors of the ECM in
  the task's decomposition (their *active* versions, loaded like the runtime loads them) one
  after the other, each until its termination predicate holds, it ends itself, or
  ``prefix_budget`` steps pass; then the ECM takes over. The first ECM of a decomposition
  starts right after the reset. If the task episode ends during the prefix (it cannot with the
  horizon :func:`make_ecm_env` sets, but a custom one might), the next seed is tried.
* the observation is the ECM's interface inputs, concatenated in interface order as float32
  (what :class:`~capevo.runtime.ecm.neural.NeuralPolicy` feeds a policy);
* the action (clipped to [-1, 1]) goes through the governor of Φ; ⊥ becomes the hold action;
* the reward is the task's dense reward (add :mod:`capevo.learner.reward`'s shaping on top);
* ``terminated`` when the ECM's termination predicate holds (an empty predicate: when the
  task succeeds), ``truncated`` after ``max_steps`` ECM steps (the runtime's per-ECM budget).

Training on the whole task instead would ask every ECM to solve every step with inputs meant
for one; training on its own step from the predecessors' real end states gives each ECM the
state distribution it will meet and credit only for its own job.

``info`` after every step: ``is_success`` (the ECM's termination reached; latched),
``task_success``, ``retries`` (times the ECM's applicability predicate stopped holding after it
held: the runtime's policy would have re-planned), ``interventions`` (governance, this
episode), ``prefix_steps``, ``ecm_steps`` and ``task_seed``. :attr:`EcmEnv.env_steps` counts every
simulated step since the environment was made, the predecessors' (retried prefixes too) and the
ECM's: what a learner that uses it has spent of an env-step budget.

Invariants:
1. Observations are float32 of shape ``(sum of input sizes,)``; actions outside [-1, 1] are
   clipped before governance.
2. ``terminated`` and ``truncated`` are never both true; ``terminated`` implies ``is_success``.
3. Episode ``k`` after ``reset(seed=s)`` runs task seed ``seed_base + s + k``; without any
   seed, ``seed_base + config.seed + k``. Training seeds therefore never collide with the
   small seeds gates and tests use (see :data:`capevo.learner.presets.TRAIN_SEED_BASE`).
4. ``close`` releases the task environment and the predecessors it owns; it is idempotent.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any, Protocol, runtime_checkable

import gymnasium as gym
import numpy as np

from capevo.errors import Invalid, NotFound
from capevo.records import Descriptor, EcmVersion, Interface, IOSpec, Kind, Predicate
from capevo.registry.api import Registry
from capevo.registry.predicates import predicate_holds
from capevo.runtime.ecm.marshal import flatten_inputs, marshal_inputs, spec_size
from capevo.runtime.envelope import DEFAULT_PHI, check_phi_choice, resolve_phi
from capevo.runtime.tasks import Perturbations, TaskEnv, TaskSpec, make_task, task_spec
from capevo.runtime.tasks.spec import EcmStep

DEFAULT_TRAIN_SEED_BASE = 1_000_000
"""Task seeds of training episodes start here (gate and test seeds are small)."""
MAX_PREFIX_RETRIES = 5


def _positive_int(name: str, value: object) -> int:
    if isinstance(value, bool) or not isinstance(value, int) or value < 1:
        raise Invalid(f"{name} must be a positive integer, got {value!r}", details={"field": name})
    return value


@dataclass(frozen=True, slots=True, kw_only=True)
class EcmEnvConfig:
    """How an ECM's training episodes run.

    Args:
        max_steps: ECM steps per episode (the runtime's per-ECM step budget).
        prefix_budget: Steps each predecessor may take before the ECM takes over anyway.
        governance: Govern every action with Φ.
        phi: Which Φ governs: ``"task"`` (the task's scene-aware envelope, the runtime's
            default), ``"paper"`` or a Φ YAML path (see :mod:`capevo.runtime.envelope`); an
            :class:`EcmEnv` given a ``phi`` object uses that instead.
        perturbations: Task perturbations; default all on (the benchmark setting).
        seed: First training seed offset (see invariant 3).
        seed_base: Added to every training seed.
        prefix_timeout_s: Per-call compute limit of predecessor ECMs.

    Raises:
        Invalid: a non-positive budget, a negative seed.
    """

    max_steps: int = 200
    prefix_budget: int = 200
    governance: bool = True
    phi: str = DEFAULT_PHI
    perturbations: Perturbations = field(default_factory=Perturbations)
    seed: int = 0
    seed_base: int = DEFAULT_TRAIN_SEED_BASE
    prefix_timeout_s: float = 0.5

    def __post_init__(self) -> None:
        _positive_int("max_steps", self.max_steps)
        _positive_int("prefix_budget", self.prefix_budget)
        for name in ("seed", "seed_base"):
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, int) or v < 0:
                raise Invalid(f"{name} must be a non-negative integer, got {v!r}", details={"field": name})
        if not isinstance(self.perturbations, Perturbations):
            raise Invalid("perturbations must be a Perturbations", details={"field": "perturbations"})
        check_phi_choice(self.phi)
        t = self.prefix_timeout_s
        if isinstance(t, bool) or not isinstance(t, (int, float)) or not math.isfinite(t) or t <= 0:
            raise Invalid(
                f"prefix_timeout_s must be a positive number, got {t!r}", details={"field": "prefix_timeout_s"}
            )

    def to_dict(self) -> dict[str, Any]:
        p = self.perturbations
        return {
            "max_steps": self.max_steps,
            "prefix_budget": self.prefix_budget,
            "governance": self.governance,
            "phi": self.phi,
            "perturbations": {
                "object_position_jitter": p.object_position_jitter,
                "obs_position_noise_std": p.obs_position_noise_std,
                "actuation_failure_p": p.actuation_failure_p,
            },
            "seed": self.seed,
            "seed_base": self.seed_base,
            "prefix_timeout_s": self.prefix_timeout_s,
        }


@runtime_checkable
class Driver(Protocol):
    """Runs one predecessor ECM during the prefix of an :class:`EcmEnv` episode."""

    name: str
    termination: Predicate

    def start(self) -> None:
        """Begin a fresh activation (budget and recovery state at zero)."""
        ...

    def act(self, obs: Mapping[str, np.ndarray]) -> np.ndarray | None:
        """The action for the raw observation dict, or None when the ECM is over."""
        ...

    def close(self) -> None: ...


class InvokerDriver:
    """A :class:`Driver` running a loaded registry version through the runtime's invoker.

    Args:
        caps: The loaded predecessors (a :class:`~capevo.runtime.capabilities.LoadedCapabilitySet`).
        name: Which of them.
        step_budget: Steps per activation.
        timeout_s: Per-call compute limit.
    """

    def __init__(self, caps: Any, name: str, *, step_budget: int, timeout_s: float) -> None:
        self.name = name
        self.termination = caps.records[name].descriptor.termination
        self._caps = caps
        self._budget = step_budget
        self._timeout = timeout_s
        self._invoker: Any = None

    def start(self) -> None:
        self._invoker = self._caps.make_invoker(self.name, step_budget=self._budget, timeout_s=self._timeout)

    def act(self, obs: Mapping[str, np.ndarray]) -> np.ndarray | None:
        if self._invoker is None:
            self.start()
        result = self._invoker.step(obs)
        return None if result.action is None else np.asarray(result.action, dtype=np.float64)

    def close(self) -> None:
        """The capability set is closed by its owner."""


@dataclass(frozen=True, slots=True, kw_only=True)
class EcmTarget:
    """The ECM being learned: its name, interface and descriptor."""

    name: str
    interface: Interface
    descriptor: Descriptor

    @property
    def input_size(self) -> int:
        return sum(spec_size(s) for s in self.interface.inputs)


def step_of(task: str | TaskSpec, ecm: str) -> EcmStep:
    """The decomposition step of ``ecm`` in ``task``.

    Raises:
        Invalid: ``ecm`` is not in the task's decomposition (lists the valid names).
    """
    spec = task if isinstance(task, TaskSpec) else task_spec(task)
    for step in spec.decomposition:
        if step.ecm == ecm:
            return step
    raise Invalid(
        f"task {spec.name!r} has no ECM {ecm!r}; valid: {', '.join(spec.ecm_names)}", details={"field": "ecm"}
    )


def default_interface(task: str | TaskSpec, ecm: str) -> Interface:
    """The interface a built-in ECM of ``task`` has: the step's observation keys in, one bounded action out."""
    from capevo.learner.skills._lib import interface_for

    spec = task if isinstance(task, TaskSpec) else task_spec(task)
    return interface_for(step_of(spec, ecm), spec)


def target_for(task: str | TaskSpec, ecm: str, parent: EcmVersion | None = None) -> EcmTarget:
    """The :class:`EcmTarget` of ``ecm``: the parent's descriptor, and its interface when that
    declares inputs and outputs (a neural policy needs both), else the step's default one.

    Raises:
        Invalid: ``ecm`` is not in the task's decomposition.
    """
    spec = task if isinstance(task, TaskSpec) else task_spec(task)
    step = step_of(spec, ecm)
    interface = default_interface(spec, ecm)
    descriptor = step.descriptor()
    if parent is not None:
        descriptor = parent.descriptor
        if parent.interface.inputs and parent.interface.outputs:
            interface = parent.interface
    return EcmTarget(name=ecm, interface=interface, descriptor=descriptor)


def ecm_observation(obs: Mapping[str, np.ndarray], inputs: Sequence[IOSpec], *, ecm: str = "ecm") -> np.ndarray:
    """The ECM's flat float32 observation from a raw observation dict."""
    return flatten_inputs(marshal_inputs(obs, inputs, ecm=ecm), inputs)


class EcmEnv(gym.Env[np.ndarray, np.ndarray]):
    """One ECM's step of a task as a gymnasium environment (see the module docstring).

    Args:
        task_env: The task environment (owned: closed with this one unless ``own_task_env``
            is False).
        target: The ECM being learned.
        predecessors: Drivers of the ECMs before it in the decomposition, in order.
        config: Budgets, governance, seeds.
        phi: Safety envelope; default ``config.phi`` resolved for the task.
        on_close: Called once by :meth:`close` (releases what built the predecessors).
        own_task_env: Close ``task_env`` in :meth:`close`.

    Raises:
        Invalid: the ECM's interface declares no inputs, or outputs that are not one action
            of the task's dimension.
    """

    metadata: dict[str, Any] = {"render_modes": []}  # noqa: RUF012 - gymnasium's class attribute

    def __init__(
        self,
        task_env: TaskEnv,
        target: EcmTarget,
        *,
        predecessors: Sequence[Driver] = (),
        config: EcmEnvConfig | None = None,
        phi: Any = None,
        on_close: Callable[[], Any] | None = None,
        own_task_env: bool = True,
    ) -> None:
        self.task_env = task_env
        self.target = target
        self.config = config or EcmEnvConfig()
        self.predecessors = tuple(predecessors)
        spec = task_env.task_spec
        if not target.interface.inputs:
            raise Invalid(f"{target.name}: a neural ECM needs declared interface inputs", details={"field": "inputs"})
        outputs = target.interface.outputs
        if outputs and sum(spec_size(s) for s in outputs) != spec.action_layout.dim:
            raise Invalid(
                f"{target.name}: interface outputs do not make one action of task {spec.name!r} "
                f"({spec.action_layout.dim} values)",
                details={"field": "outputs"},
            )
        self.observation_space = gym.spaces.Box(-np.inf, np.inf, shape=(target.input_size,), dtype=np.float32)
        self.action_space = gym.spaces.Box(-1.0, 1.0, shape=(spec.action_layout.dim,), dtype=np.float32)
        self._layout = spec.action_layout
        self._governor = None
        if self.config.governance:
            from capevo.runtime.episode import make_governor

            self._governor = make_governor(task_env, resolve_phi(phi if phi is not None else self.config.phi, task_env))
        self._on_close = on_close
        self._own_task_env = own_task_env
        self._next_seed = self.config.seed_base + self.config.seed
        self._last_action: tuple[float, ...] | None = None
        self._steps = 0
        self._prefix_steps = 0
        self.env_steps = 0
        """Every simulated step since this environment was made (prefixes included)."""
        self._success = False
        self._task_success = False
        self._applicable = False
        self._retries = 0
        self._interventions = 0
        self._task_seed = -1
        self._closed = False

    # --- properties ---------------------------------------------------------------------

    @property
    def control_dt(self) -> float:
        """Simulated seconds per step (1 / robosuite's control frequency)."""
        return 1.0 / float(self.task_env.robosuite_env.control_freq)

    @property
    def obs_dict(self) -> Mapping[str, np.ndarray]:
        """The task's raw observation dict now (for scripted controllers)."""
        return self.task_env.obs_dict

    def signals(self) -> dict[str, float]:
        return self.task_env.signals()

    # --- stepping -----------------------------------------------------------------------

    def _observation(self) -> np.ndarray:
        return ecm_observation(self.task_env.obs_dict, self.target.interface.inputs, ecm=self.target.name)

    def _execute(self, action: np.ndarray) -> tuple[float, bool, bool, dict[str, Any], int]:
        """Govern and apply one action; returns reward, terminated, truncated, info, interventions."""
        proposed = np.clip(np.asarray(action, dtype=np.float64), -1.0, 1.0)
        executed: Any = proposed
        n = 0
        if self._governor is not None:
            from capevo.runtime.governance import hold_action

            governed, records = self._governor(self.task_env.robot_state(), proposed)
            n = len(records)
            executed = hold_action(self._layout, self._last_action) if governed is None else governed
        executed = np.asarray(executed, dtype=np.float64)
        self._last_action = tuple(float(x) for x in executed)
        _, reward, terminated, truncated, info = self.task_env.step(executed)
        self.env_steps += 1
        return float(reward), bool(terminated), bool(truncated), info, n

    def _holds(self, predicate: Predicate) -> bool:
        return predicate_holds(predicate, self.task_env.signals())

    def _run_prefix(self) -> bool:
        """Drive the predecessors; False when the task episode ended during the prefix."""
        for driver in self.predecessors:
            driver.start()
            for _ in range(self.config.prefix_budget):
                if driver.termination.all and self._holds(driver.termination):
                    break
                action = driver.act(self.task_env.obs_dict)
                if action is None:
                    break
                _, terminated, truncated, _, _ = self._execute(action)
                self._prefix_steps += 1
                if terminated or truncated:
                    return False
        return True

    def reset(self, *, seed: int | None = None, options: dict[str, Any] | None = None) -> tuple[np.ndarray, dict]:
        """Reset the task and run the predecessors; returns the ECM's first observation.

        Raises:
            Invalid: a bad seed. NotFound: the task episode ended during the prefix on
                :data:`MAX_PREFIX_RETRIES` seeds in a row.
        """
        if self._closed:
            raise Invalid("this ECM environment is closed")
        super().reset(seed=seed)
        if seed is not None:
            if isinstance(seed, bool) or not isinstance(seed, (int, np.integer)) or seed < 0:
                raise Invalid(f"seed must be a non-negative integer, got {seed!r}", details={"field": "seed"})
            self._next_seed = self.config.seed_base + int(seed)
        for _ in range(MAX_PREFIX_RETRIES):
            self._task_seed = self._next_seed
            self._next_seed += 1
            self.task_env.reset(seed=self._task_seed)
            if self._governor is not None:
                self._governor.new_episode()
            self._last_action = None
            self._prefix_steps = 0
            if self._run_prefix():
                break
        else:
            raise NotFound(
                f"{self.target.name}: the task episode ended before the ECM could take over on "
                f"{MAX_PREFIX_RETRIES} seeds in a row; raise the horizon or lower prefix_budget"
            )
        self._steps = 0
        self._success = False
        self._task_success = bool(self.task_env.is_success)
        self._retries = 0
        self._interventions = 0
        applicability = self.target.descriptor.applicability
        self._applicable = self._holds(applicability) if applicability.all else True
        return self._observation(), self._info()

    def step(self, action: np.ndarray) -> tuple[np.ndarray, float, bool, bool, dict]:
        """One ECM step: clip, govern, apply; see the module docstring for the signals."""
        if self._closed:
            raise Invalid("this ECM environment is closed")
        reward, task_terminated, task_truncated, info, n = self._execute(action)
        self._steps += 1
        self._interventions += n
        task_success_now = bool(info.get("is_success", False)) and not self._task_success
        self._task_success = self._task_success or bool(info.get("is_success", False))
        descriptor = self.target.descriptor
        done = self._holds(descriptor.termination) if descriptor.termination.all else task_success_now
        if descriptor.applicability.all:
            applicable = self._holds(descriptor.applicability)
            if self._applicable and not applicable:
                self._retries += 1
            self._applicable = applicable
        self._success = self._success or done
        terminated = done
        truncated = not terminated and (self._steps >= self.config.max_steps or task_terminated or task_truncated)
        return self._observation(), reward, terminated, truncated, self._info()

    def _info(self) -> dict[str, Any]:
        return {
            "is_success": self._success,
            "task_success": self._task_success,
            "retries": self._retries,
            "interventions": self._interventions,
            "prefix_steps": self._prefix_steps,
            "ecm_steps": self._steps,
            "task_seed": self._task_seed,
        }

    def close(self) -> None:
        """Release the task environment (when owned) and the predecessors. Idempotent."""
        if self._closed:
            return
        self._closed = True
        for driver in self.predecessors:
            driver.close()
        if self._on_close is not None:
            self._on_close()
        if self._own_task_env:
            self.task_env.close()


def make_ecm_env(
    task: str,
    target: EcmTarget,
    *,
    registry: Registry | None = None,
    predecessors: Sequence[Driver] | None = None,
    config: EcmEnvConfig | None = None,
    phi: Any = None,
    env_kwargs: Mapping[str, Any] | None = None,
) -> EcmEnv:
    """Build the training environment of ``target`` in ``task`` (about a second).

    The predecessors are, unless given, the ECMs before ``target`` in the task's decomposition
    at their active versions in ``registry`` (loaded with the runtime's loaders and trust
    policy: untrusted code runs sandboxed).

    Args:
        task: Task id or name.
        target: The ECM being learned.
        registry: Where the predecessors come from; needed when ``target`` is not the first step
            and ``predecessors`` is None.
        predecessors: Drivers to use instead of the registry's versions.
        config: Budgets, governance, perturbations, seeds.
        phi: Safety envelope; default ``config.phi`` resolved for the task.
        env_kwargs: Extra robosuite arguments.

    Returns:
        The environment (close it when done).

    Raises:
        Invalid: ``target`` not in the task, or predecessors needed but no registry given.
        NotFound: a predecessor has no active version.
    """
    cfg = config or EcmEnvConfig()
    spec = task_spec(task)
    step_of(spec, target.name)
    before = spec.ecm_names[: spec.ecm_names.index(target.name)]
    caps = None
    drivers: list[Driver]
    if predecessors is not None:
        drivers = list(predecessors)
    elif not before:
        drivers = []
    else:
        if registry is None:
            raise Invalid(
                f"{target.name} runs after {', '.join(before)}; give a registry to load them from",
                details={"field": "registry"},
            )
        from capevo.runtime.capabilities import LoadedCapabilitySet

        caps = LoadedCapabilitySet(registry, spec.name, ecms=before)
        for name in before:
            if caps.records[name].kind is Kind.PROMPT:
                caps.close()
                raise Invalid(f"{name} is a prompt ECM and cannot drive the prefix", details={"field": name})
        drivers = [
            InvokerDriver(caps, name, step_budget=cfg.prefix_budget, timeout_s=cfg.prefix_timeout_s) for name in before
        ]
    horizon = len(drivers) * cfg.prefix_budget + cfg.max_steps + 1
    try:
        task_env = make_task(
            spec.name,
            perturbations=cfg.perturbations,
            horizon=horizon,
            terminate_on_success=False,
            **dict(env_kwargs or {}),
        )
    except BaseException:
        if caps is not None:
            caps.close()
        raise
    try:
        return EcmEnv(
            task_env,
            target,
            predecessors=drivers,
            config=cfg,
            phi=phi,
            on_close=caps.close if caps is not None else None,
        )
    except BaseException:
        task_env.close()
        if caps is not None:
            caps.close()
        raise
