'''Code ECMs: the source contract, the in-process runner, and θ tools for learners.

The contract
------------
A code ECM's artifact is one Python module (UTF-8 text, at most 256 KiB) that defines:

``PARAMS: dict[str, float]`` (optional, module level)
    The skill's tunable parameters θ, written as a *literal* dict of string keys to
    numbers, assigned once at top level. Learners read it without running the code
    (:func:`read_params`), run the skill with other values (``params_override``), and
    publish new versions by rewriting only this literal (:func:`with_params`).

``def act(obs, params) -> sequence of floats`` (required)
    ``obs`` is a dict of read-only numpy arrays: exactly the ECM's declared interface
    inputs (key = input name, shape and dtype as declared), or the whole raw observation
    when the interface declares no inputs. ``params`` is a read-only mapping: ``PARAMS``
    with any override applied. Return the action: a flat sequence (list, tuple, 1-D
    array) of as many floats as the interface's outputs (or the task's action dim).
    Values outside the declared output bounds are clipped; NaN/inf or a wrong length is
    a failed step.

``def done(obs, params) -> bool`` (optional)
    The skill's own termination check, called before ``act`` each step with the same
    arguments; ``True`` ends the skill (no action that step). Without it the skill runs
    until the caller stops it or the step budget runs out.

Both functions should be pure functions of their arguments: a sandboxed skill's worker
may be restarted (after a timeout) and then loses module-level state.

The code may import only ``math`` and ``numpy`` (``import numpy as np``,
``numpy.linalg``); it may not define classes, use ``open``/``exec``/``eval``/
``compile``/``getattr`` on private names, touch dunder or private attributes, or use
numpy's file and pickle I/O. See :mod:`capevo.runtime.sandbox.validator` for the full
rules; every version is checked before it runs, wherever it runs.

Example::

    """Move the open gripper to a hover point above the cube."""
    import numpy as np

    PARAMS = {"gain": 8.0, "hover": 0.10, "tol": 0.01}


    def _target(obs, params):
        return obs["cube_pos"] + np.array([0.0, 0.0, params["hover"]])


    def act(obs, params):
        delta = (_target(obs, params) - obs["robot0_eef_pos"]) * params["gain"]
        move = np.clip(delta, -1.0, 1.0)
        return [move[0], move[1], move[2], 0.0, 0.0, 0.0, -1.0]  # no rotation, gripper open


    def done(obs, params):
        return float(np.linalg.norm(_target(obs, params) - obs["robot0_eef_pos"])) < params["tol"]

Invariants:
1. ``read_params(with_params(src, p)) == {**read_params(src), **p}`` and the rest of the
   source text is unchanged.
2. :class:`CodeSkill` runs the same loader as the sandbox worker (validation, restricted
   builtins), so a skill behaves the same in-process and sandboxed.
'''

from __future__ import annotations

import ast
import re
import types
from collections.abc import Iterable, Mapping
from typing import Any

import numpy as np

from capevo.errors import Invalid
from capevo.runtime.sandbox.client import SkillStep
from capevo.runtime.sandbox.namespace import action_array, check_params, load_skill_module, merge_params
from capevo.runtime.sandbox.validator import ALLOWED_IMPORTS, parse_source

PARAMS_NAME = "PARAMS"
_LINE_SPLIT = re.compile(r"(?<=\r\n)|(?<=\r)(?!\n)|(?<=\n)")


class CodeSkill:
    """A code skill running in this process (trusted origins only).

    Args:
        source: Skill source following the module contract above.
        params_override: Values replacing some of ``PARAMS``; θ without editing the source.
        filename: Name shown in errors and tracebacks.
        allowed_imports: Modules the skill may import.
        _unsafe_skip_validation: TEST HOOK ONLY; skips the AST validation.

    Raises:
        SandboxViolation: the source breaks a validation rule.
        Invalid: syntax error, contract not met, top-level code raised, or bad params.
    """

    in_process = True

    def __init__(
        self,
        source: str,
        params_override: Mapping[str, Any] | None = None,
        *,
        filename: str = "<skill>",
        allowed_imports: Iterable[str] = ALLOWED_IMPORTS,
        _unsafe_skip_validation: bool = False,
    ) -> None:
        self._module = load_skill_module(
            source,
            params_override=params_override,
            filename=filename,
            validate=not _unsafe_skip_validation,
            allowed_imports=allowed_imports,
        )
        self.source = source
        self.defaults: dict[str, float] = dict(self._module.defaults)
        self.params: dict[str, float] = dict(self._module.params)
        self._proxy = types.MappingProxyType(self.params)

    def act(self, obs: Mapping[str, np.ndarray]) -> np.ndarray:
        """The skill's raw action for ``obs`` (unchecked shape).

        Raises:
            BadOutput: ``act`` returned something non-numeric.
            Exception: whatever the skill raised.
        """
        return action_array(self._module.act(obs, self._proxy))

    def done(self, obs: Mapping[str, np.ndarray]) -> bool:
        """The skill's termination check; False when it defines none."""
        fn = self._module.done
        return bool(fn(obs, self._proxy)) if fn is not None else False

    def step(self, inputs: Mapping[str, np.ndarray], *, timeout_s: float) -> SkillStep:
        """``done`` then ``act``. ``timeout_s`` cannot interrupt in-process code; the invoker
        measures the call and discards overruns."""
        if self.done(inputs):
            return SkillStep(done=True, action=None)
        return SkillStep(done=False, action=self.act(inputs))

    def set_params(self, params: Mapping[str, Any]) -> dict[str, float]:
        """Replace θ (some of ``PARAMS``) in place.

        Raises:
            Invalid: unknown key or non-finite value.
        """
        merged = merge_params(self.defaults, params)
        self.params.clear()
        self.params.update(merged)
        return dict(self.params)

    def close(self) -> None:
        """Nothing to release in-process."""


