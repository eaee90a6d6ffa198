"""Neural ECM artifacts: building SAC models for an ECM's interface, saving them, warm-starting
them from a parent's, and v0 seeds.

A neural ECM's artifact is the zip ``model.save()`` of a stable-baselines3 SAC model writes;
its observation is the ECM's interface inputs concatenated in interface order (float32), its
action the task's action vector in [-1, 1]. :func:`seed_policy` makes version 0 of a neural
ECM: a randomly initialised SAC policy (seeded, so reproducible) with a
:class:`~capevo.records.PublishSpec` of kind ``neural`` whose descriptor is the task
step's and whose interface is the built-in one (:func:`capevo.learner.ecm_env.default_interface`).

Invariants:
1. Every artifact this module writes loads with :func:`capevo.runtime.ecm.neural.load_sb3_policy`
   (no unpickling) into a policy whose observation dim is the interface's input size and whose
   action dim is the task's action dim.
2. Equal ``seed`` and ``net_arch`` give policies with equal weights.
3. Building a model needs no simulator: :class:`SpacesEnv` only carries the spaces.
4. After :func:`warm_start` the model's policy ``state_dict`` equals the parent's exactly.

Warm start reads the parent zip through SB3's ``set_parameters``-style loading, which takes only
``*.pth`` entries with ``torch.load(weights_only=True)``: nothing from the artifact is unpickled
(the architecture comes from the safe neural loader,
:func:`capevo.runtime.ecm.neural.load_sb3_policy`).
"""

from __future__ import annotations

import io
import logging
from collections.abc import Sequence
from typing import Any

import gymnasium as gym
import numpy as np

from capevo.errors import Invalid
from capevo.records import (
    DEFAULT_MEDIA_TYPES,
    Descriptor,
    EcmVersion,
    Interface,
    Kind,
    Origin,
    Provenance,
    PublishSpec,
)
from capevo.registry.api import Registry
from capevo.runtime.ecm.marshal import spec_size
from capevo.runtime.tasks import task_spec

log = logging.getLogger(__name__)

NEURAL_MEDIA_TYPE = DEFAULT_MEDIA_TYPES[Kind.NEURAL]
SEED_LEARNER_ID = "capevo.neural-seed"
DEFAULT_NET_ARCH: tuple[int, ...] = (256, 256)
SAC_POLICY_CLASS = "stable_baselines3.sac.policies.SACPolicy"
_POLICY_KWARG_KEYS = (
    "net_arch",
    "activation_fn",
    "log_std_init",
    "use_expln",
    "clip_mean",
    "n_critics",
    "optimizer_class",
    "optimizer_kwargs",
    "features_extractor_class",
    "features_extractor_kwargs",
    "normalize_images",
)


class SpacesEnv(gym.Env[np.ndarray, np.ndarray]):
    """An environment that only carries observation and action spaces (to build a model offline).

    ``reset`` returns zeros; ``step`` raises :class:`Invalid`: nothing can be simulated here.
    """

    metadata: dict[str, Any] = {"render_modes": []}  # noqa: RUF012 - gymnasium's class attribute

    def __init__(self, observation_space: gym.spaces.Box, action_space: gym.spaces.Box) -> None:
        self.observation_space = observation_space
        self.action_space = action_space

    def reset(self, *, seed: int | None = None, options: dict[str, Any] | None = None) -> tuple[np.ndarray, dict]:
        super().reset(seed=seed)
        return np.zeros(self.observation_space.shape, dtype=np.float32), {}

    def step(self, action: np.ndarray) -> tuple[np.ndarray, float, bool, bool, dict]:
        raise Invalid("SpacesEnv only carries spaces; train in a real environment")


def ecm_spaces(interface: Interface, action_dim: int) -> tuple[gym.spaces.Box, gym.spaces.Box]:
    """Observation and action spaces of a neural ECM with ``interface`` in a task of ``action_dim``.

    Raises:
        Invalid: no inputs declared, or outputs that do not total ``action_dim``.
    """
    if not interface.inputs:
        raise Invalid("a neural ECM needs declared interface inputs", details={"field": "interface.inputs"})
    if interface.outputs and sum(spec_size(s) for s in interface.outputs) != action_dim:
        raise Invalid(
            f"interface outputs total {sum(spec_size(s) for s in interface.outputs)} values, the task acts in "
            f"{action_dim}",
            details={"field": "interface.outputs"},
        )
    n = sum(spec_size(s) for s in interface.inputs)
    obs = gym.spaces.Box(-np.inf, np.inf, shape=(n,), dtype=np.float32)
    act = gym.spaces.Box(-1.0, 1.0, shape=(action_dim,), dtype=np.float32)
    return obs, act


