"""An optional LLM-backed π_A: asks an OpenAI-compatible chat endpoint which ECM to run next.

:class:`LlmPolicy` wraps a :class:`~capevo.agent.policy.DecompositionPolicy` and keeps all of
its rules (decomposition, descriptors, attempt limits, when the episode ends). Only when the
walk leaves two or more candidate ECMs (not done, applicable, under the attempt limit) does it
ask the model to choose among them, giving it the task, M_id's goals and beliefs, the signals
and each step's descriptor text. Any error, timeout, malformed reply or a reply naming an ECM
outside the candidates makes it use the decomposition policy's choice, and the decision's
reason says so. A model that picks a later candidate passes over the earlier ones: once that
ECM terminates, the walk goes on after it (as it does after any step). Nothing here runs
unless a caller builds an :class:`LlmPolicy`: the default planner needs no network.

Invariants:
1. ``LlmPolicy.decide`` returns either the decomposition policy's decision or a decision
   naming one of ``fallback.candidates(context)``; no reply of the endpoint, and no failure
   to reach it, makes it raise or name anything else.
2. It ends the episode exactly when the decomposition policy does, and raises :class:`Invalid`
   exactly when the decomposition policy does (missing ECMs, unknown signals).
3. :func:`parse_choice` never raises; it returns a candidate or None.
4. The API key is never part of the parameters, the identity hash, a reason or a repr.
5. :class:`HttpChatClient` raises only :class:`Timeout`, :class:`Unavailable` or
   :class:`Invalid`, and reads at most ``max_response_bytes`` of a reply.
"""

from __future__ import annotations

import http.client
import json
import math
import os
import re
import time
import urllib.error
import urllib.parse
import urllib.request
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any, Protocol, cast, runtime_checkable

from capevo.agent.identity import IdentityMemory
from capevo.agent.policy import DecompositionPolicy, PolicyParameters
from capevo.errors import Invalid, Timeout, Unavailable
from capevo.runtime.policy import Decision, DecisionContext

MAX_RESPONSE_BYTES = 1024 * 1024
_LOOPBACK = frozenset({"127.0.0.1", "localhost", "::1"})

SYSTEM_PROMPT = (
    "You are the decision policy of a robot's persistent agent. The robot performs a task as a "
    "sequence of skills called ECMs; each has a description, an applicability condition and a "
    "termination condition over named signals. Choose the ECM to run next. Reply with only a JSON "
    'object {"ecm": "<name>"} whose name is one of the listed candidates.'
)


def _bad(field_name: str, message: str) -> Invalid:
    return Invalid(f"{field_name}: {message}", details={"field": field_name})


@dataclass(frozen=True, slots=True, kw_only=True)
class LlmSettings:
    """Where the chat endpoint is and how to ask it.

    Args:
        base_url: The API root, e.g. ``http://127.0.0.1:8000/v1``; requests go to
            ``{base_url}/chat/completions``.
        model: Model name sent with every request.
        api_key: Sent as ``Authorization: Bearer``; None sends no header.
        temperature: Sampling temperature (0 for the most repeatable choices).
        max_tokens: Upper bound on the reply's length.
        timeout_s: Deadline for one request, connection to last byte.

    Raises:
        Invalid: a malformed URL (only http and https), empty model, or a value out of range.
    """

    base_url: str
    model: str
    api_key: str | None = field(default=None, repr=False)
    temperature: float = 0.0
    max_tokens: int = 64
    timeout_s: float = 10.0

    def __post_init__(self) -> None:
        if not isinstance(self.base_url, str):
            raise _bad("base_url", f"must be a string, got {type(self.base_url).__name__}")
        parts = urllib.parse.urlsplit(self.base_url)
        if parts.scheme not in ("http", "https") or not parts.hostname:
            raise _bad("base_url", f"must be an http:// or https:// URL with a host, got {self.base_url!r}")
        if not isinstance(self.model, str) or not self.model.strip():
            raise _bad("model", "must be a non-empty string")
        if self.api_key is not None and (not isinstance(self.api_key, str) or "\n" in self.api_key):
            raise _bad("api_key", "must be a single-line string or None")
        t = self.temperature
        if isinstance(t, bool) or not isinstance(t, (int, float)) or not 0.0 <= t <= 2.0:
            raise _bad("temperature", f"must be a number from 0 to 2, got {t!r}")
        m = self.max_tokens
        if isinstance(m, bool) or not isinstance(m, int) or not 1 <= m <= 4096:
            raise _bad("max_tokens", f"must be an integer from 1 to 4096, got {m!r}")
        s = self.timeout_s
        if isinstance(s, bool) or not isinstance(s, (int, float)) or not (math.isfinite(s) and 0 < s <= 600):
            raise _bad("timeout_s", f"must be a number of seconds in (0, 600], got {s!r}")
        object.__setattr__(self, "temperature", float(t))
        object.__setattr__(self, "timeout_s", float(s))

    @classmethod
    def from_env(cls, environ: Mapping[str, str] | None = None) -> LlmSettings:
        """Settings from ``CAPEVO_LLM_BASE_URL``, ``CAPEVO_LLM_MODEL``, ``CAPEVO_LLM_API_KEY``
        and ``CAPEVO_LLM_TIMEOUT_S``.

        Raises:
            Invalid: a required variable is unset or a value is bad.
        """
        env = os.environ if environ is None else environ
        missing = [k for k in ("CAPEVO_LLM_BASE_URL", "CAPEVO_LLM_MODEL") if not env.get(k)]
        if missing:
            raise _bad(missing[0], "environment variable is not set")
        timeout = env.get("CAPEVO_LLM_TIMEOUT_S")
        try:
            timeout_s = float(timeout) if timeout else 10.0
        except ValueError:
            raise _bad("CAPEVO_LLM_TIMEOUT_S", f"must be a number, got {timeout!r}") from None
        return cls(
            base_url=env["CAPEVO_LLM_BASE_URL"],
            model=env["CAPEVO_LLM_MODEL"],
            api_key=env.get("CAPEVO_LLM_API_KEY") or None,
            timeout_s=timeout_s,
        )


