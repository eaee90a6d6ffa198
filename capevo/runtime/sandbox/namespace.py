"""Run skill source as a module with restricted builtins, in-process or inside the worker.

The same function loads a code skill in both places, so a skill that works in-process
works in the sandbox and vice versa.

Invariants:
1. Skill code sees only :data:`SAFE_BUILTIN_NAMES` plus a no-op ``print`` and an
   ``__import__`` that admits only the allowed modules.
2. :func:`load_skill_module` raises only :class:`Invalid` or :class:`SandboxViolation`;
   an exception in the module's top-level code becomes :class:`Invalid` naming it.
3. ``params`` of a loaded module are the source's ``PARAMS`` updated with the override;
   every value is a finite float and an override may only name keys ``PARAMS`` declares.
4. :func:`action_array` turns whatever ``act`` returned into a float64 array or raises
   :class:`BadOutput`; it never reshapes or flattens.
"""

from __future__ import annotations

import builtins
import math
import sys
import types
from collections.abc import Callable, Iterable, Mapping
from dataclasses import dataclass
from typing import Any

import numpy as np

from capevo.errors import Invalid
from capevo.runtime.sandbox.validator import ALLOWED_IMPORTS, FORBIDDEN_ATTRIBUTES, parse_source, validate_source

SAFE_BUILTIN_NAMES: tuple[str, ...] = (
    "abs",
    "all",
    "any",
    "bool",
    "callable",
    "chr",
    "dict",
    "divmod",
    "enumerate",
    "filter",
    "float",
    "frozenset",
    "hash",
    "int",
    "isinstance",
    "iter",
    "len",
    "list",
    "map",
    "max",
    "min",
    "next",
    "ord",
    "pow",
    "range",
    "repr",
    "reversed",
    "round",
    "set",
    "slice",
    "sorted",
    "str",
    "sum",
    "tuple",
    "zip",
    "ArithmeticError",
    "AssertionError",
    "AttributeError",
    "Exception",
    "FloatingPointError",
    "IndexError",
    "KeyError",
    "LookupError",
    "MemoryError",
    "NameError",
    "NotImplementedError",
    "OverflowError",
    "RecursionError",
    "RuntimeError",
    "StopIteration",
    "TypeError",
    "ValueError",
    "ZeroDivisionError",
    "True",
    "False",
    "None",
)

MAX_ACTION_ELEMENTS = 4096
"""Largest action a skill may return; anything bigger is a bad output, not an action."""


class BadOutput(Exception):
    """A skill returned something that is not a numeric action."""


@dataclass(frozen=True, slots=True)
class SkillModule:
    """A loaded code skill: its two entry points and its parameters θ."""

    act: Callable[..., Any]
    done: Callable[..., Any] | None
    params: dict[str, float]
    defaults: dict[str, float]


def restricted_import(allowed: Iterable[str]) -> Callable[..., types.ModuleType]:
    """An ``__import__`` that admits only ``allowed`` absolute imports."""
    allowed_set = frozenset(allowed)
    packages = frozenset(a.partition(".")[0] for a in allowed_set)
    real_import = builtins.__import__

    def _import(
        name: str,
        globals: Mapping[str, Any] | None = None,  # mirrors __import__
        locals: Mapping[str, Any] | None = None,
        fromlist: Iterable[str] | None = (),
        level: int = 0,
    ) -> types.ModuleType:
        if level != 0:
            raise ImportError("relative imports are not allowed in skills")
        # C code running on the skill's behalf (numpy's lazy ndarray repr, its MemoryError
        # type) imports submodules through this same hook; admit those if already loaded,
        # which never touches the file system. The validator still only admits the list.
        loaded_submodule = name in sys.modules and name.partition(".")[0] in packages
        if name not in allowed_set and not loaded_submodule:
            raise ImportError(f"import of {name!r} is not allowed in skills")
        for item in fromlist or ():
            if item == "__doc__":  # what PyImport_ImportModule passes
                continue
            if not isinstance(item, str) or item.startswith("_") or item in FORBIDDEN_ATTRIBUTES:
                raise ImportError(f"importing {item!r} from {name!r} is not allowed in skills")
        return real_import(name, None, None, tuple(fromlist or ()), 0)

    return _import


def _no_print(*_args: object, **_kwargs: object) -> None:
    """Skills may call print; output goes nowhere (stdout is the worker's protocol pipe)."""


def safe_builtins(allowed_imports: Iterable[str] = ALLOWED_IMPORTS) -> dict[str, Any]:
    """The ``__builtins__`` mapping skill code runs with."""
    table: dict[str, Any] = {name: getattr(builtins, name) for name in SAFE_BUILTIN_NAMES}
    table["print"] = _no_print
    table["__import__"] = restricted_import(allowed_imports)
    return table