def new_sac(
    env: gym.Env[Any, Any],
    *,
    net_arch: Sequence[int] = DEFAULT_NET_ARCH,
    seed: int = 0,
    policy_kwargs: dict[str, Any] | None = None,
    **sac_kwargs: Any,
) -> Any:
    """A fresh SAC model on CPU for ``env`` (an :class:`~capevo.learner.ecm_env.EcmEnv` or
    :class:`SpacesEnv`).

    Args:
        env: The environment (only its spaces are used until training).
        net_arch: Hidden layer sizes of actor and critics (ignored when ``policy_kwargs`` is given).
        seed: Seeds the weights and SAC's sampling.
        policy_kwargs: Full policy arguments (e.g. a warm-start parent's).
        **sac_kwargs: Other SAC arguments (gamma, tau, buffer_size, batch_size, ...).

    Returns:
        A ``stable_baselines3.SAC``.
    """
    from stable_baselines3 import SAC

    kwargs = dict(policy_kwargs) if policy_kwargs is not None else {"net_arch": [int(n) for n in net_arch]}
    sac_kwargs.setdefault("buffer_size", 1)
    return SAC("MlpPolicy", env, policy_kwargs=kwargs, seed=seed, device="cpu", verbose=0, **sac_kwargs)


def silent_logger() -> Any:
    """An SB3 logger with no outputs, for ``model.set_logger`` before ``learn``.

    Without one, every ``learn`` call makes SB3 create an empty ``$TMPDIR/SB3-<time>`` directory
    (``stable_baselines3.common.logger.configure`` makes its folder even with no output formats).
    """
    from stable_baselines3.common.logger import Logger

    return Logger(folder=None, output_formats=[])


def model_bytes(model: Any) -> bytes:
    """The zip ``model.save()`` writes, as bytes (the neural artifact)."""
    buf = io.BytesIO()
    model.save(buf)
    return buf.getvalue()


# --- warm start ----------------------------------------------------------------------------


def sac_policy_kwargs(artifact: bytes) -> dict[str, Any]:
    """The policy arguments of a SAC model zip, read by the safe neural loader (no unpickling).

    Raises:
        Invalid: not a loadable SB3 zip, or not a SAC policy.
    """
    from capevo.runtime.ecm.neural import load_sb3_policy

    loaded = load_sb3_policy(artifact)
    if loaded.policy_class != SAC_POLICY_CLASS:
        raise Invalid(
            f"warm start needs a SAC parent; the parent is a {loaded.policy_class}", details={"field": "parent"}
        )
    ctor = loaded.policy._get_constructor_parameters()
    return {k: ctor[k] for k in _POLICY_KWARG_KEYS if k in ctor}


def warm_start(model: Any, artifact: bytes) -> None:
    """Load every parameter of the SAC zip ``artifact`` into ``model`` (built with its architecture).

    The policy (actor, critics, target critics) must match exactly; the optimizers' states and
    the entropy coefficient are loaded when the model has the same ones (else they start fresh).

    Raises:
        Invalid: the zip is unreadable or its policy does not match ``model``'s.
    """
    from stable_baselines3.common.save_util import load_from_zip_file

    try:
        _, params, variables = load_from_zip_file(io.BytesIO(artifact), device="cpu", load_data=False)
    except Exception as exc:  # SB3 and torch raise many types on corrupt input
        raise Invalid(f"warm start: parent weights unreadable: {type(exc).__name__}: {exc}") from None
    if "policy" not in params:
        raise Invalid("warm start: the parent zip holds no policy weights")
    try:
        model.policy.load_state_dict(params["policy"], strict=True)
    except RuntimeError as exc:
        raise Invalid(f"warm start: the parent's policy does not match the model: {exc}") from None
    wanted, _ = model._get_torch_save_params()
    for name in wanted:
        if name == "policy" or name not in params:
            continue
        try:
            model.set_parameters({name: params[name]}, exact_match=False, device="cpu")
        except (ValueError, RuntimeError, KeyError) as exc:
            log.warning("warm start: %s not restored (%s); it starts fresh", name, exc)
    log_ent = getattr(model, "log_ent_coef", None)
    saved = (variables or {}).get("log_ent_coef")
    if log_ent is not None and saved is not None and tuple(saved.shape) == tuple(log_ent.shape):
        log_ent.data.copy_(saved.data)