@dataclass(frozen=True, slots=True, kw_only=True)
class LlmParameters:
    """θ of :class:`LlmPolicy`: what shapes its choices (the endpoint and key do not)."""

    model: str
    temperature: float
    max_tokens: int
    timeout_s: float
    fallback: PolicyParameters

    def to_dict(self) -> dict[str, Any]:
        return {
            "model": self.model,
            "temperature": self.temperature,
            "max_tokens": self.max_tokens,
            "timeout_s": self.timeout_s,
            "fallback": self.fallback.to_dict(),
        }

    def vector(self) -> tuple[float, ...]:
        """The numeric parameters: temperature, max_tokens, timeout_s, then the fallback's."""
        return (self.temperature, float(self.max_tokens), self.timeout_s, *self.fallback.vector())


@runtime_checkable
class ChatClient(Protocol):
    """One OpenAI-style chat completion: messages in, the assistant's text out."""

    def complete(
        self,
        messages: Sequence[Mapping[str, str]],
        *,
        model: str,
        temperature: float,
        max_tokens: int,
        timeout_s: float,
    ) -> str:
        """The first choice's message content.

        Raises:
            CapevoError: any failure (the policy falls back on every exception anyway).
        """
        ...


class ScriptedChatClient:
    """In-memory :class:`ChatClient`: replies from a list, in order, and records each request.

    Args:
        replies: Reply texts; an :class:`Exception` instance in the list is raised instead.
    """

    def __init__(self, replies: Sequence[str | Exception]) -> None:
        self._replies = list(replies)
        self.requests: list[dict[str, Any]] = []

    def complete(
        self,
        messages: Sequence[Mapping[str, str]],
        *,
        model: str,
        temperature: float,
        max_tokens: int,
        timeout_s: float,
    ) -> str:
        self.requests.append({"messages": [dict(m) for m in messages], "model": model})
        if not self._replies:
            raise Unavailable("scripted chat client has no replies left")
        reply = self._replies.pop(0)
        if isinstance(reply, Exception):
            raise reply
        return reply


