"""What the invoker does when an ECM call fails: retry, fall back, or hold still.

Strategies register by name with :func:`register_recovery`; :func:`make_recovery` builds
one by name. They compose through ``then``: ``Retry(attempts=2, then=Fallback(
alternatives=[previous_version]))`` retries twice, then tries the previous version, then
(the default ``then`` of every strategy) holds still.

Invariants:
1. Every strategy ends in an action: a recovered call's, or the safe hold
   (``Resolution.outcome`` None). None of them raises on ECM failure.
2. A strategy only calls ECMs through ``ctx.call``, so every call is timed, classified
   and listed in ``Resolution.attempts``.
3. ``Resolution.strategy`` names the chain that was walked, ``>``-separated
   (``"retry>fallback>abort"``).
"""

from __future__ import annotations

import abc
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any, ClassVar, Protocol

from capevo.errors import Invalid
from capevo.runtime.ecm.base import LoadedEcm
from capevo.runtime.ecm.outcome import Outcome, Status

_DONE = frozenset({Status.OK, Status.TERMINATED})


@dataclass(frozen=True, slots=True, kw_only=True)
class Resolution:
    """How a strategy resolved one failed call."""

    outcome: Outcome | None
    """The call whose result stands (``ok`` or ``terminated``), or None: hold still."""
    attempts: tuple[Outcome, ...]
    strategy: str
    switch_to: LoadedEcm | None = None
    """ECM the invoker should use as primary from now on (sticky fallback)."""


class RecoveryContext(Protocol):
    """What a strategy may use: the primary ECM and a classified call."""

    @property
    def primary(self) -> LoadedEcm: ...

    def call(self, ecm: LoadedEcm) -> Outcome: ...


class RecoveryStrategy(abc.ABC):
    """Decides what happens after a failed call (exception, timeout, nan, bad_shape)."""

    name: ClassVar[str]

    @abc.abstractmethod
    def recover(self, failed: Outcome, ctx: RecoveryContext) -> Resolution:
        """Resolve the failed call ``failed`` of ``ctx.primary``."""

    def alternatives(self) -> tuple[LoadedEcm, ...]:
        """Every ECM this strategy (and its ``then`` chain) may call besides the primary."""
        return ()


RECOVERIES: dict[str, type[RecoveryStrategy]] = {}


def register_recovery(name: str) -> Callable[[type[RecoveryStrategy]], type[RecoveryStrategy]]:
    """Class decorator: register a strategy under ``name``."""

    def deco(cls: type[RecoveryStrategy]) -> type[RecoveryStrategy]:
        cls.name = name
        RECOVERIES[name] = cls
        return cls

    return deco


def make_recovery(name: str, **kwargs: Any) -> RecoveryStrategy:
    """Build the strategy registered as ``name`` with ``kwargs``.

    Raises:
        Invalid: unknown name (listing the valid ones) or bad arguments.
    """
    cls = RECOVERIES.get(name)
    if cls is None:
        raise Invalid(f"unknown recovery strategy {name!r}; valid: {', '.join(sorted(RECOVERIES))}")
    try:
        return cls(**kwargs)
    except TypeError as exc:
        raise Invalid(f"recovery strategy {name!r}: {exc}") from None


def _then(then: RecoveryStrategy | None) -> RecoveryStrategy:
    return then if then is not None else SafeAbort()


def _chain(prefix: str, made: Sequence[Outcome], rest: Resolution) -> Resolution:
    return Resolution(
        outcome=rest.outcome,
        attempts=(*made, *rest.attempts),
        strategy=f"{prefix}>{rest.strategy}",
        switch_to=rest.switch_to,
    )


@register_recovery("abort")
class SafeAbort(RecoveryStrategy):
    """Hold still: zero motion of the right dimension, gripper command unchanged."""

    def recover(self, failed: Outcome, ctx: RecoveryContext) -> Resolution:
        return Resolution(outcome=None, attempts=(), strategy=self.name)


@register_recovery("retry")
class Retry(RecoveryStrategy):
    """Call the same ECM again, up to ``attempts`` times, then hand over to ``then``.

    Args:
        attempts: Extra calls after the failed one (>= 1).
        then: Strategy after the last failed retry; default :class:`SafeAbort`.
    """

    def __init__(self, *, attempts: int = 1, then: RecoveryStrategy | None = None) -> None:
        if attempts < 1:
            raise Invalid(f"retry: attempts must be >= 1, got {attempts}")
        self.attempts = attempts
        self.then = _then(then)

    def recover(self, failed: Outcome, ctx: RecoveryContext) -> Resolution:
        made: list[Outcome] = []
        last = failed
        for _ in range(self.attempts):
            last = ctx.call(ctx.primary)
            made.append(last)
            if last.status in _DONE:
                return Resolution(outcome=last, attempts=tuple(made), strategy=self.name)
        return _chain(self.name, made, self.then.recover(last, ctx))

    def alternatives(self) -> tuple[LoadedEcm, ...]:
        return self.then.alternatives()


@register_recovery("fallback")
class Fallback(RecoveryStrategy):
    """Try alternative ECMs in order (e.g. the previous version), then ``then``.

    Args:
        alternatives: Loaded ECMs to try; the primary itself is skipped if listed.
        sticky: After an alternative succeeds, make it the primary for the rest of the
            activation (a crashed version tends to crash again).
        then: Strategy when every alternative fails; default :class:`SafeAbort`.
    """

    def __init__(
        self, *, alternatives: Sequence[LoadedEcm], sticky: bool = True, then: RecoveryStrategy | None = None
    ) -> None:
        if not alternatives:
            raise Invalid("fallback: needs at least one alternative ECM")
        self._alternatives = tuple(alternatives)
        self.sticky = sticky
        self.then = _then(then)

    def recover(self, failed: Outcome, ctx: RecoveryContext) -> Resolution:
        made: list[Outcome] = []
        last = failed
        for alt in self._alternatives:
            if alt is ctx.primary:
                continue
            last = ctx.call(alt)
            made.append(last)
            if last.status in _DONE:
                return Resolution(
                    outcome=last, attempts=tuple(made), strategy=self.name, switch_to=alt if self.sticky else None
                )
        return _chain(self.name, made, self.then.recover(last, ctx))

    def alternatives(self) -> tuple[LoadedEcm, ...]:
        return (*self._alternatives, *self.then.alternatives())
