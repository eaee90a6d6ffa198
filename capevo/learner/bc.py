"""Imitation learning for neural ECMs: behaviour cloning of a SAC actor, in plain torch.

Demonstrations (:class:`Demos`: ECM observations and the actions taken) come from

* traces (:func:`demos_from_traces`): the ``/env/step`` rows of MCAP files whose action came
  from this ECM, in episodes that succeeded and in which this ECM handed over to a later step
  of the decomposition (or is its last step; a step that applies only after success never acts,
  since success ends the episode, so it does not count); the flat task observation is cut down to the
  ECM's interface inputs (:func:`input_columns`). Why the hand-off: an ECM that never reached
  its own termination and finished the task alone did the later steps' jobs under its name;
  cloning those rows into it would teach it the whole task, and its successes would feed the
  same loop (on T1, a cloned ``pick.reach`` did finish the task alone in every success:
  ``results/evolution/T1-il/heldout.md``);
* a controller rolled out in the ECM's training environment (:func:`collect_demos`): the
  task's scripted reference (:func:`scripted_controller`) or any ECM version run through the
  runtime's invoker (:func:`ecm_controller`); only episodes where the ECM's step succeeded
  are kept unless asked otherwise.

* the clone's own rollouts (:meth:`BcLearner.clone`, ``BcConfig.dagger_rounds``): DAgger (Ross,
  Gordon & Bagnell 2011) runs the clone in the ECM's training environment and labels every
  observation it visits with the scripted reference's action, so the clone also learns how to
  recover from the states its own errors lead to. What is hand-written here is the expert (the
  scripted reference) and the round counts; what is learned is the actor.

:func:`behaviour_clone` trains the actor of a stable-baselines3 SAC model on them, so the
result is an ordinary SAC model zip the neural loader accepts. The loss is the mean squared
error between the actor's deterministic action (``tanh`` of the Gaussian mean) and the
demonstrated action, or the negative log-likelihood of the demonstrated action under the
actor's squashed Gaussian (``loss="nll"``, which also fits the spread). Critics are left as
they are (a later RL run trains them).

:class:`BcLearner` is the :class:`~capevo.learner.base.Learner` for modality ``il``: it warm
starts from the parent's weights when the parent is a SAC policy, gathers demonstrations
(the successful traces of the current set *and* rollouts of the task's scripted reference, so
that it keeps learning from its own successes once the set succeeds), clones, and returns a
candidate with origin ``il``. With a ``state_dir`` (:mod:`capevo.learner.continuation`) it
continues from its own latest candidate rather than the active version, and clones on every
demonstration row gathered so far, so updates add up across iterations whether or not the gate
promoted the previous one (issue 19).

Invariants:
1. :func:`behaviour_clone` changes only the actor's parameters (and its own optimizer's state).
2. ``Demos`` arrays are float32, two-dimensional, with equal row counts; actions lie in [-1, 1].
3. :func:`input_columns` picks exactly the interface inputs' values, in interface order, from a
   flat observation laid out as the task's ``observation_keys``; a layout that does not add up
   to the observation's length is :class:`Invalid`.
4. With equal demos, config and starting weights, cloning is deterministic.
"""

from __future__ import annotations

import contextlib
import dataclasses
import logging
import math
import os
import time
import uuid
from collections.abc import Callable, Iterator, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from capevo.errors import Invalid
from capevo.learner.base import Candidate, LearnRequest, config_hash
from capevo.learner.continuation import LearnerState
from capevo.learner.ecm_env import EcmEnv, EcmEnvConfig, EcmTarget, make_ecm_env, target_for
from capevo.learner.neural_seed import NEURAL_MEDIA_TYPE, model_bytes, offline_sac, sac_policy_kwargs, warm_start
from capevo.records import IOSpec, Kind, Origin, Predicate, Provenance, PublishSpec
from capevo.registry.api import Registry
from capevo.registry.predicates import condition_holds
from capevo.runtime.ecm.marshal import spec_size
from capevo.runtime.tasks import SUCCESS_SIGNAL, TaskSpec, task_spec

log = logging.getLogger(__name__)

LOSSES: tuple[str, ...] = ("mse", "nll")
Controller = Callable[[Mapping[str, np.ndarray]], np.ndarray | None]
"""Raw observation dict -> action (None: the controller is done)."""


