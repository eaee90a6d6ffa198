"""Code ECMs in-process: the contract, θ override, and source rewriting for learners."""

from __future__ import annotations

import math
import textwrap

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from capevo.errors import ErrorCode, Invalid, SandboxViolation
from capevo.runtime.ecm import code as code_module
from capevo.runtime.ecm.code import CodeSkill, read_params, with_params

SKILL = '''"""A skill with comments that must survive rewriting."""
import numpy as np

# θ, tuned by learners
PARAMS = {
    "gain": 8.0,   # proportional gain
    "hover": 0.1,
}


def act(obs, params):
    return [params["gain"] * float(obs["x"][0]), params["hover"]]


def done(obs, params):
    return float(obs["x"][0]) > 1.0
'''


def _readme_example() -> str:
    doc = code_module.__doc__ or ""
    block = doc.split("Example::", 1)[1].split("Invariants:", 1)[0]
    return textwrap.dedent(block).strip("\n") + "\n"


def test_the_documented_example_skill_is_valid_and_runs() -> None:
    skill = CodeSkill(_readme_example())
    obs = {
        "cube_pos": np.array([0.1, 0.0, 0.8], np.float32),
        "robot0_eef_pos": np.array([0.0, 0.0, 1.0], np.float32),
    }
    step = skill.step(obs, timeout_s=1)
    assert not step.done and step.action is not None and step.action.shape == (7,)
    assert step.action[0] == pytest.approx(0.8) and step.action[6] == -1.0
    at_target = {"cube_pos": obs["cube_pos"], "robot0_eef_pos": np.array([0.1, 0.0, 0.9], np.float32)}
    assert skill.step(at_target, timeout_s=1).done
    assert read_params(_readme_example()) == {"gain": 8.0, "hover": 0.1, "tol": 0.01}


def test_act_done_and_params_override() -> None:
    skill = CodeSkill(SKILL, {"gain": 2.0})
    assert skill.defaults == {"gain": 8.0, "hover": 0.1}
    assert skill.params == {"gain": 2.0, "hover": 0.1}
    assert skill.act({"x": np.array([0.5])}).tolist() == [1.0, 0.1]
    assert not skill.done({"x": np.array([0.5])})
    assert skill.step({"x": np.array([2.0])}, timeout_s=1).done
    assert skill.set_params({"hover": 0.3}) == {"gain": 8.0, "hover": 0.3}
    assert skill.act({"x": np.array([0.5])}).tolist() == [4.0, 0.3]
    with pytest.raises(Invalid, match=r"unknown parameter\(s\) \['speed'\]"):
        CodeSkill(SKILL, {"speed": 1.0})


def test_skills_cannot_mutate_their_params() -> None:
    skill = CodeSkill("def act(obs, params):\n    params['gain'] = 0.0\n    return [1.0]\nPARAMS = {'gain': 1.0}\n")
    with pytest.raises(TypeError):
        skill.act({})
    assert skill.params == {"gain": 1.0}


def test_a_skill_without_done_never_terminates() -> None:
    skill = CodeSkill("def act(obs, params):\n    return [0.0]\n")
    assert skill.params == {}
    assert not skill.done({}) and not skill.step({}, timeout_s=1).done


def test_in_process_code_is_validated_too() -> None:
    with pytest.raises(SandboxViolation) as info:
        CodeSkill("import os\ndef act(obs, params):\n    return [0.0]\n")
    assert info.value.code is ErrorCode.SANDBOX_VIOLATION and info.value.details["line"] == 1


# --- read_params / with_params -------------------------------------------------------


def test_read_params_without_running_code() -> None:
    # The top-level code would raise if run; read_params only parses.
    source = "raise SystemError('never runs')\nPARAMS: dict[str, float] = {'a': -1, 'b': 2.5e-3}\n"
    assert read_params(source) == {"a": -1.0, "b": 0.0025}
    assert read_params("def act(o, p):\n    return [0]\n") == {}


@pytest.mark.parametrize(
    ("source", "fragment"),
    [
        ("PARAMS = dict(a=1)", "must be a literal dict"),
        ("PARAMS = {'a': 1}\nPARAMS = {'a': 2}", "assigned 2 times"),
        ("PARAMS = X = {'a': 1}", "must be assigned on its own"),
        ("PARAMS = {'a': 'fast'}", "must be a number"),
        ("PARAMS = {1: 2.0}", "keys must be non-empty strings"),
        ("PARAMS = {'a': 1e999}", "must be finite"),
        ("PARAMS = {", "not valid Python"),
    ],
)
def test_bad_params_literals_are_invalid(source: str, fragment: str) -> None:
    with pytest.raises(Invalid) as info:
        read_params(source)
    assert fragment in info.value.message


def test_with_params_rewrites_only_the_literal() -> None:
    out = with_params(SKILL, {"gain": 3.5})
    assert read_params(out) == {"gain": 3.5, "hover": 0.1}
    before, after = SKILL.split("PARAMS = ", 1)[0], SKILL.split("\n}\n", 1)[1]
    assert out.startswith(before + "PARAMS = {")
    assert out.endswith(after)
    assert CodeSkill(out).act({"x": np.array([1.0])}).tolist() == [3.5, 0.1]


def test_with_params_handles_unicode_and_crlf() -> None:
    source = "# é ü\r\nX = 'ß'; PARAMS = {'ä': 1.0, 'b': 2}  # ñ\r\ndef act(o, p):\r\n    return [p['ä']]\r\n"
    out = with_params(source, {"ä": 4.0})
    assert read_params(out) == {"ä": 4.0, "b": 2.0}
    assert out.startswith("# é ü\r\nX = 'ß'; PARAMS = {")
    assert out.endswith("}  # ñ\r\ndef act(o, p):\r\n    return [p['ä']]\r\n")


def test_with_params_errors() -> None:
    with pytest.raises(Invalid, match="declares no PARAMS literal"):
        with_params("def act(o, p):\n    return [0]\n", {"a": 1.0})
    with pytest.raises(Invalid, match="unknown parameter"):
        with_params(SKILL, {"nope": 1.0})
    with pytest.raises(Invalid, match="must be finite"):
        with_params(SKILL, {"gain": math.nan})


_finite = st.floats(allow_nan=False, allow_infinity=False, width=64)


@settings(max_examples=200, deadline=None)
@given(gain=_finite, hover=_finite, only_one=st.booleans())
def test_with_params_round_trips(gain: float, hover: float, only_one: bool) -> None:
    new = {"gain": gain} if only_one else {"gain": gain, "hover": hover}
    out = with_params(SKILL, new)
    want = {"gain": 8.0, "hover": 0.1, **new}
    assert read_params(out) == want
    assert with_params(out, {}) == with_params(out, want)
    assert CodeSkill(out).params == want
