"""Neural ECMs: a stable-baselines3 model zip, loaded on CPU without unpickling anything.

The artifact is the zip ``model.save(...)`` writes (SAC, TD3, DDPG, PPO, A2C with Box
observation and action spaces). A plain ``SB3.load`` would unpickle the zip's
``:serialized:`` entries (policy class, spaces, schedules) with cloudpickle, i.e. run
whatever code the artifact carries. Here every such entry is rebuilt from the zip's
readable JSON fields instead and handed to SB3 as ``custom_objects`` (which SB3 uses
*instead of* unpickling); the weights are read with ``torch.load(weights_only=True)``.
Only policy classes from stable_baselines3's own policy modules and activation or
feature-extractor classes from an allow-list are accepted. ``policy.save()`` files are
refused: they need full unpickling.

Observation = the ECM's interface inputs, concatenated in order as float32
(:func:`capevo.runtime.ecm.marshal.flatten_inputs`); the action is
``policy.predict(obs, deterministic=True)``.

Invariants:
1. Loading never unpickles: every ``:serialized:`` key of the zip's ``data`` is covered by
   a custom object before SB3 reads it, or loading fails with :class:`Invalid`.
2. The same observation always gives the same action (deterministic prediction).
3. A loaded policy's observation dim equals the interface's total input size and its
   action dim equals the total output size (when outputs are declared), else
   :class:`Invalid` at load.
"""

from __future__ import annotations

import importlib
import inspect
import io
import json
import math
import re
import zipfile
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from capevo.errors import Invalid
from capevo.records import IOSpec
from capevo.runtime.ecm.marshal import flatten_inputs, output_size, spec_size
from capevo.runtime.sandbox.client import SkillStep

MAX_UNZIPPED_BYTES = 512 * 1024 * 1024
"""Refuse zips that would inflate beyond this (zip bombs)."""

POLICY_MODULES: frozenset[str] = frozenset(
    {
        "stable_baselines3.common.policies",
        "stable_baselines3.sac.policies",
        "stable_baselines3.td3.policies",
        "stable_baselines3.ppo.policies",
        "stable_baselines3.a2c.policies",
        "stable_baselines3.ddpg.policies",
    }
)
"""Modules a policy class may come from."""

_CLASS_ALLOW: dict[str, tuple[str, str]] = {
    # repr module path -> (module to import, attribute)
    **{
        f"torch.nn.modules.activation.{n}": ("torch.nn", n)
        for n in ("ReLU", "Tanh", "ELU", "LeakyReLU", "SiLU", "GELU", "Sigmoid", "Softplus", "Mish", "SELU")
    },
    **{
        f"stable_baselines3.common.torch_layers.{n}": ("stable_baselines3.common.torch_layers", n)
        for n in ("FlattenExtractor", "CombinedExtractor", "NatureCNN")
    },
    **{f"torch.optim.{m}.{n}": ("torch.optim", n) for m, n in (("adam", "Adam"), ("adamw", "AdamW"), ("sgd", "SGD"))},
    **{f"torch.optim.rmsprop.{n}": ("torch.optim", n) for n in ("RMSprop",)},
}
_CLASS_REPR = re.compile(r"^<class '([\w.]+)'>$")
_FUNC_REPR = re.compile(r"^<function (\w+)\.\w+ at 0x[0-9a-f]+>$")
_BOX_TYPES = frozenset({"<class 'gymnasium.spaces.box.Box'>", "<class 'gym.spaces.box.Box'>"})


@dataclass(frozen=True, slots=True)
class LoadedPolicy:
    """An SB3 policy ready for prediction, and what its zip said about it."""

    policy: Any
    observation_dim: int
    action_dim: int
    action_low: np.ndarray
    action_high: np.ndarray
    policy_class: str


def _zip_data(artifact: bytes) -> dict[str, Any]:
    try:
        zf = zipfile.ZipFile(io.BytesIO(artifact))
    except (zipfile.BadZipFile, ValueError) as exc:
        raise Invalid(f"neural artifact is not a zip file: {exc}") from None
    with zf:
        infos = zf.infolist()
        if sum(i.file_size for i in infos) > MAX_UNZIPPED_BYTES:
            raise Invalid(f"neural artifact inflates beyond {MAX_UNZIPPED_BYTES} bytes")
        names = {i.filename for i in infos}
        if "data" not in names:
            if any(n.endswith("data.pkl") for n in names):
                raise Invalid(
                    "neural artifact is a policy.save()/torch.save file, which can only be loaded by "
                    "unpickling; publish the zip that model.save() writes instead"
                )
            raise Invalid("neural artifact has no 'data' entry; it is not a stable-baselines3 model zip")
        if "policy.pth" not in names:
            raise Invalid("neural artifact has no 'policy.pth' entry")
        try:
            data = json.loads(zf.read("data"))
        except (ValueError, zipfile.BadZipFile, RuntimeError) as exc:
            raise Invalid(f"neural artifact 'data' is not JSON: {exc}") from None
    if not isinstance(data, dict):
        raise Invalid("neural artifact 'data' is not a JSON object")
    return data