@dataclass(frozen=True, slots=True, kw_only=True)
class BcConfig:
    """Behaviour cloning settings (hashed into provenance).

    Args:
        epochs: Passes over the demonstrations.
        batch_size: Minibatch size.
        learning_rate: Adam step size.
        loss: ``mse`` (deterministic action) or ``nll`` (likelihood under the actor's Gaussian).
        weight_decay: Adam L2 penalty.
        net_arch: Hidden layers of a fresh policy (a SAC parent keeps its own).
        seed: Seeds the weights of a fresh policy and the minibatch order.
        min_samples: Demonstration steps needed before cloning (fewer: :class:`Invalid`).
        dagger_rounds: Rounds of DAgger after the first clone (0: plain behaviour cloning).
            Each round rolls the clone itself out for ``dagger_episodes`` episodes in the ECM's
            training environment, labels every observation it visited with the task's scripted
            reference, adds those rows and clones again (Ross, Gordon & Bagnell 2011,
            Algorithm 3.1 with β = 0 after the first policy): the clone learns what to do in the
            states its own mistakes lead to, which plain cloning never shows it.
        dagger_episodes: Episodes per DAgger round.

    Raises:
        Invalid: a value out of range or an unknown loss.
    """

    epochs: int = 50
    batch_size: int = 256
    learning_rate: float = 1e-3
    loss: str = "mse"
    weight_decay: float = 0.0
    net_arch: tuple[int, ...] = (256, 256)
    seed: int = 0
    min_samples: int = 1
    dagger_rounds: int = 0
    dagger_episodes: int = 10

    def __post_init__(self) -> None:
        for name in ("epochs", "batch_size", "min_samples", "dagger_episodes"):
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, int) or v < 1:
                raise Invalid(f"{name} must be a positive integer, got {v!r}", details={"field": name})
        if isinstance(self.dagger_rounds, bool) or not isinstance(self.dagger_rounds, int) or self.dagger_rounds < 0:
            raise Invalid(
                f"dagger_rounds must be a non-negative integer, got {self.dagger_rounds!r}",
                details={"field": "dagger_rounds"},
            )
        for name, allow_zero in (("learning_rate", False), ("weight_decay", True)):
            v = getattr(self, name)
            ok = not isinstance(v, bool) and isinstance(v, (int, float)) and math.isfinite(v)
            if not ok or v < 0 or (v == 0 and not allow_zero):
                raise Invalid(f"{name} must be a finite number > 0, got {v!r}", details={"field": name})
        if self.loss not in LOSSES:
            raise Invalid(f"unknown loss {self.loss!r}; valid: {', '.join(LOSSES)}", details={"field": "loss"})
        if not self.net_arch or any(isinstance(n, bool) or not isinstance(n, int) or n < 1 for n in self.net_arch):
            raise Invalid(
                f"net_arch must be positive layer sizes, got {self.net_arch!r}", details={"field": "net_arch"}
            )
        if isinstance(self.seed, bool) or not isinstance(self.seed, int) or self.seed < 0:
            raise Invalid(f"seed must be a non-negative integer, got {self.seed!r}", details={"field": "seed"})

    def to_dict(self) -> dict[str, Any]:
        return {
            "epochs": self.epochs,
            "batch_size": self.batch_size,
            "learning_rate": self.learning_rate,
            "loss": self.loss,
            "weight_decay": self.weight_decay,
            "net_arch": list(self.net_arch),
            "seed": self.seed,
            "min_samples": self.min_samples,
            "dagger_rounds": self.dagger_rounds,
            "dagger_episodes": self.dagger_episodes,
        }


@dataclass(frozen=True, slots=True, kw_only=True, eq=False)
class Demos:
    """Demonstrations of one ECM: observation rows (its inputs, flat) and the actions taken."""

    obs: np.ndarray
    action: np.ndarray
    source: str
    """``traces``, ``scripted``, an ECM label, or ``+``-joined when merged."""
    episodes: int = 0
    """Episodes the rows come from."""
    episodes_seen: int = 0
    """Episodes looked at (kept or not)."""
    traces: tuple[str, ...] = ()
    env_steps: int = 0
    """Env steps simulated to collect these rows, kept or not, the predecessors' included (0 for
    rows read from traces of episodes that were run anyway)."""

    def __post_init__(self) -> None:
        if self.obs.ndim != 2 or self.action.ndim != 2 or len(self.obs) != len(self.action):
            raise Invalid(
                f"demos need 2-D obs and action arrays with equal rows, got {self.obs.shape} and {self.action.shape}"
            )

    def __len__(self) -> int:
        return len(self.obs)

    @classmethod
    def empty(cls, obs_dim: int, action_dim: int, source: str) -> Demos:
        return cls(obs=np.zeros((0, obs_dim), np.float32), action=np.zeros((0, action_dim), np.float32), source=source)

    def merged(self, other: Demos) -> Demos:
        """Both sets of rows (this one first)."""
        if len(other) == 0:
            return self
        if len(self) == 0:
            return other
        return Demos(
            obs=np.concatenate([self.obs, other.obs]),
            action=np.concatenate([self.action, other.action]),
            source=f"{self.source}+{other.source}",
            episodes=self.episodes + other.episodes,
            episodes_seen=self.episodes_seen + other.episodes_seen,
            traces=tuple(dict.fromkeys((*self.traces, *other.traces))),
            env_steps=self.env_steps + other.env_steps,
        )


def _as_demo_arrays(obs: Sequence[np.ndarray], actions: Sequence[np.ndarray], obs_dim: int, act_dim: int) -> tuple:
    o = np.asarray(obs, dtype=np.float32).reshape(len(obs), obs_dim)
    a = np.clip(np.asarray(actions, dtype=np.float32).reshape(len(actions), act_dim), -1.0, 1.0)
    return o, a


# --- demonstrations from traces ------------------------------------------------------------


