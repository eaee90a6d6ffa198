"""LlmPolicy against a real OpenAI-compatible HTTP server on loopback (http.server in a thread).

LLM invariants 1-5: a known choice is taken; errors, timeouts, garbage and non-applicable
answers fall back to the decomposition policy; the episode ends and Invalid is raised exactly
as the decomposition policy does.
"""

from __future__ import annotations

import json
import threading
import time
from collections.abc import Iterator
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer
from typing import Any

import pytest
from _agent_helpers import PICK_AT_CAN_OPEN, context, pred, step_version, task_capabilities, version
from hypothesis import given, settings
from hypothesis import strategies as st

from capevo.agent import (
    DecompositionPolicy,
    HttpChatClient,
    IdentityMemory,
    LlmPolicy,
    LlmSettings,
    ScriptedChatClient,
    parse_choice,
)
from capevo.agent.llm import build_messages
from capevo.errors import ErrorCode, Invalid, Timeout, Unavailable
from capevo.records import Descriptor
from capevo.runtime.policy import Decision, DecisionPolicy, StepEnd


class ChatServer(ThreadingHTTPServer):
    """A tiny /v1/chat/completions endpoint; what it answers is set per test."""

    daemon_threads = True

    def __init__(self) -> None:
        super().__init__(("127.0.0.1", 0), ChatHandler)
        self.requests: list[dict[str, Any]] = []
        self.content: str = '{"ecm": "t.c"}'
        self.raw: bytes | None = None  # a whole body to send instead of a chat completion
        self.status = 200
        self.delay_s = 0.0

    @property
    def base_url(self) -> str:
        return f"http://127.0.0.1:{self.server_address[1]}/v1"


class ChatHandler(BaseHTTPRequestHandler):
    server: ChatServer

    def log_message(self, *args: object) -> None:
        pass

    def do_POST(self) -> None:
        length = int(self.headers.get("Content-Length", "0"))
        body = json.loads(self.rfile.read(length))
        self.server.requests.append({"path": self.path, "headers": dict(self.headers), "body": body})
        if self.server.delay_s:
            time.sleep(self.server.delay_s)
        if self.server.raw is not None:
            payload = self.server.raw
        else:
            payload = json.dumps(
                {
                    "id": "chatcmpl-1",
                    "object": "chat.completion",
                    "model": body.get("model"),
                    "choices": [
                        {
                            "index": 0,
                            "message": {"role": "assistant", "content": self.server.content},
                            "finish_reason": "stop",
                        }
                    ],
                }
            ).encode()
        try:
            self.send_response(self.server.status)
            self.send_header("Content-Type", "application/json")
            self.send_header("Content-Length", str(len(payload)))
            self.end_headers()
            self.wfile.write(payload)
        except (BrokenPipeError, ConnectionResetError):
            pass  # the client gave up (the timeout tests)


@pytest.fixture(scope="module")
def module_server() -> Iterator[ChatServer]:
    server = ChatServer()
    thread = threading.Thread(target=server.serve_forever, daemon=True)
    thread.start()
    yield server
    server.shutdown()
    server.server_close()
    thread.join(timeout=10)


@pytest.fixture
def server(module_server: ChatServer) -> ChatServer:
    s = module_server
    s.requests.clear()
    s.content, s.raw, s.status, s.delay_s = '{"ecm": "t.c"}', None, 200, 0.0
    return s


IDENTITY = IdentityMemory(
    name="t",
    goals=(),
    decompositions={"t": ("t.a", "t.b", "t.c")},
)
CAPS = {
    "t.a": version(
        "t.a",
        Descriptor(
            description="Open the drawer.",
            applicability=pred("x positive", ("x", ">", 0)),
            termination=pred("drawer open", ("a", ">=", 1)),
        ),
    ),
    # b and c apply on their own condition, so the walk may pass over t.a to them (policy rule 3).
    "t.b": step_version("t.b", "Wave.", ("b", ">=", 1), ("y", ">", 0)),
    "t.c": step_version("t.c", "Bow.", ("c", ">=", 1), ("y", ">", 0)),
}
ALL_READY = {"x": 1.0, "y": 1.0, "a": 0.0, "b": 0.0, "c": 0.0}
FALLBACK = DecompositionPolicy(identity=IDENTITY)


def llm(server_url: str, *, timeout_s: float = 5.0, api_key: str | None = "sk-test") -> LlmPolicy:
    settings_ = LlmSettings(base_url=server_url, model="tiny-planner", api_key=api_key, timeout_s=timeout_s)
    return LlmPolicy(fallback=FALLBACK, settings=settings_)


