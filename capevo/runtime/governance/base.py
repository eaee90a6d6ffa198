"""The constraint contract, the constraint registry, and typed config for constraints.

A constraint is a frozen, layout-free config object (one entry of Φ). For a run it is
compiled against the task's :class:`~capevo.runtime.state.ActionLayout` into a *check*: a
plain closure over precomputed floats that the governor calls on every action.

A check is called as ``check(arms, a)`` with ``arms`` the ``RobotState.arms`` tuple (as many
as the layout has) and ``a`` a list or tuple of finite numbers of the layout's length, each
arm's translation already in the world frame (the governor rotates it). It returns ``None``
to allow, or ``(a_prime, reason)`` with ``a_prime`` a new list (modify) or ``None`` (⊥,
reject). It never mutates ``a``, and builds reasons from strings prepared at compile time
so an intervention costs no formatting.

Every built-in modification is one of four kinds:

* zero a component whose sign points the wrong way (the paper's box and force rules);
* clamp a component's magnitude to a bound ``>= 0`` (the speed-and-separation rules:
  ``workspace_guard``, ``surface_approach``, ``obstacle_approach``, ``arm_separation``,
  ``reach_limit``, ``force_ramp``);
* scale one arm's six pose components down by a positive factor (the cap);
* restore: push a component the other way, at a small speed, with the arm's other components
  clamped to that speed (only in states already past a limit: outside the box or the reach,
  inside a base column, above the force limit).

The first three only shrink components towards 0 without flipping a sign, and every
condition they establish has the form "a component pointing this way is at most b >= 0" or
"a norm is at most c", which any later shrink preserves. So where no restoring edit fires,
one pass through Φ in any order leaves an action that satisfies every constraint at once
(:mod:`capevo.runtime.governance.governor`, invariant 3). A new constraint must keep to these
kinds of edit, or document the order it needs.

Invariants:
1. ``make(kind, **config)`` builds exactly what ``constraints: [{kind: ..., **config}]``
   loads; an unknown kind raises :class:`Invalid` listing every registered kind.
2. Config values are coerced to their declared types (ints to floats, lists to tuples),
   so two configs that mean the same thing compare and hash equal.
3. An unknown config key, a wrong type or a non-finite number raises :class:`Invalid`
   whose message starts with the field's name and whose ``details["field"]`` is that name.
4. A constraint's optional ``name`` (its label) matches :data:`LABEL_PATTERN`.
"""

from __future__ import annotations

import dataclasses
import math
import re
import types
import typing
from collections.abc import Callable, Mapping, Sequence
from typing import Any, ClassVar, Protocol, TypeVar, Union

from capevo.errors import Conflict, Invalid
from capevo.runtime.state import ActionLayout, ArmState

Result = Union[tuple[Union[list[float], None], str], None]  # noqa: UP007 - a runtime alias, kept 3.10-safe
"""None (allow), ``(a_prime, reason)`` (modify) or ``(None, reason)`` (reject)."""
Check = Callable[[Sequence[ArmState], Sequence[float]], Result]


class Constraint(Protocol):
    """One member of Φ."""

    kind: ClassVar[str]
    name: str | None

    @property
    def label(self) -> str:
        """The name interventions carry: ``name`` if set, else ``kind``."""
        ...

    def compile(self, layout: ActionLayout) -> Check:
        """A fast check for actions of ``layout``; see the module docstring for its contract."""
        ...

    def unsafe(self, arms: Sequence[ArmState], action: Sequence[float] | None, layout: ActionLayout) -> str | None:
        """Why the executed step (``arms`` when ``action`` ran) broke this constraint's hard limit, or None."""
        ...

    def to_config(self) -> dict[str, Any]:
        """Normalized config: every field with its value (defaults filled), JSON types only."""
        ...