def observation_layout(spec: TaskSpec) -> dict[str, tuple[int, int]]:
    """``{key: (start, stop)}`` of each of the task's observation keys in its flat observation.

    Raises:
        Invalid: a key whose shape is unknown.
    """
    from capevo.learner.skills import OBS_SHAPES

    out: dict[str, tuple[int, int]] = {}
    at = 0
    for key in spec.observation_keys:
        shape = OBS_SHAPES.get(key)
        if shape is None:
            raise Invalid(f"task {spec.name!r}: no known shape for observation key {key!r}", details={"field": key})
        n = math.prod(shape)
        out[key] = (at, at + n)
        at += n
    return out


def input_columns(spec: TaskSpec, inputs: Sequence[IOSpec], obs_dim: int) -> np.ndarray:
    """Column indices of ``inputs`` (in order) in the task's flat observation of length ``obs_dim``.

    Raises:
        Invalid: the task's layout does not add up to ``obs_dim``, or an input is not one of the
            task's observation keys or has another size.
    """
    layout = observation_layout(spec)
    total = max((stop for _, stop in layout.values()), default=0)
    if total != obs_dim:
        raise Invalid(
            f"task {spec.name!r}: its observation keys add up to {total} values, the traces hold {obs_dim}",
            details={"field": "obs"},
        )
    cols: list[int] = []
    for s in inputs:
        span = layout.get(s.name)
        if span is None:
            raise Invalid(
                f"input {s.name!r} is not an observation key of task {spec.name!r}", details={"field": s.name}
            )
        if span[1] - span[0] != spec_size(s):
            raise Invalid(
                f"input {s.name!r} has {spec_size(s)} values, the task's observation has {span[1] - span[0]}",
                details={"field": s.name},
            )
        cols.extend(range(*span))
    return np.asarray(cols, dtype=np.int64)


def task_trace_files(paths: Sequence[str | os.PathLike[str]], task: str) -> list[Path]:
    """The trace files among ``paths`` (files or directories of ``*.mcap``) written for ``task``.

    Unreadable files are skipped (logged): a half-written or damaged trace must not stop learning.
    A path that does not exist yet, or a directory without traces, gives none.
    """
    from capevo.runtime.traces import TraceReader
    from capevo.runtime.traces.files import trace_files

    name = task_spec(task).name
    out = []
    for f in trace_files(paths, missing_ok=True):
        try:
            with TraceReader(f, allow_incomplete=True) as reader:
                if reader.metadata().task == name:
                    out.append(f)
        except Exception as exc:  # a trace another process is still writing, or a damaged one
            log.warning("skipping trace %s: %s", f, exc)
    return out


def _later_steps(spec: TaskSpec, ecm: str) -> list[str]:
    """The ECMs after ``ecm`` in ``spec``'s decomposition that can act (none if it is the last or
    not in it).

    A step that applies only once the task has succeeded (T4's ``release``, T6's ``hold``: their
    applicability needs the ``success`` signal) never acts, because success ends the episode; the
    step before it hands over to nothing, so it counts as the last.
    """
    names = list(spec.ecm_names)
    if ecm not in names:
        return []
    return [s.ecm for s in spec.decomposition[names.index(ecm) + 1 :] if not _only_after_success(s.applicability)]


def _only_after_success(applicability: Predicate) -> bool:
    """Whether ``applicability`` can hold only while the task's success signal is 1."""
    return any(
        c.signal == SUCCESS_SIGNAL.name
        and condition_holds(c, {c.signal: 1.0})
        and not condition_holds(c, {c.signal: 0.0})
        for c in applicability.all
    )


def demos_from_traces(
    paths: Sequence[str | os.PathLike[str]],
    *,
    task: str,
    target: EcmTarget,
    only_successful: bool = True,
) -> Demos:
    """Demonstrations of ``target`` from trace files (or directories of them) of ``task``.

    Args:
        paths: Trace files or directories; files of other tasks are ignored.
        task: Task id or name.
        target: The ECM; rows whose action came from another ECM are dropped.
        only_successful: Keep only episodes that succeeded and in which a later step of the
            decomposition acted too (any episode, for the last step): see the module docstring.
            False keeps every row of the ECM.

    Returns:
        The demonstrations (possibly empty).

    Raises:
        Invalid: the traces' observations do not match the task's layout.
    """
    from capevo.runtime.traces import export_transitions

    spec = task_spec(task)
    obs_dim = target.input_size
    act_dim = spec.action_layout.dim
    files = task_trace_files(paths, spec.name)
    if not files:
        return Demos.empty(obs_dim, act_dim, "traces")
    rows = export_transitions(files, allow_incomplete=True)
    if len(rows) == 0:
        return Demos.empty(obs_dim, act_dim, "traces")
    keys = np.char.add(np.char.add(rows.run_id.astype(str), "#"), rows.episode.astype(str))
    succeeded = set(np.unique(keys[rows.is_success]))
    mine = rows.ecm == target.name
    later = _later_steps(spec, target.name)
    handed_over = set(np.unique(keys[np.isin(rows.ecm, later)])) if later else set(np.unique(keys))
    keep = mine & np.isin(keys, list(succeeded & handed_over)) if only_successful else mine
    cols = input_columns(spec, target.interface.inputs, rows.obs.shape[1])
    finite = np.all(np.isfinite(rows.obs[:, cols]), axis=1) & np.all(np.isfinite(rows.action), axis=1)
    keep &= finite
    obs, act = _as_demo_arrays(list(rows.obs[keep][:, cols]), list(rows.action[keep]), obs_dim, act_dim)
    return Demos(
        obs=obs,
        action=act,
        source="traces",
        episodes=len(set(keys[keep].tolist())),
        episodes_seen=len(set(keys[mine].tolist())),
        traces=tuple(str(f) for f in files),
    )