def test_it_is_a_decision_policy(server: ChatServer) -> None:
    assert isinstance(llm(server.base_url), DecisionPolicy)


def test_the_model_choice_is_taken(server: ChatServer) -> None:
    d = llm(server.base_url).decide(context("t", ALL_READY, CAPS))
    assert d == Decision(ecm="t.c", reason="llm tiny-planner chose t.c among t.a, t.b, t.c")
    assert FALLBACK.decide(context("t", ALL_READY, CAPS)).ecm == "t.a"  # the default would differ
    (req,) = server.requests
    assert req["path"] == "/v1/chat/completions"
    assert req["headers"]["Authorization"] == "Bearer sk-test"
    assert req["headers"]["Content-Type"] == "application/json"
    body = req["body"]
    assert body["model"] == "tiny-planner" and body["temperature"] == 0.0 and body["stream"] is False
    assert [m["role"] for m in body["messages"]] == ["system", "user"]
    prompt = body["messages"][1]["content"]
    assert "Candidates: t.a, t.b, t.c" in prompt
    assert "t.a [applicable, started 0x]: Open the drawer." in prompt
    assert "Done when: drawer open (a >= 1)" in prompt
    assert "- x = 1" in prompt


def test_no_api_key_sends_no_authorization(server: ChatServer) -> None:
    llm(server.base_url, api_key=None).decide(context("t", ALL_READY, CAPS))
    assert "Authorization" not in server.requests[0]["headers"]


@pytest.mark.parametrize(
    ("content", "expected"),
    [
        ("t.b", "t.b"),
        ("`t.b`.", "t.b"),
        ('Sure! {"ecm": "t.b"}', "t.b"),
        ("I would run t.b next, since it is quick.", "t.b"),
    ],
)
def test_reply_forms(server: ChatServer, content: str, expected: str) -> None:
    server.content = content
    assert llm(server.base_url).decide(context("t", ALL_READY, CAPS)).ecm == expected


def test_a_reply_naming_a_non_applicable_ecm_falls_back(server: ChatServer) -> None:
    server.content = '{"ecm": "t.a"}'
    signals = {**ALL_READY, "x": 0.0}  # t.a does not apply
    d = llm(server.base_url).decide(context("t", signals, CAPS))
    assert d.ecm == "t.b"
    assert d.reason == 'llm fallback (reply names no candidate: \'{"ecm": "t.a"}\'); start: t.b'


def test_a_reply_naming_an_unknown_ecm_falls_back(server: ChatServer) -> None:
    server.content = '{"ecm": "rm -rf"}'
    assert llm(server.base_url).decide(context("t", ALL_READY, CAPS)).ecm == "t.a"


def test_garbage_body_falls_back(server: ChatServer) -> None:
    server.raw = b"<html>definitely not json"
    d = llm(server.base_url).decide(context("t", ALL_READY, CAPS))
    assert d.ecm == "t.a"
    assert d.reason == (
        f"llm fallback (chat endpoint {server.base_url}/chat/completions replied with something that is not a "
        "chat completion); start: t.a"
    )


def test_http_error_falls_back(server: ChatServer) -> None:
    server.status = 500
    d = llm(server.base_url).decide(context("t", ALL_READY, CAPS))
    assert d.ecm == "t.a"
    assert d.reason.startswith(f"llm fallback (chat endpoint {server.base_url}/chat/completions answered HTTP 500)")


def test_unreachable_server_falls_back(free_port: int) -> None:
    d = llm(f"http://127.0.0.1:{free_port}/v1").decide(context("t", ALL_READY, CAPS))
    assert d.ecm == "t.a"
    assert d.reason.startswith(f"llm fallback (chat endpoint http://127.0.0.1:{free_port}/v1/chat/completions is not")


def test_a_slow_server_times_out_and_falls_back(server: ChatServer) -> None:
    server.delay_s = 2.0
    d = llm(server.base_url, timeout_s=0.3).decide(context("t", ALL_READY, CAPS))
    assert d.ecm == "t.a"
    assert "did not answer within 0.3 s" in d.reason