def _find_params_node(tree: ast.Module, filename: str) -> ast.Assign | ast.AnnAssign | None:
    found: list[ast.Assign | ast.AnnAssign] = []
    for node in tree.body:
        if isinstance(node, ast.Assign) and any(isinstance(t, ast.Name) and t.id == PARAMS_NAME for t in node.targets):
            if len(node.targets) != 1:
                raise Invalid(f"{filename}: line {node.lineno}: PARAMS must be assigned on its own")
            found.append(node)
        elif (
            isinstance(node, ast.AnnAssign)
            and isinstance(node.target, ast.Name)
            and node.target.id == PARAMS_NAME
            and node.value is not None
        ):
            found.append(node)
    if len(found) > 1:
        raise Invalid(f"{filename}: PARAMS is assigned {len(found)} times at top level; assign it once")
    return found[0] if found else None


def read_params(source: str, *, filename: str = "<skill>") -> dict[str, float]:
    """The ``PARAMS`` literal of a skill, read without running any of its code.

    Returns:
        The parameters, in source order; empty when the skill declares none.

    Raises:
        Invalid: not valid Python, or ``PARAMS`` is not a literal dict of finite numbers.
    """
    tree = parse_source(source, filename=filename)
    node = _find_params_node(tree, filename)
    if node is None:
        return {}
    if node.value is None:  # pragma: no cover - _find_params_node only returns assignments with values
        return {}
    try:
        value = ast.literal_eval(node.value)
    except (ValueError, TypeError, SyntaxError, RecursionError, MemoryError) as exc:
        raise Invalid(f"{filename}: line {node.lineno}: PARAMS must be a literal dict: {exc}") from None
    return check_params(value, where=f"{filename}: PARAMS")


def _format_params(params: Mapping[str, float]) -> str:
    if not params:
        return "{}"
    body = "".join(f"    {k!r}: {v!r},\n" for k, v in params.items())
    return "{\n" + body + "}"


def with_params(source: str, params: Mapping[str, Any], *, filename: str = "<skill>") -> str:
    """New source whose ``PARAMS`` literal holds ``params`` merged over the old values.

    Only the literal's text changes; comments, code and formatting elsewhere are kept.

    Args:
        source: Skill source that declares ``PARAMS``.
        params: New values for some or all declared keys.
        filename: Name used in messages.

    Returns:
        The rewritten source.

    Raises:
        Invalid: no ``PARAMS`` literal, an unknown key, or a non-finite value.
    """
    current = read_params(source, filename=filename)
    tree = parse_source(source, filename=filename)
    node = _find_params_node(tree, filename)
    if node is None or node.value is None:
        raise Invalid(f"{filename}: declares no PARAMS literal to rewrite")
    merged = merge_params(current, params)
    value = node.value
    if value.end_lineno is None or value.end_col_offset is None:  # pragma: no cover - parser always sets them
        raise Invalid(f"{filename}: cannot locate PARAMS in the source")
    lines = _LINE_SPLIT.split(source)
    start = _char_offset(lines, value.lineno, value.col_offset)
    end = _char_offset(lines, value.end_lineno, value.end_col_offset)
    out = source[:start] + _format_params(merged) + source[end:]
    if read_params(out, filename=filename) != merged:  # pragma: no cover - guards the splice itself
        raise Invalid(f"{filename}: rewriting PARAMS failed")
    return out


def _char_offset(lines: list[str], lineno: int, col_utf8: int) -> int:
    """Character offset of an AST position (1-based line, UTF-8 byte column)."""
    before = sum(len(line) for line in lines[: lineno - 1])
    return before + len(lines[lineno - 1].encode()[:col_utf8].decode())
