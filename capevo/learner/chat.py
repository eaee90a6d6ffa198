"""The chat endpoint learners talk to: any OpenAI-compatible ``POST {base_url}/chat/completions``.

Transport is :class:`capevo.agent.llm.HttpChatClient` (standard library only, loopback
endpoints bypass proxies, replies size-capped); this module adds the learner's settings
(longer replies and timeouts than the planner needs) and where they come from.

Environment (all optional; without ``CAPEVO_LLM_BASE_URL`` there is no endpoint and the
LLM learners fall back to parameter search)::

    CAPEVO_LLM_BASE_URL   e.g. http://127.0.0.1:8000/v1
    CAPEVO_LLM_MODEL      model name sent with each request (required with a base URL)
    CAPEVO_LLM_API_KEY    sent as "Authorization: Bearer ..."
    CAPEVO_LLM_TIMEOUT_S  per-request deadline in seconds (default 120)

Invariants:
1. The API key never appears in ``repr``, ``to_dict`` or a config hash.
2. ``ChatConfig`` refuses what :class:`capevo.agent.llm.LlmSettings` refuses (URL scheme and
   host, empty model, temperature outside [0, 2], max_tokens outside [1, 4096], timeout outside
   (0, 600] s) with :class:`Invalid`.
3. :meth:`Chat.complete` raises only :class:`Timeout`, :class:`Unavailable` or :class:`Invalid`.
"""

from __future__ import annotations

import os
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any

from capevo.agent.llm import ChatClient, HttpChatClient, LlmSettings
from capevo.errors import Invalid

__all__ = ["Chat", "ChatClient", "ChatConfig"]

DEFAULT_TIMEOUT_S = 120.0
DEFAULT_MAX_TOKENS = 4096


@dataclass(frozen=True, slots=True, kw_only=True)
class ChatConfig:
    """Where the chat endpoint is and how learners ask it.

    Args:
        base_url: API root, e.g. ``http://127.0.0.1:8000/v1``.
        model: Model name.
        api_key: Bearer token or None.
        timeout_s: Deadline of one request.
        temperature: Sampling temperature.
        max_tokens: Longest reply (a whole skill module is a few thousand tokens).

    Raises:
        Invalid: see invariant 2.
    """

    base_url: str
    model: str
    api_key: str | None = field(default=None, repr=False)
    timeout_s: float = DEFAULT_TIMEOUT_S
    temperature: float = 0.2
    max_tokens: int = DEFAULT_MAX_TOKENS

    def __post_init__(self) -> None:
        # One set of rules for every chat endpoint in capevo.
        LlmSettings(
            base_url=self.base_url,
            model=self.model,
            api_key=self.api_key,
            temperature=self.temperature,
            max_tokens=self.max_tokens,
            timeout_s=self.timeout_s,
        )

    @classmethod
    def from_env(cls, environ: Mapping[str, str] | None = None) -> ChatConfig | None:
        """Settings from the ``CAPEVO_LLM_*`` variables; None when no base URL is set.

        Raises:
            Invalid: a base URL without a model, or a bad value.
        """
        env = os.environ if environ is None else environ
        base = env.get("CAPEVO_LLM_BASE_URL")
        if not base:
            return None
        model = env.get("CAPEVO_LLM_MODEL")
        if not model:
            raise Invalid("CAPEVO_LLM_MODEL: must be set with CAPEVO_LLM_BASE_URL", details={"field": "model"})
        timeout = env.get("CAPEVO_LLM_TIMEOUT_S")
        try:
            timeout_s = float(timeout) if timeout else DEFAULT_TIMEOUT_S
        except ValueError:
            raise Invalid(
                f"CAPEVO_LLM_TIMEOUT_S: must be a number, got {timeout!r}", details={"field": "timeout_s"}
            ) from None
        return cls(base_url=base, model=model, api_key=env.get("CAPEVO_LLM_API_KEY") or None, timeout_s=timeout_s)

    def to_dict(self) -> dict[str, Any]:
        """Everything but the key (for logs and config hashes)."""
        return {
            "base_url": self.base_url,
            "model": self.model,
            "timeout_s": self.timeout_s,
            "temperature": self.temperature,
            "max_tokens": self.max_tokens,
        }


class Chat:
    """One configured endpoint.

    Args:
        config: Endpoint settings.
        client: Transport; default :class:`HttpChatClient` for ``config.base_url``.
    """

    def __init__(self, config: ChatConfig, client: ChatClient | None = None) -> None:
        self.config = config
        self.client: ChatClient = client if client is not None else HttpChatClient(config.base_url, config.api_key)

    def __repr__(self) -> str:
        return f"Chat({self.config.base_url!r}, model={self.config.model!r})"

    def complete(self, messages: Sequence[Mapping[str, str]]) -> str:
        """The assistant's reply text to ``messages``.

        Raises:
            Timeout, Unavailable, Invalid: from the transport.
        """
        return self.client.complete(
            messages,
            model=self.config.model,
            temperature=self.config.temperature,
            max_tokens=self.config.max_tokens,
            timeout_s=self.config.timeout_s,
        )