# --- demonstrations from a controller ------------------------------------------------------


def scripted_controller(task: str) -> Controller | None:
    """The task's scripted reference controller, or None when the task has none."""
    from capevo.runtime.tasks.scripted import REFERENCES

    return REFERENCES.get(task_spec(task).name)


def ecm_controller(loaded: Any, *, layout: Any, timeout_s: float = 0.5) -> Controller:
    """A controller running a loaded ECM (:class:`~capevo.runtime.ecm.LoadedEcm`) through the
    runtime's invoker (inputs marshalled, failures held still, actions clipped to its bounds).

    Args:
        loaded: The ECM version.
        layout: The task's :class:`~capevo.runtime.state.ActionLayout`.
        timeout_s: Per-call compute limit.
    """
    from capevo.runtime.ecm import EcmInvoker

    invoker = EcmInvoker(loaded, timeout_s=timeout_s, step_budget=None, layout=layout)

    def act(obs: Mapping[str, np.ndarray]) -> np.ndarray | None:
        result = invoker.step(obs)
        return None if result.action is None else np.asarray(result.action, dtype=np.float64)

    return act


def collect_demos(
    env: EcmEnv,
    controller: Controller,
    *,
    episodes: int,
    only_successful: bool = True,
    source: str = "controller",
    seed: int | None = None,
    should_stop: Callable[[], bool] | None = None,
    driver: Callable[[np.ndarray], np.ndarray] | None = None,
    max_env_steps: int | None = None,
) -> Demos:
    """Roll ``controller`` out in the ECM's environment and record (ECM observation, action).

    Each episode runs until the ECM's step is done, its budget ends, or the controller returns
    None. The controller sees the raw observation dict (``env.obs_dict``); the recorded
    observation is the ECM's. With a ``driver`` (DAgger's data collection), the driver's action
    on the ECM observation is the one executed, and the controller only labels the states the
    driver visits.

    Args:
        env: The ECM's training environment.
        controller: Acts on the raw observation dict.
        episodes: Episodes to run.
        only_successful: Keep only episodes where the ECM's step succeeded.
        source: Recorded in the demos.
        seed: Seed of the first episode (see :class:`EcmEnv`); default continue.
        should_stop: Polled every step; True ends the collection (what was kept so far is returned).
        driver: ECM observation -> the action to execute; None executes the controller's.
        max_env_steps: Simulate at most this many steps (an env-step budget): no episode starts
            unless its reset's predecessors (``prefix_budget`` steps each) and one step still
            fit, and an episode that reaches the cap ends there (kept only when
            ``only_successful`` is off).

    Returns:
        The demonstrations (``action``: always the controller's; ``env_steps``: every step the
        environment simulated meanwhile, the predecessors' and the discarded episodes' too).
    """
    if isinstance(episodes, bool) or not isinstance(episodes, int) or episodes < 0:
        raise Invalid(f"episodes must be a non-negative integer, got {episodes!r}", details={"field": "episodes"})
    obs_rows: list[np.ndarray] = []
    act_rows: list[np.ndarray] = []
    kept = run = 0
    steps_before = env.env_steps
    reset_steps = len(env.predecessors) * env.config.prefix_budget  # a reset's worst case

    def room(steps: int) -> bool:
        return max_env_steps is None or env.env_steps - steps_before + steps <= max_env_steps

    for i in range(episodes):
        if (should_stop is not None and should_stop()) or not room(reset_steps + 1):
            break
        run += 1
        obs, info = env.reset(seed=seed + i if seed is not None else None)
        ep_obs: list[np.ndarray] = []
        ep_act: list[np.ndarray] = []
        while room(1):
            action = controller(env.obs_dict)
            if action is None:
                break
            a = np.clip(np.asarray(action, dtype=np.float32), -1.0, 1.0)
            ep_obs.append(obs)
            ep_act.append(a)
            executed = a if driver is None else np.clip(np.asarray(driver(obs), dtype=np.float32), -1.0, 1.0)
            obs, _, terminated, truncated, info = env.step(executed)
            if terminated or truncated or (should_stop is not None and should_stop()):
                break
        if ep_obs and (info.get("is_success") or not only_successful):
            obs_rows.extend(ep_obs)
            act_rows.extend(ep_act)
            kept += 1
    obs_dim = int(env.observation_space.shape[0])
    act_dim = int(env.action_space.shape[0])
    steps = env.env_steps - steps_before
    if not obs_rows:
        d = Demos.empty(obs_dim, act_dim, source)
        return Demos(obs=d.obs, action=d.action, source=source, episodes_seen=run, env_steps=steps)
    o, a = _as_demo_arrays(obs_rows, act_rows, obs_dim, act_dim)
    return Demos(obs=o, action=a, source=source, episodes=kept, episodes_seen=run, env_steps=steps)