def _resolve_class(text: str, where: str) -> type:
    m = _CLASS_REPR.match(text)
    target = _CLASS_ALLOW.get(m.group(1)) if m else None
    if target is None:
        raise Invalid(
            f"neural artifact: {where} = {text[:120]!r} is not an allowed class (loading it needs unpickling)"
        )
    return getattr(importlib.import_module(target[0]), target[1])  # type: ignore[no-any-return]


def _policy_class(entry: object) -> type:
    if not isinstance(entry, dict):
        raise Invalid("neural artifact: policy_class is missing")
    module = entry.get("__module__")
    if module not in POLICY_MODULES:
        raise Invalid(f"neural artifact: policy class module {module!r} is not one of {sorted(POLICY_MODULES)}")
    name = None
    init = entry.get("__init__")
    candidates = [init] if isinstance(init, str) else []
    candidates += [v for v in entry.values() if isinstance(v, str)]
    for text in candidates:
        m = _FUNC_REPR.match(text)
        if m:
            name = m.group(1)
            break
    if name is None:
        raise Invalid("neural artifact: cannot tell the policy class name from the zip")
    from stable_baselines3.common.policies import BasePolicy

    cls = getattr(importlib.import_module(module), name, None)
    if not (isinstance(cls, type) and issubclass(cls, BasePolicy)):
        raise Invalid(f"neural artifact: {module}.{name} is not a stable-baselines3 policy class")
    return cls


def _parse_numbers(text: object, count: int, where: str) -> np.ndarray:
    if not isinstance(text, str) or "..." in text:
        raise Invalid(f"neural artifact: {where} is not readable without unpickling")
    tokens = text.replace("[", " ").replace("]", " ").split()
    try:
        values = np.array([float(t) for t in tokens], dtype=np.float64)
    except ValueError:
        raise Invalid(f"neural artifact: {where} is not a list of numbers") from None
    if values.size != count:
        raise Invalid(f"neural artifact: {where} has {values.size} values, expected {count}")
    return values


def _box(entry: object, where: str) -> Any:
    from gymnasium import spaces

    if not isinstance(entry, dict) or entry.get(":type:") not in _BOX_TYPES:
        got = entry.get(":type:") if isinstance(entry, dict) else type(entry).__name__
        raise Invalid(f"neural artifact: {where} must be a Box space, got {got}")
    try:
        raw_shape = entry["_shape"]
        shape = tuple(int(s) for s in (raw_shape if isinstance(raw_shape, list) else json.loads(str(raw_shape))))
        dtype = np.dtype(str(entry.get("dtype", "float32")))
    except (KeyError, ValueError, TypeError) as exc:
        raise Invalid(f"neural artifact: {where} shape/dtype unreadable: {exc}") from None
    n = math.prod(shape)
    low = _parse_numbers(entry.get("low"), n, f"{where}.low").reshape(shape)
    high = _parse_numbers(entry.get("high"), n, f"{where}.high").reshape(shape)
    return spaces.Box(low=low.astype(dtype), high=high.astype(dtype), shape=shape, dtype=dtype)


def _policy_kwargs(entry: object) -> dict[str, Any]:
    if entry is None:
        return {}
    if not isinstance(entry, dict):
        raise Invalid("neural artifact: policy_kwargs is not an object")
    serialized = ":serialized:" in entry
    out: dict[str, Any] = {}
    for key, value in entry.items():
        if key in (":type:", ":serialized:"):
            continue
        if serialized and isinstance(value, str) and value.startswith("<"):
            out[key] = _resolve_class(value, f"policy_kwargs.{key}")
        else:
            out[key] = value
    out.pop("device", None)
    return out


def _constant_schedule(_progress: float) -> float:
    return 0.0