class ConstraintBase:
    """What every built-in constraint shares: its label, its normalized config, and no hard limit.

    Built-in kinds are frozen dataclasses with a ``name`` field that derive from this and
    override :meth:`unsafe` when they have a hard limit of their own.
    """

    __slots__ = ()
    kind: ClassVar[str]
    name: str | None

    @property
    def label(self) -> str:
        """The name interventions carry: ``name`` if set, else ``kind``."""
        return self.name or self.kind

    def to_config(self) -> dict[str, Any]:
        """Normalized config: every field with its value (defaults filled), JSON types only."""
        return config_of(self)

    def unsafe(self, arms: Sequence[ArmState], action: Sequence[float] | None, layout: ActionLayout) -> str | None:
        """None: a rule without a hard limit of its own never makes a step unsafe."""
        return None


def edited(b: list[float] | None, notes: Sequence[str]) -> Result:
    """A check's answer: None when it left the action alone, else the edited copy ``b`` with its reasons."""
    return None if b is None else (b, "; ".join(notes))


AXES = ("x", "y", "z")


def check_corners(low: Sequence[float], high: Sequence[float]) -> None:
    """Check that ``low`` is below ``high`` on every axis (a box's corners, world frame).

    Raises:
        Invalid: naming ``high`` and the first axis where it is not above ``low``.
    """
    for k, axis in enumerate(AXES):
        if not low[k] < high[k]:
            raise invalid("high", f"high.{axis} ({high[k]}) must be above low.{axis} ({low[k]})")


C = TypeVar("C")
LABEL_PATTERN = re.compile(r"[A-Za-z0-9_.-]{1,64}")
CONSTRAINTS: dict[str, type[Any]] = {}
"""Registered constraint classes by kind; fill it with :func:`register`."""


def register(kind: str) -> Callable[[type[C]], type[C]]:
    """Class decorator adding a constraint class to :data:`CONSTRAINTS` under ``kind``.

    Raises:
        Conflict: if ``kind`` is taken.
    """

    def deco(cls: type[C]) -> type[C]:
        if kind in CONSTRAINTS:
            raise Conflict(f"constraint kind {kind!r} is already registered", details={"field": "kind"})
        cls.kind = kind  # type: ignore[attr-defined]
        CONSTRAINTS[kind] = cls
        return cls

    return deco


def constraint_kinds() -> list[str]:
    """Registered kinds, sorted."""
    return sorted(CONSTRAINTS)


def make(kind: str, **config: Any) -> Constraint:
    """Build a registered constraint from keyword config (values as YAML would give them).

    Raises:
        Invalid: for an unknown kind (the message lists the valid ones) or a bad config value.
    """
    cls = CONSTRAINTS.get(kind)
    if cls is None:
        raise Invalid(
            f"kind: unknown constraint kind {kind!r}; valid kinds: {', '.join(constraint_kinds())}",
            details={"field": "kind", "valid": constraint_kinds()},
        )
    return typing.cast(Constraint, build(cls, config))


def build(cls: type[C], config: Mapping[str, Any]) -> C:
    """Instantiate the frozen dataclass ``cls`` from ``config``; its ``__post_init__`` coerces the values.

    Raises:
        Invalid: naming the field on an unknown key, a missing required key, a wrong type or a rejected value.
    """
    if not isinstance(config, Mapping):
        raise Invalid(f"<config>: expected a mapping, got {type(config).__name__}", details={"field": "<config>"})
    fields = {f.name: f for f in dataclasses.fields(typing.cast(Any, cls)) if f.init}
    for key in config:
        if key not in fields:
            raise Invalid(
                f"{key}: unknown key; valid keys: {', '.join(sorted(fields))}",
                details={"field": str(key), "valid": sorted(fields)},
            )
    missing = [
        name
        for name, f in fields.items()
        if name not in config and f.default is dataclasses.MISSING and f.default_factory is dataclasses.MISSING
    ]
    if missing:
        raise Invalid(f"{missing[0]}: required key is missing", details={"field": missing[0]})
    return cls(**config)


_HINTS: dict[type, dict[str, Any]] = {}