# --- cloning -------------------------------------------------------------------------------


@contextlib.contextmanager
def torch_threads(n: int | None) -> Iterator[None]:
    """Run the block with torch limited to ``n`` CPU threads (None: leave torch alone).

    Small networks train several times faster on one thread when the cores are shared with a
    simulator and other processes.
    """
    if n is None:
        yield
        return
    if isinstance(n, bool) or not isinstance(n, int) or n < 1:
        raise Invalid(f"torch threads must be a positive integer, got {n!r}", details={"field": "torch_threads"})
    import torch

    previous = torch.get_num_threads()
    torch.set_num_threads(n)
    try:
        yield
    finally:
        torch.set_num_threads(previous)


@dataclass(frozen=True, slots=True, kw_only=True)
class BcReport:
    """What one cloning run did."""

    samples: int
    epochs: int
    loss: str
    loss_before: float
    loss_after: float
    seconds: float

    def to_dict(self) -> dict[str, Any]:
        return {
            "samples": self.samples,
            "epochs": self.epochs,
            "loss": self.loss,
            "loss_before": self.loss_before,
            "loss_after": self.loss_after,
            "seconds": self.seconds,
        }


def _batch_loss(actor: Any, obs: Any, act: Any, loss: str) -> Any:
    import torch

    if loss == "mse":
        return torch.nn.functional.mse_loss(actor(obs, deterministic=True), act)
    mean, log_std, kwargs = actor.get_action_dist_params(obs)
    dist = actor.action_dist.proba_distribution(mean, log_std, **kwargs)
    return -dist.log_prob(act).mean()


def imitation_loss(model: Any, demos: Demos, *, loss: str = "mse", batch_size: int = 4096) -> float:
    """Mean imitation loss of ``model``'s actor on ``demos`` (no gradient).

    Raises:
        Invalid: empty demos, unknown loss, or demos that do not fit the model's spaces.
    """
    import torch

    if loss not in LOSSES:
        raise Invalid(f"unknown loss {loss!r}; valid: {', '.join(LOSSES)}", details={"field": "loss"})
    if len(demos) == 0:
        raise Invalid("no demonstrations to measure the loss on")
    _check_fits(model, demos)
    actor = model.actor
    total = 0.0
    with torch.no_grad():
        for start in range(0, len(demos), batch_size):
            o = torch.as_tensor(demos.obs[start : start + batch_size])
            a = torch.as_tensor(demos.action[start : start + batch_size])
            total += float(_batch_loss(actor, o, a, loss)) * len(o)
    return total / len(demos)


def _check_fits(model: Any, demos: Demos) -> None:
    obs_dim = int(model.observation_space.shape[0])
    act_dim = int(model.action_space.shape[0])
    if demos.obs.shape[1] != obs_dim or demos.action.shape[1] != act_dim:
        raise Invalid(
            f"demos are ({demos.obs.shape[1]} obs, {demos.action.shape[1]} action) values, the policy takes "
            f"{obs_dim} and acts in {act_dim}",
            details={"field": "demos"},
        )


def behaviour_clone(
    model: Any,
    demos: Demos,
    config: BcConfig,
    *,
    progress: Callable[[int, int, float], Any] | None = None,
) -> BcReport:
    """Fit ``model``'s SAC actor to ``demos`` (see the module docstring).

    Args:
        model: A stable-baselines3 SAC model.
        demos: Demonstrations matching the model's spaces.
        config: Epochs, batch size, loss, learning rate.
        progress: Called after each epoch as ``progress(epoch, epochs, loss)``.

    Returns:
        The losses before and after (over all demos).

    Raises:
        Invalid: fewer than ``config.min_samples`` demonstrations, or demos that do not fit.
    """
    import torch

    if len(demos) < config.min_samples or len(demos) == 0:
        raise Invalid(
            f"behaviour cloning needs at least {max(1, config.min_samples)} demonstration steps, got {len(demos)}",
            details={"field": "demos"},
        )
    _check_fits(model, demos)
    started = time.perf_counter()
    before = imitation_loss(model, demos, loss=config.loss)
    actor = model.actor
    optimizer = torch.optim.Adam(actor.parameters(), lr=config.learning_rate, weight_decay=config.weight_decay)
    generator = torch.Generator().manual_seed(config.seed)
    obs = torch.as_tensor(demos.obs)
    act = torch.as_tensor(demos.action)
    n = len(demos)
    model.policy.set_training_mode(True)
    try:
        for epoch in range(config.epochs):
            order = torch.randperm(n, generator=generator)
            running = 0.0
            for start in range(0, n, config.batch_size):
                idx = order[start : start + config.batch_size]
                batch_loss = _batch_loss(actor, obs[idx], act[idx], config.loss)
                optimizer.zero_grad()
                batch_loss.backward()
                optimizer.step()
                running += float(batch_loss.detach()) * len(idx)
            if progress is not None:
                progress(epoch + 1, config.epochs, running / n)
    finally:
        model.policy.set_training_mode(False)
    after = imitation_loss(model, demos, loss=config.loss)
    return BcReport(
        samples=n,
        epochs=config.epochs,
        loss=config.loss,
        loss_before=before,
        loss_after=after,
        seconds=time.perf_counter() - started,
    )


