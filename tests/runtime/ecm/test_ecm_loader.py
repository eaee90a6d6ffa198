"""Loading registry versions by kind, and the trust policy that routes code."""

from __future__ import annotations

import numpy as np
import pytest
from ecm_helpers import PENDULUM_INTERFACE, make_record

from capevo.errors import Corrupt, ErrorCode, Invalid, SandboxViolation
from capevo.records import Kind, Origin
from capevo.runtime.ecm import (
    SANDBOX_EVERYTHING,
    CodeSkill,
    LoadOptions,
    NeuralPolicy,
    TrustPolicy,
    load_ecm,
    make_loader,
)
from capevo.runtime.ecm.trust import parse_origins
from capevo.runtime.sandbox import SandboxedSkill

SOURCE = b"PARAMS = {'gain': 1.0}\ndef act(obs, params):\n    return [params['gain']]\n"


@pytest.mark.parametrize(
    ("origin", "in_process"),
    [
        (Origin.MANUAL, True),
        (Origin.LLM, False),
        (Origin.HYBRID, False),
        (Origin.RL, False),
        (Origin.CLONE, False),
    ],
)
def test_default_trust_runs_only_manual_code_in_process(origin: Origin, in_process: bool) -> None:
    ecm = load_ecm(make_record("reach", SOURCE, origin=origin), SOURCE)
    try:
        assert ecm.in_process is in_process
        assert isinstance(ecm.runner, CodeSkill if in_process else SandboxedSkill)
        step = ecm.runner.step({}, timeout_s=5)  # type: ignore[union-attr]
        assert step.action is not None and step.action.tolist() == [1.0]
    finally:
        ecm.close()


def test_trust_policy_is_configurable() -> None:
    trusting = LoadOptions(trust=TrustPolicy(in_process_origins=frozenset({Origin.MANUAL, Origin.LLM})))
    ecm = load_ecm(make_record("reach", SOURCE, origin=Origin.LLM), SOURCE, options=trusting)
    assert isinstance(ecm.runner, CodeSkill)
    paranoid = LoadOptions(trust=SANDBOX_EVERYTHING, params_override={"gain": 3.0})
    ecm = load_ecm(make_record("reach", SOURCE, origin=Origin.MANUAL), SOURCE, options=paranoid)
    try:
        assert isinstance(ecm.runner, SandboxedSkill)
        assert ecm.runner.params == {"gain": 3.0}
    finally:
        ecm.close()
    assert TrustPolicy.from_dict(TrustPolicy().to_dict()) == TrustPolicy()
    with pytest.raises(Invalid, match="unknown origin 'gpt'; valid: manual, llm"):
        parse_origins(["manual", "gpt"])


def test_untrusted_code_is_validated_before_a_worker_starts() -> None:
    bad = b"import os\ndef act(obs, params):\n    return [0.0]\n"
    with pytest.raises(SandboxViolation) as info:
        load_ecm(make_record("evil", bad, origin=Origin.LLM), bad)
    assert info.value.details["construct"] == "import os"


def test_artifact_hash_is_checked() -> None:
    record = make_record("reach", SOURCE)
    with pytest.raises(Corrupt) as info:
        load_ecm(record, SOURCE + b"# tampered\n")
    assert info.value.code is ErrorCode.CORRUPT
    assert "does not match the record's" in str(info.value)


def test_neural_versions_load_from_records(sac_zip: bytes) -> None:
    record = make_record("swing", sac_zip, kind=Kind.NEURAL, origin=Origin.RL, interface=PENDULUM_INTERFACE)
    ecm = load_ecm(record, sac_zip)
    assert isinstance(ecm.runner, NeuralPolicy) and ecm.in_process
    obs = {"cos_sin": np.array([1.0, 0.0], np.float32), "omega": np.zeros(1, np.float32)}
    assert ecm.runner.step(obs, timeout_s=1).action.shape == (1,)  # type: ignore[union-attr]


def test_prompt_versions_expose_their_text() -> None:
    text = b"You are a careful planner.\n"
    ecm = load_ecm(make_record("planner", text, kind=Kind.PROMPT), text)
    assert ecm.text == "You are a careful planner.\n" and ecm.runner is None
    bad = b"\xff\xfe"
    with pytest.raises(Invalid, match="prompt is not UTF-8"):
        load_ecm(make_record("planner", bad, kind=Kind.PROMPT), bad)


def test_code_must_be_utf8() -> None:
    bad = b"\xff def act"
    with pytest.raises(Invalid, match="code artifact is not UTF-8"):
        load_ecm(make_record("reach", bad), bad)


def test_loader_registry_lists_valid_kinds() -> None:
    assert make_loader("code") is make_loader(Kind.CODE)
    with pytest.raises(Invalid) as info:
        make_loader("wasm")
    assert info.value.message == "no loader for kind 'wasm'; valid: code, neural, prompt"