def test_http_client_error_classes(server: ChatServer, free_port: int) -> None:
    msgs = [{"role": "user", "content": "hi"}]
    kw = {"model": "m", "temperature": 0.0, "max_tokens": 8, "timeout_s": 5.0}
    server.content = "hello"
    assert HttpChatClient(server.base_url).complete(msgs, **kw) == "hello"
    server.status = 503
    with pytest.raises(Unavailable) as info:
        HttpChatClient(server.base_url).complete(msgs, **kw)
    assert info.value.code is ErrorCode.UNAVAILABLE and info.value.details["status"] == 503
    server.status = 200
    server.raw = json.dumps({"choices": [{"message": {"content": 5}}]}).encode()
    with pytest.raises(Invalid) as info:
        HttpChatClient(server.base_url).complete(msgs, **kw)
    assert info.value.message.endswith("replied with a non-text message content")
    server.raw = b"x" * 2048
    with pytest.raises(Invalid) as info:
        HttpChatClient(server.base_url, max_response_bytes=1024).complete(msgs, **kw)
    assert info.value.message.endswith("replied with more than 1024 bytes")
    server.raw, server.delay_s = None, 1.0
    with pytest.raises(Timeout) as info:
        HttpChatClient(server.base_url).complete(msgs, **{**kw, "timeout_s": 0.2})
    assert info.value.code is ErrorCode.TIMEOUT
    with pytest.raises(Unavailable):
        HttpChatClient(f"http://127.0.0.1:{free_port}/v1").complete(msgs, **kw)


def test_a_single_candidate_needs_no_call(server: ChatServer) -> None:
    signals = {**ALL_READY, "x": 0.0, "b": 1.0}  # only t.c is ready
    d = llm(server.base_url).decide(context("t", signals, CAPS))
    assert d == FALLBACK.decide(context("t", signals, CAPS)) and d.ecm == "t.c"
    assert server.requests == []


def test_the_episode_ends_when_the_decomposition_policy_ends_it(server: ChatServer) -> None:
    done = {**ALL_READY, "a": 1.0, "b": 1.0, "c": 1.0}
    assert llm(server.base_url).decide(context("t", done, CAPS)) == Decision(ecm=None, reason="all steps done")
    limited = context("t", ALL_READY, CAPS, attempts={"t.a": 3})
    assert llm(server.base_url).decide(limited) == FALLBACK.decide(limited)
    assert server.requests == []


def test_ecms_over_their_attempt_limit_are_not_offered(server: ChatServer) -> None:
    server.content = '{"ecm": "t.a"}'
    ctx = context("t", ALL_READY, CAPS, prev="t.a", end=StepEnd.FAILED, attempts={"t.a": 3})
    # The decomposition policy ends the episode (t.a is next and over its limit); so does the LLM policy.
    assert llm(server.base_url).decide(ctx).ecm is None
    ctx = context("t", ALL_READY, CAPS, prev="t.a", end=StepEnd.TERMINATED, attempts={"t.a": 3})
    assert FALLBACK.candidates(ctx) == ("t.b", "t.c")
    assert llm(server.base_url).decide(ctx).ecm == "t.b"  # t.a named, but not a candidate


def test_missing_ecms_raise_like_the_decomposition_policy(server: ChatServer) -> None:
    caps = {k: v for k, v in CAPS.items() if k != "t.b"}
    with pytest.raises(Invalid) as info:
        llm(server.base_url).decide(context("t", ALL_READY, caps))
    assert info.value.message.startswith("task 't' needs ECM(s) t.b, which the runtime has not loaded")


def test_any_client_exception_falls_back() -> None:
    policy = LlmPolicy(
        fallback=FALLBACK,
        settings=LlmSettings(base_url="http://127.0.0.1:9/v1", model="m"),
        client=ScriptedChatClient([RuntimeError("boom"), '{"ecm": "t.b"}']),
    )
    d = policy.decide(context("t", ALL_READY, CAPS))
    assert d == Decision(ecm="t.a", reason="llm fallback (RuntimeError: boom); start: t.a")
    assert policy.decide(context("t", ALL_READY, CAPS)).ecm == "t.b"


_bodies = st.one_of(
    st.binary(max_size=200),
    st.text(max_size=200).map(str.encode),
    st.recursive(
        st.none() | st.booleans() | st.integers() | st.text(max_size=10),
        lambda inner: (
            st.lists(inner, max_size=3)
            | st.dictionaries(st.sampled_from(["choices", "message", "content", "x"]), inner, max_size=3)
        ),
        max_leaves=10,
    ).map(lambda v: json.dumps(v).encode()),
)