# --- the learner ---------------------------------------------------------------------------


def neural_candidate(
    model: Any,
    target: EcmTarget,
    *,
    request: LearnRequest,
    origin: Origin,
    provenance: Provenance,
    notes: Mapping[str, Any],
) -> Candidate:
    """The candidate of a trained SAC ``model`` for ``target``: its zip, checked to load as the
    runtime will, with a neural publish spec whose parent is the request's.

    Raises:
        Invalid: the zip does not load or does not match the interface.
    """
    artifact = model_bytes(model)
    check_loadable(artifact, target)
    spec = PublishSpec(
        kind=Kind.NEURAL,
        descriptor=target.descriptor,
        interface=target.interface,
        media_type=NEURAL_MEDIA_TYPE,
        parent=request.parent.version,
        origin=origin,
        provenance=provenance,
    )
    return Candidate(ecm=request.ecm, artifact=artifact, spec=spec, notes=notes)


def check_loadable(artifact: bytes, target: EcmTarget) -> None:
    """Load ``artifact`` the way the runtime will (no unpickling) against ``target``'s interface.

    Raises:
        Invalid: it does not load or does not match the interface.
    """
    from capevo.runtime.ecm.neural import NeuralPolicy

    NeuralPolicy(artifact, inputs=target.interface.inputs, outputs=target.interface.outputs, name=target.name)


def parent_artifact_of(request: LearnRequest, registry: Registry | None, given: bytes | None) -> bytes | None:
    """The parent's artifact bytes: ``given``, else the request's source (code), else the registry's."""
    if given is not None:
        return given
    if request.parent.kind is Kind.CODE and request.source:
        return request.source.encode()
    if registry is None:
        return None
    return registry.get_artifact(request.ecm, request.parent.version)


def default_learner_id(modality: str) -> str:
    """A unique learner id: ``<modality>-<host>-<pid>-<random>``."""
    import socket

    host = socket.gethostname().split(".")[0] or "host"
    return f"{modality}-{host}-{os.getpid()}-{uuid.uuid4().hex[:6]}"