def load_sb3_policy(artifact: bytes) -> LoadedPolicy:
    """Rebuild an SB3 policy from model-zip bytes on CPU without unpickling.

    Raises:
        Invalid: not a supported SB3 zip, or an entry that only unpickling could restore.
    """
    from stable_baselines3.common.save_util import load_from_zip_file

    data = _zip_data(artifact)
    policy_cls = _policy_class(data.get("policy_class"))
    obs_space = _box(data.get("observation_space"), "observation_space")
    act_space = _box(data.get("action_space"), "action_space")
    kwargs = _policy_kwargs(data.get("policy_kwargs"))
    custom: dict[str, Any] = {
        key: None for key, value in data.items() if isinstance(value, dict) and ":serialized:" in value
    }
    custom.update(
        policy_class=policy_cls,
        observation_space=obs_space,
        action_space=act_space,
        policy_kwargs=kwargs,
        lr_schedule=_constant_schedule,
    )
    try:
        _, params, _ = load_from_zip_file(io.BytesIO(artifact), device="cpu", custom_objects=custom)
    except Exception as exc:  # SB3 and torch raise many types on corrupt input
        raise Invalid(f"neural artifact: weights unreadable: {type(exc).__name__}: {exc}") from None
    if not params or "policy" not in params:
        raise Invalid("neural artifact: no policy weights")
    ctor_kwargs = dict(kwargs)
    # On-policy algorithms pass use_sde beside policy_kwargs, not inside them.
    takes_sde = "use_sde" in inspect.signature(policy_cls).parameters
    if takes_sde and "use_sde" not in ctor_kwargs and isinstance(data.get("use_sde"), bool):
        ctor_kwargs["use_sde"] = data["use_sde"]
    try:
        policy = policy_cls(obs_space, act_space, _constant_schedule, **ctor_kwargs)
        policy.load_state_dict(params["policy"])
    except Exception as exc:  # constructor and load_state_dict raise TypeError/RuntimeError/KeyError
        raise Invalid(f"neural artifact: policy does not match its weights: {type(exc).__name__}: {exc}") from None
    policy.set_training_mode(False)
    policy.to("cpu")
    if len(obs_space.shape) != 1 or len(act_space.shape) != 1:
        raise Invalid(
            f"neural artifact: observation and action spaces must be flat vectors, got "
            f"{obs_space.shape} and {act_space.shape}"
        )
    return LoadedPolicy(
        policy=policy,
        observation_dim=int(obs_space.shape[0]),
        action_dim=int(act_space.shape[0]),
        action_low=np.asarray(act_space.low, dtype=np.float64),
        action_high=np.asarray(act_space.high, dtype=np.float64),
        policy_class=f"{policy_cls.__module__}.{policy_cls.__name__}",
    )


class NeuralPolicy:
    """A neural ECM runner: marshalled inputs -> deterministic SB3 action, on CPU, in-process.

    Args:
        artifact: Model-zip bytes.
        inputs: Interface inputs; their total size must equal the policy's observation dim.
        outputs: Interface outputs; when given, their total size must equal the action dim
            and declared bounds must contain the policy's action space.
        name: Used in messages.

    Raises:
        Invalid: unsupported or unsafe artifact, or an interface mismatch.
    """

    in_process = True

    def __init__(
        self, artifact: bytes, *, inputs: Sequence[IOSpec], outputs: Sequence[IOSpec] = (), name: str = "policy"
    ) -> None:
        self.loaded = load_sb3_policy(artifact)
        self.inputs = tuple(inputs)
        want_obs = sum(spec_size(s) for s in self.inputs)
        if want_obs != self.loaded.observation_dim:
            raise Invalid(
                f"{name}: interface inputs total {want_obs} values "
                f"({', '.join(f'{s.name}{list(s.shape)}' for s in self.inputs) or 'none'}), "
                f"but the policy observes {self.loaded.observation_dim}",
                details={"field": "interface.inputs", "expected": self.loaded.observation_dim, "got": want_obs},
            )
        if outputs:
            want_act = output_size(outputs)
            if want_act != self.loaded.action_dim:
                raise Invalid(
                    f"{name}: interface outputs total {want_act} values, but the policy acts in "
                    f"{self.loaded.action_dim}",
                    details={"field": "interface.outputs", "expected": self.loaded.action_dim, "got": want_act},
                )
            _check_action_bounds(outputs, self.loaded, name)

    def predict(self, observation: np.ndarray) -> np.ndarray:
        """Deterministic action for one flat float32 observation."""
        action, _ = self.loaded.policy.predict(observation, deterministic=True)
        return np.asarray(action, dtype=np.float64)

    def step(self, inputs: Mapping[str, np.ndarray], *, timeout_s: float) -> SkillStep:
        """One action; a neural ECM never terminates itself (its descriptor's predicate does)."""
        return SkillStep(done=False, action=self.predict(flatten_inputs(inputs, self.inputs)))

    def close(self) -> None:
        """Nothing to release."""


def _check_action_bounds(outputs: Sequence[IOSpec], loaded: LoadedPolicy, name: str) -> None:
    i = 0
    for spec in outputs:
        n = spec_size(spec)
        low = loaded.action_low[i : i + n]
        high = loaded.action_high[i : i + n]
        if spec.low is not None and bool(np.any(low < spec.low)):
            raise Invalid(
                f"{name}: output {spec.name!r} declares low {spec.low}, but the policy can act down to {low.min()}",
                details={"field": f"interface.outputs.{spec.name}.low"},
            )
        if spec.high is not None and bool(np.any(high > spec.high)):
            raise Invalid(
                f"{name}: output {spec.name!r} declares high {spec.high}, but the policy can act up to {high.max()}",
                details={"field": f"interface.outputs.{spec.name}.high"},
            )
        i += n
