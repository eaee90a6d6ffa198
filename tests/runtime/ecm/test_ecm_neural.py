"""Neural ECMs: a real SB3 zip, loaded without unpickling, acting deterministically."""

from __future__ import annotations

import base64
import contextlib
import io
import json
import pickle
import warnings
import zipfile
from pathlib import Path

import numpy as np
import pytest
from ecm_helpers import PENDULUM_INTERFACE

from capevo.errors import ErrorCode, Invalid
from capevo.records import Interface, IOSpec
from capevo.runtime.ecm import EcmInvoker, NeuralPolicy, Status, load_neural, load_sb3_policy
from capevo.runtime.state import ActionLayout

OBS = {"cos_sin": np.array([0.6, 0.8], dtype=np.float32), "omega": np.array([-1.5], dtype=np.float32)}


def _rewrite_data(artifact: bytes, edit: object) -> bytes:
    """The same zip with its ``data`` JSON passed through ``edit``."""
    src = zipfile.ZipFile(io.BytesIO(artifact))
    out = io.BytesIO()
    with zipfile.ZipFile(out, "w") as dst:
        for info in src.infolist():
            body = src.read(info.filename)
            if info.filename == "data":
                data = json.loads(body)
                edit(data)  # type: ignore[operator]
                body = json.dumps(data).encode()
            dst.writestr(info, body)
    return out.getvalue()


def _pickle_that_creates(path: Path) -> str:
    class Payload:
        def __reduce__(self) -> tuple[object, tuple[str, str]]:
            return (open, (str(path), "w"))

    return base64.b64encode(pickle.dumps(Payload())).decode()


def test_loads_on_cpu_and_matches_stable_baselines3(sac_zip: bytes) -> None:
    from stable_baselines3 import SAC

    loaded = load_sb3_policy(sac_zip)
    assert loaded.policy_class == "stable_baselines3.sac.policies.SACPolicy"
    assert (loaded.observation_dim, loaded.action_dim) == (3, 1)
    assert str(next(loaded.policy.parameters()).device) == "cpu"
    reference = SAC.load(io.BytesIO(sac_zip), device="cpu")
    for obs in (np.array([0.6, 0.8, -1.5], np.float32), np.array([1.0, 0.0, 0.0], np.float32)):
        want, _ = reference.predict(obs, deterministic=True)
        got, _ = loaded.policy.predict(obs, deterministic=True)
        np.testing.assert_array_equal(got, want)


def test_same_observation_gives_the_same_action(sac_zip: bytes) -> None:
    a = NeuralPolicy(sac_zip, inputs=PENDULUM_INTERFACE.inputs, outputs=PENDULUM_INTERFACE.outputs)
    b = NeuralPolicy(sac_zip, inputs=PENDULUM_INTERFACE.inputs, outputs=PENDULUM_INTERFACE.outputs)
    first = a.step(OBS, timeout_s=1).action
    assert first is not None and first.shape == (1,)
    for _ in range(5):
        np.testing.assert_array_equal(a.step(OBS, timeout_s=1).action, first)
    np.testing.assert_array_equal(b.step(OBS, timeout_s=1).action, first)
    other = a.step({"cos_sin": np.array([1.0, 0.0], np.float32), "omega": np.array([3.0], np.float32)}, timeout_s=1)
    assert other.action is not None and not np.array_equal(other.action, first)


def test_inputs_are_concatenated_in_interface_order(sac_zip: bytes) -> None:
    policy = NeuralPolicy(sac_zip, inputs=PENDULUM_INTERFACE.inputs)
    direct = policy.predict(np.array([0.6, 0.8, -1.5], np.float32))
    np.testing.assert_array_equal(policy.step(OBS, timeout_s=1).action, direct)


def test_invoked_deterministically_through_the_invoker(sac_zip: bytes) -> None:
    ecm = load_neural(sac_zip, name="swing", version=3, interface=PENDULUM_INTERFACE)
    inv = EcmInvoker(ecm, layout=ActionLayout(dim=1, arms=()), timeout_s=5.0)
    r1, r2 = inv.step(OBS), inv.step(OBS)
    assert r1.status is Status.OK and r1.action == r2.action
    assert r1.attempts[0].ecm == "swing" and r1.attempts[0].version == 3
    assert r1.action is not None and -2.0 <= r1.action[0] <= 2.0