class HttpChatClient:
    """:class:`ChatClient` for an OpenAI-compatible ``POST {base_url}/chat/completions``.

    Uses only the standard library. Loopback endpoints bypass any proxy from the environment.

    Args:
        base_url: The API root (``.../v1``).
        api_key: Bearer token, or None.
        max_response_bytes: Replies longer than this are refused.
    """

    def __init__(self, base_url: str, api_key: str | None = None, *, max_response_bytes: int = MAX_RESPONSE_BYTES):
        self._url = base_url.rstrip("/") + "/chat/completions"
        self._api_key = api_key
        self._max = max_response_bytes
        host = urllib.parse.urlsplit(base_url).hostname or ""
        handlers = [urllib.request.ProxyHandler({})] if host in _LOOPBACK else []
        self._opener = urllib.request.build_opener(*handlers)

    def __repr__(self) -> str:
        return f"HttpChatClient({self._url!r})"

    def complete(
        self,
        messages: Sequence[Mapping[str, str]],
        *,
        model: str,
        temperature: float,
        max_tokens: int,
        timeout_s: float,
    ) -> str:
        """POST the request and return ``choices[0].message.content``.

        Raises:
            Timeout: no complete reply within ``timeout_s``.
            Unavailable: connection refused or reset, or an HTTP error status.
            Invalid: a reply that is too long, not JSON, or not the chat-completion shape.
        """
        body = json.dumps(
            {
                "model": model,
                "messages": [dict(m) for m in messages],
                "temperature": temperature,
                "max_tokens": max_tokens,
                "stream": False,
            }
        ).encode()
        headers = {"Content-Type": "application/json", "Accept": "application/json"}
        if self._api_key:
            headers["Authorization"] = f"Bearer {self._api_key}"
        request = urllib.request.Request(self._url, data=body, headers=headers, method="POST")
        deadline = time.monotonic() + timeout_s
        try:
            with self._opener.open(request, timeout=timeout_s) as response:
                raw = self._read(response, deadline)
        except urllib.error.HTTPError as exc:
            raise Unavailable(
                f"chat endpoint {self._url} answered HTTP {exc.code}", details={"status": exc.code}
            ) from None
        except urllib.error.URLError as exc:
            if isinstance(exc.reason, TimeoutError):
                raise Timeout(f"chat endpoint {self._url} did not answer within {timeout_s:g} s") from None
            raise Unavailable(f"chat endpoint {self._url} is not reachable: {exc.reason}") from None
        except TimeoutError:
            raise Timeout(f"chat endpoint {self._url} did not answer within {timeout_s:g} s") from None
        except (OSError, http.client.HTTPException) as exc:
            raise Unavailable(f"chat endpoint {self._url} failed: {type(exc).__name__}: {exc}") from None
        return _content(raw, self._url)

    def _read(self, response: Any, deadline: float) -> bytes:
        chunks: list[bytes] = []
        total = 0
        while True:
            # The socket timeout bounds each read; the deadline bounds a reply that trickles in.
            if time.monotonic() > deadline:
                raise TimeoutError
            chunk = response.read1(64 * 1024)
            if not chunk:
                return b"".join(chunks)
            total += len(chunk)
            if total > self._max:
                raise Invalid(f"chat endpoint {self._url} replied with more than {self._max} bytes")
            chunks.append(chunk)


def _content(raw: bytes, url: str) -> str:
    try:
        content = json.loads(raw)["choices"][0]["message"]["content"]
    except (ValueError, KeyError, IndexError, TypeError, RecursionError):
        raise Invalid(f"chat endpoint {url} replied with something that is not a chat completion") from None
    if not isinstance(content, str):
        raise Invalid(f"chat endpoint {url} replied with a non-text message content")
    return content


def _name_pattern(name: str) -> re.Pattern[str]:
    return re.compile(rf"(?<![\w.-]){re.escape(name)}(?![\w-]|\.\w)")


def parse_choice(text: object, candidates: Sequence[str]) -> str | None:
    """The candidate an LLM reply names, or None.

    Accepted, in order: JSON ``{"ecm": name}`` (alone or embedded in prose), a JSON string, the
    bare name (quotes, backticks and a final period ignored), or prose that mentions exactly one
    candidate.
    """
    if not isinstance(text, str) or not candidates:
        return None
    wanted = set(candidates)
    stripped = text.strip()
    objects: list[Any] = []
    try:
        objects.append(json.loads(stripped))
    except (ValueError, RecursionError):
        for match in re.finditer(r"\{[^{}]*\}", stripped):
            try:
                objects.append(json.loads(match.group(0)))
            except (ValueError, RecursionError):
                continue
    for obj in objects:
        name = obj.get("ecm") if isinstance(obj, dict) else obj
        if isinstance(name, str):
            return name.strip() if name.strip() in wanted else None
    bare = stripped.strip("`'\" \t\r\n").rstrip(".").strip("`'\" ")
    if bare in wanted:
        return bare
    mentioned = [c for c in candidates if _name_pattern(c).search(stripped)]
    return mentioned[0] if len(mentioned) == 1 else None


