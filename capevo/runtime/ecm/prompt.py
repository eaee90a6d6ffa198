"""Prompt ECMs: a text artifact, loaded and exposed for an LLM-backed planner.

Invariants:
1. :func:`load_prompt` returns the artifact decoded as UTF-8 or raises :class:`Invalid`.
"""

from __future__ import annotations

from capevo.errors import Invalid

MAX_PROMPT_BYTES = 1024 * 1024


def load_prompt(artifact: bytes, *, name: str = "prompt") -> str:
    """The prompt text.

    Raises:
        Invalid: too large or not UTF-8.
    """
    if len(artifact) > MAX_PROMPT_BYTES:
        raise Invalid(f"{name}: prompt is {len(artifact)} bytes; the limit is {MAX_PROMPT_BYTES}")
    try:
        return artifact.decode("utf-8")
    except UnicodeDecodeError as exc:
        raise Invalid(f"{name}: prompt is not UTF-8: {exc}") from None