@pytest.mark.parametrize(
    ("interface", "fragment"),
    [
        (
            Interface(inputs=(IOSpec(name="cos_sin", shape=(2,)),)),
            "inputs total 2 values (cos_sin[2]), but the policy observes 3",
        ),
        (Interface(), "inputs total 0 values (none)"),
        (
            Interface(inputs=PENDULUM_INTERFACE.inputs, outputs=(IOSpec(name="torque", shape=(2,)),)),
            "outputs total 2 values, but the policy acts in 1",
        ),
        (
            Interface(inputs=PENDULUM_INTERFACE.inputs, outputs=(IOSpec(name="torque", shape=(1,), high=1.0),)),
            "declares high 1.0, but the policy can act up to 2.0",
        ),
    ],
)
def test_interface_mismatch_is_invalid(sac_zip: bytes, interface: Interface, fragment: str) -> None:
    with pytest.raises(Invalid) as info:
        NeuralPolicy(sac_zip, inputs=interface.inputs, outputs=interface.outputs, name="swing@1")
    assert info.value.code is ErrorCode.INVALID
    assert fragment in info.value.message
    assert info.value.message.startswith("swing@1: ")


def test_loading_never_unpickles_what_the_zip_carries(sac_zip: bytes, tmp_path: Path) -> None:
    from stable_baselines3 import SAC

    canary = tmp_path / "pwned"

    def poison(data: dict) -> None:
        data["lr_schedule"][":serialized:"] = _pickle_that_creates(canary)
        data["smuggled"] = {":type:": "<class 'object'>", ":serialized:": _pickle_that_creates(canary)}

    poisoned = _rewrite_data(sac_zip, poison)
    policy = NeuralPolicy(poisoned, inputs=PENDULUM_INTERFACE.inputs)
    assert not canary.exists()
    np.testing.assert_array_equal(
        policy.step(OBS, timeout_s=1).action,
        NeuralPolicy(sac_zip, inputs=PENDULUM_INTERFACE.inputs).step(OBS, timeout_s=1).action,
    )
    # The control: stable-baselines3's own loader runs the payload.
    with warnings.catch_warnings(), contextlib.suppress(Exception):
        warnings.simplefilter("ignore")
        SAC.load(io.BytesIO(poisoned), device="cpu")
    assert canary.exists()


@pytest.mark.parametrize(
    ("edit", "fragment"),
    [
        (lambda d: d["policy_class"].__setitem__("__module__", "os"), "policy class module 'os' is not one of"),
        (
            lambda d: d.__setitem__(
                "policy_class",
                {k: v for k, v in d["policy_class"].items() if k in (":type:", ":serialized:", "__module__")},
            ),
            "cannot tell the policy class name",
        ),
        (
            lambda d: d.__setitem__(
                "policy_kwargs",
                {":type:": "<class 'dict'>", ":serialized:": "", "activation_fn": "<class 'os.system'>"},
            ),
            "policy_kwargs.activation_fn = \"<class 'os.system'>\" is not an allowed class",
        ),
        (
            lambda d: d["action_space"].__setitem__(":type:", "<class 'gymnasium.spaces.discrete.Discrete'>"),
            "must be a Box",
        ),
        (lambda d: d["observation_space"].__setitem__("low", "[-1. ... 1.]"), "not readable without unpickling"),
        (lambda d: d["observation_space"].__setitem__("low", "[-1. -1.]"), "has 2 values, expected 3"),
    ],
)
def test_artifacts_that_need_unpickling_are_refused(sac_zip: bytes, edit: object, fragment: str) -> None:
    with pytest.raises(Invalid) as info:
        load_sb3_policy(_rewrite_data(sac_zip, edit))
    assert fragment in info.value.message


def test_non_sb3_artifacts_are_invalid(sac_zip: bytes, tmp_path: Path) -> None:
    with pytest.raises(Invalid, match="not a zip file"):
        load_sb3_policy(b"definitely not a zip")
    buf = io.BytesIO()
    with zipfile.ZipFile(buf, "w") as zf:
        zf.writestr("hello.txt", "hi")
    with pytest.raises(Invalid, match="no 'data' entry"):
        load_sb3_policy(buf.getvalue())
    # policy.save() writes a torch pickle, which cannot be loaded without unpickling
    from stable_baselines3 import SAC

    model = SAC.load(io.BytesIO(sac_zip), device="cpu")
    model.policy.save(str(tmp_path / "policy.pt"))
    with pytest.raises(Invalid, match=r"policy.save\(\)/torch.save file"):
        load_sb3_policy((tmp_path / "policy.pt").read_bytes())


def test_corrupt_weights_are_invalid(sac_zip: bytes) -> None:
    src = zipfile.ZipFile(io.BytesIO(sac_zip))
    out = io.BytesIO()
    with zipfile.ZipFile(out, "w") as dst:
        for info in src.infolist():
            dst.writestr(info, b"garbage" if info.filename == "policy.pth" else src.read(info.filename))
    with pytest.raises(Invalid, match="weights unreadable"):
        load_sb3_policy(out.getvalue())