def check_params(value: object, *, where: str = "PARAMS") -> dict[str, float]:
    """``value`` as a ``dict[str, float]`` of finite numbers.

    Raises:
        Invalid: naming ``where`` and the offending key.
    """
    if not isinstance(value, Mapping):
        raise Invalid(f"{where}: must be a dict of name -> number, got {type(value).__name__}")
    out: dict[str, float] = {}
    for key, v in value.items():
        if not isinstance(key, str) or not key:
            raise Invalid(f"{where}: keys must be non-empty strings, got {key!r}")
        if isinstance(v, bool) or not isinstance(v, (int, float, np.integer, np.floating)):
            raise Invalid(f"{where}[{key!r}]: must be a number, got {type(v).__name__}")
        f = float(v)
        if not math.isfinite(f):
            raise Invalid(f"{where}[{key!r}]: must be finite, got {f}")
        out[key] = f
    return out


def merge_params(defaults: Mapping[str, float], override: Mapping[str, Any] | None) -> dict[str, float]:
    """``defaults`` updated with ``override``.

    Raises:
        Invalid: the override names a key ``defaults`` lacks, or a value is not a finite number.
    """
    merged = dict(defaults)
    if override:
        checked = check_params(override, where="params_override")
        unknown = sorted(set(checked) - set(defaults))
        if unknown:
            raise Invalid(
                f"params_override: unknown parameter(s) {unknown}; the skill's PARAMS declares "
                f"{sorted(defaults) or 'none'}"
            )
        merged.update(checked)
    return merged


def load_skill_module(
    source: str,
    *,
    params_override: Mapping[str, Any] | None = None,
    filename: str = "<skill>",
    validate: bool = True,
    allowed_imports: Iterable[str] = ALLOWED_IMPORTS,
) -> SkillModule:
    """Validate, compile and run skill source, and pick out ``act``, ``done`` and ``PARAMS``.

    Args:
        source: The skill's Python source (see :mod:`capevo.runtime.ecm.code` for the contract).
        params_override: Values replacing some of ``PARAMS``.
        filename: Name shown in tracebacks.
        validate: Run :func:`validate_source` first. Only the sandbox's test hook turns this off.
        allowed_imports: Modules the skill may import.

    Returns:
        The loaded module's entry points and merged parameters.

    Raises:
        SandboxViolation: the source breaks a validation rule.
        Invalid: syntax error, the top-level code raised, or the contract is not met.
    """
    allowed = tuple(allowed_imports)
    tree = (
        validate_source(source, filename=filename, allowed_imports=allowed)
        if validate
        else parse_source(source, filename=filename)
    )
    try:
        code = compile(tree, filename, "exec")
    except (SyntaxError, ValueError, RecursionError, MemoryError) as exc:
        raise Invalid(f"{filename}: does not compile: {type(exc).__name__}: {exc}") from None
    namespace: dict[str, Any] = {"__builtins__": safe_builtins(allowed), "__name__": "capevo_skill"}
    try:
        exec(code, namespace)
    except Exception as exc:
        raise Invalid(f"{filename}: top-level code raised {type(exc).__name__}: {exc}") from None
    act = namespace.get("act")
    if not callable(act):
        raise Invalid(f"{filename}: a code skill must define a function act(obs, params)")
    done = namespace.get("done")
    if done is not None and not callable(done):
        raise Invalid(f"{filename}: done must be a function done(obs, params) if defined")
    defaults = check_params(namespace.get("PARAMS", {}), where=f"{filename}: PARAMS")
    return SkillModule(act=act, done=done, params=merge_params(defaults, params_override), defaults=defaults)


def action_array(result: object) -> np.ndarray:
    """What ``act`` returned as a float64 array, unflattened.

    Raises:
        BadOutput: the result is not numeric, is ragged, or is implausibly large.
    """
    if isinstance(result, (str, bytes, Mapping)) or result is None:
        raise BadOutput(f"act returned {type(result).__name__}, expected a sequence of floats")
    try:
        arr = np.asarray(result, dtype=np.float64)
    except (TypeError, ValueError, OverflowError) as exc:
        raise BadOutput(f"act returned {type(result).__name__} that is not numeric: {exc}") from None
    if arr.size > MAX_ACTION_ELEMENTS:
        raise BadOutput(f"act returned {arr.size} values; at most {MAX_ACTION_ELEMENTS} are accepted")
    return arr