def policy_state(model_or_policy: Any) -> dict[str, np.ndarray]:
    """The policy's parameters as numpy arrays (copies), for comparisons."""
    policy = getattr(model_or_policy, "policy", model_or_policy)
    return {k: v.detach().cpu().numpy().copy() for k, v in policy.state_dict().items()}


def offline_sac(
    interface: Interface,
    action_dim: int,
    *,
    net_arch: Sequence[int] = DEFAULT_NET_ARCH,
    seed: int = 0,
    policy_kwargs: dict[str, Any] | None = None,
) -> Any:
    """A fresh SAC model for ``interface`` without a simulator (for seeding and cloning)."""
    obs, act = ecm_spaces(interface, action_dim)
    return new_sac(SpacesEnv(obs, act), net_arch=net_arch, seed=seed, policy_kwargs=policy_kwargs)


def neural_spec(
    task: str,
    ecm: str,
    *,
    interface: Interface | None = None,
    descriptor: Descriptor | None = None,
    origin: Origin = Origin.MANUAL,
    parent: int | None = None,
    provenance: Provenance | None = None,
) -> PublishSpec:
    """A :class:`PublishSpec` of kind ``neural`` for ``ecm`` of ``task``.

    Args:
        interface: Default: the step's built-in interface.
        descriptor: Default: the step's descriptor.
        origin, parent, provenance: As recorded in the registry.

    Raises:
        Invalid: ``ecm`` is not in the task's decomposition.
    """
    from capevo.learner.ecm_env import default_interface, step_of

    spec = task_spec(task)
    step = step_of(spec, ecm)
    return PublishSpec(
        kind=Kind.NEURAL,
        descriptor=descriptor if descriptor is not None else step.descriptor(),
        interface=interface if interface is not None else default_interface(spec, ecm),
        media_type=NEURAL_MEDIA_TYPE,
        parent=parent,
        origin=origin,
        provenance=provenance or Provenance(learner_id=SEED_LEARNER_ID),
    )


def seed_policy(
    task: str, ecm: str, *, net_arch: Sequence[int] = DEFAULT_NET_ARCH, seed: int = 0
) -> tuple[bytes, PublishSpec]:
    """Version 0 of a neural ECM: a randomly initialised SAC policy and its publish spec.

    Args:
        task: Task id or name.
        ecm: An ECM of the task's decomposition.
        net_arch: Hidden layer sizes.
        seed: Seeds the initial weights.

    Returns:
        ``(model zip bytes, spec)`` ready for ``registry.publish``.

    Raises:
        Invalid: ``ecm`` is not in the task's decomposition, or bad ``net_arch``.
    """
    arch = tuple(net_arch)
    if not arch or any(isinstance(n, bool) or not isinstance(n, int) or n < 1 for n in arch):
        raise Invalid(f"net_arch must be positive layer sizes, got {list(arch)!r}", details={"field": "net_arch"})
    spec = neural_spec(task, ecm)
    model = offline_sac(spec.interface, task_spec(task).action_layout.dim, net_arch=arch, seed=seed)
    return model_bytes(model), spec


def seed_neural_registry(
    registry: Registry,
    task: str,
    *,
    ecms: Sequence[str] | None = None,
    promote: bool = True,
    net_arch: Sequence[int] = DEFAULT_NET_ARCH,
    seed: int = 0,
    reason: str = "neural v0 (random init)",
) -> list[EcmVersion]:
    """Publish (and by default promote) a random-init neural v0 of each named ECM of ``task``.

    Args:
        registry: Where to publish.
        task: Task id or name.
        ecms: Which ECMs; default every ECM of the decomposition.
        promote: Make each new version active.
        net_arch, seed: As :func:`seed_policy` (each ECM gets ``seed + its index``).
        reason: Audit reason of the promotions.

    Returns:
        The records published (after promotion when ``promote``).
    """
    names = list(ecms) if ecms is not None else list(task_spec(task).ecm_names)
    out = []
    for i, name in enumerate(names):
        artifact, spec = seed_policy(task, name, net_arch=net_arch, seed=seed + i)
        record = registry.publish(name, artifact, spec)
        if promote:
            record = registry.promote(name, record.version, reason=reason)
        out.append(record)
    return out
