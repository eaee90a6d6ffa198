"""The gymnasium environment every task is: a thin wrapper over one robosuite environment.

Why not robosuite's GymWrapper: it seeds numpy's global generator, reports the horizon as
``terminated``, returns float64 and hides the per-key observation dict we need for
observation noise and for scripted references. This wrapper owns those parts instead.

One robosuite environment is built per :class:`TaskEnv` (about a second) and reused across
episodes: robosuite runs with ``hard_reset=False`` so ``reset`` only resets the MuJoCo data.

Episode contract:
- ``reset(seed=s)`` fixes the whole instance (see :mod:`.perturbations`); ``reset()`` without a
  seed continues the current streams (the first one uses the seed given at construction).
- ``step`` returns float32 observations; ``truncated`` is True at the horizon and
  ``terminated`` only on success (when ``terminate_on_success``).
- ``info["is_success"]`` is present after every reset and step and latched: once True it stays
  True until the next reset. ``info["success_now"]`` is the unlatched value;
  ``info["actuation_dropped"]`` says whether the step's action was replaced by zeros.

Invariants:
1. Same seed, same actions -> identical observations, rewards, infos and signals, whether the
   episode runs on a fresh environment or a reused one.
2. ``terminated`` and ``truncated`` are never both True; ``terminated`` implies
   ``info["is_success"]``.
3. Observations are float32, finite, of the shape of ``observation_space``.
4. Stepping after the episode ended, or before the first reset, raises :class:`Invalid`.
5. Every observation is of the final simulator state of the step: after each step every
   robosuite observable equals robosuite's forced two-pass refresh (``_raw_observations``),
   computed in one pass in dependency order (:mod:`.observables`).
6. The wrapped environment skips the work of robosuite's ``step`` that nothing reads
   (:mod:`.lean_stepping`: per-substep sampling, recomputed action sizes, and robosuite's
   reward where :attr:`TaskEnv.reads_robosuite_reward` is False); :attr:`TaskEnv.robosuite_overrides`
   lists what was switched off.
"""

from __future__ import annotations

import contextlib
import logging
from collections.abc import Iterator
from dataclasses import dataclass
from typing import Any, ClassVar

import gymnasium as gym
import numpy as np

from capevo.errors import Invalid
from capevo.runtime.governance.proximity import ArmScene, ProximitySensor
from capevo.runtime.governance.robosuite_state import force_sensor, sensor_contact_force
from capevo.runtime.state import RobotState
from capevo.runtime.tasks import lean_stepping
from capevo.runtime.tasks.observables import ObservablePlan, plan_observables
from capevo.runtime.tasks.perturbations import EpisodeRngs, Perturbations
from capevo.runtime.tasks.spec import TaskSpec

RESERVED_ENV_KWARGS: frozenset[str] = frozenset(
    {
        "robots",
        "has_renderer",
        "has_offscreen_renderer",
        "use_camera_obs",
        "use_object_obs",
        "hard_reset",
        "ignore_done",
        "renderer",
    }
)
"""robosuite arguments a task fixes itself; passing them to ``make_task`` is refused (``seed`` and
``horizon`` are ``make_task``'s own arguments and mean the episode seed and length)."""

PENETRATION_LIMIT = 0.002
"""Metres of overlap with another geom beyond which a jittered object placement is redrawn."""
JITTER_TRIES = 20


@contextlib.contextmanager
def quiet_robosuite() -> Iterator[None]:
    """Silence robosuite's per-robot controller warnings while an environment is built."""
    import robosuite  # noqa: F401  (its import sets the logger's level; do that first)

    logger = logging.getLogger("robosuite_logs")
    level = logger.level
    logger.setLevel(logging.ERROR)
    try:
        yield
    finally:
        logger.setLevel(level)


def panda_controller_config() -> dict[str, Any]:
    """The BASIC composite controller for a Panda: OSC_POSE arm + gripper."""
    from robosuite.controllers import load_composite_controller_config

    with quiet_robosuite():
        return load_composite_controller_config(controller="BASIC", robot="Panda")


@dataclass(frozen=True, slots=True, kw_only=True)
class Movable:
    """A free-jointed object whose initial x, y the jitter perturbation moves."""

    joint: str
    geom_ids: frozenset[int]
    x_bounds: tuple[float, float]
    y_bounds: tuple[float, float]
    """World-frame bounds the jittered centre is clipped into (bin or reachable table area)."""