def normalize(obj: Any) -> None:
    """Coerce every init field of the frozen dataclass ``obj`` in place; call it first in ``__post_init__``.

    Direct construction and YAML then yield equal objects (invariant 2).

    Raises:
        Invalid: naming the field whose value has the wrong type or is not finite.
    """
    cls = type(obj)
    hints = _HINTS.get(cls)
    if hints is None:
        hints = _HINTS[cls] = typing.get_type_hints(cls)
    for f in dataclasses.fields(obj):
        if f.init:
            object.__setattr__(obj, f.name, coerce(getattr(obj, f.name), hints[f.name], f.name))
    name = getattr(obj, "name", None)
    if name is not None and not LABEL_PATTERN.fullmatch(name):
        raise invalid("name", f"{name!r} is not a label: use 1-64 letters, digits, '_', '.' or '-'")


def coerce(value: Any, hint: Any, field: str) -> Any:
    """``value`` as the type ``hint`` (float, int, bool, str, ``X | None``, fixed or variadic tuple, dataclass).

    Raises:
        Invalid: whose message starts with ``field``.
    """
    origin, args = typing.get_origin(hint), typing.get_args(hint)
    if origin in (Union, types.UnionType):
        if value is None and type(None) in args:
            return None
        (inner,) = [a for a in args if a is not type(None)]
        return coerce(value, inner, field)
    if hint is float:
        if isinstance(value, str) and _looks_numeric(value):
            # PyYAML follows YAML 1.1, where 1e-3 (no '.') is a string; say so rather than just "got str".
            raise Invalid(
                f"{field}: expected a number, got str {value!r} (YAML reads an exponent without a '.' as text; "
                f"write {float(value)!r})",
                details={"field": field},
            )
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            raise _bad(field, "a number", value)
        if not math.isfinite(value):
            raise Invalid(f"{field}: must be a finite number, got {value}", details={"field": field})
        return float(value)
    if hint is int:
        if isinstance(value, bool) or not isinstance(value, int):
            raise _bad(field, "an integer", value)
        return value
    if hint is bool or hint is str:
        if not isinstance(value, hint):
            raise _bad(field, "a boolean" if hint is bool else "a string", value)
        return value
    if origin is tuple:
        if not isinstance(value, (list, tuple)):
            raise _bad(field, "a list", value)
        if len(args) == 2 and args[1] is Ellipsis:
            return tuple(coerce(v, args[0], f"{field}[{i}]") for i, v in enumerate(value))
        if len(value) != len(args):
            raise Invalid(
                f"{field}: expected a list of {len(args)} values, got {len(value)}",
                details={"field": field},
            )
        return tuple(coerce(v, a, f"{field}[{i}]") for i, (v, a) in enumerate(zip(value, args, strict=True)))
    if dataclasses.is_dataclass(hint):
        if isinstance(value, hint):
            return value
        try:
            return build(hint, value)
        except Invalid as exc:
            raise prefixed(exc, field) from None
    raise TypeError(f"unsupported config type {hint!r} for {field}")  # a bug in a constraint class


def _looks_numeric(text: str) -> bool:
    try:
        return math.isfinite(float(text))
    except ValueError:
        return False


def _bad(field: str, expected: str, value: Any) -> Invalid:
    return Invalid(f"{field}: expected {expected}, got {type(value).__name__}", details={"field": field})


def prefixed(exc: Invalid, prefix: str) -> Invalid:
    """The same error with ``prefix`` put in front of its field path."""
    inner = exc.details.get("field", "<config>")
    field = prefix if inner == "<config>" else f"{prefix}.{inner}" if not inner.startswith("[") else prefix + inner
    message = exc.message
    if message.startswith(f"{inner}:"):
        message = message[len(inner) + 1 :].lstrip()
    return Invalid(f"{field}: {message}", details={**exc.details, "field": field})


def invalid(field: str, message: str) -> Invalid:
    """An :class:`Invalid` for a constraint's own validation, in the shape :func:`build` uses."""
    return Invalid(f"{field}: {message}", details={"field": field})


def config_of(obj: Any) -> dict[str, Any]:
    """Every init field of a frozen dataclass as JSON types (tuples to lists, nested dataclasses to dicts)."""

    def plain(v: Any) -> Any:
        if dataclasses.is_dataclass(v) and not isinstance(v, type):
            return config_of(v)
        if isinstance(v, tuple):
            return [plain(x) for x in v]
        return v

    return {f.name: plain(getattr(obj, f.name)) for f in dataclasses.fields(obj) if f.init}
