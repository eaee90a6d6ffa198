"""LLM code synthesis against a real local chat server: prompts, accepted edits, rejected code
that never runs, repair attempts, and the offline fallback to CEM."""

from __future__ import annotations

import logging
import re

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from learner_support import TARGET, ChatServer, SyntheticEvaluator

from capevo.errors import ErrorCode, Invalid, SandboxViolation, Unavailable
from capevo.learner.base import request_for
from capevo.learner.chat import Chat, ChatConfig
from capevo.learner.search import CemSearch
from capevo.learner.skills import seed_source
from capevo.learner.synthesis import LlmSynthesis, build_messages, check_source, extract_code
from capevo.records import Origin
from capevo.runtime.ecm.code import read_params, with_params


def _request(registry):
    return request_for(registry, "pick", "pick.reach", train_seeds=list(range(12)))


def _edited() -> str:
    """A known edit of v0 pick.reach: right grasp height, higher gain, a done() that never fires."""
    source = with_params(seed_source("pick", "pick.reach"), {"grasp_dz": 0.0, "gain": 8.0})
    head, _ = source.split("def done(obs, params):")
    return head + "def done(obs, params):\n    return False\n"


def _fenced(code: str) -> str:
    return f"Here is the improved skill.\n\n```python\n{code}```\n\nIt aims at the can's middle."


def _malicious(marker) -> str:
    return (
        "import os\n\n"
        "PARAMS = {'gain': 1.0}\n"
        f"os.system('touch {marker}')\n\n\n"
        "def act(obs, params):\n    return [0.0] * 7\n"
    )


def _chat(server: ChatServer, **kw) -> Chat:
    return Chat(ChatConfig(base_url=server.base_url, model="test-model", api_key="sk-secret", **kw))


def test_an_accepted_edit_becomes_an_llm_candidate(registry) -> None:
    request = _request(registry)
    with ChatServer([_fenced(_edited())]) as server:
        cand = LlmSynthesis(_chat(server)).learn(request)
    assert cand.source == _edited()
    assert cand.spec.origin is Origin.LLM and cand.spec.parent == 0
    assert cand.spec.descriptor == request.parent.descriptor
    assert cand.spec.provenance.learner_id == "llm:test-model"
    assert re.fullmatch(r"[0-9a-f]{64}", cand.spec.provenance.config_hash or "")
    assert cand.notes["attempts"] == [{"reply_chars": len(_fenced(_edited())), "accepted": True, "error": None}]
    # what the endpoint was asked: the contract, φ, the interface and the current source
    (req,) = server.requests
    assert req["path"] == "/v1/chat/completions" and req["auth"] == "Bearer sk-secret"
    body = req["body"]
    assert body["model"] == "test-model" and body["max_tokens"] == 4096
    system, user = body["messages"]
    assert system["role"] == "system" and "PARAMS" in system["content"] and "import math" in system["content"]
    text = user["content"]
    assert "pick.reach" in text and "eef_object_xy_dist < 0.02" in text and "gripper_opening > 0.06" in text
    assert "robot0_eef_pos: shape [3]" in text and "action: shape [7] float32 in [-1, 1]" in text
    assert request.source in text
    assert "No traced episodes are available." in text


def test_code_that_breaks_the_sandbox_rules_is_rejected_and_never_runs(registry, tmp_path) -> None:
    marker = tmp_path / "MARKER"
    with ChatServer([_fenced(_malicious(marker))]) as server, pytest.raises(SandboxViolation) as e:
        LlmSynthesis(_chat(server), max_attempts=1).learn(_request(registry))
    assert e.value.code is ErrorCode.SANDBOX_VIOLATION
    assert e.value.message.startswith("line 1, col 0: import os")
    assert not marker.exists()


def test_a_rejection_is_fed_back_and_the_corrected_reply_accepted(registry, tmp_path) -> None:
    marker = tmp_path / "MARKER"
    with ChatServer([_fenced(_malicious(marker)), _fenced(_edited())]) as server:
        cand = LlmSynthesis(_chat(server), max_attempts=2).learn(_request(registry))
    assert not marker.exists()
    assert cand.source == _edited()
    assert [a["accepted"] for a in cand.notes["attempts"]] == [False, True]
    second = server.requests[1]["body"]["messages"]
    assert [m["role"] for m in second] == ["system", "user", "assistant", "user"]
    assert second[2]["content"] == _fenced(_malicious(marker))
    assert "was rejected" in second[3]["content"] and "import os" in second[3]["content"]