class TaskEnv(gym.Env[np.ndarray, np.ndarray]):
    """A capevo task as a gymnasium environment.

    Args:
        seed: Seed of the first episode (used by the first ``reset()`` without a seed); None
            draws OS entropy.
        perturbations: Perturbation settings; default :class:`Perturbations` (all on).
        horizon: Steps after which ``truncated`` is set; default ``task_spec.default_horizon``.
        terminate_on_success: End the episode (``terminated=True``) on the first success step.
        **env_kwargs: Passed to the robosuite environment (e.g. ``control_freq``,
            ``initialization_noise``); the keys in :data:`RESERVED_ENV_KWARGS` are refused.

    Raises:
        Invalid: bad seed, horizon or perturbations, a reserved or unknown robosuite argument.
    """

    metadata: ClassVar[dict[str, Any]] = {"render_modes": []}
    task_spec: ClassVar[TaskSpec]
    reads_robosuite_reward: ClassVar[bool] = True
    """False for a task whose :meth:`_reward` ignores robosuite's: the wrapped environment then
    does not compute it (it is 0.0)."""
    sensed_wrist_links: ClassVar[int] = 3
    """Links above each hand whose geoms proximity sensing covers too (see
    :meth:`~capevo.runtime.governance.proximity.ProximitySensor.for_robots`): the Panda's links
    5-7, braked by how the action moves them (:mod:`capevo.runtime.governance.link_motion`). A
    learned whole-task policy (the AM baseline of ``results/cpu-small``, T1) twisting its hand
    drove the forearm (link 5) into the bin at 315 N while the hand moved clear of everything."""

    def __init__(
        self,
        *,
        seed: int | None = None,
        perturbations: Perturbations | None = None,
        horizon: int | None = None,
        terminate_on_success: bool = True,
        **env_kwargs: Any,
    ) -> None:
        spec = self.task_spec
        self._seed = _check_seed(seed)
        if perturbations is not None and not isinstance(perturbations, Perturbations):
            raise Invalid(
                f"perturbations must be a Perturbations, got {type(perturbations).__name__}",
                details={"field": "perturbations"},
            )
        self.perturbations = perturbations if perturbations is not None else Perturbations()
        if horizon is None:
            horizon = spec.default_horizon
        if isinstance(horizon, bool) or not isinstance(horizon, int) or horizon < 1:
            raise Invalid(f"horizon must be a positive integer, got {horizon!r}", details={"field": "horizon"})
        self.horizon = horizon
        self.terminate_on_success = bool(terminate_on_success)
        reserved = sorted(RESERVED_ENV_KWARGS.intersection(env_kwargs))
        if reserved:
            raise Invalid(
                f"{spec.name}: robosuite argument(s) {', '.join(reserved)} are fixed by the task",
                details={"field": reserved[0]},
            )

        kwargs: dict[str, Any] = {
            "controller_configs": panda_controller_config(),
            "reward_shaping": True,
            "reward_scale": 1.0,
            **env_kwargs,
            "has_renderer": False,
            "has_offscreen_renderer": False,
            "use_camera_obs": False,
            "use_object_obs": True,
            "hard_reset": False,
            "ignore_done": True,
            "horizon": horizon,
            "renderer": "mujoco",
            # Construction-time randomness (none in these tasks' models) is pinned; episode
            # randomness comes from reseeding env.rng in reset().
            "seed": 0,
        }
        with quiet_robosuite():
            try:
                self._env = self._build(kwargs)
            except TypeError as e:
                raise Invalid(f"{spec.name}: bad robosuite argument: {e}", details={"field": "env_kwargs"}) from e
        self.robosuite_overrides = lean_stepping.lean_overrides(self._env, reads_reward=self.reads_robosuite_reward)
        """The instance overrides (:mod:`.lean_stepping`) installed on the robosuite environment."""
        lean_stepping.install(self._env, self.robosuite_overrides)
        self._sim = self._env.sim
        self._model = self._sim.model._model
        self._data = self._sim.data._data
        self._bind()
        self._eef_sites = tuple(int(r.eef_site_id["right"]) for r in self._env.robots)
        self._force_sensors = tuple(force_sensor(r, "right") for r in self._env.robots)
        self._proximity = ProximitySensor.for_robots(
            self._model, self._data, self._env.robots, wrist_links=self.sensed_wrist_links
        )
        self.sense_proximity = True
        """Whether :meth:`robot_state` measures proximity pairs; :func:`capevo.runtime.episode.make_governor`
        turns it off when the governing Φ does not read them (they cost ~0.08 ms per step)."""
        self._gravity = tuple(float(g) for g in self._model.opt.gravity)

        self.action_space = gym.spaces.Box(-1.0, 1.0, shape=(spec.action_layout.dim,), dtype=np.float32)
        self._action_shape = (spec.action_layout.dim,)
        if self._env.action_dim != spec.action_layout.dim:
            raise AssertionError(f"{spec.name}: robosuite action dim {self._env.action_dim} != spec")

        self._rngs = EpisodeRngs(self._seed)
        self._episode_started = False
        self._over = True
        self._signals_cache: dict[str, float] | None = None
        self._t = 0
        self._success = False
        self._obs_dict: dict[str, np.ndarray] = {}
        self._clean_obs_dict: dict[str, np.ndarray] = {}
        self._key_sizes: dict[str, int] = {}
        self._obs_plan: ObservablePlan | None = None
        # A throwaway reset to learn observation sizes; the first real reset reseeds.
        self._env.reset()
        raw = self._raw_observations()
        missing = [k for k in spec.observation_keys if k not in raw]
        if missing:
            raise AssertionError(f"{spec.name}: robosuite gives no observation keys {missing}")
        self._key_sizes = {k: int(np.asarray(raw[k]).size) for k in spec.observation_keys}
        self._pos_sizes = tuple(int(np.asarray(raw[k]).size) for k in spec.position_keys)
        self._pos_total = sum(self._pos_sizes)
        self._flat_keys = spec.observation_keys
        n = sum(self._key_sizes.values())
        self.observation_space = gym.spaces.Box(-np.inf, np.inf, shape=(n,), dtype=np.float32)

    # ------------------------------------------------------------------ subclass hooks

    def _build(self, kwargs: dict[str, Any]) -> Any:
        """Construct the robosuite environment from the common ``kwargs``."""
        raise NotImplementedError

    def _bind(self) -> None:
        """Cache simulator ids once the environment exists."""

    def _movables(self) -> tuple[Movable, ...]:
        """Objects the position jitter moves."""
        return ()

    def _apply_jitter(self, rng: np.random.Generator, half_width: float) -> None:
        """Move the initial scene by up to ``half_width`` in x, y; default: every :meth:`_movables`."""
        for m in self._movables():
            self._jitter_object(m, rng, half_width)

    def _on_reset(self) -> None:
        """Record per-episode references (initial heights, ...) after the scene is final."""

    def _extra_observations(self) -> dict[str, np.ndarray]:
        """Task-provided observation keys added to robosuite's (e.g. exact goal positions)."""
        return {}

    def _is_success(self) -> bool:
        raise NotImplementedError

    def _reward(self, robosuite_reward: float, success: bool) -> float:
        """Dense reward of the step; default: robosuite's shaped reward."""
        return robosuite_reward

    def signals(self) -> dict[str, float]:
        """Named scalars of the current simulator state (exact, not perturbed).

        Computed once per simulator state: the reward, the episode loop's termination checks
        and the planner all read the same step's signals, so later calls return a copy of
        the first (``step`` and ``reset`` start a new state).

        Returns:
            One float per name in ``task_spec.signals``.
        """
        if self._signals_cache is None:
            self._signals_cache = self._signals()
        return dict(self._signals_cache)

    def _signals(self) -> dict[str, float]:
        """Compute :meth:`signals` from the simulator (the hook each task fills in)."""
        raise NotImplementedError

    # ------------------------------------------------------------------ gymnasium API

    def reset(self, *, seed: int | None = None, options: dict[str, Any] | None = None) -> tuple[np.ndarray, dict]:
        """Start an episode.

        Args:
            seed: Fixes the scene and all perturbation draws of this episode; None continues
                the current streams (the first reset uses the construction seed).
            options: Unused.

        Returns:
            ``(observation, info)``; ``info`` has ``is_success``, ``success_now`` and
            ``actuation_dropped`` (all False).

        Raises:
            Invalid: ``seed`` is not a non-negative integer.
        """
        if seed is not None:
            seed = _check_seed(seed)
        super().reset(seed=seed)
        if seed is not None:
            self._rngs = EpisodeRngs(seed)
        elif not self._episode_started:
            self._rngs = EpisodeRngs(self._seed)
        # robosuite's samplers hold a reference to env.rng, so reseed it in place.
        self._env.rng.bit_generator.state = self._rngs.scene.bit_generator.state
        self._rngs.scene = self._env.rng
        self._env.reset()
        if self.perturbations.object_position_jitter > 0:
            self._apply_jitter(self._rngs.jitter, self.perturbations.object_position_jitter)
            self._sim.forward()
        self._signals_cache = None  # the scene moved: reset and jitter
        self._on_reset()
        self._episode_started = True
        self._over = False
        self._t = 0
        self._success = False
        obs = self._observe(self._raw_observations())
        # Planned per episode: a reset may switch observables on or off (robosuite's
        # single-object modes), and the cache is full now.
        self._obs_plan = plan_observables(self._env)
        return obs, {"is_success": False, "success_now": False, "actuation_dropped": False}

    def step(self, action: np.ndarray) -> tuple[np.ndarray, float, bool, bool, dict]:
        """Advance one control step.

        Args:
            action: ``task_spec.action_layout.dim`` values, clipped to [-1, 1].

        Returns:
            ``(observation, reward, terminated, truncated, info)``.

        Raises:
            Invalid: wrong action shape or non-finite values; the episode is over or not started.
        """
        if self._over:
            raise Invalid(f"{self.task_spec.name}: the episode is over (or never started); call reset()")
        a = np.asarray(action, dtype=np.float64)
        if a.shape != self._action_shape:
            raise Invalid(
                f"{self.task_spec.name}: action shape {a.shape} != {self._action_shape}",
                details={"field": "action"},
            )
        if not np.isfinite(a).all():
            raise Invalid(f"{self.task_spec.name}: action has non-finite values", details={"field": "action"})
        dropped = bool(self._rngs.drop.random() < self.perturbations.actuation_failure_p)
        # minimum(maximum()) is np.clip's arithmetic for finite values, without its dispatch cost.
        applied = np.zeros_like(a) if dropped else np.minimum(np.maximum(a, -1.0), 1.0)
        _, rs_reward, _, _ = self._env.step(applied)
        self._signals_cache = None
        self._t += 1
        success_now = bool(self._is_success())
        self._success = self._success or success_now
        reward = float(self._reward(float(rs_reward), success_now))
        terminated = self.terminate_on_success and success_now
        truncated = (not terminated) and self._t >= self.horizon
        self._over = terminated or truncated
        obs = self._observe(self._fresh_observations())
        info = {"is_success": self._success, "success_now": success_now, "actuation_dropped": dropped}
        return obs, reward, terminated, truncated, info

    def close(self) -> None:
        env = getattr(self, "_env", None)
        if env is not None:
            env.close()
            self._env = None

    # ------------------------------------------------------------------ extra API

    @property
    def obs_dict(self) -> dict[str, np.ndarray]:
        """The last observation as a dict of float32 arrays, with the same noise as the flat one.

        Holds every robosuite key (without the concatenated ``*-state`` keys) plus the task's
        extra keys. Scripted references read this.
        """
        return self._obs_dict

    @property
    def clean_obs_dict(self) -> dict[str, np.ndarray]:
        """The last observation dict without observation noise."""
        return self._clean_obs_dict

    @property
    def robosuite_env(self) -> Any:
        """The wrapped robosuite environment (for inspection; don't step it directly)."""
        return self._env

    @property
    def elapsed_steps(self) -> int:
        return self._t

    @property
    def is_success(self) -> bool:
        """Latched success of the current episode."""
        return self._success

    @property
    def strict_success(self) -> bool | None:
        """A stricter success check reported beside :attr:`is_success`, latched per episode, for
        tasks whose robosuite criterion passes short of the job (T6: the peg through the plate);
        None for tasks without one."""
        return None

    def flatten(self, obs_dict: dict[str, np.ndarray]) -> np.ndarray:
        """Concatenate ``task_spec.observation_keys`` of ``obs_dict`` into the flat float32 vector."""
        return np.concatenate(
            [np.asarray(obs_dict[k], dtype=np.float32) for k in self.task_spec.observation_keys], axis=None
        )

    def robot_state(self) -> RobotState:
        """Each arm's end-effector position, external force and orientation, world frame, plain floats.

        The force is the robot's wrist force sensor (MuJoCo ``force`` sensor at the gripper's
        ``ft_frame``) rotated to the world frame with the static weight of everything below the
        sensor removed (:func:`capevo.runtime.governance.robosuite_state.sensor_contact_force`):
        the force the environment exerts on the end effector, about 0 in free motion, plus
        inertial terms while accelerating and the weight of a held object. Arms are
        :class:`~capevo.runtime.governance.proximity.ArmScene`: an ``ArmState`` plus the end-effector
        site's rotation, which governance uses for the hand's extent, and the hand's nearest
        points to the rest of the scene (``ProximitySensor``), with how fast each closes, which
        ``contact_approach``, ``keep_clear`` and ``stopping_distance`` read (empty while
        :attr:`sense_proximity` is off).
        """
        d = self._data
        arms = []
        sense = self.sense_proximity
        for i, site in enumerate(self._eef_sites):
            x, y, z = d.site_xpos[site].tolist()
            near, link_rows, closing = self._proximity.sense(i) if sense else ((), (), ())
            arms.append(
                ArmScene(
                    eef_pos=(x, y, z),
                    eef_force=self._arm_force(i),
                    eef_rot=tuple(d.site_xmat[site].tolist()),
                    near=near,
                    link_rows=link_rows,
                    closing=closing,
                )
            )
        return RobotState(arms=tuple(arms))

    # ------------------------------------------------------------------ helpers

    def _arm_force(self, arm: int) -> tuple[float, float, float]:
        return sensor_contact_force(self._data, self._force_sensors[arm], self._gravity)

    def _raw_observations(self) -> dict[str, Any]:
        # Relative-pose observables read other observables from robosuite's cache, which is empty
        # right after a reset or a teleport; a second forced pass fills them.
        self._env._get_observations(force_update=True)
        raw = dict(self._env._get_observations(force_update=True))
        raw.update(self._extra_observations())
        return raw

    def _fresh_observations(self) -> dict[str, Any]:
        """:meth:`_raw_observations` after a step, in one forced pass instead of two.

        robosuite samples its observables early in a control step, so the values its ``step``
        returns are stale; a forced pass reads the final state. Run in :attr:`_obs_plan`'s
        order (every observable after those whose cached values it reads), one pass gives
        the values the two-pass refresh gives, bit for bit, at half the cost and without
        building robosuite's concatenated ``*-state`` arrays, which capevo drops.
        """
        env = self._env
        plan = self._obs_plan
        if plan is None or plan.source is not env._observables:
            return self._raw_observations()
        cache, dt = env._obs_cache, env.model_timestep
        for observable in plan.order:
            observable.update(timestep=dt, obs_cache=cache, force=True)
        raw = {name: observable.obs for name, observable in plan.active}
        raw.update(self._extra_observations())
        return raw

    def _observe(self, raw: dict[str, Any]) -> np.ndarray:
        f32 = np.float32
        clean = {k: np.asarray(v, dtype=f32) for k, v in raw.items() if not k.endswith("-state")}
        noisy = dict(clean)
        std = self.perturbations.obs_position_noise_std
        if std > 0 and self.task_spec.position_keys:
            draws = self._rngs.obs_noise.normal(0.0, std, size=self._pos_total)
            at = 0
            for k, n in zip(self.task_spec.position_keys, self._pos_sizes, strict=True):
                v = clean[k]
                noisy[k] = (v + draws[at : at + n].reshape(v.shape)).astype(f32)
                at += n
        self._clean_obs_dict = clean
        self._obs_dict = noisy
        # Every value is a float32 array now: concatenate them as they are.
        return np.concatenate([noisy[k] for k in self._flat_keys], axis=None)

    def _jitter_object(self, m: Movable, rng: np.random.Generator, half_width: float) -> None:
        """Shift one object's initial x, y; redraw while it would overlap another geom."""
        sim = self._sim
        qpos = np.array(sim.data.get_joint_qpos(m.joint))
        for _ in range(JITTER_TRIES):
            dx, dy = rng.uniform(-half_width, half_width, size=2)
            moved = qpos.copy()
            moved[0] = float(np.clip(qpos[0] + dx, *m.x_bounds))
            moved[1] = float(np.clip(qpos[1] + dy, *m.y_bounds))
            sim.data.set_joint_qpos(m.joint, moved)
            sim.forward()
            if self._max_penetration(m.geom_ids) <= PENETRATION_LIMIT:
                return
        sim.data.set_joint_qpos(m.joint, qpos)
        sim.forward()

    def _max_penetration(self, geom_ids: frozenset[int]) -> float:
        d = self._data
        worst = 0.0
        for i in range(d.ncon):
            c = d.contact[i]
            if (c.geom1 in geom_ids or c.geom2 in geom_ids) and -c.dist > worst:
                worst = -float(c.dist)
        return worst


def _check_seed(seed: object) -> int | None:
    if seed is None:
        return None
    if isinstance(seed, bool) or not isinstance(seed, (int, np.integer)) or seed < 0:
        raise Invalid(f"seed must be a non-negative integer or None, got {seed!r}", details={"field": "seed"})
    return int(seed)