def build_messages(
    context: DecisionContext, identity: IdentityMemory, policy: DecompositionPolicy, candidates: Sequence[str]
) -> list[dict[str, str]]:
    """The chat messages asking the model to choose among ``candidates``."""
    status = {s.ecm: s for s in policy.assess(context)}
    steps = policy.plan(context.task, context.capabilities)
    lines = [f"Task: {context.task}"]
    if identity.goals:
        lines.append("Goals:")
        lines.extend(f"- {g.text}" for g in identity.goals)
    if identity.beliefs:
        lines.append("Beliefs:")
        lines.extend(f"- {b.text}" for b in identity.beliefs)
    prev = context.previous_ecm or "none (the episode just started)"
    lines.append(f"Previous ECM: {prev} ({context.previous_end.value})")
    lines.append("Signals:")
    lines.extend(f"- {k} = {float(v):.4g}" for k, v in sorted(context.signals.items()))
    lines.append("Plan, in order:")
    for step in steps:
        s = status[step.ecm]
        state = "done" if s.done else ("applicable" if s.applicable else "not applicable")
        d = step.descriptor
        lines.append(
            f"{step.index + 1}. {step.ecm} [{state}, started {s.attempts}x]: {d.description} "
            f"Applies when: {_predicate_text(d.applicability)}. Done when: {_predicate_text(d.termination)}."
        )
    lines.append(f"Candidates: {', '.join(candidates)}")
    lines.append('Answer with {"ecm": "<one candidate>"}.')
    return [{"role": "system", "content": SYSTEM_PROMPT}, {"role": "user", "content": "\n".join(lines)}]


def _predicate_text(predicate: Any) -> str:
    conditions = " and ".join(f"{c.signal} {c.op} {c.value:g}" for c in predicate.all)
    if not conditions:
        return "always"
    return f"{predicate.text} ({conditions})" if predicate.text else conditions


@dataclass(frozen=True, slots=True, kw_only=True)
class LlmPolicy:
    """π_A that lets a chat model choose among the decomposition policy's candidates.

    Args:
        fallback: The decomposition policy whose rules and choices it keeps.
        settings: Endpoint, model and sampling settings.
        client: How to reach the model; default an :class:`HttpChatClient` for ``settings``.
    """

    fallback: DecompositionPolicy
    settings: LlmSettings
    client: ChatClient | None = field(default=None, compare=False, repr=False)

    def __post_init__(self) -> None:
        if self.client is None:
            object.__setattr__(self, "client", HttpChatClient(self.settings.base_url, self.settings.api_key))

    @property
    def identity(self) -> IdentityMemory:
        return self.fallback.identity

    @property
    def parameters(self) -> LlmParameters:
        return LlmParameters(
            model=self.settings.model,
            temperature=self.settings.temperature,
            max_tokens=self.settings.max_tokens,
            timeout_s=self.settings.timeout_s,
            fallback=self.fallback.parameters,
        )

    def parameters_vector(self) -> tuple[float, ...]:
        """θ as a vector, for Δπ (see :meth:`LlmParameters.vector`)."""
        return self.parameters.vector()

    def decide(self, context: DecisionContext) -> Decision:
        """The model's pick among the candidates, else the decomposition policy's decision.

        Raises:
            Invalid: exactly when :meth:`DecompositionPolicy.decide` does.
        """
        base = self.fallback.decide(context)
        if base.ecm is None:
            return base
        candidates = self.fallback.candidates(context)
        if len(candidates) < 2:
            return base
        s = self.settings
        try:
            messages = build_messages(context, self.fallback.identity, self.fallback, candidates)
            client = cast(ChatClient, self.client)  # never None after __post_init__
            reply = client.complete(
                messages, model=s.model, temperature=s.temperature, max_tokens=s.max_tokens, timeout_s=s.timeout_s
            )
        except Exception as exc:  # any failure of the optional planner must not stop the robot
            why = exc.message if hasattr(exc, "message") else f"{type(exc).__name__}: {exc}"
            return Decision(ecm=base.ecm, reason=f"llm fallback ({_clip(why)}); {base.reason}")
        choice = parse_choice(reply, candidates)
        if choice is None:
            return Decision(
                ecm=base.ecm,
                reason=f"llm fallback (reply names no candidate: {_clip(repr(reply))}); {base.reason}",
            )
        return Decision(ecm=choice, reason=f"llm {s.model} chose {choice} among {', '.join(candidates)}")


def _clip(text: str, limit: int = 160) -> str:
    return text if len(text) <= limit else text[: limit - 3] + "..."