@pytest.mark.parametrize(
    ("reply", "message"),
    [
        ("I cannot help with that.", "holds no Python code block"),
        (_fenced("PARAMS = {}\n\n\ndef act(obs, params):\n    return [0.0] * 3\n"), "expected [7]"),
        (_fenced("PARAMS = {}\n\n\ndef act(obs, params):\n    return [1.0 / 0.0] * 7\n"), "smoke run failed"),
        (_fenced("PARAMS = {'gain': 'high'}\n\n\ndef act(obs, params):\n    return [0.0] * 7\n"), "PARAMS"),
        (_fenced("def helper(obs):\n    return obs\n"), "act(obs, params)"),
    ],
)
def test_replies_that_do_not_run_are_rejected(registry, reply: str, message: str) -> None:
    with ChatServer([reply]) as server, pytest.raises(Invalid) as e:
        LlmSynthesis(_chat(server), max_attempts=1).learn(_request(registry))
    assert e.value.code is ErrorCode.INVALID
    assert message in e.value.message


def test_endpoint_errors_surface_as_unavailable(registry) -> None:
    with ChatServer([500]) as server, pytest.raises(Unavailable) as e:
        LlmSynthesis(_chat(server)).learn(_request(registry))
    assert "HTTP 500" in e.value.message


def test_without_an_endpoint_it_falls_back_to_cem(registry, caplog) -> None:
    request = _request(registry)
    fake = SyntheticEvaluator("pick.reach", read_params(request.source), TARGET)
    cem = CemSearch(fake, population=3, iterations=1, episodes_per_candidate=1)
    with caplog.at_level(logging.WARNING, logger="capevo.learner.synthesis"):
        cand = LlmSynthesis(None, fallback=cem).learn(request)
    assert cand.spec.origin is Origin.CLONE and cand.spec.provenance.learner_id == "cem"
    assert "no chat endpoint" in cand.notes["fallback"]
    assert any("falling back to cem" in r.getMessage() for r in caplog.records)
    assert len(fake.calls) == 3
    with pytest.raises(Unavailable):
        LlmSynthesis(None).learn(request)


def test_chat_config_from_env_and_secrecy() -> None:
    assert ChatConfig.from_env({}) is None
    cfg = ChatConfig.from_env(
        {"CAPEVO_LLM_BASE_URL": "http://127.0.0.1:9/v1", "CAPEVO_LLM_MODEL": "m", "CAPEVO_LLM_API_KEY": "sk-x"}
    )
    assert cfg is not None and cfg.api_key == "sk-x" and cfg.timeout_s == 120.0
    assert "sk-x" not in repr(cfg) and "sk-x" not in str(cfg.to_dict())
    with pytest.raises(Invalid) as e:
        ChatConfig.from_env({"CAPEVO_LLM_BASE_URL": "http://127.0.0.1:9/v1"})
    assert e.value.message.startswith("CAPEVO_LLM_MODEL")
    with pytest.raises(Invalid) as e:
        ChatConfig(base_url="ftp://x", model="m")
    assert e.value.message.startswith("base_url")


def test_extract_code_prefers_the_longest_fenced_block() -> None:
    reply = "```\nx = 1\n```\nand\n```python\ndef act(obs, params):\n    return [0.0] * 7\n```"
    assert extract_code(reply).startswith("def act")
    assert extract_code("def act(obs, params):\n    return []") == "def act(obs, params):\n    return []\n"


@settings(max_examples=200, deadline=None)
@given(st.text())
def test_extract_code_only_ever_raises_invalid(text: str) -> None:
    try:
        out = extract_code(text)
    except Invalid:
        return
    assert out.endswith("\n")


def test_check_source_uses_real_inputs_and_rejects_violations(registry) -> None:
    request = _request(registry)
    assert check_source(_edited(), request)["grasp_dz"] == 0.0
    with pytest.raises(SandboxViolation):
        check_source("import subprocess\n\n\ndef act(obs, params):\n    return [0.0] * 7\n", request)
    messages = build_messages(request, failures="3 of 4 failed")
    assert "3 of 4 failed" in messages[1]["content"]