@settings(max_examples=40, deadline=None)
@given(content=st.text(max_size=120), raw=st.none() | _bodies, status=st.sampled_from([200, 200, 404, 500]))
def test_any_server_answer_yields_a_candidate(
    module_server: ChatServer, content: str, raw: bytes | None, status: int
) -> None:
    module_server.content, module_server.raw, module_server.status, module_server.delay_s = content, raw, status, 0.0
    d = llm(module_server.base_url).decide(context("t", ALL_READY, CAPS))
    assert d.ecm in ("t.a", "t.b", "t.c")
    if d.ecm != "t.a":
        assert d.reason.startswith("llm tiny-planner chose")


def test_parse_choice() -> None:
    c = ("pick.reach", "pick.grasp")
    assert parse_choice('{"ecm": "pick.grasp"}', c) == "pick.grasp"
    assert parse_choice('"pick.grasp"', c) == "pick.grasp"
    assert parse_choice("pick.grasp.", c) == "pick.grasp"
    assert parse_choice('{"ecm": "pick.lift"}', c) is None
    assert parse_choice("pick.reach or pick.grasp", c) is None  # ambiguous
    assert parse_choice("pick.graspx", c) is None
    assert parse_choice("use pick.grasp.v2", c) is None
    assert parse_choice(None, c) is None
    assert parse_choice("pick.grasp", ()) is None


@settings(max_examples=300, deadline=None)
@given(text=st.text(max_size=200), candidates=st.lists(st.text(min_size=1, max_size=12), max_size=4))
def test_parse_choice_never_raises(text: str, candidates: list[str]) -> None:
    got = parse_choice(text, candidates)
    assert got is None or got in candidates


@pytest.mark.parametrize(
    ("kwargs", "message"),
    [
        (
            {"base_url": "file:///etc/passwd"},
            "base_url: must be an http:// or https:// URL with a host, got 'file:///etc/passwd'",
        ),
        ({"base_url": "http://"}, "base_url: must be an http:// or https:// URL with a host, got 'http://'"),
        ({"model": " "}, "model: must be a non-empty string"),
        ({"temperature": 3}, "temperature: must be a number from 0 to 2, got 3"),
        ({"max_tokens": 0}, "max_tokens: must be an integer from 1 to 4096, got 0"),
        ({"timeout_s": float("inf")}, "timeout_s: must be a number of seconds in (0, 600], got inf"),
    ],
)
def test_settings_are_validated(kwargs: dict[str, Any], message: str) -> None:
    with pytest.raises(Invalid) as info:
        LlmSettings(**{"base_url": "http://127.0.0.1:1/v1", "model": "m", **kwargs})
    assert info.value.code is ErrorCode.INVALID
    assert info.value.message == message


def test_settings_from_env() -> None:
    s = LlmSettings.from_env(
        {
            "CAPEVO_LLM_BASE_URL": "http://h:1/v1",
            "CAPEVO_LLM_MODEL": "m",
            "CAPEVO_LLM_API_KEY": "sk-secret-xyz",
            "CAPEVO_LLM_TIMEOUT_S": "2",
        }
    )
    assert (s.base_url, s.model, s.api_key, s.timeout_s) == ("http://h:1/v1", "m", "sk-secret-xyz", 2.0)
    assert "sk-secret-xyz" not in repr(s)
    with pytest.raises(Invalid) as info:
        LlmSettings.from_env({"CAPEVO_LLM_MODEL": "m"})
    assert info.value.message == "CAPEVO_LLM_BASE_URL: environment variable is not set"


def test_parameters_and_vector() -> None:
    p = llm("http://127.0.0.1:1/v1", timeout_s=2.5)
    assert p.parameters.to_dict() == {
        "model": "tiny-planner",
        "temperature": 0.0,
        "max_tokens": 64,
        "timeout_s": 2.5,
        "fallback": {"max_attempts_per_ecm": 3},
    }
    assert p.parameters_vector() == (0.0, 64.0, 2.5, 3.0)
    assert p.identity is IDENTITY


def test_prompt_lists_goals_and_state() -> None:
    identity = IdentityMemory.default()
    policy = DecompositionPolicy(identity=identity)
    ctx = context("pick", PICK_AT_CAN_OPEN, task_capabilities("pick"), prev="pick.reach", end=StepEnd.TERMINATED)
    user = build_messages(ctx, identity, policy, ("pick.grasp",))[1]["content"]
    assert "Previous ECM: pick.reach (terminated)" in user
    assert identity.goals[0].text in user
    assert "1. pick.reach [done, started 0x]" in user
    assert "Applies when: gripper near the can (eef_object_dist < 0.04)" in user