class BcLearner:
    """Behaviour cloning learner (modality ``il``) for neural ECMs.

    Args:
        config: Cloning settings.
        env_config: How demonstration episodes run (budgets, governance, perturbations, seeds).
        registry: Loads the parent's artifact and the predecessors of later ECMs.
        traces: Trace files or directories to take successful demonstrations from (the
            request's outcomes' traces are added).
        scripted_episodes: Episodes of the task's scripted reference to roll out when traces
            give fewer than ``config.min_samples`` rows (0: never).
        only_successful: Keep only successful episodes' demonstrations.
        learner_id: Recorded in provenance; default a unique id.
        progress: Called after each epoch as ``progress(epoch, epochs, loss)``.
        torch_threads: CPU threads for torch while learning (None: leave as is).
        should_stop: Polled while rolling out demonstrations; True cuts the rollouts short.
        state_dir: Where this learner keeps its state between updates (its latest candidate and
            every demonstration row so far, per ECM; :class:`~capevo.learner.continuation.LearnerState`);
            None starts every update afresh from the parent.
        env_step_budget: Env steps one :meth:`learn` (or one :meth:`gather` and :meth:`clone`) may
            simulate for its scripted demonstrations and DAgger's rounds together (issue 20's
            budget; see :func:`collect_demos`). None: as many as the settings ask.

    Raises:
        Invalid: bad settings.
    """

    modality = "il"

    def __init__(
        self,
        *,
        config: BcConfig | None = None,
        env_config: EcmEnvConfig | None = None,
        registry: Registry | None = None,
        traces: Sequence[str | os.PathLike[str]] = (),
        scripted_episodes: int = 5,
        only_successful: bool = True,
        learner_id: str | None = None,
        progress: Callable[[int, int, float], Any] | None = None,
        torch_threads: int | None = None,
        should_stop: Callable[[], bool] | None = None,
        state_dir: str | os.PathLike[str] | None = None,
        env_step_budget: int | None = None,
    ) -> None:
        if env_step_budget is not None and (
            isinstance(env_step_budget, bool) or not isinstance(env_step_budget, int) or env_step_budget < 1
        ):
            raise Invalid(
                f"env_step_budget must be a positive integer, got {env_step_budget!r}",
                details={"field": "env_step_budget"},
            )
        self.env_step_budget = env_step_budget
        self.state_dir = Path(state_dir) if state_dir is not None else None
        self.config = config or BcConfig()
        self.torch_threads = torch_threads
        self.should_stop = should_stop
        self.env_config = env_config or EcmEnvConfig()
        self.registry = registry
        self.traces = tuple(str(t) for t in traces)
        if isinstance(scripted_episodes, bool) or not isinstance(scripted_episodes, int) or scripted_episodes < 0:
            raise Invalid(f"scripted_episodes must be >= 0, got {scripted_episodes!r}", details={"field": "scripted"})
        self.scripted_episodes = scripted_episodes
        self.only_successful = only_successful
        self.learner_id = learner_id or default_learner_id(self.modality)
        self.progress = progress

    def gather(self, request: LearnRequest, target: EcmTarget) -> Demos:
        """Demonstrations for ``request``: the successful steps of its traces, plus
        ``scripted_episodes`` rollouts of the task's scripted reference.

        Raises:
            Invalid: too few demonstrations from every source.
        """
        from capevo.learner.experience import trace_paths

        paths = [*self.traces, *trace_paths(request.outcomes)]
        demos = (
            demos_from_traces(paths, task=request.task, target=target, only_successful=self.only_successful)
            if paths
            else Demos.empty(target.input_size, task_spec(request.task).action_layout.dim, "traces")
        )
        log.info("%s: %d demonstration steps from %d trace episodes", request.ecm, len(demos), demos.episodes)
        if self.scripted_episodes > 0:
            controller = scripted_controller(request.task)
            if controller is not None:
                env = make_ecm_env(request.task, target, registry=self.registry, config=self.env_config)
                try:
                    more = collect_demos(
                        env,
                        controller,
                        episodes=self.scripted_episodes,
                        only_successful=self.only_successful,
                        source="scripted",
                        should_stop=self.should_stop,
                        max_env_steps=self.env_step_budget,
                    )
                finally:
                    env.close()
                log.info(
                    "%s: %d demonstration steps from %d/%d scripted episodes",
                    request.ecm,
                    len(more),
                    more.episodes,
                    more.episodes_seen,
                )
                demos = demos.merged(more)
        if len(demos) < max(1, self.config.min_samples):
            raise Invalid(
                f"{request.ecm}: only {len(demos)} demonstration steps (need {max(1, self.config.min_samples)}); "
                "give traces with successful episodes or a task with a scripted reference",
                details={"field": "demos"},
            )
        return demos

    def provenance(self, request: LearnRequest, demos: Demos) -> Provenance:
        config = {
            "learner": "bc",
            "bc": self.config.to_dict(),
            "env": self.env_config.to_dict(),
            "task": request.task,
            "ecm": request.ecm,
            "parent": request.parent.version,
            "demos": {"source": demos.source, "samples": len(demos), "episodes": demos.episodes},
            "scripted_episodes": self.scripted_episodes,
            "only_successful": self.only_successful,
        }
        return Provenance(learner_id=self.learner_id, config_hash=config_hash(config), traces=demos.traces)

    def learn(
        self, request: LearnRequest, *, parent_artifact: bytes | None = None, demos: Demos | None = None
    ) -> Candidate:
        """Clone demonstrations into a SAC policy for ``request.ecm`` (origin ``il``).

        Args:
            request: The ECM, its parent (active) version, training seeds, recent outcomes.
            parent_artifact: The parent's bytes (default: the request's source or the registry).
            demos: Use these instead of gathering.

        Raises:
            Invalid: too few demonstrations, or a result that does not load.
        """
        with torch_threads(self.torch_threads):
            return self._learn(request, parent_artifact=parent_artifact, demos=demos)

    def _learn(self, request: LearnRequest, *, parent_artifact: bytes | None, demos: Demos | None) -> Candidate:
        target = target_for(request.task, request.ecm, request.parent)
        act_dim = task_spec(request.task).action_layout.dim
        state = LearnerState(self.state_dir, request.ecm) if self.state_dir is not None else None
        latest = state.latest() if state is not None else None
        artifact = latest if latest is not None else parent_artifact_of(request, self.registry, parent_artifact)
        warm = (latest is not None or request.parent.kind is Kind.NEURAL) and artifact is not None
        kwargs = sac_policy_kwargs(artifact) if warm and artifact is not None else None
        model = offline_sac(
            target.interface, act_dim, net_arch=self.config.net_arch, seed=self.config.seed, policy_kwargs=kwargs
        )
        if warm and artifact is not None:
            warm_start(model, artifact)
        if demos is None:
            demos = self.gather(request, target)
        new_rows = len(demos)
        gathered_steps = demos.env_steps
        demos, report, dagger = self.clone_keeping(model, request, target, demos, state)
        candidate = neural_candidate(
            model,
            target,
            request=request,
            origin=Origin.IL,
            provenance=self.provenance(request, demos),
            notes={
                "learner": self.learner_id,
                "modality": self.modality,
                "warm_start": warm,
                "continued": latest is not None,
                "demos": {
                    "source": demos.source,
                    "samples": len(demos),
                    "new_samples": new_rows,
                    "episodes": demos.episodes,
                    "episodes_seen": demos.episodes_seen,
                },
                "bc": report.to_dict(),
                "dagger": dagger,
                "env_steps": {
                    "demos": gathered_steps,
                    "dagger": dagger["env_steps"],
                    "total": gathered_steps + dagger["env_steps"],
                },
            },
        )
        if state is not None:
            state.save_latest(candidate.artifact)
        return candidate

    def clone_keeping(
        self,
        model: Any,
        request: LearnRequest,
        target: EcmTarget,
        demos: Demos,
        state: LearnerState | None,
        *,
        config: BcConfig | None = None,
    ) -> tuple[Demos, BcReport, dict[str, Any]]:
        """:meth:`clone` on every row ``state`` keeps for the ECM with ``demos`` appended, each
        DAgger round's rows kept there too, so clones of later updates fit everything gathered
        so far (None: ``demos`` alone). Returns what :meth:`clone` returns."""
        if state is None:
            return self.clone(model, request, target, demos, config=config)
        obs, action = state.add_demos(demos.obs, demos.action)
        if len(obs) > len(demos):
            demos = dataclasses.replace(demos, obs=obs, action=action, source=f"{demos.source}+earlier")
        return self.clone(
            model, request, target, demos, config=config, add_rows=lambda more: state.add_demos(more.obs, more.action)
        )

    def clone(
        self,
        model: Any,
        request: LearnRequest,
        target: EcmTarget,
        demos: Demos,
        *,
        config: BcConfig | None = None,
        add_rows: Callable[[Demos], tuple[np.ndarray, np.ndarray]] | None = None,
    ) -> tuple[Demos, BcReport, dict[str, Any]]:
        """Fit ``model``'s actor to ``demos``, then run ``config.dagger_rounds`` rounds of DAgger
        (see :class:`BcConfig`) with the task's scripted reference as the expert (none: no rounds).

        Args:
            model: The SAC model whose actor is fitted (in place).
            request: The ECM and task.
            target: The ECM's training target.
            demos: The demonstrations to start from.
            config: Cloning settings (default: this learner's).
            add_rows: Keeps each round's rows and returns every row so far (the learner's
                state); None merges them in memory.

        Returns:
            The demonstrations the last fit used, its report, and the DAgger record (``rounds``,
            ``expert``, ``env_steps``).
        """
        config = config or self.config
        total_epochs = config.epochs * (1 + config.dagger_rounds)
        report = behaviour_clone(model, demos, config, progress=self._progress_from(0, total_epochs))
        rounds: list[dict[str, Any]] = []
        expert = scripted_controller(request.task) if config.dagger_rounds else None
        for r in range(config.dagger_rounds if expert is not None else 0):
            left = None if self.env_step_budget is None else self.env_step_budget - demos.env_steps
            more = self._dagger_round(request, target, model, expert, r, config.dagger_episodes, left)
            if more.episodes_seen == 0:  # the budget is spent
                break
            rounds.append(
                {"round": r + 1, "episodes": more.episodes_seen, "rows": len(more), "env_steps": more.env_steps}
            )
            if add_rows is not None:
                obs, action = add_rows(more)
                demos = dataclasses.replace(
                    demos,
                    obs=obs,
                    action=action,
                    source=f"{demos.source}+dagger",
                    episodes_seen=demos.episodes_seen + more.episodes_seen,
                    env_steps=demos.env_steps + more.env_steps,
                )
            else:
                demos = demos.merged(more)
            progress = self._progress_from(config.epochs * (r + 1), total_epochs)
            report = behaviour_clone(model, demos, config, progress=progress)
        dagger = {
            "rounds": rounds,
            "expert": "scripted" if expert is not None else None,
            # the clone's rollouts, its predecessors' steps included
            "env_steps": sum(d["env_steps"] for d in rounds),
        }
        return demos, report, dagger

    def _progress_from(self, done: int, total: int) -> Callable[[int, int, float], Any] | None:
        """The progress callback, counting epochs over the first clone and every DAgger round."""
        if self.progress is None:
            return None
        progress = self.progress
        return lambda epoch, _epochs, loss: progress(done + epoch, total, loss)

    def _dagger_round(
        self,
        request: LearnRequest,
        target: EcmTarget,
        model: Any,
        expert: Controller,
        r: int,
        episodes: int,
        max_env_steps: int | None,
    ) -> Demos:
        """One DAgger round: ``model`` acts (deterministically) in the ECM's training environment,
        the scripted reference labels every observation it visits. Seeds follow the scripted
        demonstrations' (:class:`EcmEnv` invariant 3), so no round repeats another's episodes."""
        first = self.env_config.seed + self.scripted_episodes + r * episodes
        env = make_ecm_env(request.task, target, registry=self.registry, config=self.env_config)
        try:
            more = collect_demos(
                env,
                expert,
                episodes=episodes,
                only_successful=False,
                source="dagger",
                seed=first,
                should_stop=self.should_stop,
                driver=lambda obs: model.predict(obs, deterministic=True)[0],
                max_env_steps=max_env_steps,
            )
        finally:
            env.close()
        log.info(
            "%s: DAgger round %d: %d labelled steps from %d episodes of the clone",
            request.ecm,
            r + 1,
            len(more),
            more.episodes_seen,
        )
        return more
